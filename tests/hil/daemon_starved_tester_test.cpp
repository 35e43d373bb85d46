// cellbenchd on the simulated bench while the simulated tester's host is starved (no CPU for a moment, what
// `make test-loaded` does to it by chance): the incident of DaemonHil.FullHppc under load, made deterministic.
// There, after a Neware download timeout and a reconnect, the run aborted on "voltage 4.239 V outside the safety
// window 2.80-4.20 V" in an HPPC whose CCCV charges hold 4.1 V.
//
// Here a CCCV charge to the cell's 4.1 V (config/cells/p45b.json) from 60 % SOC is running in its CC phase when
// the simulated tester's thread is held (sim::NewareServer::set_starved): the client's requests go unanswered
// (it times out and reconnects, as in the incident) while the paced bench clock, the simulated chamber and DAQ
// go on for longer than the whole CC phase. A real tester's current is its own hardware's, CV limit included,
// whatever its PC and the client do: the run must complete with no reading above the CV limit.
//
// Time scale 400 (the full HPPC's until session 26). Nothing waits on wall time except bounded waits that only end a broken test.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/plant.hpp"
#include "hil/hil_support.hpp"

using namespace cellbench;
using namespace std::chrono_literals;
using cellbench::test::eventually;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

const fs::path kSource = CELLBENCH_SOURCE_DIR;
constexpr double kScale = 400.0;
constexpr double kCvV = 4.1;  // config/cells/p45b.json max_voltage_v, the charge's CV set value

// A fault episode of the instrument recorded for the run (its first fault: a timeout here).
bool has_fault(const json& events, const std::string& instrument) {
    for (const auto& e : events)
        if (e["kind"] == "fault" && e["detail"].is_object() && e["detail"].value("instrument", "") == instrument)
            return true;
    return false;
}

}  // namespace

TEST(DaemonHil, CccvChargeStaysWithinItsVoltageLimitWhenTheTestersHostIsStarved) {
    test::TempDir tmp("daemon-starved-tester");
    const fs::path dir = tmp.path;
    test::write_bench_folder(dir, "charge", R"({
      "schema": "cellbench.bench-program/1", "name": "charge",
      "segments": [
        {"type": "chamber_setpoint", "setpoint_c": 30},
        {"type": "cycler", "name": "charge", "steps": [
          {"type": "rest", "time_s": 10},
          {"type": "cccv_charge", "current_a": "one_c_a", "voltage_v": "max_voltage_v", "cutoff_current_a": 0.05},
          {"type": "rest", "time_s": 120},
          {"type": "end"}]}]})");
    auto cfg = test::sim_bench_config(dir / "bench.sim.json");
    ASSERT_TRUE(cfg.simulation);
    cfg.simulation->initial_soc = 0.6;  // a CC phase of about 1000 bench s at 1C
    // The starved tester is silent for longer than the usual grace: this test is about what it reads after.
    cfg.faults.cycler.grace_s = 1e6;
    cfg.safety.instrument_loss_grace_s = 1e6;
    if (std::getenv("CELLBENCH_HIL_VERBOSE")) spdlog::set_level(spdlog::level::debug);
    auto d = std::make_unique<daemon::BenchDaemon>(cfg, test::daemon_options_in(tmp, kScale, "t"));
    d->start();
    ASSERT_TRUE(eventually([&] { return test::instruments_connected(*d); }, 30s)) << d->status().dump(2);

    const auto id = d->start_run({"charge", "p45b", {}})["id"].get<daemon::RunId>();
    auto state = [&] { return d->get_run(id)["state"].get<std::string>(); };
    sim::NewareServer& tester = *d->neware_server();
    // The charge's CC phase (step 2, "cc"; "cv" once the tester holds the voltage).
    ASSERT_TRUE(eventually([&] {
        const auto s = tester.snapshot();
        return (s.step_id == 2 && s.step_type == "cc") || !test::live_run_state(state());
    }, 60s, 1ms)) << state();
    tester.set_starved(true);
    const auto at_freeze = tester.snapshot();
    ASSERT_EQ(at_freeze.step_id, 2);
    ASSERT_EQ(at_freeze.step_type, "cc") << "starved after the CC phase: the test needs it in CC";
    ASSERT_LT(at_freeze.voltage_v, kCvV);
    // The client declares an answer lost and reconnects; the bench goes on for 2000 s (more than the whole CC
    // phase from 60 % SOC at 4.5 A): the chamber and the DAQ read the plant at the clock's "now" meanwhile.
    ASSERT_TRUE(eventually([&] { return has_fault(d->events(id)["events"], "neware"); }, 60s))
        << d->events(id).dump(1);
    ASSERT_TRUE(eventually([&] { return d->bench_now_s() > at_freeze.bench_time_s + 2000.0; }, 120s));
    tester.set_starved(false);

    ASSERT_TRUE(eventually([&] { return !test::live_run_state(state()); }, 120s)) << state();
    const json run = d->get_run(id);
    EXPECT_EQ(run["state"], "completed") << run.dump(1) << "\n" << d->events(id).dump(1);

    // The charge ended in its CV phase, on the cut-off current, and never above the CV limit.
    const auto snap = tester.snapshot();
    ASSERT_GE(snap.history.size(), 2u);
    EXPECT_EQ(snap.history[1].end_reason, "current");
    EXPECT_LE(snap.history[1].end_voltage_v, kCvV + 0.002);
    EXPECT_LE(d->plant()->read().soc, 1.0 + 1e-3) << "a CCCV charge to 4.1 V overcharged the cell";
    d->store().flush();
    const auto w = d->store().samples(id, std::nullopt, std::nullopt, 100000);
    const auto* cyc = w.source("cycler");
    ASSERT_NE(cyc, nullptr);
    const auto iv = cyc->channel("voltage_v");
    double max_v = 0;
    for (std::size_t k = 0; k < cyc->size(); ++k)
        if (std::isfinite(cyc->max[iv][k])) max_v = std::max(max_v, cyc->max[iv][k]);
    std::printf("starved in CC at bench %.1f s (%.3f V); run %s; max stored voltage %.4f V; SOC after %.4f\n",
                at_freeze.bench_time_s, at_freeze.voltage_v, run["state"].get<std::string>().c_str(), max_v,
                d->plant()->read().soc);
    EXPECT_LE(max_v, kCvV + 0.005) << "stored cycler samples above the CV limit";
}
