// Instrument faults on the simulated bench (issue 6): cellbenchd in process on config/bench.sim.json, faults
// injected through the simulated instruments' switches while a run holds a 2 A discharge. What a user relies
// on is asserted: the run's state (running after a recoverable fault, `aborted` after a fatal one or one past
// its grace), the fault and recovery events (GET /runs/{id}/events), the cell's current off after an abort
// (the simulated plant's truth).
//
// Time scale 10: every grace is at least 10 s of wall time (the daemon's floor), so a test that waits for an
// abort waits that long; recoverable faults are injected for well under the (long) grace of those tests.
// Waits are bounded only to end a broken test; nothing here asserts a duration.
#include <gtest/gtest.h>

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <sstream>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/sim/chamber_server.hpp"
#include "cellbench/sim/dewe_publisher.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/plant.hpp"
#include "hil/hil_support.hpp"

using namespace cellbench;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using cellbench::test::eventually;

const fs::path kSource = CELLBENCH_SOURCE_DIR;
constexpr double kScale = 10.0;
constexpr double kLongGraceS = 300.0;  // 30 s wall: recoverable faults must not reach it
constexpr double kShortGraceS = 100.0;  // the 10 s wall floor at this scale

// A bench of our own: config folder with the bench file, the cell and a program holding a 2 A discharge
// (3000 s of bench time, far longer than any test) after an optional chamber set point.
class FaultBench {
public:
    explicit FaultBench(const std::string& tag, const std::function<void(daemon::BenchConfig&)>& tweak = {},
                        double chamber_setpoint_c = 30.0, double equilibrium_hold_s = 0.0)
        : tmp_("faults-" + tag), dir_(tmp_.path) {
        std::ostringstream program;
        program << R"({
          "schema": "cellbench.bench-program/1", "name": "hold",
          "segments": [
            {"type": "chamber_setpoint", "setpoint_c": )" << chamber_setpoint_c << R"(},)"
                                          << (equilibrium_hold_s > 0.0
                                                  ? R"({"type": "wait_equilibrium", "tolerance_c": 20, "timeout_s": 3000, "hold_s": )" +
                                                        std::to_string(equilibrium_hold_s) + "},"
                                                  : std::string()) << R"(
            {"type": "cycler", "name": "hold", "steps": [
              {"type": "rest", "time_s": 2},
              {"type": "cc_discharge", "current_a": 2.0, "cutoff_voltage_v": 2.9, "time_s": 3000},
              {"type": "rest", "time_s": 10},
              {"type": "end"}]}]})";
        test::write_bench_folder(dir_, "hold", program.str());
        cfg_ = test::sim_bench_config(dir_ / "bench.sim.json");
        cfg_.cycler.response_timeout_ms = 300;  // wall: a stalled answer is declared lost quickly
        cfg_.faults.cycler.grace_s = cfg_.faults.chamber.grace_s = cfg_.faults.daq.grace_s = kLongGraceS;
        cfg_.faults.chamber.response_timeout_ms = 200;
        cfg_.faults.chamber.retries = 1;
        if (tweak) tweak(cfg_);
        const auto o = test::daemon_options_in(tmp_, kScale, "t");
        if (std::getenv("CELLBENCH_HIL_VERBOSE")) spdlog::set_level(spdlog::level::debug);
        d_ = std::make_unique<daemon::BenchDaemon>(cfg_, o);
        d_->start();
    }
    ~FaultBench() { d_.reset(); }  // before the folder goes

    daemon::BenchDaemon& d() { return *d_; }
    sim::NewareServer& neware() { return *d_->neware_server(); }
    sim::ChamberServer& chamber() { return *d_->chamber_server(); }
    sim::DewePublisher& dewe() { return *d_->dewe_publisher(); }

    // Starts the hold program once every instrument is connected; returns when the tester discharges.
    ::testing::AssertionResult start_discharging() {
        if (!eventually([&] { return test::instruments_connected(*d_); }, 30s))
            return ::testing::AssertionFailure() << "instruments not connected: " << d_->status().dump();
        start_run();
        if (!eventually([&] { return plant_current_a() < -1.5 || !test::live_run_state(state()); }, 30s) || state() != "running")
            return ::testing::AssertionFailure() << "the run never discharged: " << state() << " " << events().dump(1);
        return ::testing::AssertionSuccess();
    }

    void start_run() { id_ = d_->start_run({"hold", "p45b", {}})["id"].get<daemon::RunId>(); }
    daemon::RunId id() const { return id_; }
    std::string state() { return d_->get_run(id_)["state"].get<std::string>(); }
    json run() { return d_->get_run(id_); }
    json events() { return d_->events(id_)["events"]; }
    double plant_current_a() { return d_->plant()->read().current_a; }

    // The run's events of a kind (and instrument, and fault kind when given).
    std::vector<json> find(const std::string& kind, const std::string& instrument = "", const std::string& fault = "") {
        std::vector<json> out;
        for (const auto& e : events()) {
            if (e["kind"] != kind) continue;
            const auto& det = e["detail"];
            if (!instrument.empty() && !(det.is_object() && det.value("instrument", "") == instrument)) continue;
            if (!fault.empty() && !(det.is_object() && det.value("fault", "") == fault)) continue;
            out.push_back(e);
        }
        return out;
    }
    bool has(const std::string& kind, const std::string& instrument = "", const std::string& fault = "") {
        return !find(kind, instrument, fault).empty();
    }
    bool wait_for(const std::string& kind, const std::string& instrument, const std::string& fault = "",
                  std::chrono::seconds limit = 30s) {
        return eventually([&] { return has(kind, instrument, fault); }, limit);
    }
    // The run aborted; the API shows the state at once, the store commits the abort's events with its next batch,
    // so wait for that commit before the events are read.
    bool wait_failed(std::chrono::seconds limit = 60s) {
        if (!eventually([&] { return state() == "aborted"; }, limit)) return false;
        d_->store().flush();
        return true;
    }
    // Current off: the tester stopped (0 A plus the simulated sensor noise).
    bool wait_current_off(std::chrono::seconds limit = 30s) {
        return eventually([&] { return std::abs(plant_current_a()) < 0.05; }, limit);
    }
    // The run still runs, and the tester still discharges with 2 A.
    ::testing::AssertionResult still_running() {
        const auto s = state();
        if (s != "running") return ::testing::AssertionFailure() << "run is " << s << ": " << run().dump() << events().dump(1);
        if (!eventually([&] { return plant_current_a() < -1.5; }, 10s))
            return ::testing::AssertionFailure() << "the cell no longer discharges: " << plant_current_a() << " A";
        return ::testing::AssertionSuccess();
    }
    void stop() {
        if (state() == "running") d_->stop_run(id_);
    }
    std::string error() {
        const auto r = run();
        return r["error"].is_string() ? r["error"].get<std::string>() : std::string();
    }

private:
    test::TempDir tmp_;
    fs::path dir_;
    daemon::BenchConfig cfg_;
    std::unique_ptr<daemon::BenchDaemon> d_;
    daemon::RunId id_ = 0;
};

#define DUMP(b) "events: " << (b).events().dump(1)

// One sample of GET /metrics (what Prometheus scrapes), e.g. `cellbench_instrument_faults_total{instrument="neware"}`;
// -1 when the series is absent.
double metric(FaultBench& b, const std::string& series) {
    const std::string text = b.d().metrics_text();
    for (std::size_t at = text.find(series + " "); at != std::string::npos; at = text.find(series + " ", at + 1))
        if (at == 0 || text[at - 1] == '\n') return std::stod(text.substr(at + series.size() + 1));
    return -1.0;
}
std::string series(const std::string& family, const std::string& instrument) {
    return family + "{instrument=\"" + instrument + "\"}";
}

}  // namespace

// ---- Neware ----------------------------------------------------------------------------------------------

TEST(DaemonFaults, NewareConnectionDroppedReconnectsAndTheRunContinues) {
    FaultBench b("neware-drop");
    ASSERT_TRUE(b.start_discharging());
    const double faults0 = metric(b, series("cellbench_instrument_faults_total", "neware"));
    const double reconnects0 = metric(b, series("cellbench_instrument_reconnects_total", "neware"));
    ASSERT_GE(faults0, 0.0) << b.d().metrics_text();
    ASSERT_GE(reconnects0, 0.0);
    b.neware().drop_connections();
    ASSERT_TRUE(b.wait_for("fault", "neware")) << DUMP(b);
    ASSERT_TRUE(b.wait_for("recovery", "neware")) << DUMP(b);
    // /metrics counts the fault and the reconnect.
    EXPECT_GT(metric(b, series("cellbench_instrument_faults_total", "neware")), faults0);
    EXPECT_TRUE(eventually([&] { return metric(b, series("cellbench_instrument_reconnects_total", "neware")) > reconnects0; }, 10s))
        << b.d().metrics_text();
    const auto f = b.find("fault", "neware").front();
    EXPECT_EQ(f["level"], "warning");
    EXPECT_EQ(f["detail"]["action"], "reconnect");
    EXPECT_TRUE(f["test_time_s"].is_number());
    const auto r = b.find("recovery", "neware").front();
    EXPECT_EQ(r["level"], "info");
    EXPECT_GE(r["detail"]["occurrences"].get<int>(), 1);
    EXPECT_TRUE(b.still_running());
    // Readings flow again: the live voltage keeps being refreshed.
    const double t0 = b.d().status()["live"]["time_unix_s"].get<double>();
    EXPECT_TRUE(eventually([&] { return b.d().status()["live"]["time_unix_s"].get<double>() > t0; }, 10s));
    b.stop();
}

TEST(DaemonFaults, NewareUnreachableWhenARunStartsTheStartIsSentWhenItIsBack) {
    // The start command cannot leave the daemon (no connection): the tester cannot have acted on it, so it is
    // sent again while the loss grace lasts instead of aborting the run.
    // The program waits 30 bench s (3 s wall) for thermal equilibrium before its cycler segment; the tester
    // becomes unreachable during that wait (a run cannot be started while the cycler is offline).
    FaultBench b("neware-refuse-start", {}, 30.0, 30.0);
    ASSERT_TRUE(eventually([&] { return test::instruments_connected(b.d()); }, 30s)) << b.d().status().dump();
    b.start_run();
    b.neware().set_refuse_connections(true);
    b.neware().drop_connections();
    ASSERT_TRUE(b.wait_for("fault", "neware", "", 30s)) << DUMP(b);
    ASSERT_TRUE(eventually([&] {
        for (const auto& e : b.find("fault", "neware"))
            if (e["message"].get<std::string>().find("start not sent") != std::string::npos) return true;
        return false;
    }, 30s)) << "the start was never attempted while the tester was unreachable: " << DUMP(b);
    // Longer than the client's request timeout: starts keep expiring unsent.
    std::this_thread::sleep_for(2s);
    EXPECT_EQ(b.state(), "running") << b.error() << " " << DUMP(b);
    EXPECT_GT(b.plant_current_a(), -0.5) << "nothing can have started the tester's program yet";
    b.neware().set_refuse_connections(false);
    EXPECT_TRUE(b.still_running()) << DUMP(b);
    EXPECT_TRUE(b.wait_for("recovery", "neware")) << DUMP(b);
}

TEST(DaemonFaults, NewareRefusedBeyondGraceAbortsAndTheStopReachesTheTesterWhenItIsBack) {
    FaultBench b("neware-refuse", [](daemon::BenchConfig& c) { c.faults.cycler.grace_s = kShortGraceS; });
    ASSERT_TRUE(b.start_discharging());
    b.neware().set_refuse_connections(true);
    b.neware().drop_connections();
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("no cell voltage"), std::string::npos) << b.error();
    EXPECT_TRUE(b.has("fault", "neware"));
    EXPECT_TRUE(b.has("abort"));
    EXPECT_FALSE(b.has("recovery", "neware"));
    // The tester runs its step file on its own: unreachable, it still discharges. The stop is sent again
    // until it is acknowledged, so the current goes off as soon as the tester can be reached.
    // Unreachable for longer than a request's timeout: the first stop fails, the cell still discharges.
    std::this_thread::sleep_for(1500ms);
    EXPECT_LT(b.plant_current_a(), -1.5) << "the simulated tester should still run its program";
    // The record says so while it is true: the abort does not claim the current is off, and an error event
    // says the stop has not reached the tester yet.
    const auto aborts = b.find("abort");
    ASSERT_FALSE(aborts.empty()) << DUMP(b);
    EXPECT_EQ(aborts.front()["message"].get<std::string>().find("current stopped"), std::string::npos)
        << aborts.front().dump();
    EXPECT_TRUE(eventually([&] {
        for (const auto& e : b.find("cycler"))
            if (e["level"] == "error" && e["message"].get<std::string>().find("stop not acknowledged") != std::string::npos)
                return true;
        return false;
    }, 20s)) << "no event says the stop did not reach the tester: " << DUMP(b);
    b.neware().set_refuse_connections(false);
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A; " << DUMP(b);
    json ack;
    ASSERT_TRUE(eventually([&] {
        for (const auto& e : b.find("cycler"))
            if (e["detail"].is_object() && e["detail"].contains("acknowledged_t_s")) return ack = e, true;
        return false;
    }, 20s)) << DUMP(b);
    EXPECT_GE(ack["detail"]["attempts"].get<int>(), 2) << "the first stop could not reach the tester: " << ack.dump();
    EXPECT_TRUE(b.wait_for("recovery", "neware")) << DUMP(b);
    EXPECT_EQ(b.state(), "aborted");
}

TEST(DaemonFaults, NewareStalledResponsesWithinGraceRecover) {
    FaultBench b("neware-stall");
    ASSERT_TRUE(b.start_discharging());
    b.neware().set_stall_responses(true);
    ASSERT_TRUE(b.wait_for("fault", "neware", "timeout")) << DUMP(b);
    b.neware().set_stall_responses(false);
    ASSERT_TRUE(b.wait_for("recovery", "neware")) << DUMP(b);
    EXPECT_TRUE(b.still_running());
    b.stop();
}

TEST(DaemonFaults, NewareStalledBeyondGraceAbortsWithCurrentOff) {
    FaultBench b("neware-stall-abort", [](daemon::BenchConfig& c) { c.faults.cycler.grace_s = kShortGraceS; });
    ASSERT_TRUE(b.start_discharging());
    b.neware().set_stall_responses(true);  // requests are carried out, never answered
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("no cell voltage"), std::string::npos) << b.error();
    EXPECT_TRUE(b.has("fault", "neware", "timeout")) << DUMP(b);
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
    b.neware().set_stall_responses(false);
}

TEST(DaemonFaults, NewareMalformedFramesAreFaultsAndTheRunContinuesWhenTheyStop) {
    FaultBench b("neware-malformed");
    ASSERT_TRUE(b.start_discharging());
    const double lost0 = metric(b, series("cellbench_instrument_lost_frames_total", "neware"));
    ASSERT_GE(lost0, 0.0) << b.d().metrics_text();
    b.neware().set_malformed_responses(true);
    ASSERT_TRUE(b.wait_for("fault", "neware", "protocol_error")) << DUMP(b);
    EXPECT_GT(metric(b, series("cellbench_instrument_lost_frames_total", "neware")), lost0);
    std::this_thread::sleep_for(300ms);
    b.neware().set_malformed_responses(false);
    ASSERT_TRUE(b.wait_for("recovery", "neware")) << DUMP(b);
    EXPECT_EQ(b.find("fault", "neware").size(), 1u) << "one episode, one fault event; " << DUMP(b);
    EXPECT_GT(b.find("recovery", "neware").front()["detail"]["occurrences"].get<int>(), 1);
    EXPECT_TRUE(b.still_running());
    b.stop();
}

TEST(DaemonFaults, ParallelGroupMemberInProtectAbortsAtOnce) {
    FaultBench b("neware-protect");
    ASSERT_TRUE(b.start_discharging());
    ASSERT_TRUE(b.neware().inject_member_status(2, protocol::neware::ChannelStatus::protect));
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
    const auto faults = b.find("fault", "neware");
    ASSERT_FALSE(faults.empty()) << DUMP(b);
    bool fatal = false;
    for (const auto& f : faults) fatal = fatal || (f["level"] == "error" && f["detail"]["action"] == "abort");
    EXPECT_TRUE(fatal) << DUMP(b);
    EXPECT_TRUE(b.has("abort"));
    EXPECT_NE(b.error().find("protect"), std::string::npos) << b.error();
}

// ---- Chamber ---------------------------------------------------------------------------------------------

TEST(DaemonFaults, ChamberTimeoutsWithinGraceReconnectAndTheRunContinues) {
    FaultBench b("chamber-timeout");
    ASSERT_TRUE(b.start_discharging());
    b.chamber().set_unresponsive(true);
    ASSERT_TRUE(b.wait_for("fault", "chamber", "timeout")) << DUMP(b);
    b.chamber().set_unresponsive(false);
    ASSERT_TRUE(b.wait_for("recovery", "chamber")) << DUMP(b);
    EXPECT_TRUE(b.still_running());
    b.stop();
}

TEST(DaemonFaults, ChamberUnresponsiveBeyondGraceAbortsWithCurrentOff) {
    FaultBench b("chamber-silent", [](daemon::BenchConfig& c) { c.faults.chamber.grace_s = kShortGraceS; });
    ASSERT_TRUE(b.start_discharging());
    b.chamber().set_unresponsive(true);
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("chamber silent"), std::string::npos) << b.error();
    EXPECT_TRUE(b.has("fault", "chamber", "timeout")) << DUMP(b);
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
    // The safe set point is written again until the chamber takes it.
    b.chamber().set_unresponsive(false);
    EXPECT_TRUE(eventually([&] { return std::abs(b.d().status()["live"]["setpoint_c"].get<double>() - 25.0) < 1e-6; }, 20s))
        << b.d().status()["live"].dump();
}

TEST(DaemonFaults, ChamberExceptionResponsesAreRetriedUnderTheReconnectPolicy) {
    FaultBench b("chamber-exception");
    ASSERT_TRUE(b.start_discharging());
    b.chamber().set_exception_response(std::uint8_t{6});  // server device busy
    ASSERT_TRUE(b.wait_for("fault", "chamber", "exception_response")) << DUMP(b);
    EXPECT_EQ(b.find("fault", "chamber", "exception_response").front()["detail"]["exception_code"], 6);
    b.chamber().set_exception_response(std::nullopt);
    ASSERT_TRUE(b.wait_for("recovery", "chamber")) << DUMP(b);
    EXPECT_TRUE(b.still_running());
    b.stop();
}

TEST(DaemonFaults, ChamberExceptionResponsesAbortUnderTheAbortPolicy) {
    FaultBench b("chamber-exception-abort",
                 [](daemon::BenchConfig& c) { c.faults.chamber.exception_response = daemon::FaultAction::abort; });
    ASSERT_TRUE(b.start_discharging());
    b.chamber().set_exception_response(std::uint8_t{4});  // server device failure
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("exception"), std::string::npos) << b.error();
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
    b.chamber().set_exception_response(std::nullopt);
}

TEST(DaemonFaults, ChamberAlarmBitAbortsAtOnce) {
    FaultBench b("chamber-alarm");
    ASSERT_TRUE(b.start_discharging());
    ASSERT_TRUE(b.chamber().set_alarm("door_open", true));
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("alarm"), std::string::npos) << b.error();
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
    EXPECT_TRUE(b.has("abort"));
}

TEST(DaemonFaults, ChamberSetpointNotReachedIsAnEventUnderTheEventPolicy) {
    // 40 degC asked of a chamber whose heater failed: the air drifts to the lab's 22 degC instead.
    FaultBench b("chamber-setpoint", [](daemon::BenchConfig& c) { c.faults.chamber.setpoint_timeout_s = 20.0; }, 40.0);
    b.d().plant()->set_chamber_heater_failed(true);
    ASSERT_TRUE(b.start_discharging());
    ASSERT_TRUE(b.wait_for("fault", "chamber", "setpoint_not_reached")) << DUMP(b);
    EXPECT_EQ(b.find("fault", "chamber", "setpoint_not_reached").front()["level"], "warning");
    EXPECT_TRUE(b.still_running());
    b.stop();
}

TEST(DaemonFaults, ChamberSetpointNotReachedAbortsUnderTheAbortPolicy) {
    FaultBench b("chamber-setpoint-abort", [](daemon::BenchConfig& c) {
        c.faults.chamber.setpoint_timeout_s = 20.0;
        c.faults.chamber.setpoint_not_reached = daemon::SetpointAction::abort;
    }, 40.0);
    b.d().plant()->set_chamber_heater_failed(true);
    ASSERT_TRUE(b.start_discharging());
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("setpoint_not_reached"), std::string::npos) << b.error();
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
}

// ---- DEWE ------------------------------------------------------------------------------------------------

TEST(DaemonFaults, DeweSilenceBeyondGraceAbortsForWantOfCellTemperature) {
    FaultBench b("dewe-silence", [](daemon::BenchConfig& c) { c.faults.daq.grace_s = kShortGraceS; });
    ASSERT_TRUE(b.start_discharging());
    b.dewe().set_silent(true);
    ASSERT_TRUE(b.wait_for("fault", "dewe", "silence")) << DUMP(b);
    ASSERT_TRUE(b.wait_failed()) << DUMP(b);
    EXPECT_NE(b.error().find("no cell temperature"), std::string::npos) << b.error();
    EXPECT_TRUE(b.wait_current_off()) << b.plant_current_a() << " A";
    b.dewe().set_silent(false);
}

TEST(DaemonFaults, DeweSilenceWithinGraceRecovers) {
    FaultBench b("dewe-silence-short");
    ASSERT_TRUE(b.start_discharging());
    const double faults0 = metric(b, series("cellbench_instrument_faults_total", "dewe"));
    const double reconnects0 = metric(b, series("cellbench_instrument_reconnects_total", "dewe"));
    b.dewe().set_silent(true);
    ASSERT_TRUE(b.wait_for("fault", "dewe", "silence")) << DUMP(b);
    EXPECT_GT(metric(b, series("cellbench_instrument_faults_total", "dewe")), faults0) << b.d().metrics_text();
    b.dewe().set_silent(false);
    ASSERT_TRUE(b.wait_for("recovery", "dewe")) << DUMP(b);
    EXPECT_TRUE(eventually([&] { return metric(b, series("cellbench_instrument_reconnects_total", "dewe")) > reconnects0; }, 10s))
        << b.d().metrics_text();
    EXPECT_TRUE(b.still_running());
    b.stop();
}

// A loss event of this run whose counts satisfy pred.
json loss_event(FaultBench& b, const std::function<bool(const json&)>& pred) {
    json hit;
    eventually([&] {
        for (const auto& e : b.find("fault", "dewe", "data_loss"))
            if (pred(e["detail"])) return hit = e, true;
        return false;
    }, 30s);
    return hit;
}

TEST(DaemonFaults, DeweLostFramesAreCountedInAnEvent) {
    FaultBench b("dewe-lost", [](daemon::BenchConfig& c) { c.faults.daq.loss_event_interval_s = 0.5; });
    ASSERT_TRUE(b.start_discharging());
    const double lost0 = metric(b, series("cellbench_instrument_lost_frames_total", "dewe"));
    ASSERT_GE(lost0, 0.0) << b.d().metrics_text();
    b.dewe().drop_samples(5);
    // 5 samples of 2 frames each missing from the counters (all in one event, or spread over a few).
    const json e = loss_event(b, [](const json& d) { return d["total_lost_samples"].get<int>() >= 5; });
    ASSERT_TRUE(e.is_object()) << DUMP(b);
    EXPECT_GE(e["detail"]["total_lost_frames"].get<int>(), 10) << e.dump();
    EXPECT_EQ(e["level"], "warning");
    int lost = 0;
    for (const auto& x : b.find("fault", "dewe", "data_loss")) lost += x["detail"]["lost_samples"].get<int>();
    EXPECT_GE(lost, 5);
    EXPECT_GE(metric(b, series("cellbench_instrument_lost_frames_total", "dewe")), lost0 + 10) << b.d().metrics_text();
    EXPECT_TRUE(b.still_running());
    EXPECT_GE(b.d().status()["live"]["surface_c"].get<double>(), 20.0);
    b.stop();
}

TEST(DaemonFaults, DeweGarbageFramesAreIgnoredAndCounted) {
    FaultBench b("dewe-garbage", [](daemon::BenchConfig& c) { c.faults.daq.loss_event_interval_s = 0.5; });
    ASSERT_TRUE(b.start_discharging());
    const auto samples_before = b.d().store().get_run(b.id())->daq_samples;
    b.dewe().send_garbage(10);
    const json e = loss_event(b, [](const json& d) { return d["total_garbage_frames"].get<int>() >= 10; });
    ASSERT_TRUE(e.is_object()) << DUMP(b);
    int garbage = 0, lost = 0;
    for (const auto& x : b.find("fault", "dewe", "data_loss")) {
        garbage += x["detail"]["garbage_frames"].get<int>();
        lost += x["detail"]["lost_samples"].get<int>();
    }
    EXPECT_GE(garbage, 10);
    EXPECT_EQ(lost, 0) << "garbage between frames loses no sample; " << DUMP(b);
    EXPECT_TRUE(b.still_running());
    // Samples keep arriving after the garbage.
    EXPECT_TRUE(eventually([&] {
        b.d().store().flush();
        return b.d().store().get_run(b.id())->daq_samples > samples_before + 20;
    }, 10s));
    b.stop();
}

namespace {

// Issue 14: at shutdown the daemon waited a fixed 3 s for the stop and the safe set point, although the
// chamber's config allows (retries + 1) x response_timeout_ms per command: behind a poll answered on its third
// 2 s attempt, the safe set point was still queued when the connections closed, and never written. The wait
// now follows the configured timeouts.
TEST(DaemonFaults, ShutdownWaitsForTheSafeSetPointAsLongAsTheChamberTimeoutsAllow) {
    FaultBench b("shutdown-wait", [](daemon::BenchConfig& c) {
        c.faults.chamber.response_timeout_ms = 2000;
        c.faults.chamber.retries = 2;
    });
    ASSERT_TRUE(b.start_discharging());
    ASSERT_NEAR(b.d().plant()->read().chamber_setpoint_c, 30.0, 1e-9);
    // A poll is under way when the daemon shuts down: its first two attempts (0 s, 2 s) go unanswered, the
    // third (4 s) is answered; the safe set point write waits behind it on the chamber's worker.
    b.chamber().set_unresponsive(true);
    std::thread back([&] {
        std::this_thread::sleep_for(3s);
        b.chamber().set_unresponsive(false);
    });
    std::this_thread::sleep_for(500ms);
    b.d().shutdown();
    back.join();
    EXPECT_NEAR(b.d().plant()->read().chamber_setpoint_c, 25.0, 1e-9) << "the safe set point never reached the chamber";
    EXPECT_LT(std::abs(b.plant_current_a()), 0.05);
}

}  // namespace
