// The global fit's window Jacobian (issue 11, speed): the derivative passes that start where a variable first
// enters a window and stop where the RC voltages have forgotten it must give Ceres' dynamic autodiff over the
// whole window (the reference), on the layouts where they skip most: a slow discharge across every knot, logged
// finely, next to an HPPC, with the temperature and current dependences, the slow pair, the step lag and a slow
// discharge's SOC offset and capacity scale fitted.
#include <gtest/gtest.h>

#include <cmath>
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

}  // namespace
