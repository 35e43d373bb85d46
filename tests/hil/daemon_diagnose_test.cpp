// The daemon's diagnosis jobs end to end, in process: BenchDaemon on config/bench.sim.json (every instrument
// simulated on loopback) records a short HPPC (config/programs/hppc_short.json) at a high time scale; then,
// over HTTP as the dashboard does it:
//  - POST /runs/{id}/diagnose is refused while the run is active (409), without the token (401), for an
//    unknown run (404) and an unknown parameter set or effect (400);
//  - with {"params": "p45b-thesis"} (the whole catalogue) it answers 202 with a job; GET /diagnoses/{job} reports
//    progress and ends "done" with a cellbench.diagnosis/1 report whose baseline voltage error is small (the
//    simulated cell IS the parameter set, so only sensor noise and sampling remain), with no significant finding
//    (a clean bench diagnosed against its own parameter set: issue 13), and decimated traces of equal lengths;
//  - the run exported as BDF CSV (GET /runs/{id}/export.bdf.csv) and uploaded to POST /diagnose is diagnosed
//    too; a malformed upload is a 400 JSON error;
//  - with "confirm_runs" naming a second run of the cell, every finding that is a property of the cell carries its
//    verdict on that run; the run itself, an unknown run or a malformed list is a 400, a run still recording a 409.
// CELLBENCH_HIL_TIME_SCALE overrides the time scale; the wall times of the run and the jobs are printed.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "hil/hil_support.hpp"
#include "unit/api_test_support.hpp"

using namespace cellbench;
using cellbench::test::eventually;
using cellbench::test::instruments_connected;
using cellbench::test::TempDir;
using cellbench::testing::Headers;
using cellbench::testing::Response;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;
namespace http = boost::beast::http;

namespace {

// hppc_short is about 4000 bench seconds (about 13 s of wall time here).
constexpr double kTimeScale = 300.0;
const fs::path kSource = CELLBENCH_SOURCE_DIR;
const std::string kToken = "hil-token";

// The run is diagnosed against the whole catalogue (as the dashboard asks); the upload, the same recording
// again, against two candidates only, to keep the test short on a loaded two-core machine.
const json kUploadEffects = {"series_resistance_offset", "ocv_hysteresis"};

class Api {
public:
    explicit Api(std::uint16_t port) : port_(port) {}
    Response get(const std::string& path) { return cellbench::testing::request(port_, http::verb::get, "/api/v1" + path); }
    Response post(const std::string& path, const std::string& body, bool auth = true,
                  const std::string& type = "application/json") {
        Headers h = {{"Content-Type", type}};
        if (auth) h.emplace_back("Authorization", "Bearer " + kToken);
        return cellbench::testing::request(port_, http::verb::post, "/api/v1" + path, body, h);
    }

private:
    std::uint16_t port_;
};

::testing::AssertionResult json_error(const Response& r, unsigned status) {
    if (r.result_int() != status)
        return ::testing::AssertionFailure() << "status " << r.result_int() << ", expected " << status << ": "
                                             << r.body().substr(0, 500);
    const auto j = json::parse(r.body(), nullptr, false);
    if (!j.is_object() || !j.contains("error") || !j["error"].is_string())
        return ::testing::AssertionFailure() << "not a JSON error: " << r.body().substr(0, 500);
    return ::testing::AssertionSuccess();
}

// Polls the job until it is no longer running; checks on the way that progress never goes back.
json wait_for_job(Api& api, std::int64_t job, double& wall_s) {
    const auto t0 = std::chrono::steady_clock::now();
    json j;
    double last_progress = 0.0;
    bool went_back = false;
    eventually([&] {
        const auto r = api.get("/diagnoses/" + std::to_string(job));
        if (r.result_int() != 200) return false;
        j = json::parse(r.body());
        const double p = j.value("progress", 0.0);
        if (p < last_progress) went_back = true;
        last_progress = p;
        return !test::live_run_state(j.value("state", ""));
    }, 120s, 200ms);
    wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    EXPECT_FALSE(went_back) << "progress went backwards";
    return j;
}

void expect_report(const json& job, const char* what, std::size_t candidates) {
    SCOPED_TRACE(what);
    ASSERT_EQ(job.value("state", ""), "done") << job.value("error", "") << "\n" << job.dump().substr(0, 2000);
    EXPECT_DOUBLE_EQ(job.value("progress", 0.0), 1.0);
    ASSERT_TRUE(job.contains("diagnosis"));
    const json& d = job["diagnosis"];
    EXPECT_EQ(d.value("schema", ""), "cellbench.diagnosis/1");
    ASSERT_TRUE(d.contains("baseline") && d["baseline"].is_object());
    ASSERT_TRUE(d["baseline"]["voltage_rms_v"].is_number()) << d["baseline"].dump();
    const double v_rms = d["baseline"]["voltage_rms_v"].get<double>();
    EXPECT_TRUE(std::isfinite(v_rms));
    // The simulated cell is p45b-thesis itself (config/bench.sim.json, no hidden physics): what is left is the
    // sensor noise and the sampling of a time-scaled bench, a few mV.
    EXPECT_LT(v_rms, 0.02) << d["baseline"].dump();
    ASSERT_TRUE(d["where"].is_array());
    ASSERT_TRUE(d["findings"].is_array());
    EXPECT_EQ(d["findings"].size(), candidates);
    for (const auto& f : d["findings"]) {
        EXPECT_TRUE(f["effect"].is_string());
        EXPECT_TRUE(f["significant"].is_boolean());
        EXPECT_TRUE(f["score"].is_number());
        EXPECT_TRUE(f["explanation"].is_string());
    }

    ASSERT_TRUE(job.contains("traces") && job["traces"].is_object());
    const json& t = job["traces"];
    const std::size_t n = t["time_s"].size();
    EXPECT_GT(n, 100u);
    EXPECT_LE(n, 2000u);
    EXPECT_GE(t["rows"].get<std::size_t>(), n);
    EXPECT_EQ(t["points"].get<std::size_t>(), n);
    EXPECT_EQ(t["voltage_v"]["measured"].size(), n);
    EXPECT_EQ(t["voltage_v"]["baseline"].size(), n);
    EXPECT_EQ(t["voltage_error_v"]["baseline"].size(), n);
    if (t["voltage_v"].contains("improved")) {
        EXPECT_EQ(t["voltage_v"]["improved"].size(), n);
    }
    for (std::size_t k = 1; k < n; ++k)
        if (t["time_s"][k].get<double>() <= t["time_s"][k - 1].get<double>()) {
            ADD_FAILURE() << "trace time not increasing at " << k;
            break;
        }
    // The DEWE stream of the simulated bench measures surface temperature: it is traced too.
    ASSERT_TRUE(t.contains("surface_c")) << "no surface temperature trace";
    EXPECT_EQ(t["surface_c"]["measured"].size(), n);
    EXPECT_EQ(t["surface_c"]["baseline"].size(), n);
}

}  // namespace

TEST(DaemonDiagnoseHil, DiagnosesARunAndAnUploadedRecording) {
    double scale = kTimeScale;
    if (const char* env = std::getenv("CELLBENCH_HIL_TIME_SCALE")) scale = std::atof(env);
    TempDir dir("daemon-diagnose");
    daemon::BenchDaemon d(test::sim_bench_config(kSource / "config/bench.sim.json"),
                          test::daemon_options_in(dir, scale, kToken));
    d.start();
    ASSERT_TRUE(eventually([&] { return instruments_connected(d); }, 20s)) << d.status().dump(2);
    Api api(d.http_port());

    // The parameter sets the dashboard offers.
    {
        const auto r = api.get("/cells");
        ASSERT_EQ(r.result_int(), 200u) << r.body();
        const json c = json::parse(r.body());
        bool thesis = false;
        for (const auto& p : c["parameter_sets"]) thesis |= p["name"] == "p45b-thesis";
        EXPECT_TRUE(thesis) << c.dump();
        bool p45b = false;
        for (const auto& x : c["cells"]) p45b |= x["name"] == "p45b" && x["params"] == "p45b-thesis";
        EXPECT_TRUE(p45b) << c.dump();
    }

    const auto wall0 = std::chrono::steady_clock::now();
    const json started = d.start_run({"hppc_short", "p45b", {{"program", "hppc_short"}, {"cell", "p45b"}}});
    const auto id = started["id"].get<daemon::RunId>();
    const std::string run_path = "/runs/" + std::to_string(id) + "/diagnose";
    // The whole catalogue (the default): a clean simulated bench diagnosed against the parameter set its cell is
    // made of must show nothing significant.
    const std::string body = R"({"params": "p45b-thesis"})";

    // Not while it records.
    EXPECT_TRUE(json_error(api.post(run_path, body), 409));

    const std::string state = test::wait_for_run_end(d, id, 300s, 250ms);
    ASSERT_TRUE(cellbench::test::ended_run_state(state)) << state;
    ASSERT_EQ(state, "completed");
    d.store().flush();
    const double run_wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();

    // Refusals: no token, unknown run, unknown parameter set or effect, a body that is no request.
    EXPECT_TRUE(json_error(api.post(run_path, body, false), 401));
    EXPECT_TRUE(json_error(api.post("/runs/" + std::to_string(id + 100) + "/diagnose", body), 404));
    EXPECT_TRUE(json_error(api.post(run_path, R"({"params": "no-such-cell"})"), 400));
    EXPECT_TRUE(json_error(api.post(run_path, R"({"params": "p45b-thesis", "effects": ["warp_drive"]})"), 400));
    EXPECT_TRUE(json_error(api.post(run_path, R"({"parameters": "p45b-thesis"})"), 400));

    // The run, diagnosed with the parameter set the simulated cell is made of.
    const auto posted = api.post(run_path, body);
    ASSERT_EQ(posted.result_int(), 202u) << posted.body();
    const json job0 = json::parse(posted.body());
    ASSERT_TRUE(job0["id"].is_number_integer()) << job0.dump();
    EXPECT_EQ(job0["state"], "running");
    double run_job_s = 0;
    const json run_job = wait_for_job(api, job0["id"].get<std::int64_t>(), run_job_s);
    {
        std::size_t skipped = 0;
        if (run_job.contains("diagnosis")) skipped = run_job["diagnosis"].value("skipped_in_baseline", json::array()).size();
        expect_report(run_job, "run diagnosis", estimator::effect_catalogue().size() - skipped);
    }
    if (run_job.contains("diagnosis")) {
        for (const auto& f : run_job["diagnosis"]["findings"])
            EXPECT_FALSE(f.value("significant", false))
                << "a clean bench diagnosed against its own parameter set: " << f.dump();
    }
    EXPECT_EQ(run_job["source"]["kind"], "run");
    EXPECT_EQ(run_job["source"]["run_id"], id);

    // The run exported and uploaded back: the same recording, from a file.
    const auto exported = api.get("/runs/" + std::to_string(id) + "/export.bdf.csv");
    ASSERT_EQ(exported.result_int(), 200u);
    const auto uploaded = api.post("/diagnose?params=p45b-thesis&effects=series_resistance_offset,ocv_hysteresis&name=run.bdf.csv",
                                   exported.body(), true, "text/csv");
    ASSERT_EQ(uploaded.result_int(), 202u) << uploaded.body();
    double upload_job_s = 0;
    const json up_job = wait_for_job(api, json::parse(uploaded.body())["id"].get<std::int64_t>(), upload_job_s);
    expect_report(up_job, "uploaded recording", kUploadEffects.size());
    EXPECT_EQ(up_job["source"]["kind"], "upload");
    EXPECT_EQ(up_job["source"]["bytes"].get<std::size_t>(), exported.body().size());
    // Same recording, same parameters: the same baseline.
    if (run_job.contains("diagnosis") && up_job.contains("diagnosis")) {
        EXPECT_NEAR(up_job["diagnosis"]["baseline"]["voltage_rms_v"].get<double>(),
                    run_job["diagnosis"]["baseline"]["voltage_rms_v"].get<double>(), 1e-4);
    }

    // Malformed uploads: 400 JSON at once.
    EXPECT_TRUE(json_error(api.post("/diagnose?params=p45b-thesis", "time,volts\n1,2\n", true, "text/csv"), 400));
    EXPECT_TRUE(json_error(api.post("/diagnose?params=p45b-thesis",
                                    "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,abc,0\n", true, "text/csv"), 400));
    EXPECT_TRUE(json_error(api.post("/diagnose?params=no-such-cell", exported.body(), true, "text/csv"), 400));
    // A second run of the cell: the first one's findings confirmed on it (confirm_runs).
    const auto id2 = d.start_run({"hppc_short", "p45b", {{"program", "hppc_short"}, {"cell", "p45b"}}})["id"].get<daemon::RunId>();
    auto with_confirm = [](const std::string& runs) {
        return R"({"params": "p45b-thesis", "effects": ["series_resistance_offset", "ocv_hysteresis", "initial_soc"], )"
               R"("confirm_runs": )" + runs + "}";
    };
    EXPECT_TRUE(json_error(api.post(run_path, with_confirm("[" + std::to_string(id2) + "]")), 409))
        << "not on a run still recording";
    ASSERT_TRUE(cellbench::test::ended_run_state(test::wait_for_run_end(d, id2, 300s, 250ms)));
    d.store().flush();
    EXPECT_TRUE(json_error(api.post(run_path, with_confirm("[" + std::to_string(id) + "]")), 400)) << "the run itself";
    EXPECT_TRUE(json_error(api.post(run_path, with_confirm("[" + std::to_string(id2 + 100) + "]")), 400)) << "no such run";
    EXPECT_TRUE(json_error(api.post(run_path, with_confirm("\"" + std::to_string(id2) + "\"")), 400)) << "not an array";
    EXPECT_TRUE(json_error(api.post(run_path, with_confirm("[0]")), 400));
    const auto posted2 = api.post(run_path, with_confirm("[" + std::to_string(id2) + "]"));
    ASSERT_EQ(posted2.result_int(), 202u) << posted2.body();
    double confirm_job_s = 0;
    const json confirm_job = wait_for_job(api, json::parse(posted2.body())["id"].get<std::int64_t>(), confirm_job_s);
    ASSERT_EQ(confirm_job["state"], "done") << confirm_job.dump(2);
    EXPECT_EQ(confirm_job["confirm_runs"], json::array({id2}));
    const json& dg2 = confirm_job["diagnosis"];
    EXPECT_EQ(dg2["confirmation"]["recordings"], json::array({"run " + std::to_string(id2)})) << dg2.dump(2);
    ASSERT_EQ(dg2["findings"].size(), 3u);
    for (const auto& f : dg2["findings"]) {
        EXPECT_FALSE(f["significant"].get<bool>()) << "a clean bench: " << f.dump();
        EXPECT_EQ(f["confirmation"].size(), f["effect"] == "initial_soc" ? 0u : 1u) << f.dump();
        for (const auto& c : f["confirmation"]) {
            EXPECT_EQ(c["recording"], "run " + std::to_string(id2));
            EXPECT_TRUE(c["verdict"] == "confirms" || c["verdict"] == "neutral" || c["verdict"] == "contradicts") << c.dump();
        }
    }

    // Every job is listed, newest first.
    const json list = json::parse(api.get("/diagnoses").body());
    ASSERT_GE(list["diagnoses"].size(), 3u);
    EXPECT_FALSE(list["diagnoses"][0].contains("traces"));

    std::printf("hppc_short at time scale %.0f: run %.1f s wall, %zu rows; diagnosis of the run %.1f s, of the "
                "upload %.1f s\n",
                scale, run_wall_s, run_job.contains("traces") ? run_job["traces"]["rows"].get<std::size_t>() : 0u,
                run_job_s, upload_job_s);
    if (run_job.contains("diagnosis"))
        std::printf("baseline voltage RMS %.2f mV, surface temperature RMS %s degC; accepted %s; %zu trace points\n",
                    run_job["diagnosis"]["baseline"]["voltage_rms_v"].get<double>() * 1e3,
                    run_job["diagnosis"]["baseline"]["temperature_rms_c"].dump().c_str(),
                    run_job["diagnosis"]["accepted"].dump().c_str(), run_job["traces"]["time_s"].size());
    d.shutdown();
}
