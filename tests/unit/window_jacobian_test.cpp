// The global fit's window Jacobian (issue 11, speed): the derivative passes that start where a variable first
// enters a window and stop where the RC voltages have forgotten it must give Ceres' dynamic autodiff over the
// whole window (the reference), on the layouts where they skip most: a slow discharge across every knot, logged
// finely, next to an HPPC, with the temperature and current dependences, the slow pair, the step lag and a slow
// discharge's SOC offset and capacity scale fitted.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "unit/hppc_synthetic.hpp"

namespace {

namespace est = cellbench::estimator;

TEST(WindowJacobian, DerivativePassesGiveTheDynamicAutodiffJacobianAtTheStartAndAtTheFit) {
    constexpr double kPulseA = 4.5;
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    const auto hppc = cellbench::test::synthesize(cellbench::test::hppc_program(5, 900.0, kPulseA), so);
    // A C/10 discharge from 95 % through the whole table, then a rest long enough for the slow pair.
    so.dt_s = 2.0;
    so.soc0 = 0.95;
    const double c10_a = cellbench::test::kCapacityAh / 10.0;
    auto c10 = cellbench::test::synthesize({{60.0, 0.0, "Rest"}, {30000.0, -c10_a, "CC DChg"}, {1800.0, 0.0, "Rest"}}, so);
    // The surface warming by 8 K over the discharge: the resistances' temperature dependence (Ea) is fitted too.
    c10.surface_c.resize(c10.size());
    for (std::size_t k = 0; k < c10.size(); ++k) c10.surface_c[k] = 25.0 + 8.0 * c10.time_s[k] / c10.time_s.back();

    auto o = cellbench::test::characterization_options();
    o.global.check_jacobian = true;
    o.global.smoothness = 300.0;  // one weight: the check, not the cross-validation, is under test
    o.global.start_time_constants_s.clear();
    o.global.max_iterations = 15;
    const auto c = est::characterize({hppc, c10}, o);
    ASSERT_TRUE(c.global.has_value());
    ASSERT_GE(c.global->windows.size(), 3u);
    EXPECT_TRUE(c.global->temperature_dependence) << "Ea not fitted: the check would not exercise its derivative";
    bool slow_discharge = false;
    for (const auto& w : c.global->windows) slow_discharge |= w.kind == "discharge" && w.soc_max - w.soc_min > 0.5;
    EXPECT_TRUE(slow_discharge) << "no window crosses most of the table: the check would not exercise the skipping";
    ASSERT_TRUE(std::isfinite(c.global->jacobian_mismatch));
    EXPECT_LT(c.global->jacobian_mismatch, 1e-9);
}

// A drive cycle logged every 0.1 s, its current changing at every row (every row a tick): its window keeps at most
// GlobalFitOptions::max_residual_rate_hz voltage residuals per second (every m-th tick's, step residuals with them),
// the model still stepping through every tick, and the derivative passes still give the reference Jacobian there.
TEST(WindowJacobian, ADenselyLoggedDriveCycleIsThinnedToItsResidualRateAndItsJacobianHolds) {
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    const auto hppc = cellbench::test::synthesize(cellbench::test::hppc_program(3, 900.0, 4.5), so);
    so.dt_s = 0.1;
    so.soc0 = 0.9;
    std::vector<cellbench::test::Step> program{{60.0, 0.0, "Rest"}};
    double i = -4.0;
    for (int k = 0; k < 3000; ++k) {  // 5 min: a smooth walk plus a jump every second, about 1.5C of discharge
        i = std::clamp(i + 0.15 * std::sin(0.37 * k) + (k % 10 == 0 ? 1.5 * std::cos(1.3 * k) : 0.0), -12.0, 4.0);
        program.push_back({0.1, i, "Drive"});
    }
    program.push_back({700.0, 0.0, "Rest"});
    auto drive = cellbench::test::synthesize(program, so);
    drive.source = "drive";
    for (auto& c : drive.step_count) c = c == 0 ? 0 : (c < program.size() ? 1 : 2);  // one logger step for the drive

    auto o = cellbench::test::characterization_options();
    o.global.check_jacobian = true;
    o.global.smoothness = 300.0;
    o.global.start_time_constants_s.clear();
    o.global.max_iterations = 10;
    const auto c = est::characterize({hppc, drive}, o);
    ASSERT_TRUE(c.global.has_value());
    const est::GlobalWindow* dense = nullptr;
    for (const auto& w : c.global->windows)
        if (w.recording == 1 && (!dense || w.end - w.begin > dense->end - dense->begin)) dense = &w;
    ASSERT_NE(dense, nullptr);
    const double duration_s = drive.time_s[dense->end - 1] - drive.time_s[dense->begin];
    EXPECT_LE(static_cast<double>(dense->residuals), o.global.max_residual_rate_hz * duration_s + 1.0);
    EXPECT_GT(dense->residuals, 100u) << "thinned to almost nothing";
    EXPECT_TRUE(std::any_of(c.global->notes.begin(), c.global->notes.end(),
                            [](const std::string& n) { return n.find("drive: logged so densely") != std::string::npos; }));
    for (const auto& w : c.global->windows) {
        if (w.recording == 0) {
            EXPECT_LT(w.residuals, 2000u);  // the HPPC at 1 s: untouched (no note for it)
        }
    }
    EXPECT_FALSE(std::any_of(c.global->notes.begin(), c.global->notes.end(),
                             [](const std::string& n) { return n.find("synthetic: logged so densely") != std::string::npos; }));
    ASSERT_TRUE(std::isfinite(c.global->jacobian_mismatch));
    EXPECT_LT(c.global->jacobian_mismatch, 1e-9);

    // Without the limit every tick of the drive is a residual.
    o.global.max_residual_rate_hz = 0.0;
    o.global.check_jacobian = false;
    const auto full = est::characterize({hppc, drive}, o);
    ASSERT_TRUE(full.global.has_value());
    std::size_t most = 0;
    for (const auto& w : full.global->windows)
        if (w.recording == 1) most = std::max(most, w.residuals);
    EXPECT_GT(most, 2000u);
    EXPECT_GT(most, 2 * dense->residuals);
}

}  // namespace
