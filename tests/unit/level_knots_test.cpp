// The global fit's table breakpoints sit at the test's own SOC levels (issue 11, layout-agnostic): a test whose
// levels are unevenly spaced (here 7 % and 12 % steps, as the Panasonic 18650PF's HPPC mixes 5 % and 10 %) gets a
// breakpoint at every level, where a uniform grid puts knots between levels that only the SOC-step discharges
// reach (their resistances then alternate along SOC), and R0 comes out right at every level.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "unit/hppc_synthetic.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::test::Step;

TEST(LevelKnots, UnevenLevelsEachGetABreakpointAndTheirR0) {
    const std::vector<double> steps = {0.07, 0.07, 0.12, 0.12, 0.07};  // SOC drained between levels
    constexpr double kPulseA = 4.5;
    std::vector<Step> program;
    std::vector<double> levels = {1.0};
    for (double d : steps) {
        for (const auto& s : cellbench::test::pulse_set_program(700.0, kPulseA)) program.push_back(s);
        // The step drains d of the capacity net of the pulse set (30 s discharge, 10 s charge).
        const double ah = d * cellbench::test::kCapacityAh - 20.0 * kPulseA / 3600.0;
        program.push_back({std::round(ah / kPulseA * 3600.0), -kPulseA, "CC DChg"});
        levels.push_back(levels.back() - d);
    }
    for (const auto& s : cellbench::test::pulse_set_program(700.0, kPulseA)) program.push_back(s);
    program.push_back({700.0, 0.0, "Rest"});

    cellbench::test::SyntheticOptions so;
    so.dt_s = 0.1;  // as the P45B bench logs (at 1 s the first row after a step carries 1 s of the pairs)
    so.voltage_noise_v = 2e-4;
    const auto rec = cellbench::test::synthesize(program, so);
    auto o = cellbench::test::characterization_options();
    const auto c = est::characterize({rec}, o);
    ASSERT_TRUE(c.global.has_value());
    // The test stops at 55 % SOC: it does not measure the capacity, the given one is used.
    EXPECT_EQ(c.capacity.method, "given") << c.capacity.method;

    // The RC breakpoints are every ocv_knots_per_interval-th table row (the OCV has its own finer grid).
    const auto& soc = c.params.soc;
    const int m = c.global->ocv_knots_per_interval;
    ASSERT_GE(m, 2);
    std::vector<double> knots;
    for (std::size_t j = 0; j < soc.size(); j += static_cast<std::size_t>(m)) knots.push_back(soc[j]);
    const double r0_true = cellbench::test::p45b_discharge().r0_ohm;
    for (double level : levels) {
        const auto nearest = *std::min_element(knots.begin(), knots.end(), [&](double a, double b) {
            return std::abs(a - level) < std::abs(b - level);
        });
        EXPECT_NEAR(nearest, level, 0.006) << "no breakpoint at the level " << level;
        const double r0 = c.params.rc_at(level, -1).r0_ohm;
        EXPECT_NEAR(r0, r0_true, 0.03 * r0_true) << "discharge R0 at the level " << level;
    }
}

// The current dependence's reference current (the tables hold the RC resistances at it) is the pulses' current,
// whatever else was handed in and however often it was logged: a C/20 discharge logged 4 times a second has more
// rows than the whole HPPC, and a median over every row had made the tables resistances at C/20.
TEST(GlobalFitReference, IsThePulseCurrentNotTheRowMedianOfALowRateDischarge) {
    constexpr double kPulseA = 4.5;
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    const auto hppc = cellbench::test::synthesize(cellbench::test::hppc_program(4, 600.0, kPulseA), so);
    const double c20_a = cellbench::test::kCapacityAh / 20.0;
    so.dt_s = 0.25;
    so.soc0 = 0.9;
    const auto c20 = cellbench::test::synthesize({{60.0, 0.0, "Rest"}, {5400.0, -c20_a, "CC DChg"}, {600.0, 0.0, "Rest"}}, so);
    std::size_t hppc_rows = 0, c20_rows = 0;
    for (double i : hppc.current_a) hppc_rows += std::abs(i) > 0.1;
    for (double i : c20.current_a) c20_rows += std::abs(i) > 0.1;
    ASSERT_GT(c20_rows, hppc_rows);  // the case: the low-rate rows outnumber the pulse rows
    auto o = cellbench::test::characterization_options();
    const auto c = est::characterize({hppc, c20}, o);
    ASSERT_TRUE(c.global.has_value());
    EXPECT_GT(c.global->reference_current_a, 0.5 * kPulseA);
    EXPECT_LT(c.global->reference_current_a, 1.01 * kPulseA);
}

// A test's last level, after its SOC step stopped near empty, gets pulses too: on a real cell they run into the
// cut-off. Those windows lie wholly below 2 % SOC; the global fit leaves them out and says so, and fits the
// levels above them as before.
TEST(GlobalFitWindows, PulsesNearEmptyAreLeftOutAndNamed) {
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    auto program = cellbench::test::hppc_program(10, 700.0, 4.5);  // levels 100, 90, ..., 10 %, then empty
    program.pop_back();                                            // its final rest: the near-empty set follows
    for (const auto& s : cellbench::test::pulse_set_program(700.0, 4.5)) program.push_back(s);
    program.push_back({700.0, 0.0, "Rest"});
    const auto rec = cellbench::test::synthesize(program, so);
    const auto c = est::characterize({rec}, cellbench::test::characterization_options());
    ASSERT_TRUE(c.global.has_value());
    std::size_t pulse_windows = 0;
    double lowest_top = 1.0;  // the lowest SOC a pulse window reaches up to
    for (const auto& w : c.global->windows)
        if (w.kind == "pulses") ++pulse_windows, lowest_top = std::min(lowest_top, w.soc_max);
    EXPECT_EQ(pulse_windows, 10u);  // the ten levels above 2 % (each with the SOC step after it)
    EXPECT_GT(lowest_top, 0.09);    // the window of the set at empty is not among them
    const bool named = std::any_of(c.global->notes.begin(), c.global->notes.end(),
                                   [](const std::string& n) { return n.find("left out of the fit") != std::string::npos; });
    EXPECT_TRUE(named) << "the summary must say which pulses were left out";
}

TEST(GlobalFitWindows, PulsesLeftOutDoNotSetTheCurrentRange) {
    // Every level pulsed at 4.5 A, then a set at three times that current near empty: the fit leaves that set out,
    // so its current must not count either (a 13.5 A pulse would otherwise span a 3:1 current range and switch
    // the current dependence on, identified from pulses the fit never saw).
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    auto program = cellbench::test::hppc_program(10, 700.0, 4.5);
    program.pop_back();
    for (const auto& s : cellbench::test::pulse_set_program(700.0, 13.5)) program.push_back(s);
    program.push_back({700.0, 0.0, "Rest"});
    const auto rec = cellbench::test::synthesize(program, so);
    const auto c = est::characterize({rec}, cellbench::test::characterization_options());
    ASSERT_TRUE(c.global.has_value());
    for (const auto& w : c.global->windows) EXPECT_GT(w.soc_max, 0.05) << "the set near empty is left out";
    EXPECT_FALSE(c.global->current_dependence) << "every pulse the fit uses is at 4.5 A";
    EXPECT_NEAR(c.global->reference_current_a, 4.5, 0.1);
}

}  // namespace
