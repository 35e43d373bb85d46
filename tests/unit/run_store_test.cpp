// The SQLite run store: what the daemon and the REST API rely on. Round trips of every record, decimation that
// keeps spikes, export to a BDF recording, restart recovery (interrupted runs, also after kill -9), readers
// beside a busy writer, clear errors for bad database paths, and faults (disk full, locked) reported, not
// thrown or crashed on.
#include <gtest/gtest.h>

#include <signal.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <fstream>
#include <mutex>
#include <random>
#include <sstream>
#include <thread>

#include "cellbench/daemon/run_store.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

using namespace cellbench;
using namespace cellbench::daemon;
using nlohmann::json;
namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

class RunStoreTest : public ::testing::Test {
protected:
    void SetUp() override {
        std::random_device rd;
        dir_ = fs::temp_directory_path() / ("cellbench-run-store-test-" + std::to_string(::getpid()) + "-" + std::to_string(rd()));
        fs::create_directories(dir_);
        db_ = dir_ / "bench.sqlite";
    }
    void TearDown() override {
        std::error_code ec;
        fs::permissions(dir_, fs::perms::owner_all, fs::perm_options::add, ec);
        fs::remove_all(dir_, ec);
    }

    static NewRun new_run(const std::string& program = "hppc") {
        NewRun r;
        r.program = program;
        r.cell = "p45b";
        r.config = {{"program", {{"name", program}}}, {"parameters", {{"c_rate", 1.0}}}};
        return r;
    }
    // One pulse-set fit through the store (recorded, flushed, read back from a reopened file) as GET
    // /runs/{id}/fits shows it.
    json stored_fit_json(const estimator::PulseSetFit& fit) {
        RunId id = 0;
        {
            auto store = RunStore::open(db_);
            id = store->create_run(new_run("hppc"));
            store->record_pulse_fit(pulse_fit_record(id, 1, 100.0, 1.7e9, fit));
            EXPECT_TRUE(store->flush());
        }
        const auto fits = RunStore::open(db_)->pulse_fits(id);
        EXPECT_EQ(fits.size(), 1u);
        return fits.empty() ? json() : to_json(fits[0]);
    }
    static CyclerSample cycler(double t, double v = 3.7, double i = -4.5) {
        CyclerSample s;
        s.t_s = t;
        s.unix_s = 1.7e9 + t;
        s.voltage_v = v;
        s.current_a = i;
        s.capacity_ah = 0.001 * t;
        s.energy_wh = 0.0037 * t;
        s.soc = 0.9;
        s.step_id = 4;
        s.cycle = 1;
        s.step_type = "dc";
        s.status = "working";
        return s;
    }
    static DaqSample daq(double t, double surface_c) {
        DaqSample s;
        s.t_s = t;
        s.unix_s = 1.7e9 + t;
        s.thermopile_v = 1e-4;
        s.surface_c = surface_c;
        s.t1_c = surface_c + 1.0;
        s.t2_c = surface_c + 0.5;
        s.heat_flux_w_per_m2 = 40.0;
        s.sequence = static_cast<std::int64_t>(t * 10);
        return s;
    }
    static ChamberSample chamber(double t, double ambient_c = 30.0) {
        ChamberSample s;
        s.t_s = t;
        s.unix_s = 1.7e9 + t;
        s.ambient_c = ambient_c;
        s.setpoint_c = 30.0;
        s.running = true;
        s.alarm_bits = 0;
        return s;
    }

    fs::path dir_, db_;
};

std::string open_error(const fs::path& p) {
    try {
        RunStore::open(p);
    } catch (const InputError& e) {
        return e.what();
    }
    return "";
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------

TEST_F(RunStoreTest, EveryRecordRoundTripsAndSurvivesReopening) {
    RunId id = 0, other = 0;
    {
        auto store = RunStore::open(db_);
        id = store->create_run(new_run("hppc"));
        other = store->create_run(new_run("cc"));
        EXPECT_GT(other, id);
        for (int k = 0; k < 100; ++k) EXPECT_TRUE(store->push(id, cycler(k * 0.1)));
        std::vector<DaqSample> d;
        for (int k = 0; k < 1000; ++k) d.push_back(daq(k * 0.01, 30.0));
        EXPECT_EQ(store->push(id, std::span<const DaqSample>(d)), 1000u);
        for (int k = 0; k < 10; ++k) EXPECT_TRUE(store->push(id, chamber(k * 1.0)));

        StepRecord step{1, 2, 4, 1, "cc_discharge", 0.0, 1.7e9, std::nullopt, std::nullopt, std::nullopt, std::nullopt, ""};
        store->record_step(id, step);
        step.ended_t_s = 9.9;
        step.ended_unix_s = 1.7e9 + 9.9;
        step.capacity_ah = 0.0124;
        step.energy_wh = 0.046;
        step.end_reason = "voltage";
        store->record_step(id, step);  // the same step, ended
        store->record_step(id, StepRecord{2, 2, 5, 1, "rest", 9.9, 1.7e9 + 9.9, {}, {}, {}, {}, ""});

        EventRecord e;
        e.run_id = id;
        e.t_s = 5.0;
        e.level = EventLevel::warning;
        e.kind = "alarm";
        e.step = 1;
        e.message = "surface temperature 45 degC";
        e.detail = {{"surface_c", 45.0}};
        store->record_event(e);
        store->record_event(EventRecord{0, std::nullopt, 0.0, std::nullopt, EventLevel::info, "daemon", std::nullopt, "daemon started", nullptr});

        PulseFitRecord f;
        f.run_id = id;
        f.pulse_set = 1;
        f.t_s = 3.0;
        f.soc = 0.9;
        f.ocv_v = 4.05;
        f.temperature_c = 30.2;
        f.discharge = {0.0075, 0.0017, 1215.0, 0.011, 28000.0};
        f.charge = {0.0074, 0.0015, 1300.0, kNaN, kNaN};
        f.method = "joint";
        f.rms_v = 0.0011;
        f.detail = {{"warnings", json::array()}};
        store->record_pulse_fit(f);
        f.rms_v = 0.0009;  // a refit of the same pulse set replaces it
        store->record_pulse_fit(f);

        ParameterSetRecord ps;
        ps.run_id = id;
        ps.cell = "p45b";
        ps.params = {{"schema", "cellbench.params/1"}, {"capacity_ah", 4.4}};
        store->record_parameter_set(ps);
        store->set_run_state(id, RunState::completed, "program finished", 1.7e9 + 100.0);
        ASSERT_TRUE(store->flush());
        const auto st = store->stats();
        EXPECT_EQ(st.samples_written, 1110u);
        EXPECT_EQ(st.samples_dropped, 0u);
        EXPECT_EQ(st.failed_batches, 0u);
        EXPECT_FALSE(st.last_fault.has_value());
    }
    auto store = RunStore::open(db_);  // everything is on disk
    const auto runs = store->list_runs();
    ASSERT_EQ(runs.size(), 2u);
    EXPECT_EQ(runs[0].id, other);  // newest first
    EXPECT_EQ(runs[1].id, id);

    const auto run = store->get_run(id);
    ASSERT_TRUE(run);
    EXPECT_EQ(run->program, "hppc");
    EXPECT_EQ(run->cell, "p45b");
    EXPECT_EQ(run->state, RunState::completed);
    EXPECT_EQ(run->reason, "program finished");
    ASSERT_TRUE(run->ended_unix_s);
    EXPECT_DOUBLE_EQ(*run->ended_unix_s, 1.7e9 + 100.0);
    ASSERT_TRUE(run->started_unix_s);
    EXPECT_EQ(run->cycler_samples, 100);
    EXPECT_EQ(run->daq_samples, 1000);
    EXPECT_EQ(run->chamber_samples, 10);
    EXPECT_EQ(run->config, new_run().config);
    EXPECT_FALSE(store->get_run(9999));

    const auto steps = store->steps(id);
    ASSERT_EQ(steps.size(), 2u);
    EXPECT_EQ(steps[0].type, "cc_discharge");
    EXPECT_EQ(steps[0].end_reason, "voltage");
    ASSERT_TRUE(steps[0].capacity_ah);
    EXPECT_DOUBLE_EQ(*steps[0].capacity_ah, 0.0124);
    EXPECT_FALSE(steps[1].ended_t_s);

    const auto events = store->events(id);
    ASSERT_EQ(events.size(), 1u);
    EXPECT_EQ(events[0].level, EventLevel::warning);
    EXPECT_EQ(events[0].kind, "alarm");
    EXPECT_EQ(events[0].step, 1);
    EXPECT_EQ(events[0].detail, (json{{"surface_c", 45.0}}));
    EXPECT_EQ(store->events(id, events[0].id).size(), 0u);  // paging
    const auto bench_events = store->bench_events();
    ASSERT_EQ(bench_events.size(), 1u);
    EXPECT_EQ(bench_events[0].message, "daemon started");
    EXPECT_GT(bench_events[0].unix_s, 1.6e9);  // stamped now when not given

    const auto fits = store->pulse_fits(id);
    ASSERT_EQ(fits.size(), 1u);
    EXPECT_DOUBLE_EQ(fits[0].discharge.c1_f, 1215.0);
    EXPECT_TRUE(std::isnan(fits[0].charge.r2_ohm));
    EXPECT_DOUBLE_EQ(fits[0].rms_v, 0.0009);
    EXPECT_EQ(fits[0].method, "joint");

    const auto params = store->latest_parameter_set();
    ASSERT_TRUE(params);
    EXPECT_EQ(params->run_id, id);
    EXPECT_DOUBLE_EQ(params->params.at("capacity_ah").get<double>(), 4.4);
    EXPECT_FALSE(store->latest_parameter_set(other));

    const auto j = to_json(*run);
    EXPECT_EQ(j.at("state"), "completed");
    EXPECT_EQ(j.at("samples"), 1110);
}

TEST_F(RunStoreTest, RawRowsReadBackInTheOrderTheyWereStored) {
    // What `cellbench fit --db` replays: every row of one run, in arrival order (not time order), all fields.
    auto store = RunStore::open(db_);
    const RunId id = store->create_run(new_run("hppc"));
    const RunId other = store->create_run(new_run("cc"));
    for (double t : {1.0, 2.0, 0.5, 3.0}) EXPECT_TRUE(store->push(id, cycler(t)));
    EXPECT_TRUE(store->push(other, cycler(9.0)));
    auto live = cycler(3.5, 3.65, 0.0);
    live.step_id = 0;
    live.step_type = "rest";
    live.status = "finish";
    EXPECT_TRUE(store->push(id, live));
    for (int k = 0; k < 5; ++k) EXPECT_TRUE(store->push(id, daq(k * 0.1, 30.0 + k)));
    EXPECT_TRUE(store->push(id, chamber(1.0)));
    ASSERT_TRUE(store->flush());

    const auto c = store->cycler_rows(id);
    ASSERT_EQ(c.size(), 5u);
    EXPECT_EQ((std::vector<double>{c[0].t_s, c[1].t_s, c[2].t_s, c[3].t_s, c[4].t_s}),
              (std::vector<double>{1.0, 2.0, 0.5, 3.0, 3.5}));
    EXPECT_DOUBLE_EQ(c[1].voltage_v, 3.7);
    EXPECT_DOUBLE_EQ(c[1].current_a, -4.5);
    EXPECT_DOUBLE_EQ(c[1].capacity_ah, 0.002);
    EXPECT_EQ(c[1].step_id, 4);
    EXPECT_EQ(c[1].cycle, 1);
    EXPECT_EQ(c[1].step_type, "dc");
    EXPECT_EQ(c[4].status, "finish");
    EXPECT_EQ(c[4].step_id, 0);
    const auto d = store->daq_rows(id);
    ASSERT_EQ(d.size(), 5u);
    EXPECT_DOUBLE_EQ(d[4].t_s, 0.4);
    EXPECT_DOUBLE_EQ(d[4].surface_c, 34.0);
    const auto ch = store->chamber_rows(id);
    ASSERT_EQ(ch.size(), 1u);
    EXPECT_DOUBLE_EQ(ch[0].t_s, 1.0);
    EXPECT_EQ(store->cycler_rows(other).size(), 1u);
    EXPECT_TRUE(store->cycler_rows(999).empty());
}

TEST_F(RunStoreTest, ReadsOnOneConnectionSeeEveryCommitAndTheirOwnArguments) {
    // The reader connections keep their prepared statements between requests: a kept statement must hold no
    // read snapshot (a later read sees what was committed since) and no argument of the read before it.
    auto store = RunStore::open(db_);
    const RunId a = store->create_run(new_run("hppc"));
    const RunId b = store->create_run(new_run("cc"));
    for (int round = 1; round <= 20; ++round) {
        EXPECT_TRUE(store->push(a, cycler(round)));
        EXPECT_TRUE(store->push(a, daq(round, 30.0 + round)));
        if (round % 2 == 0) {
            EXPECT_TRUE(store->push(b, cycler(100.0 + round)));
        }
        ASSERT_TRUE(store->flush());
        const auto ca = store->cycler_rows(a), cb = store->cycler_rows(b);
        ASSERT_EQ(ca.size(), static_cast<std::size_t>(round));
        ASSERT_EQ(cb.size(), static_cast<std::size_t>(round / 2));
        EXPECT_DOUBLE_EQ(ca.back().t_s, round);
        if (!cb.empty()) {
            EXPECT_DOUBLE_EQ(cb.back().t_s, 100.0 + 2 * (round / 2));
        }
        const auto w = store->samples(a, std::nullopt, std::nullopt, 1000);
        const auto* daq_window = w.source("daq");
        ASSERT_NE(daq_window, nullptr);
        ASSERT_EQ(daq_window->size(), static_cast<std::size_t>(round));
        const RunId asked = round % 2 ? a : b;
        const auto info = store->get_run(asked);
        ASSERT_TRUE(info);
        EXPECT_EQ(info->id, asked);
        EXPECT_EQ(info->cycler_samples, asked == a ? round : round / 2);
    }
}

TEST_F(RunStoreTest, TheFirstTerminalStateWins) {
    auto store = RunStore::open(db_);
    const RunId id = store->create_run(new_run());
    store->set_run_state(id, RunState::paused);
    store->set_run_state(id, RunState::aborted, "cell above 60 degC");
    store->set_run_state(id, RunState::completed, "program finished");
    ASSERT_TRUE(store->flush());
    const auto run = store->get_run(id);
    EXPECT_EQ(run->state, RunState::aborted);
    EXPECT_EQ(run->reason, "cell above 60 degC");
}

TEST_F(RunStoreTest, DecimationKeepsSpikesAndSmallWindowsAreRaw) {
    auto store = RunStore::open(db_);
    const RunId id = store->create_run(new_run());
    std::vector<CyclerSample> rows;
    for (int k = 0; k < 10000; ++k) {
        double v = 3.7;
        if (k == 4321) v = 4.5;  // one-sample spike
        if (k == 7000) v = 2.5;  // one-sample dip
        rows.push_back(cycler(k / 10.0, v));
    }
    ASSERT_EQ(store->push(id, std::span<const CyclerSample>(rows)), rows.size());
    ASSERT_TRUE(store->flush());

    const auto w = store->samples(id, std::nullopt, std::nullopt, 200);
    EXPECT_TRUE(w.decimated);
    EXPECT_EQ(w.bucket_count, 100u);
    EXPECT_DOUBLE_EQ(w.from_s, 0.0);
    EXPECT_DOUBLE_EQ(w.to_s, 999.9);
    const auto* c = w.source("cycler");
    ASSERT_NE(c, nullptr);
    EXPECT_LE(c->size(), 100u);
    const auto v = c->channel("voltage_v");
    ASSERT_NE(v, static_cast<std::size_t>(-1));
    EXPECT_DOUBLE_EQ(*std::max_element(c->max[v].begin(), c->max[v].end()), 4.5);
    EXPECT_DOUBLE_EQ(*std::min_element(c->min[v].begin(), c->min[v].end()), 2.5);
    std::uint64_t total = 0;
    for (auto n : c->count) total += n;
    EXPECT_EQ(total, 10000u);
    // The spike's bucket starts at or before the spike.
    const auto spike = std::max_element(c->max[v].begin(), c->max[v].end()) - c->max[v].begin();
    EXPECT_LE(c->time_s[static_cast<std::size_t>(spike)], 432.1);
    EXPECT_GT(c->time_s[static_cast<std::size_t>(spike)] + w.bucket_s, 432.1);
    EXPECT_EQ(w.source("daq"), nullptr);  // not measured in this run

    // Narrow buckets (1 s) come from the rows, wide ones from the 1-second rollups plus the rows of the partial
    // seconds at the window's edges: both count every sample in the window exactly once and keep the extremes.
    const auto sum = [](const SourceWindow& sw) {
        std::uint64_t n = 0;
        for (auto k : sw.count) n += k;
        return n;
    };
    const auto narrow = store->samples(id, 0.0, 100.0, 200);
    ASSERT_TRUE(narrow.decimated);
    EXPECT_DOUBLE_EQ(narrow.bucket_s, 1.0);
    EXPECT_EQ(sum(*narrow.source("cycler")), 1001u);
    const auto& nv = narrow.source("cycler")->max[v];
    EXPECT_DOUBLE_EQ(*std::max_element(nv.begin(), nv.end()), 3.7);
    const auto wide = store->samples(id, 100.05, 900.05, 200);
    ASSERT_TRUE(wide.decimated);
    EXPECT_EQ(sum(*wide.source("cycler")), 8000u);  // t = 100.1 ... 900.0
    const auto* wc = wide.source("cycler");
    EXPECT_DOUBLE_EQ(*std::max_element(wc->max[v].begin(), wc->max[v].end()), 4.5);
    EXPECT_DOUBLE_EQ(*std::min_element(wc->min[v].begin(), wc->min[v].end()), 2.5);
    for (std::size_t k = 1; k < wc->size(); ++k) EXPECT_GT(wc->bucket[k], wc->bucket[k - 1]);

    // A window small enough is returned as recorded.
    const auto raw = store->samples(id, 100.0, 110.0, 200);
    EXPECT_FALSE(raw.decimated);
    const auto* r = raw.source("cycler");
    ASSERT_NE(r, nullptr);
    EXPECT_EQ(r->size(), 101u);  // 100.0, 100.1, ..., 110.0 (inclusive)
    EXPECT_NEAR(r->time_s.front(), 100.0, 1e-9);
    EXPECT_DOUBLE_EQ(r->min[v][0], 3.7);
    const auto j = to_json(raw);
    EXPECT_EQ(j.at("sources").at("cycler").at("series").at("voltage_v").size(), 101u);
}

// The dashboard's whole-run and 10-minute views: a single DAQ sample (100 Hz heat flux) far off the rest must be
// in the decimated window, both through the 1-second rollups (wide buckets) and through the rows (narrow ones).
TEST_F(RunStoreTest, ASingleSampleSpikeSurvivesDecimationOfEveryChannel) {
    auto store = RunStore::open(db_);
    const RunId id = store->create_run(new_run());
    std::vector<DaqSample> rows;
    constexpr int kSpike = 73457;  // t = 734.57 s, inside a rollup second, not on a bucket edge
    for (int k = 0; k < 120000; ++k) {  // 20 minutes at 100 Hz
        DaqSample s = daq(k / 100.0, 30.0);
        if (k == kSpike) {
            s.heat_flux_w_per_m2 = 900.0;
            s.t1_c = 80.0;
        }
        if (k == kSpike + 1000) s.surface_c = -5.0;  // a one-sample dip on another channel
        rows.push_back(s);
    }
    ASSERT_EQ(store->push(id, std::span<const DaqSample>(rows)), rows.size());
    ASSERT_TRUE(store->flush());

    const auto check = [&](const SampleWindow& w, bool expect_dip) {
        ASSERT_TRUE(w.decimated);
        const auto* d = w.source("daq");
        ASSERT_NE(d, nullptr);
        const auto hf = d->channel("heat_flux_w_per_m2"), t1 = d->channel("t1_c"), sc = d->channel("surface_c");
        ASSERT_NE(hf, std::string::npos);
        EXPECT_DOUBLE_EQ(*std::max_element(d->max[hf].begin(), d->max[hf].end()), 900.0);
        EXPECT_DOUBLE_EQ(*std::min_element(d->min[hf].begin(), d->min[hf].end()), 40.0);
        EXPECT_DOUBLE_EQ(*std::max_element(d->max[t1].begin(), d->max[t1].end()), 80.0);
        if (expect_dip) {
            EXPECT_DOUBLE_EQ(*std::min_element(d->min[sc].begin(), d->min[sc].end()), -5.0);
        }
        // Exactly one bucket holds the spike, and it is the one whose span contains t = 734.57 s.
        std::size_t holding = 0;
        for (std::size_t k = 0; k < d->size(); ++k) {
            if (d->max[hf][k] != 900.0) continue;
            ++holding;
            EXPECT_LE(d->time_s[k], 734.57);
            EXPECT_GT(d->time_s[k] + w.bucket_s + 1.0, 734.57);  // rollup seconds are placed by their first sample
        }
        EXPECT_EQ(holding, 1u);
    };
    check(store->samples(id, std::nullopt, std::nullopt, 200), true);  // whole run: 12 s buckets from the rollups
    check(store->samples(id, 600.0, 1200.0, 200), true);               // 10 minutes in 6 s buckets (rollups)
    check(store->samples(id, 600.0, 1200.0, 2000), true);              // 10 minutes in 0.6 s buckets (rows)
    check(store->samples(id, 734.0, 735.0, 10), false);                // 0.2 s buckets (rows)
}

TEST_F(RunStoreTest, ExportGivesOneRecordingOnTheCyclerTimeBase) {
    auto store = RunStore::open(db_);
    const RunId id = store->create_run(new_run());
    for (int k = 0; k <= 100; ++k) store->push(id, cycler(k, 3.7 - 0.001 * k, k < 50 ? -4.5 : 4.5));
    // DAQ at 10 Hz, surface = 25 + 0.01 t, silent from 40 s to 60 s.
    for (int k = 0; k <= 1000; ++k) {
        const double t = k * 0.1;
        if (t > 40.05 && t < 59.95) continue;
        store->push(id, daq(t, 25.0 + 0.01 * t));
    }
    for (int k = 0; k <= 50; ++k) store->push(id, chamber(2.0 * k + 0.5, 30.0));
    ASSERT_TRUE(store->flush());

    const Recording rec = store->export_recording(id);
    ASSERT_EQ(rec.size(), 101u);
    EXPECT_DOUBLE_EQ(rec.time_s[10], 10.0);
    EXPECT_DOUBLE_EQ(rec.voltage_v[10], 3.69);
    EXPECT_DOUBLE_EQ(rec.current_a[10], -4.5);  // + = charge, as stored
    EXPECT_DOUBLE_EQ(rec.current_a[60], 4.5);
    ASSERT_EQ(rec.unix_time_s.size(), 101u);
    EXPECT_DOUBLE_EQ(rec.unix_time_s[10], 1.7e9 + 10.0);
    ASSERT_EQ(rec.step_type.size(), 101u);
    EXPECT_EQ(rec.step_type[0], "dc");
    EXPECT_DOUBLE_EQ(rec.step_count[0], 4.0);
    ASSERT_EQ(rec.surface_c.size(), 101u);
    EXPECT_NEAR(rec.surface_c[10], 25.1, 1e-9);
    EXPECT_NEAR(rec.t1_c[30], 26.3, 1e-9);
    EXPECT_TRUE(std::isnan(rec.surface_c[50])) << "the DAQ was silent: no invented data";
    EXPECT_NEAR(rec.heat_flux_w_per_m2[70], 40.0, 1e-9);
    ASSERT_EQ(rec.ambient_c.size(), 101u);
    EXPECT_NEAR(rec.ambient_c[50], 30.0, 1e-12);  // interpolated between 2 s chamber samples
    EXPECT_TRUE(std::isnan(rec.ambient_c[0])) << "before the chamber's first sample";

    // It writes and reads back as BDF.
    std::ostringstream out;
    protocol::write_bdf_csv(out, rec);
    const Recording back = protocol::parse_bdf_csv(out.str(), "export.bdf.csv");
    ASSERT_EQ(back.size(), rec.size());
    for (std::size_t k = 0; k < rec.size(); ++k)  // written at the instruments' resolution (0.1 mV and finer)
        EXPECT_NEAR(back.voltage_v[k], rec.voltage_v[k], 1e-9) << k;
    EXPECT_NEAR(back.surface_c[10], 25.1, 1e-9);

    // A window of it (paging a long run).
    const Recording part = store->export_recording(id, 20.0, 29.0);
    ASSERT_EQ(part.size(), 10u);
    EXPECT_DOUBLE_EQ(part.time_s.front(), 20.0);
    // An empty run exports as an empty recording.
    const RunId empty = store->create_run(new_run());
    EXPECT_TRUE(store->export_recording(empty).empty());
}

TEST_F(RunStoreTest, RunsLeftLiveAreMarkedInterruptedAtRestart) {
    RunId live = 0, done = 0, paused = 0;
    {
        auto store = RunStore::open(db_);
        done = store->create_run(new_run());
        store->set_run_state(done, RunState::completed, "program finished");
        NewRun nr = new_run();
        nr.created_unix_s = 1.7e9;  // the samples' clock
        live = store->create_run(nr);
        for (int k = 0; k < 50; ++k) store->push(live, cycler(k));
        store->push(live, daq(55.0, 30.0));  // the latest sample of any source sets the end
        paused = store->create_run(new_run());
        store->set_run_state(paused, RunState::paused);
        ASSERT_TRUE(store->flush());
    }  // closed without ending the runs: as after a crash
    auto store = RunStore::open(db_);
    auto ids = store->mark_interrupted_runs();
    std::sort(ids.begin(), ids.end());
    EXPECT_EQ(ids, (std::vector<RunId>{live, paused}));
    const auto run = store->get_run(live);
    EXPECT_EQ(run->state, RunState::interrupted);
    ASSERT_TRUE(run->ended_unix_s);
    EXPECT_DOUBLE_EQ(*run->ended_unix_s, 1.7e9 + 55.0);
    EXPECT_FALSE(run->reason.empty());
    EXPECT_EQ(store->get_run(done)->state, RunState::completed);
    EXPECT_TRUE(store->mark_interrupted_runs().empty());  // only once
}

TEST_F(RunStoreTest, ReadersSeeCommittedDataWhileTheWriterRuns) {
    RunStoreOptions opt;
    opt.flush_period = 20ms;
    auto store = RunStore::open(db_, opt);
    const RunId id = store->create_run(new_run());
    constexpr int kTotal = 60000;
    std::atomic<bool> done{false};
    std::thread producer([&] {
        for (int k = 0; k < kTotal;) {
            std::vector<DaqSample> chunk;
            for (int n = 0; n < 500; ++n, ++k) chunk.push_back(daq(k * 0.01, 30.0));
            std::size_t pushed = 0;
            while (pushed < chunk.size())  // the queue never overflows here, but be exact
                pushed += store->push(id, std::span<const DaqSample>(chunk).subspan(pushed));
            std::this_thread::sleep_for(1ms);
        }
        store->flush();
        done = true;
    });
    std::int64_t last = 0;
    int reads = 0;
    while (true) {
        const bool finished = done.load();
        const auto run = store->get_run(id);
        ASSERT_TRUE(run);
        EXPECT_GE(run->daq_samples, last) << "a reader went back in time";
        last = run->daq_samples;
        const auto w = store->samples(id, std::nullopt, std::nullopt, 500);
        if (const auto* d = w.source("daq")) {
            std::uint64_t n = 0;
            for (auto c : d->count) n += c;
            EXPECT_GE(n, static_cast<std::uint64_t>(last));  // the window was read after the counter
        }
        ++reads;
        if (finished) break;
    }
    producer.join();
    EXPECT_EQ(last, kTotal);
    EXPECT_GT(reads, 1);
}

TEST_F(RunStoreTest, IntegrityHoldsAfterHeavyWrites) {
    RunStoreOptions opt;
    opt.flush_rows = 5000;
    auto store = RunStore::open(db_, opt);
    std::vector<RunId> ids{store->create_run(new_run()), store->create_run(new_run())};
    std::vector<std::thread> writers;
    for (int w = 0; w < 3; ++w) {
        writers.emplace_back([&, w] {
            for (int k = 0; k < 50000; ++k) {
                const RunId id = ids[static_cast<std::size_t>(k % 2)];
                const double t = k * 0.01;
                if (w == 0) while (!store->push(id, cycler(t))) std::this_thread::yield();
                if (w == 1) while (!store->push(id, daq(t, 30.0))) std::this_thread::yield();
                if (w == 2) {
                    while (!store->push(id, chamber(t))) std::this_thread::yield();
                    if (k % 1000 == 0)
                        store->record_event({0, id, 0.0, t, EventLevel::info, "step", std::nullopt, "tick", {{"k", k}}});
                }
            }
        });
    }
    for (auto& t : writers) t.join();
    ASSERT_TRUE(store->flush());
    EXPECT_EQ(store->integrity_check(), "ok");
    const auto a = store->get_run(ids[0]);
    const auto b = store->get_run(ids[1]);
    EXPECT_EQ(a->cycler_samples + b->cycler_samples, 50000);
    EXPECT_EQ(a->daq_samples + b->daq_samples, 50000);
    EXPECT_EQ(a->chamber_samples + b->chamber_samples, 50000);
    EXPECT_EQ(store->events(ids[0]).size() + store->events(ids[1]).size(), 50u);
    EXPECT_EQ(store->stats().samples_written, 150000u);
}

// Between runs the daemon gives memory back: the store's page caches first, then malloc_trim. The trim must
// come after the writer has freed its cache (it does so at its next commit), else the whole cache (up to 16
// MiB) stays resident as free heap (issue 14's soak: RSS after the last run +17-21 % over the first). The
// future release_memory() returns is that moment: when it is ready, SQLite's memory is down.
TEST_F(RunStoreTest, ReleaseMemoryIsReadyOnceTheWritersPageCacheIsFreed) {
    RunStoreOptions opt;
    opt.flush_period = std::chrono::milliseconds(500);  // the writer commits on its own rhythm, not at the call
    auto store = RunStore::open(db_, opt);
    const RunId id = store->create_run(new_run());
    for (int k = 0; k < 60000; ++k) {
        const double t = k * 0.1;
        while (!store->push(id, cycler(t, 3.0 + 1e-5 * k))) std::this_thread::yield();
        while (!store->push(id, daq(t, 30.0 + 1e-4 * k))) std::this_thread::yield();
    }
    ASSERT_TRUE(store->flush());
    const auto cached = sqlite3_memory_used();
    ASSERT_GT(cached, 4 << 20) << "the writer's page cache should hold several MiB after 120 000 rows";
    auto released = store->release_memory();
    ASSERT_TRUE(released.valid());
    ASSERT_EQ(released.wait_for(10s), std::future_status::ready);
    const auto after = sqlite3_memory_used();
    EXPECT_LT(after, cached / 2) << "SQLite still holds " << after << " of " << cached << " bytes when the future is ready";
    // A read-only or closed store has no writer cache: ready at once.
    store->close();
    EXPECT_EQ(store->release_memory().wait_for(0s), std::future_status::ready);
}

// ---------------------------------------------------------------------------------------------------------
// Bad paths and faults

TEST_F(RunStoreTest, BadDatabasePathsGiveAClearError) {
    std::string e = open_error(dir_ / "no-such-folder" / "bench.sqlite");
    EXPECT_NE(e.find("no-such-folder"), std::string::npos) << e;
    EXPECT_NE(e.find("does not exist"), std::string::npos) << e;

    e = open_error(dir_);  // a folder
    EXPECT_NE(e.find("cannot use as the run database"), std::string::npos) << e;

    const fs::path garbage = dir_ / "garbage.sqlite";
    std::ofstream(garbage) << std::string(8192, 'x');
    e = open_error(garbage);
    EXPECT_NE(e.find("not an SQLite database"), std::string::npos) << e;

    const fs::path foreign = dir_ / "foreign.sqlite";
    {
        sqlite3* db = nullptr;
        ASSERT_EQ(sqlite3_open(foreign.c_str(), &db), SQLITE_OK);
        sqlite3_stmt* s = nullptr;
        sqlite3_prepare_v2(db, "CREATE TABLE invoices(id INTEGER)", -1, &s, nullptr);
        sqlite3_step(s);
        sqlite3_finalize(s);
        sqlite3_close(db);
    }
    e = open_error(foreign);
    EXPECT_NE(e.find("another application"), std::string::npos) << e;

    try {
        RunStore::open_readonly(dir_ / "missing.sqlite");
        ADD_FAILURE() << "opened a missing file read-only";
    } catch (const InputError& err) {
        EXPECT_NE(std::string(err.what()).find("no such file"), std::string::npos) << err.what();
    }
}

TEST_F(RunStoreTest, AnUnwritableLocationGivesAClearError) {
    // /proc takes no new files, whoever runs the test.
    const std::string e = open_error("/proc/cellbench-run-store-test.sqlite");
    EXPECT_NE(e.find("/proc/cellbench-run-store-test.sqlite: cannot use as the run database: cannot create files in "
                     "the folder /proc"),
              std::string::npos)
        << e;
    EXPECT_NE(e.find("must be writable"), std::string::npos) << e;
}

TEST_F(RunStoreTest, AReadOnlyFolderGivesAClearError) {
    if (::geteuid() == 0) GTEST_SKIP() << "root ignores file permissions";
    const fs::path ro = dir_ / "ro";
    fs::create_directories(ro);
    fs::permissions(ro, fs::perms::owner_read | fs::perms::owner_exec);
    const std::string e = open_error(ro / "bench.sqlite");
    EXPECT_NE(e.find((ro / "bench.sqlite").string()), std::string::npos) << e;
    fs::permissions(ro, fs::perms::owner_all);
}

TEST_F(RunStoreTest, AClosedOrReadOnlyStoreRefusesWritesClearly) {
    auto store = RunStore::open(db_);
    const RunId id = store->create_run(new_run());
    store->push(id, cycler(0.0));
    store->close();  // commits what was queued
    EXPECT_FALSE(store->push(id, cycler(1.0)));
    try {
        store->create_run(new_run());
        ADD_FAILURE() << "a closed store created a run";
    } catch (const StoreError& e) {
        EXPECT_EQ(e.kind(), StoreFaultKind::closed);
        EXPECT_NE(std::string(e.what()).find("closed"), std::string::npos);
    }
    EXPECT_THROW((void)store->get_run(id), StoreError);

    auto ro = RunStore::open_readonly(db_);
    EXPECT_TRUE(ro->read_only());
    EXPECT_EQ(ro->get_run(id)->cycler_samples, 1);
    EXPECT_EQ(ro->export_recording(id).size(), 1u);
    try {
        ro->create_run(new_run());
        ADD_FAILURE() << "a read-only store created a run";
    } catch (const StoreError& e) {
        EXPECT_EQ(e.kind(), StoreFaultKind::readonly);
    }
    EXPECT_FALSE(ro->push(id, cycler(2.0)));
}

TEST_F(RunStoreTest, DiskFullIsReportedAndTheFileStaysSound) {
    std::mutex mu;
    std::vector<StoreFault> faults;
    RunStoreOptions opt;
    opt.max_page_count = 120;  // ~480 kB: a full disk after a few thousand rows
    opt.on_fault = [&](const StoreFault& f) {
        std::lock_guard lk(mu);
        faults.push_back(f);
    };
    auto store = RunStore::open(db_, opt);
    const RunId id = store->create_run(new_run());
    for (int k = 0; k < 50000; ++k) {
        store->push(id, cycler(k * 0.01));
        if (k % 5000 == 0) store->flush();
    }
    ASSERT_TRUE(store->flush());
    {
        std::lock_guard lk(mu);
        ASSERT_FALSE(faults.empty());
        EXPECT_EQ(faults.front().kind, StoreFaultKind::disk_full);
        EXPECT_NE(faults.front().message.find("disk full"), std::string::npos) << faults.front().message;
        EXPECT_GT(faults.front().samples_lost, 0u);
    }
    const auto st = store->stats();
    EXPECT_GT(st.samples_lost, 0u);
    EXPECT_EQ(st.samples_lost + st.samples_written, 50000u);
    ASSERT_TRUE(st.last_fault);
    // Reads still work and the committed part is consistent.
    const auto run = store->get_run(id);
    ASSERT_TRUE(run);
    EXPECT_EQ(static_cast<std::uint64_t>(run->cycler_samples), st.samples_written);
    EXPECT_EQ(store->integrity_check(), "ok");
}

// The run's abort on a full disk must reach the database or the sidecar, whatever failed before it. A record
// that failed on the full disk leaves its statement stopped on the error; SQLite refuses to bind such a
// statement again (SQLITE_MISUSE, "bad parameter or other API misuse"), which once made the abort record that
// followed a failed event a non-transient fault, dropped. Found by the disk-full HIL test under load in CI.
TEST_F(RunStoreTest, RecordsAfterAFailedRecordOnAFullDiskAreKeptNotDropped) {
    std::mutex mu;
    std::vector<StoreFault> faults;
    RunStoreOptions opt;
    opt.max_page_count = 120;
    opt.on_fault = [&](const StoreFault& f) {
        std::lock_guard lk(mu);
        faults.push_back(f);
    };
    RunId id = 0;
    {
        auto store = RunStore::open(db_, opt);
        id = store->create_run(new_run());
        store->set_run_state(id, RunState::running);
        for (int k = 0; k < 50000 && store->stats().samples_lost == 0; ++k) {
            store->push(id, cycler(k * 0.01));
            if (k % 1000 == 0) store->flush();
        }
        ASSERT_TRUE(store->flush());
        ASSERT_GT(store->stats().samples_lost, 0u) << "the size limit was never reached";
        // An event too large for the full file fails inside its own statement ...
        EventRecord big{0, id, 0.0, 1.0, EventLevel::warning, "fault", std::nullopt, std::string(400000, 'x'), nullptr};
        store->record_event(big);
        ASSERT_TRUE(store->flush());
        // ... and the next ones must bind that statement again: the abort and its event.
        store->set_run_state(id, RunState::aborted, "database full");
        store->record_event(EventRecord{0, id, 0.0, 2.0, EventLevel::error, "abort", std::nullopt, "run aborted: database full", nullptr});
        ASSERT_TRUE(store->flush());
        store->close();
    }
    {
        std::lock_guard lk(mu);
        for (const auto& f : faults)
            EXPECT_EQ(f.message.find("misuse"), std::string::npos) << f.message;
    }
    auto reopened = RunStore::open(db_);  // no size limit: space freed; a sidecar is imported first
    ASSERT_TRUE(reopened->flush());
    const auto run = reopened->get_run(id);
    ASSERT_TRUE(run);
    EXPECT_EQ(run->state, RunState::aborted);
    const auto ev = reopened->events(id);
    EXPECT_TRUE(std::any_of(ev.begin(), ev.end(), [](const EventRecord& e) { return e.kind == "abort"; }));
}

TEST_F(RunStoreTest, ALockedDatabaseIsReportedAndTheStoreRecovers) {
    std::atomic<int> busy{0};
    RunStoreOptions opt;
    opt.busy_timeout = 50ms;
    opt.on_fault = [&](const StoreFault& f) {
        if (f.kind == StoreFaultKind::busy) ++busy;
    };
    auto store = RunStore::open(db_, opt);
    const RunId id = store->create_run(new_run());

    sqlite3* other = nullptr;  // another process holding the write lock
    ASSERT_EQ(sqlite3_open(db_.c_str(), &other), SQLITE_OK);
    sqlite3_stmt* s = nullptr;
    ASSERT_EQ(sqlite3_prepare_v2(other, "BEGIN IMMEDIATE", -1, &s, nullptr), SQLITE_OK);
    ASSERT_EQ(sqlite3_step(s), SQLITE_DONE);
    sqlite3_finalize(s);

    for (int k = 0; k < 100; ++k) store->push(id, cycler(k));
    ASSERT_TRUE(store->flush());
    EXPECT_GE(busy.load(), 1);
    EXPECT_EQ(store->stats().samples_lost, 100u);
    EXPECT_EQ(store->get_run(id)->cycler_samples, 0);  // readers are not blocked by the lock

    ASSERT_EQ(sqlite3_prepare_v2(other, "COMMIT", -1, &s, nullptr), SQLITE_OK);
    ASSERT_EQ(sqlite3_step(s), SQLITE_DONE);
    sqlite3_finalize(s);
    sqlite3_close(other);

    for (int k = 100; k < 200; ++k) store->push(id, cycler(k));
    ASSERT_TRUE(store->flush());
    EXPECT_EQ(store->get_run(id)->cycler_samples, 100);
}

TEST_F(RunStoreTest, AFullQueueRefusesNewSamplesAndSaysSo) {
    std::atomic<std::uint64_t> overflowed{0};
    RunStoreOptions opt;
    opt.queue_capacity_samples = 1000;
    opt.on_fault = [&](const StoreFault& f) {
        if (f.kind == StoreFaultKind::overflow) overflowed += f.samples_lost;
    };
    auto store = RunStore::open(db_, opt);
    const RunId id = store->create_run(new_run());
    std::vector<CyclerSample> rows;
    for (int k = 0; k < 5000; ++k) rows.push_back(cycler(k * 0.01));
    EXPECT_EQ(store->push(id, std::span<const CyclerSample>(rows)), 1000u);  // one call: exactly the bound
    ASSERT_TRUE(store->flush());
    EXPECT_EQ(overflowed.load(), 4000u);
    EXPECT_EQ(store->stats().samples_dropped, 4000u);
    EXPECT_EQ(store->get_run(id)->cycler_samples, 1000);
    // Samples without a time are refused (a NULL time would fail the whole batch).
    EXPECT_FALSE(store->push(id, cycler(kNaN)));
}

TEST_F(RunStoreTest, KillNineLeavesASoundFileAndTheRunIsMarkedInterrupted) {
    int fds[2];
    ASSERT_EQ(::pipe(fds), 0);
    const pid_t pid = ::fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {  // child: a daemon writing as fast as it can
        ::close(fds[0]);
        try {
            RunStoreOptions opt;
            opt.flush_period = 50ms;
            auto store = RunStore::open(db_, opt);
            const RunId id = store->create_run(new_run());
            const auto start = std::chrono::steady_clock::now();
            for (int k = 0;; ++k) {
                store->push(id, cycler(k * 0.001));
                store->push(id, daq(k * 0.001, 30.0));
                if (k == 1000) {
                    store->flush();
                    if (::write(fds[1], &id, sizeof id) != sizeof id) ::_exit(4);
                }
                if (k % 100 == 0) std::this_thread::sleep_for(100us);
                if (std::chrono::steady_clock::now() - start > 60s) ::_exit(5);  // never outlive a dead parent
            }
        } catch (...) {
            ::_exit(3);
        }
    }
    ::close(fds[1]);
    RunId id = 0;
    ASSERT_EQ(::read(fds[0], &id, sizeof id), static_cast<ssize_t>(sizeof id));
    ::close(fds[0]);
    std::this_thread::sleep_for(300ms);  // mid-stream, most likely mid-transaction
    ::kill(pid, SIGKILL);
    int status = 0;
    ::waitpid(pid, &status, 0);
    ASSERT_TRUE(WIFSIGNALED(status));

    auto store = RunStore::open(db_);
    EXPECT_EQ(store->integrity_check(), "ok");
    EXPECT_EQ(store->mark_interrupted_runs(), std::vector<RunId>{id});
    const auto run = store->get_run(id);
    ASSERT_TRUE(run);
    EXPECT_EQ(run->state, RunState::interrupted);
    EXPECT_GE(run->cycler_samples, 1001);
    // The counters are committed with the rows they count.
    EXPECT_EQ(static_cast<std::int64_t>(store->export_recording(id).size()), run->cycler_samples);
}

TEST(RunStorePulseFit, TheRecordTakesTheChosenMethodWithCapacitancesFromTimeConstants) {
    estimator::PulseSetFit fit;
    fit.soc = 0.8;
    fit.ocv_v = 3.96;
    fit.temperature_c = 30.1;
    fit.joint_discharge = {0.0075, 0.0017, 2.0, 0.011, 300.0};
    fit.joint_charge = {0.0074, 0.0015, 1.8, 0.010, 280.0};
    fit.thesis_discharge = {0.0076, 0.0018, 2.1, 0.012, 310.0};
    fit.joint_rms_v = 0.0008;
    fit.thesis_rms_v = 0.0012;
    fit.chosen = estimator::PulseSetFit::Method::Joint;
    fit.warnings = {"tau2 near its bound"};
    const auto r = pulse_fit_record(7, 3, 4200.0, 1.7e9, fit);
    EXPECT_EQ(r.run_id, 7);
    EXPECT_EQ(r.pulse_set, 3);
    EXPECT_DOUBLE_EQ(r.discharge.r0_ohm, 0.0075);
    EXPECT_DOUBLE_EQ(r.discharge.c1_f, 2.0 / 0.0017);
    EXPECT_DOUBLE_EQ(r.charge.c2_f, 280.0 / 0.010);
    EXPECT_DOUBLE_EQ(r.rms_v, 0.0008);
    EXPECT_EQ(r.method, estimator::to_string(estimator::PulseSetFit::Method::Joint));
    EXPECT_EQ(r.detail.at("warnings").size(), 1u);
    const auto j = to_json(r);
    EXPECT_DOUBLE_EQ(j.at("discharge").at("r1_ohm").get<double>(), 0.0017);
    EXPECT_DOUBLE_EQ(j.at("soc").get<double>(), 0.8);
}

// Issue 11: an online fit's value that is physically implausible or less certain than itself is flagged in
// GET /runs/{id}/fits (with its sigma), and the flags survive the store.
TEST_F(RunStoreTest, PulseFitValuesCarryTheirSigmaAndFlagsThroughTheStore) {
    estimator::PulseSetFit fit;
    fit.soc = 0.9;
    fit.ocv_v = 4.0;
    // Discharge: the first pulse set of issue 11 (R1 0.002 mOhm: below any cell), R2 known to 10 %.
    fit.joint_discharge = {0.0075, 2e-6, 1.0, 0.011, 300.0};
    fit.joint_discharge_sigma = {0.0001, 1e-6, 0.5, 0.0011, 30.0};
    // Charge: plausible values, but R2's sigma is twice R2 (the slow pair not identified by the pulse).
    fit.joint_charge = {0.0074, 0.0015, 1.8, 0.010, 280.0};
    fit.joint_charge_sigma = {0.0001, 0.0001, 0.1, 0.020, 400.0};
    fit.chosen = estimator::PulseSetFit::Method::Joint;
    const auto j = stored_fit_json(fit);
    ASSERT_FALSE(j.is_null());
    const auto& d = j.at("discharge");
    EXPECT_EQ(d.at("flags").at("r1_ohm"), json::array({"implausible"}));
    EXPECT_FALSE(d.at("flags").contains("r2_ohm")) << d.dump();
    EXPECT_FALSE(d.at("flags").contains("r0_ohm")) << d.dump();
    EXPECT_DOUBLE_EQ(d.at("r2_ohm_sd").get<double>(), 0.0011);
    // C2 = tau2 / R2: its sigma from both relative sigmas (10 % each).
    EXPECT_NEAR(d.at("c2_f_sd").get<double>(), 300.0 / 0.011 * std::hypot(0.1, 0.1), 1e-6);
    const auto& c = j.at("charge");
    EXPECT_EQ(c.at("flags").at("r2_ohm"), json::array({"uncertain"}));
    EXPECT_EQ(c.at("flags").at("c2_f"), json::array({"uncertain"}));
    EXPECT_FALSE(c.at("flags").contains("r0_ohm"));
}

// A value the fit gives no uncertainty for (the thesis' per-segment fits have no covariance) carries the flag
// "no_uncertainty" with its null sigma: never a made-up sigma, and never shown as fine.
TEST_F(RunStoreTest, PulseFitValuesWithoutASigmaAreFlagged) {
    estimator::PulseSetFit fit;
    fit.soc = 0.8;
    fit.ocv_v = 3.9;
    fit.thesis_discharge = {0.0075, 0.0015, 1.8, 0.009, 250.0};
    fit.thesis_charge = {0.0074, 0.0014, 1.6, 0.010, 240.0};
    fit.chosen = estimator::PulseSetFit::Method::Thesis;
    const auto j = stored_fit_json(fit);
    ASSERT_FALSE(j.is_null());
    for (const char* dir : {"discharge", "charge"})
        for (const char* k : {"r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f"}) {
            const auto& d = j.at(dir);
            EXPECT_TRUE(d.at(std::string(k) + "_sd").is_null()) << dir << " " << k;
            EXPECT_EQ(d.at("flags").value(k, json()), json::array({"no_uncertainty"})) << dir << " " << k << ": " << d.dump();
        }
}
