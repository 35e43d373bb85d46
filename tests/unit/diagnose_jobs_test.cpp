// cellbenchd's diagnosis job queue (daemon/include/cellbench/daemon/diagnose_jobs.hpp) without a bench: one job at
// a time on its worker, a bounded queue (409 beyond), failures with their message, the last `keep` finished
// jobs kept, stop() failing what waits; and a real (small) diagnosis with its decimated traces.
#include "cellbench/daemon/diagnose_jobs.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <future>
#include <thread>

#include "cellbench/daemon/api.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "unit/thesis_params.hpp"

using namespace cellbench;
using daemon::DiagnoseInput;
using daemon::DiagnoseJobs;
using daemon::DiagnoseJobsOptions;
using nlohmann::json;
using namespace std::chrono_literals;

namespace {

json wait_done(const DiagnoseJobs& jobs, std::int64_t id, std::chrono::seconds limit = 60s) {
    const auto end = std::chrono::steady_clock::now() + limit;
    json j;
    do {
        j = jobs.get(id);
        if (j["state"] != "running") return j;
        std::this_thread::sleep_for(10ms);
    } while (std::chrono::steady_clock::now() < end);
    return j;
}

estimator::ParameterSet thesis() { return test::thesis_parameter_set(); }

// 10 minutes at 1 s: rest, 1C discharge pulses and rests; the voltage a crude OCV minus IR (so the model misses).
Recording synthetic() {
    Recording r;
    r.source = "synthetic";
    for (int k = 0; k <= 600; ++k) {
        const double t = k;
        const double i = (k % 120) < 30 && k > 60 ? -4.0 : 0.0;
        r.time_s.push_back(t);
        r.current_a.push_back(i);
        r.voltage_v.push_back(4.0 - 0.0002 * t + 0.01 * i);
        r.surface_c.push_back(30.0 + 0.001 * t);
    }
    return r;
}

}  // namespace

TEST(DiagnoseJobs, OneAtATimeABoundedQueueAndFailuresWithTheirMessage) {
    DiagnoseJobsOptions o;
    o.max_waiting = 2;
    o.keep = 3;
    DiagnoseJobs jobs(o);
    std::promise<void> release;
    std::shared_future<void> gate = release.get_future().share();
    const auto blocked = [gate](const auto& stage) -> DiagnoseInput {
        stage("held by the test");
        gate.wait();
        throw InputError("test.bdf.csv:3: not a number");
    };
    const json first = jobs.submit({{"source", {{"kind", "upload"}}}}, {}, blocked);
    EXPECT_EQ(first["state"], "running");
    ASSERT_TRUE(first["id"].is_number_integer());
    const auto id1 = first["id"].get<std::int64_t>();
    // The worker takes it (stage from the loader), the next two wait behind it, a fourth is refused.
    const auto t_end = std::chrono::steady_clock::now() + 10s;
    while (jobs.get(id1)["stage"] != "held by the test" && std::chrono::steady_clock::now() < t_end)
        std::this_thread::sleep_for(5ms);
    EXPECT_EQ(jobs.get(id1)["stage"], "held by the test");
    EXPECT_EQ(jobs.get(id1)["position"], 0);
    const auto id2 = jobs.submit(json::object(), {}, blocked)["id"].get<std::int64_t>();
    const auto id3 = jobs.submit(json::object(), {}, blocked)["id"].get<std::int64_t>();
    EXPECT_EQ(jobs.get(id3)["position"], 2);
    EXPECT_EQ(jobs.get(id3)["stage"], "waiting (2 ahead)");
    EXPECT_THROW(jobs.submit(json::object(), {}, blocked), daemon::Conflict);
    EXPECT_EQ(jobs.list()["diagnoses"].size(), 3u);
    EXPECT_EQ(jobs.list()["diagnoses"][0]["id"], id3) << "newest first";

    release.set_value();
    for (const auto id : {id1, id2, id3}) {
        const json j = wait_done(jobs, id);
        EXPECT_EQ(j["state"], "failed");
        EXPECT_EQ(j["error"], "test.bdf.csv:3: not a number");
        EXPECT_TRUE(j["wall_s"].is_number());
        EXPECT_FALSE(j.contains("diagnosis"));
    }
    // Keep 3: two more finished jobs push the first two out.
    const auto id4 = jobs.submit(json::object(), {}, blocked)["id"].get<std::int64_t>();
    wait_done(jobs, id4);
    const auto id5 = jobs.submit(json::object(), {}, blocked)["id"].get<std::int64_t>();
    wait_done(jobs, id5);
    std::this_thread::sleep_for(50ms);  // the worker trims after storing the result
    EXPECT_THROW(jobs.get(id1), daemon::NotFound);
    EXPECT_THROW(jobs.get(id2), daemon::NotFound);
    EXPECT_EQ(jobs.get(id3)["state"], "failed");
    EXPECT_THROW(jobs.get(999), daemon::NotFound);
}

TEST(DiagnoseJobs, StopFailsWhatWaitsAndRefusesMore) {
    DiagnoseJobs jobs;
    std::promise<void> release;
    std::shared_future<void> gate = release.get_future().share();
    const auto held = [gate](const auto&) -> DiagnoseInput {
        gate.wait();
        throw InputError("released");
    };
    const auto id1 = jobs.submit(json::object(), {}, held)["id"].get<std::int64_t>();
    const auto id2 = jobs.submit(json::object(), {}, held)["id"].get<std::int64_t>();
    std::thread stopper([&] { jobs.stop(); });
    std::this_thread::sleep_for(50ms);
    release.set_value();
    stopper.join();
    EXPECT_EQ(jobs.get(id1)["state"], "failed");
    EXPECT_EQ(jobs.get(id2)["state"], "failed");
    EXPECT_NE(jobs.get(id2)["error"].get<std::string>().find("stopped"), std::string::npos);
    EXPECT_THROW(jobs.submit(json::object(), {}, held), daemon::Unavailable);
}

TEST(DiagnoseJobs, ADiagnosisWithItsReportAndTraces) {
    DiagnoseJobsOptions o;
    o.max_trace_points = 200;
    DiagnoseJobs jobs(o);
    const auto id = jobs.submit({{"params", "p45b-thesis"}}, {"series_resistance_offset"}, [](const auto&) {
        return DiagnoseInput{thesis(), synthetic(), {}};
    })["id"].get<std::int64_t>();
    const json j = wait_done(jobs, id);
    ASSERT_EQ(j["state"], "done") << j.dump().substr(0, 1000);
    EXPECT_EQ(j["progress"], 1.0);
    EXPECT_EQ(j["params"], "p45b-thesis");
    EXPECT_EQ(j["diagnosis"]["schema"], "cellbench.diagnosis/1");
    ASSERT_EQ(j["diagnosis"]["findings"].size(), 1u);
    EXPECT_EQ(j["diagnosis"]["findings"][0]["effect"], "series_resistance_offset");
    const json& t = j["traces"];
    EXPECT_EQ(t["rows"], 601);
    const std::size_t n = t["time_s"].size();
    EXPECT_GT(n, 20u);
    EXPECT_LE(n, 200u);
    EXPECT_EQ(t["points"], n);
    for (const char* k : {"measured", "baseline"}) {
        EXPECT_EQ(t["voltage_v"][k].size(), n) << k;
        EXPECT_EQ(t["surface_c"][k].size(), n) << k;
    }
    EXPECT_EQ(t["voltage_error_v"]["baseline"].size(), n);
    const bool accepted = !j["diagnosis"]["accepted"].empty();
    EXPECT_EQ(t["voltage_v"].contains("improved"), accepted);
    EXPECT_EQ(j["improved_params"].is_null(), !accepted);
    // The error trace is the baseline minus the measurement at the same rows.
    for (std::size_t k = 0; k < n; ++k)
        EXPECT_NEAR(t["voltage_error_v"]["baseline"][k].get<double>(),
                    t["voltage_v"]["baseline"][k].get<double>() - t["voltage_v"]["measured"][k].get<double>(), 1e-12);
    // The list leaves the results out.
    EXPECT_FALSE(jobs.list()["diagnoses"][0].contains("traces"));
}

TEST(DiagnoseTraces, DecimationKeepsEveryBucketsExtremes) {
    std::vector<double> t, y;
    for (int k = 0; k < 10000; ++k) {
        t.push_back(k * 0.1);
        y.push_back(std::sin(k * 0.01));
    }
    y[5555] = 40.0;   // a one-row spike
    y[7777] = -40.0;
    y[100] = NAN;
    const auto rows = estimator::decimate_rows(t, {&y}, 500);
    EXPECT_LE(rows.size(), 500u);
    EXPECT_GT(rows.size(), 400u);
    EXPECT_TRUE(std::is_sorted(rows.begin(), rows.end()));
    EXPECT_NE(std::find(rows.begin(), rows.end(), 5555u), rows.end());
    EXPECT_NE(std::find(rows.begin(), rows.end(), 7777u), rows.end());
    EXPECT_EQ(std::find(rows.begin(), rows.end(), 100u), rows.end()) << "NaN rows are never an extreme";
    EXPECT_TRUE(estimator::decimate_rows({}, {&y}, 500).empty());
    // Fewer rows than the budget: every (finite) row.
    std::vector<double> t3 = {0, 1, 2}, y3 = {1, 2, 3};
    EXPECT_EQ(estimator::decimate_rows(t3, {&y3}, 2000), (std::vector<std::size_t>{0, 1, 2}));
}

// cellbenchd's shutdown cancels a running diagnosis through DiagnoseOptions::cancel.
TEST(DiagnoseTraces, ACancelledDiagnosisThrows) {
    std::atomic<bool> cancel{true};
    estimator::DiagnoseOptions o;
    o.effects = {"series_resistance_offset"};
    o.cancel = &cancel;
    EXPECT_THROW(estimator::diagnose(thesis(), synthetic(), o), estimator::DiagnoseCancelled);
    cancel = false;
    EXPECT_NO_THROW(estimator::diagnose(thesis(), synthetic(), o));
}
