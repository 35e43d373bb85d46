// cellbenchd end to end, in process: BenchDaemon on config/bench.sim.json hosts the simulated Neware tester,
// Modbus chamber and DEWE CAN stream on loopback, connects the real drivers to them and runs programs through
// the sequencer into the run store.
//  - The FULL HPPC (config/programs/hppc.json: pilot discharge, pulse sets 100 % -> 10 % SOC, final discharge
//    to 0 %): every step and samples stored, one fit per pulse set, fitted discharge R0 within 3 % of the
//    simulated cell's; R1, C1, R2, C2 of both directions within 15 % of the cell's (issue 11), with no flag on
//    them. CELLBENCH_HIL_SEED sets the simulated instruments' noise seed; CELLBENCH_HIL_KEEP_DB=PATH keeps the
//    run's database (for `cellbench fit --db PATH --run 1`).
//    Time scale: CELLBENCH_HIL_TIME_SCALE (default kHppcTimeScale); the wall time is printed.
//    CELLBENCH_HIL_VERBOSE=1 logs at debug level and lists the steps; CELLBENCH_HIL_Z=1 prints beside each RC value
//    its error and the fit's own 1-sigma, in % of the reference.
//  - Safety: an over-temperature (a low max_temperature_c, heated by a 40 A discharge) stops the current
//    within one DAQ sample period and aborts the run with the reason recorded as an event.
#include <gtest/gtest.h>

#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <utility>
#include <thread>
#include <tuple>
#include <vector>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/estimator/pulse_fit.hpp"
#include "cellbench/sim/plant.hpp"
#include "hil/hil_support.hpp"

using namespace cellbench;
using cellbench::test::eventually;
using cellbench::test::instruments_connected;
using cellbench::test::TempDir;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

// Bench seconds per wall second for the full HPPC (about 70 000 bench seconds). x800 since session 26: the pace
// gate slows the bench down on a busy host instead of aborting (docs/daemon.md); idle 82 s wall and 104 s CPU
// against 157 s and 162 s at x400, and it passed beside two busy loops at nice 0 (x604-672 achieved at times).
constexpr double kHppcTimeScale = 800.0;

const fs::path kSource = CELLBENCH_SOURCE_DIR;

estimator::ParameterSet thesis_cell() {
    std::ifstream in(kSource / "config/cells/p45b-thesis.json");
    return estimator::ParameterSet::from_json(json::parse(in), "p45b-thesis.json");
}

}  // namespace

TEST(DaemonHil, FullHppcStoresEveryStepAndFitsR0AtEverySocWithinThreePercent) {
    double scale = kHppcTimeScale;
    if (const char* env = std::getenv("CELLBENCH_HIL_TIME_SCALE")) scale = std::atof(env);
    TempDir dir("daemon-hppc");
    if (std::getenv("CELLBENCH_HIL_VERBOSE")) spdlog::set_level(spdlog::level::debug);
    auto cfg = test::sim_bench_config(kSource / "config/bench.sim.json");
    ASSERT_TRUE(cfg.simulation.has_value());
    // CELLBENCH_HIL_SEED: the simulated instruments' noise seed (default: the bench file's).
    if (const char* env = std::getenv("CELLBENCH_HIL_SEED")) cfg.simulation->seed = static_cast<std::uint32_t>(std::atol(env));
    std::printf("simulation seed %u\n", static_cast<unsigned>(cfg.simulation->seed));
    // CELLBENCH_HIL_KEEP_DB=PATH: the run's database is copied there when the daemon has closed it (for
    // `cellbench fit --db PATH --run 1`).
    struct KeepDb {
        fs::path from;
        ~KeepDb() {
            const char* to = std::getenv("CELLBENCH_HIL_KEEP_DB");
            std::error_code ec;
            if (to && fs::exists(from, ec)) fs::copy_file(from, to, fs::copy_options::overwrite_existing, ec);
        }
    } keep_db{dir.path / "bench.sqlite"};
    daemon::BenchDaemon d(cfg, test::daemon_options_in(dir, scale));
    d.start();
    ASSERT_TRUE(eventually([&] { return instruments_connected(d); }, 20s)) << d.status().dump(2);

    const auto wall0 = std::chrono::steady_clock::now();
    const json started = d.start_run({"hppc", "p45b", {{"program", "hppc"}, {"cell", "p45b"}}});
    const daemon::RunId id = started["id"].get<daemon::RunId>();
    std::string state;
    // Fit latency, measured, not asserted (timing goals live in benchmarks): the live test time (run-relative
    // bench s) when each fit first shows in GET /runs/{id}/fits, polled every 100 ms of wall time.
    std::vector<double> fit_seen_t_s;
    ASSERT_TRUE(eventually([&] {
        state = d.get_run(id)["state"].get<std::string>();
        const std::size_t n = d.fits(id)["fits"].size();
        if (n > fit_seen_t_s.size()) {
            const json status = d.status();
            const json& t = status["live"]["test_time_s"];
            while (fit_seen_t_s.size() < n) fit_seen_t_s.push_back(t.is_number() ? t.get<double>() : NAN);
        }
        return cellbench::test::ended_run_state(state);
    }, 1800s, 100ms));
    const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
    // The online fit of the last pulse set may still be running when the program ends.
    eventually([&] { return d.fits(id)["fits"].size() >= 10; }, 60s);
    d.store().flush();

    const auto events = d.events(id);
    std::string last_error;
    for (const auto& e : events["events"])
        if (e["level"] != "info") last_error = e["message"].get<std::string>();
    ASSERT_EQ(state, "completed") << last_error;

    const auto run = d.store().get_run(id);
    ASSERT_TRUE(run);
    EXPECT_GT(run->cycler_samples, 10000);
    EXPECT_GT(run->daq_samples, 10000);
    EXPECT_GT(run->chamber_samples, 100);
    // Steps: rest, charge, rest, pilot discharge, rest, charge, rest, then per pulse set (pulse d, rest, pulse c,
    // rest, SOC step, rest), final discharge and rest. hppc.json's `"count": "pulse_sets"` (10) is the number of
    // passes the tester makes through steps 8-13 (Neware cycle semantics, the simulated tester's too): pulse
    // sets at 100 % down to 10 % SOC, and the final discharge to the cut-off takes the cell to 0 %.
    constexpr std::size_t kPulseSets = 10;
    const auto steps = d.store().steps(id);
    if (::testing::Test::HasFailure() || std::getenv("CELLBENCH_HIL_VERBOSE"))
        for (const auto& s : steps)
            std::printf("step %3d seg %d id %2d cycle %2d %-4s %9.1f s .. %9.1f s  %s\n", s.index, s.segment, s.step_id,
                        s.cycle, s.type.c_str(), s.started_t_s, s.ended_t_s.value_or(NAN), s.end_reason.c_str());
    EXPECT_GE(steps.size(), 7u + kPulseSets * 6u + 2u);
    const auto pulses = std::count_if(steps.begin(), steps.end(), [](const auto& s) { return s.step_id == 8; });
    EXPECT_EQ(static_cast<std::size_t>(pulses), kPulseSets);
    for (const auto& s : steps) EXPECT_TRUE(s.ended_t_s.has_value()) << "step " << s.index << " never ended";
    // The same steps through the API (GET /runs/{id}/steps), for the dashboard's run page.
    const auto api_steps = d.steps(id)["steps"];
    ASSERT_EQ(api_steps.size(), steps.size());
    for (std::size_t k = 0; k < steps.size(); ++k) {
        EXPECT_EQ(api_steps[k]["step_id"], steps[k].step_id) << "step " << k;
        EXPECT_EQ(api_steps[k]["end_reason"], steps[k].end_reason) << "step " << k;
        EXPECT_DOUBLE_EQ(api_steps[k]["started_s"].get<double>(), steps[k].started_t_s) << "step " << k;
    }

    const auto fits = d.fits(id)["fits"];
    const auto truth = thesis_cell();
    std::printf("HPPC at time scale %.0f: %.1f s wall, %lld cycler samples, %zu steps, %zu fits\n", scale, wall_s,
                static_cast<long long>(run->cycler_samples), steps.size(), fits.size());
    std::printf("  set   SOC    R0 fit mOhm  R0 truth mOhm  error %%\n");
    double worst = 0;
    for (const auto& f : fits) {
        const double soc = f["soc"].get<double>();
        const double r0 = f["discharge"].is_null() || f["discharge"]["r0_ohm"].is_null() ? NAN
                                                                                          : f["discharge"]["r0_ohm"].get<double>();
        const double r0_true = truth.rc_at(soc, -1).r0_ohm;
        const double err = 100.0 * (r0 - r0_true) / r0_true;
        worst = std::max(worst, std::abs(err));
        std::printf("  %3d  %5.3f  %10.3f  %13.3f  %+7.2f\n", f["pulse_set"].get<int>(), soc, r0 * 1e3, r0_true * 1e3, err);
        EXPECT_NEAR(r0, r0_true, 0.03 * r0_true) << "pulse set " << f["pulse_set"] << " at SOC " << soc;
    }
    std::printf("  worst R0 error %.2f %%\n", worst);
    // Issue 11 (Daemon HIL): the online fits recover the RC pairs too -- R1, C1, R2, C2 of both directions within
    // 15 % of the simulated cell's at every SOC level, none flagged (Sequencer.RunsAShortHppcAndFitsEveryPulseSetOnline
    // asserts the same without noise). On the noisy tester they did not (worst 78 %, seed 1), for three reasons:
    //  - the fit took the OCV slope from a chord above the level while the pulse set runs below it (the cell's OCV
    //    table has its knots at the levels: discharge R1 +36 % at 90 %, +47 % at 20 %). The fit now waits for the
    //    SOC step and the long rest after it and takes the chord below (sequencer.cpp);
    //  - R0 was held at its eq. 3.2 steps, two-row differences that carry the voltage noise into the fast pair
    //    (C1 up to 22 % off). R0 is now fitted with the pairs;
    //  - the simulated instruments let the DAQ and the chamber advance the shared cell past a late tester tick
    //    under the previous current, so the tester's rows showed voltage steps of 2-7 mV 1-2 s after a current
    //    step (C1 -70 % where that hit). The tester now drives the cell's time: each tick's current is held on
    //    the plant only up to the tick's end (BenchPlant::set_current), and no one integrates the cell past it.
    // Not asserted: a direction whose pulse turned CV (the fit says so in its warnings). At 100 % SOC the charge
    // pulse meets the 4.1 V limit (the full cell's OCV) from its first row and carries 1.2 A falling to 0.5 A
    // instead of 4.5 A, so the charge pair has a quarter of the signal: its C1 has a 1-sigma of ~15 % from the
    // fit itself (its worst value 5-37 % off in five runs). It is printed; the test asserts that only the pulse
    // set at 100 % SOC turns CV.
    //
    // The reference is the cell's values over the rows a direction's pair is fitted on: the time mean of the cell's
    // table values while its pulse runs and the cell rests after it (steps 8-9 for discharge, 10-11 for charge), at
    // the cell's own SOC (from the SOC its OCV table gives for the pulse set's rested voltage, the fit's OCV, less
    // the charge the steps moved). A pulse-set fit holds each value constant over those rows, and on this cell the
    // values change within them: between 30 % and 20 % the discharge R2 triples, so over the 0.8 % SOC the
    // discharge pulse removes at 29.5 % it rises by 14 %. Taken at the rested start, that alone put the fitted R2
    // 10-12 % off in every run (seeds 1-4). Two more references are printed: the cell at the rested start, and at
    // the bench's SOC (the fit's "soc", which counts from the end of a CCCV charge as 1.0 and leaves this cell
    // ~0.2 % below its table's 1.0).
    const auto records = d.store().pulse_fits(id);
    ASSERT_EQ(records.size(), fits.size());
    // Steps 8-11 of each pulse set (discharge pulse, rest, charge pulse, rest), in order.
    std::vector<std::array<const daemon::StepRecord*, 4>> set_steps;
    for (std::size_t k = 0; k + 3 < steps.size(); ++k)
        if (steps[k].step_id == 8 && steps[k + 1].step_id == 9 && steps[k + 2].step_id == 10 && steps[k + 3].step_id == 11)
            set_steps.push_back({&steps[k], &steps[k + 1], &steps[k + 2], &steps[k + 3]});
    ASSERT_EQ(set_steps.size(), fits.size());
    // The cell's R1, C1, R2, C2 of direction `sign`, time-averaged over a pulse (SOC moving linearly by `dsoc`
    // from `soc0`) and the rest after it (at soc0 + dsoc).
    auto mean_over_pulse_and_rest = [&](double soc0, double dsoc, double pulse_s, double rest_s, int sign) {
        estimator::RcValues m{0, 0, 0, 0, 0};
        constexpr int kPoints = 200;
        for (int j = 0; j < kPoints; ++j) {
            const double frac = (j + 0.5) / kPoints;
            const auto v = estimator::to_rc_values(truth.rc_at(soc0 + dsoc * frac, sign));
            for (auto [sum, x] : {std::pair{&m.r1_ohm, v.r1_ohm}, {&m.c1_f, v.c1_f}, {&m.r2_ohm, v.r2_ohm}, {&m.c2_f, v.c2_f}})
                *sum += x * pulse_s / kPoints;
        }
        const auto rest = estimator::to_rc_values(truth.rc_at(soc0 + dsoc, sign));
        for (auto [sum, x] : {std::pair{&m.r1_ohm, rest.r1_ohm}, {&m.c1_f, rest.c1_f}, {&m.r2_ohm, rest.r2_ohm}, {&m.c2_f, rest.c2_f}})
            *sum = (*sum + x * rest_s) / (pulse_s + rest_s);
        return m;
    };
    auto duration = [](const daemon::StepRecord* st) { return st->ended_t_s.value_or(st->started_t_s) - st->started_t_s; };
    std::printf("  set   SOC  cell SOC  dir        R1 mOhm (truth)      C1 F (truth)     R2 mOhm (truth)      C2 F (truth)\n");
    double worst_rc = 0, worst_rc_rested = 0, worst_rc_bench_soc = 0, worst_rc_cv = 0;
    for (std::size_t k = 0; k < fits.size(); ++k) {
        const auto& f = fits[k];
        const double soc = f["soc"].get<double>();
        ASSERT_TRUE(f["ocv_v"].is_number()) << "pulse set " << f["pulse_set"];
        const double cell_soc = truth.soc_from_ocv(f["ocv_v"].get<double>());
        EXPECT_NEAR(cell_soc, soc, 0.01) << "pulse set " << f["pulse_set"];
        bool turned_cv[2] = {false, false};  // discharge, charge
        for (const auto& w : records[k].detail["warnings"]) {
            const std::string text = w.get<std::string>();
            if (text.rfind("the discharge pulse hit the lower voltage limit", 0) == 0) turned_cv[0] = true;
            if (text.rfind("the charge pulse hit the upper voltage limit", 0) == 0) turned_cv[1] = true;
        }
        EXPECT_FALSE(turned_cv[0]) << "pulse set " << f["pulse_set"];
        EXPECT_EQ(turned_cv[1], k == 0) << "pulse set " << f["pulse_set"] << " at SOC " << soc;
        for (const char* dir : {"discharge", "charge"}) {
            const json& got = f[dir];
            ASSERT_TRUE(got.is_object()) << dir << " values missing, pulse set " << f["pulse_set"];
            const int sign = std::string(dir) == "charge" ? +1 : -1;
            const bool cv = turned_cv[sign > 0 ? 1 : 0];
            // The cell's SOC over the direction's pulse: the discharge pulse starts at the rested SOC, the charge
            // pulse where the discharge pulse left it (the tester's count of each step's charge).
            const auto& st = set_steps[k];
            const double q_discharge_soc = st[0]->capacity_ah.value_or(NAN) / truth.capacity_ah;
            const double q_charge_soc = st[2]->capacity_ah.value_or(NAN) / truth.capacity_ah;
            const auto truth_rc = sign < 0 ? mean_over_pulse_and_rest(cell_soc, -q_discharge_soc, duration(st[0]), duration(st[1]), sign)
                                           : mean_over_pulse_and_rest(cell_soc - q_discharge_soc, q_charge_soc, duration(st[2]),
                                                                      duration(st[3]), sign);
            const auto rested_rc = estimator::to_rc_values(truth.rc_at(cell_soc, sign));
            const auto bench_rc = estimator::to_rc_values(truth.rc_at(soc, sign));
            const std::tuple<const char*, double, double, double> want[] = {
                {"r1_ohm", truth_rc.r1_ohm, rested_rc.r1_ohm, bench_rc.r1_ohm},
                {"c1_f", truth_rc.c1_f, rested_rc.c1_f, bench_rc.c1_f},
                {"r2_ohm", truth_rc.r2_ohm, rested_rc.r2_ohm, bench_rc.r2_ohm},
                {"c2_f", truth_rc.c2_f, rested_rc.c2_f, bench_rc.c2_f}};
            std::printf("  %3d  %5.3f  %6.4f  %-9s", f["pulse_set"].get<int>(), soc, cell_soc, dir);
            for (const auto& [name, value, value_at_rested_soc, value_at_bench_soc] : want) {
                const double v = got.contains(name) && got[name].is_number() ? got[name].get<double>() : NAN;
                const double scale_v = name[0] == 'r' ? 1e3 : 1.0;
                std::printf(" %8.3f (%8.3f)", v * scale_v, value * scale_v);
                if (std::getenv("CELLBENCH_HIL_Z")) {
                    const std::string sd_name = std::string(name) + "_sd";
                    const double sd = got.contains(sd_name) && got[sd_name].is_number() ? got[sd_name].get<double>() : NAN;
                    std::printf(" [%+5.1f%% sd %4.1f%%]", 100 * (v - value) / value, 100 * sd / value);
                }
                const double err = std::isfinite(v) ? std::abs(v - value) / value : INFINITY;
                const double err_rested = std::isfinite(v) ? std::abs(v - value_at_rested_soc) / value_at_rested_soc : INFINITY;
                const double err_bench = std::isfinite(v) ? std::abs(v - value_at_bench_soc) / value_at_bench_soc : INFINITY;
                if (cv) {
                    worst_rc_cv = std::max(worst_rc_cv, err);
                } else {
                    worst_rc = std::max(worst_rc, err);
                    worst_rc_rested = std::max(worst_rc_rested, err_rested);
                    worst_rc_bench_soc = std::max(worst_rc_bench_soc, err_bench);
                }
                EXPECT_TRUE(std::isfinite(v) && v > 0.0) << dir << " " << name << ", pulse set " << f["pulse_set"];
                if (!cv) {
                    EXPECT_NEAR(v, value, 0.15 * value) << dir << " " << name << ", pulse set " << f["pulse_set"]
                                                        << " at SOC " << soc << " (cell SOC " << cell_soc << ")";
                }
            }
            std::printf("%s\n", cv ? "  (pulse turned CV: not asserted)" : "");
            if (got.contains("flags")) {
                EXPECT_TRUE(got["flags"].empty()) << dir << " flags " << got["flags"].dump();
            }
        }
        if (f.contains("flags")) {
            EXPECT_TRUE(f["flags"].empty()) << "flags " << f["flags"].dump();
        }
    }
    std::printf("  worst R1/C1/R2/C2 error %.1f %% (against the cell at the rested start: %.1f %%, at the bench's SOC: "
                "%.1f %%); the pair whose pulse turned CV: %.1f %%\n",
                100.0 * worst_rc, 100.0 * worst_rc_rested, 100.0 * worst_rc_bench_soc, 100.0 * worst_rc_cv);
    RecordProperty("worst_rc_error_at_rested_start_percent", std::to_string(100.0 * worst_rc_rested));
    RecordProperty("worst_rc_error_cv_pulse_percent", std::to_string(100.0 * worst_rc_cv));
    RecordProperty("worst_rc_error_at_bench_soc_percent", std::to_string(100.0 * worst_rc_bench_soc));
    RecordProperty("worst_rc_error_percent", std::to_string(100.0 * worst_rc));
    // A pulse set's fit waits for the SOC step (id 12) and the long rest after it (id 13): the sequencer sees
    // that rest end when the next step begins. Latency in wall time = bench seconds / time scale (+- one 100 ms
    // poll) after that.
    std::vector<double> rest_end_t_s;
    for (const auto& st : steps)
        if (st.step_id == 13 && st.ended_t_s) rest_end_t_s.push_back(*st.ended_t_s);
    double worst_latency_ms = 0;
    for (std::size_t k = 0; k < fit_seen_t_s.size() && k < rest_end_t_s.size(); ++k) {
        const double ms = 1e3 * (fit_seen_t_s[k] - rest_end_t_s[k]) / scale;
        worst_latency_ms = std::max(worst_latency_ms, ms);
        std::printf("  pulse set %2zu: fit in the API %.0f ms (wall) after the rest after its SOC step ended\n", k + 1, ms);
    }
    RecordProperty("worst_fit_latency_ms", std::to_string(worst_latency_ms));
    RecordProperty("time_scale", std::to_string(scale));
    RecordProperty("wall_s", std::to_string(wall_s));
    RecordProperty("worst_r0_error_percent", std::to_string(worst));
    ASSERT_EQ(fits.size(), kPulseSets);
    // One per SOC level, from full down in steps of 10 %.
    EXPECT_GT(fits[0]["soc"].get<double>(), 0.97);
    EXPECT_NEAR(fits[kPulseSets - 1]["soc"].get<double>(), 0.1, 0.03);
    for (std::size_t k = 1; k < fits.size(); ++k)
        EXPECT_NEAR(fits[k - 1]["soc"].get<double>() - fits[k]["soc"].get<double>(), 0.1, 0.02) << "pulse set " << k + 1;

    // Issue 14: each step's capacity is the tester's count of that step (it was the latest live reading's
    // when the next step began: 0.0 Ah for the SOC steps, 0.0034 Ah for a 30 s 1C pulse).
    std::vector<const daemon::StepRecord*> pulse_steps;
    for (const auto& st : steps) {
        if (st.step_id == 8) pulse_steps.push_back(&st);
        if (st.step_id == 12) {
            ASSERT_TRUE(st.capacity_ah.has_value()) << "SOC step " << st.index;
            EXPECT_GT(*st.capacity_ah, 0.3) << "SOC step " << st.index;
        }
    }
    ASSERT_EQ(pulse_steps.size(), kPulseSets);
    for (const auto* st : pulse_steps) {
        ASSERT_TRUE(st->capacity_ah.has_value()) << "pulse step " << st->index;
        EXPECT_NEAR(*st->capacity_ah, 4.5 * 30.0 / 3600.0, 0.002) << "pulse step " << st->index;
    }
    // One owner of SOC: the rows' SOC (what the live value and the dashboard show) just before each pulse set
    // is the SOC its fit was placed at.
    for (std::size_t k = 0; k < pulse_steps.size(); ++k) {
        daemon::SampleQuery q;
        q.from_s = pulse_steps[k]->started_t_s - 3.0;
        q.to_s = pulse_steps[k]->started_t_s - 0.5;
        const json w = d.samples(id, q);
        ASSERT_FALSE(w["series"]["soc"].empty()) << "pulse set " << k + 1;
        const json& last = w["series"]["soc"].back();
        ASSERT_TRUE(last.is_number()) << w.dump();
        EXPECT_NEAR(last.get<double>(), fits[k]["soc"].get<double>(), 0.01) << "pulse set " << k + 1;
    }

    // The export streams the stored run as BDF CSV.
    auto cursor = d.export_bdf_csv(id);
    const auto head = cursor->next();
    ASSERT_TRUE(head.has_value());
    EXPECT_NE(head->find("Test Time / s"), std::string::npos);

    d.shutdown();
    // The wall time (goal: under 3 minutes) is printed, not asserted: timing lives in benchmarks. The fits do
    // not depend on the time scale: they use the rows the tester recorded at 0.1 s (download), not the polls.
    // R0 is the joint fit's (fitted with the pairs over every row; eq. 3.2's steps are in the fit's detail):
    // eq. 3.2 reads the first row 0.1 s after the step, so it carries that much of the RC relaxation (about +1 to
    // +2.6 % on this cell), and its two-row differences carry the tester's voltage noise.
}

// A cell of another size on the bench (session 50): the thesis parameter set as a 40 Ah pouch (resistances /10,
// capacitances and C_th x10, R_th /10^(2/3), surface x10^(2/3)), its own cell config, hppc_short. Every online
// value has its uncertainty and no flag (the joint fit's covariance read J'J in raw units and gave the first pulse
// set none), the discharge pairs are the cell's within 15 %, and the end-of-run parameter set turns the heat flux
// into heat over the pouch's surface (it took a 21700's: C_th 136 J/K for 633).
TEST(DaemonHil, AFortyAmpHourPouchIsFittedWithItsUncertaintiesAndItsOwnSurface) {
    TempDir dir("daemon-pouch");
    std::stringstream program;
    program << std::ifstream(kSource / "config/programs/hppc_short.json").rdbuf();
    test::write_bench_folder(dir.path, "hppc_short", program.str());
    constexpr double f = 10.0;  // the thesis set's 4 Ah -> 40 Ah
    json p = json::parse(std::ifstream(kSource / "config/cells/p45b-thesis.json"));
    p["cell"] = "40 Ah pouch (the thesis set scaled)";
    p["capacity_ah"] = p["capacity_ah"].get<double>() * f;
    for (const char* dir_name : {"discharge", "charge"})
        for (const auto& [key, by] : {std::pair{"r0_ohm", 1 / f}, std::pair{"r1_ohm", 1 / f}, std::pair{"r2_ohm", 1 / f},
                                      std::pair{"c1_f", f}, std::pair{"c2_f", f}})
            for (auto& v : p[dir_name][key]) v = v.get<double>() * by;
    auto& th = p["thermal"];
    th["c_th_j_per_k"] = th["c_th_j_per_k"].get<double>() * f;
    th["r_th_k_per_w"] = th["r_th_k_per_w"].get<double>() / std::cbrt(f * f);
    th["area_m2"] = th["area_m2"].get<double>() * std::cbrt(f * f);
    const double area_m2 = th["area_m2"].get<double>();
    std::ofstream(dir.path / "cells/pouch40-params.json") << p.dump(1);
    json cell = json::parse(std::ifstream(kSource / "config/cells/p45b.json"));
    cell["name"] = "40 Ah pouch";
    cell["nominal_capacity_ah"] = 40.0;
    cell["max_charge_current_a"] = 40.0;
    cell["max_discharge_current_a"] = 60.0;
    cell["surface_area_m2"] = area_m2;
    cell["params"] = "pouch40-params.json";
    std::ofstream(dir.path / "cells/pouch40.json") << cell.dump(1);
    json bench = json::parse(std::ifstream(dir.path / "bench.sim.json"));
    bench["simulation"]["params"] = "cells/pouch40-params.json";
    std::ofstream(dir.path / "bench.sim.json") << bench.dump(1);
    const auto truth = estimator::ParameterSet::from_json(p, "pouch40-params.json");

    auto cfg = test::sim_bench_config(dir.path / "bench.sim.json");
    daemon::BenchDaemon d(cfg, test::daemon_options_in(dir, 200.0));
    d.start();
    ASSERT_TRUE(eventually([&] { return instruments_connected(d); }, 20s)) << d.status().dump(2);
    const auto id = d.start_run({"hppc_short", "pouch40", {}})["id"].get<daemon::RunId>();
    const std::string state = test::wait_for_run_end(d, id, 600s, 100ms);
    ASSERT_TRUE(cellbench::test::ended_run_state(state)) << state;
    eventually([&] { return d.fits(id)["fits"].size() >= 3 && d.store().latest_parameter_set(id).has_value(); }, 120s);
    ASSERT_EQ(state, "completed") << d.events(id).dump(1);

    const auto fits = d.fits(id)["fits"];
    ASSERT_EQ(fits.size(), 3u);
    for (const auto& fit : fits) {
        const double soc = fit["soc"].get<double>();
        for (const char* dir_name : {"discharge", "charge"}) {
            const json& got = fit[dir_name];
            ASSERT_TRUE(got.is_object()) << dir_name << ", pulse set " << fit["pulse_set"];
            EXPECT_TRUE(got["flags"].empty()) << dir_name << " flags " << got["flags"].dump() << ", pulse set " << fit["pulse_set"];
            for (const char* name : {"r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f"}) {
                const json& sd = got[std::string(name) + "_sd"];
                EXPECT_TRUE(sd.is_number() && sd.get<double>() > 0) << dir_name << " " << name << "_sd " << sd.dump()
                                                                    << ", pulse set " << fit["pulse_set"];
            }
        }
        const auto want = estimator::to_rc_values(truth.rc_at(soc, -1));
        for (const auto& [name, value] : {std::pair{"r1_ohm", want.r1_ohm}, std::pair{"c1_f", want.c1_f},
                                          std::pair{"r2_ohm", want.r2_ohm}, std::pair{"c2_f", want.c2_f}}) {
            const double v = fit["discharge"][name].get<double>();
            std::printf("pulse set %d SOC %.3f discharge %s %.6g (cell %.6g)\n", fit["pulse_set"].get<int>(), soc, name, v, value);
            EXPECT_NEAR(v, value, 0.15 * value) << "discharge " << name << ", pulse set " << fit["pulse_set"];
        }
    }
    const auto params = d.store().latest_parameter_set(id);
    ASSERT_TRUE(params.has_value()) << "no end-of-run parameter set";
    const auto& pt = params->params["thermal"];
    std::printf("end of run: C_th %.1f J/K (cell %.1f), area %.5f m^2 (cell %.5f)\n", pt["c_th_j_per_k"].get<double>(),
                truth.thermal.c_th_j_per_k, pt["area_m2"].get<double>(), area_m2);
    EXPECT_NEAR(pt["area_m2"].get<double>(), area_m2, 1e-9);
    EXPECT_NEAR(pt["c_th_j_per_k"].get<double>(), truth.thermal.c_th_j_per_k, 0.05 * truth.thermal.c_th_j_per_k);
}

TEST(DaemonHil, OverTemperatureStopsTheCurrentWithinOneSampleAndAbortsTheRun) {
    // A config folder of our own: the bench file, the cell, and a program that heats the cell with 40 A.
    TempDir dir("daemon-safety");
    test::write_bench_folder(dir.path, "heat", R"({
      "schema": "cellbench.bench-program/1", "name": "heat",
      "segments": [
        {"type": "chamber_setpoint", "setpoint_c": 30.0},
        {"type": "cycler", "name": "heat", "steps": [
          {"type": "rest", "time_s": 5},
          {"type": "cc_discharge", "current_a": 40.0, "cutoff_voltage_v": 2.9, "time_s": 600},
          {"type": "rest", "time_s": 60},
          {"type": "end"}]}]})");

    auto cfg = test::sim_bench_config(dir.path / "bench.sim.json");
    const double max_c = 33.0;  // 3 K above the start: the 40 A discharge gets there in about 10 bench s
    cfg.safety.max_temperature_c = max_c;
    const double daq_period_s = 0.1;  // the simulated DEWE samples at 10 Hz of bench time
    daemon::BenchDaemon d(cfg, test::daemon_options_in(dir, 2.0));
    d.start();
    ASSERT_TRUE(eventually([&] { return instruments_connected(d); }, 20s)) << d.status().dump(2);

    const auto id = d.start_run({"heat", "p45b", {}})["id"].get<daemon::RunId>();
    const std::string state = test::wait_for_run_end(d, id, 300s);
    ASSERT_TRUE(cellbench::test::ended_run_state(state)) << state;
    eventually([&] {
        const auto ev = d.events(id);
        for (const auto& e : ev["events"])
            if (e["kind"] == "cycler" && !e["detail"].is_null() && e["detail"].contains("acknowledged_t_s")) return true;
        return false;
    }, 10s);
    d.store().flush();

    const auto run = d.get_run(id);
    EXPECT_EQ(state, "aborted");
    ASSERT_TRUE(run["error"].is_string()) << run.dump();
    EXPECT_NE(run["error"].get<std::string>().find("temperature"), std::string::npos) << run["error"];

    double abort_t = NAN, ack_t = NAN;
    const auto events = d.events(id);  // kept: a range-for over a temporary's member would dangle
    for (const auto& e : events["events"]) {
        if (e["kind"] == "abort") {
            abort_t = e["test_time_s"].get<double>();
            EXPECT_EQ(e["level"], "error");
            EXPECT_NE(e["message"].get<std::string>().find("temperature"), std::string::npos) << e["message"];
        }
        if (e["kind"] == "cycler" && !e["detail"].is_null() && e["detail"].contains("acknowledged_t_s"))
            ack_t = e["detail"]["acknowledged_t_s"].get<double>();
    }
    ASSERT_TRUE(std::isfinite(abort_t)) << "no abort event: " << events.dump(1);
    ASSERT_TRUE(std::isfinite(ack_t)) << "the tester never acknowledged the stop";

    // The abort came from the first DAQ sample over the limit (none before it was over).
    const auto w = d.store().samples(id, std::nullopt, std::nullopt, 100000);
    const auto* daq = w.source("daq");
    ASSERT_NE(daq, nullptr);
    ASSERT_FALSE(w.decimated);
    double first_over = NAN;
    for (std::size_t k = 0; k < daq->size() && std::isnan(first_over); ++k)
        for (const char* ch : {"surface_c", "t1_c", "t2_c"})
            if (daq->min[daq->channel(ch)][k] > max_c) first_over = daq->time_s[k];
    ASSERT_TRUE(std::isfinite(first_over));
    EXPECT_NEAR(abort_t, first_over, 1e-6);

    // Current off within one sample period of the violating sample (bench time, the tester's acknowledgement)...
    std::printf("over-temperature at %.3f s (test time), stop acknowledged %.1f ms later (bench), scale 2\n", abort_t,
                (ack_t - abort_t) * 1e3);
    EXPECT_GE(ack_t, abort_t);
    EXPECT_LE(ack_t - abort_t, daq_period_s);
    // ...and the cell carries no current since (the plant's truth; the run stores samples while it is live).
    const auto* cyc = w.source("cycler");
    ASSERT_NE(cyc, nullptr);
    const auto ic = cyc->channel("current_a");
    double max_before = 0;
    for (std::size_t k = 0; k < cyc->size(); ++k)
        if (cyc->time_s[k] < abort_t) max_before = std::max(max_before, std::abs(cyc->min[ic][k]));
    EXPECT_GT(max_before, 39.0);  // it was heating with 40 A
    ASSERT_NE(d.plant(), nullptr);
    EXPECT_LT(std::abs(d.plant()->read().current_a), 0.02);  // 0 A plus the simulated sensor noise
    EXPECT_TRUE(eventually([&] {
        const auto live = d.status()["live"];
        return live["current_a"].is_number() && std::abs(live["current_a"].get<double>()) < 0.05;
    }, 10s));
    d.shutdown();
}
