// The bench file's "fault_policy" (issue 6): defaults when absent (every grace = safety.instrument_loss_grace_s),
// every field read, every problem reported at once with its JSON path.
#include <gtest/gtest.h>

#include <functional>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/config.hpp"
#include "config_test_support.hpp"

using namespace cellbench;
using namespace cellbench::daemon;
using namespace cellbench::testing;
using nlohmann::json;

namespace {

json sim_document() { return read_json(kConfigDir / "bench.sim.json"); }

BenchConfig parse(const json& j) { return parse_bench_config_text(j.dump(), "bench.json", kConfigDir); }

}  // namespace

TEST(FaultPolicyConfig, AbsentMeansEveryGraceIsTheSafetyGraceAndTheDriversDefaults) {
    json j = sim_document();
    j.erase("fault_policy");
    j["safety"]["instrument_loss_grace_s"] = 7.5;
    const auto b = parse(j);
    EXPECT_DOUBLE_EQ(b.faults.cycler.grace_s, 7.5);
    EXPECT_DOUBLE_EQ(b.faults.chamber.grace_s, 7.5);
    EXPECT_DOUBLE_EQ(b.faults.daq.grace_s, 7.5);
    EXPECT_EQ(b.faults.cycler.reconnect_initial_ms, 100);
    EXPECT_EQ(b.faults.cycler.reconnect_max_ms, 5000);
    EXPECT_EQ(b.faults.chamber.exception_response, FaultAction::reconnect);
    EXPECT_EQ(b.faults.chamber.setpoint_not_reached, SetpointAction::event);
    EXPECT_DOUBLE_EQ(b.faults.chamber.setpoint_timeout_s, 1800.0);
}

TEST(FaultPolicyConfig, EveryFieldIsRead) {
    json j = sim_document();
    j["fault_policy"] = {
        {"cycler", {{"grace_s", 30}, {"reconnect_initial_ms", 200}, {"reconnect_max_ms", 8000}}},
        {"chamber", {{"grace_s", 120}, {"response_timeout_ms", 800}, {"retries", 3}, {"exception_response", "abort"},
                     {"setpoint_tolerance_c", 0.5}, {"setpoint_timeout_s", 900}, {"setpoint_not_reached", "abort"}}},
        {"daq", {{"grace_s", 4}, {"loss_event_interval_s", 10}}}};
    const auto b = parse(j);
    EXPECT_DOUBLE_EQ(b.faults.cycler.grace_s, 30);
    EXPECT_EQ(b.faults.cycler.reconnect_initial_ms, 200);
    EXPECT_EQ(b.faults.cycler.reconnect_max_ms, 8000);
    EXPECT_DOUBLE_EQ(b.faults.chamber.grace_s, 120);
    EXPECT_EQ(b.faults.chamber.response_timeout_ms, 800);
    EXPECT_EQ(b.faults.chamber.retries, 3);
    EXPECT_EQ(b.faults.chamber.exception_response, FaultAction::abort);
    EXPECT_DOUBLE_EQ(b.faults.chamber.setpoint_tolerance_c, 0.5);
    EXPECT_DOUBLE_EQ(b.faults.chamber.setpoint_timeout_s, 900);
    EXPECT_EQ(b.faults.chamber.setpoint_not_reached, SetpointAction::abort);
    EXPECT_DOUBLE_EQ(b.faults.daq.grace_s, 4);
    EXPECT_DOUBLE_EQ(b.faults.daq.loss_event_interval_s, 10);
}

TEST(FaultPolicyConfig, EveryProblemIsReportedAtOnce) {
    json j = sim_document();
    j["fault_policy"] = {
        {"cycler", {{"grace_s", 0}, {"reconnect_initial_ms", 5000}, {"reconnect_max_ms", 100}}},
        {"chamber", {{"exception_response", "ignore"}, {"setpoint_not_reached", true}, {"retries", -1}}},
        {"daq", {{"grace_s", 1.0}, {"loss_interval", 3}}},
        {"dewe", {}}};
    const auto issues = issues_of([&] { parse(j); });
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.cycler.grace_s", "number > 0"));
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.cycler", "reconnect_initial_ms <= reconnect_max_ms"));
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.chamber.exception_response", "\"reconnect\" or \"abort\""));
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.chamber.setpoint_not_reached", "\"event\" or \"abort\""));
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.chamber.retries"));
    // The DAQ's grace cannot be shorter than the time after which the stream counts as silent (2 s here).
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.daq.grace_s", "stale_after_s"));
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.daq.loss_interval", "unknown field"));
    EXPECT_TRUE(has_issue(issues, "$.fault_policy.dewe", "unknown field"));
    EXPECT_GE(issues.size(), 8u);
}

TEST(FaultPolicyConfig, ShippedBenchFilesLoadWithTheirPolicy) {
    for (const char* f : {"bench.sim.json", "bench.hil.json", "bench.lab.json"}) {
        const auto b = load_bench_config(kConfigDir / f);
        EXPECT_GT(b.faults.cycler.grace_s, 0) << f;
        EXPECT_GE(b.faults.daq.grace_s, b.daq.stale_after_s) << f;
    }
}
