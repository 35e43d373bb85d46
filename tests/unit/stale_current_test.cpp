// Rows a cycler writes at the start of a step with the new voltage and the old current (a published Digatron
// HPPC starts every pulse so): found by what they show, given the step's current, said in the fit's warnings.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/stale_current.hpp"
#include "unit/hppc_synthetic.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;

Recording rows(const std::vector<double>& current_a, const std::vector<double>& voltage_v) {
    Recording r;
    r.source = "rows";
    for (std::size_t k = 0; k < current_a.size(); ++k) r.time_s.push_back(static_cast<double>(k));
    r.current_a = current_a;
    r.voltage_v = voltage_v;
    return r;
}

TEST(StaleCurrentRows, AStepsFirstRowWithTheOldCurrentAndTheNewVoltageIsFound) {
    // As in the FZJ INR21700 reference file: rest at 4.0211 V, a row 7 ms into a 5 A discharge reading 0 A at
    // 3.9420 V, then -5 A at 3.9345 V.
    Recording r = rows({0, 0, 0, -5, -5, 0, 0}, {4.0211, 4.0211, 3.9420, 3.9345, 3.9234, 3.9736, 3.9776});
    EXPECT_EQ(est::stale_current_rows(r), (std::vector<std::size_t>{2}));
    EXPECT_EQ(est::take_next_current_for_stale_rows(r), 1u);
    EXPECT_EQ(r.current_a[2], -5.0);
    EXPECT_EQ(r.voltage_v[2], 3.9420) << "the measured voltage is kept";
    EXPECT_TRUE(est::stale_current_rows(r).empty());
}

TEST(StaleCurrentRows, OrdinaryStepsNoiseAndTaperingAreLeftAlone) {
    // A step whose first row shows the new current.
    EXPECT_TRUE(est::stale_current_rows(rows({0, 0, -5, -5}, {4.0211, 4.0211, 3.9345, 3.9234})).empty());
    // A voltage that moved by less than 5 mV (noise and quantization of a drive cycle's steps).
    EXPECT_TRUE(est::stale_current_rows(rows({0, 0, -0.4, -0.4}, {4.0288, 4.0294, 4.0294, 4.0290})).empty());
    // A move against the step's direction (a relaxation, not the step's drop).
    EXPECT_TRUE(est::stale_current_rows(rows({0, 0, -5, -5}, {4.0211, 4.0300, 3.9345, 3.9234})).empty());
    // A step from a current, not from a rest (a CC-CV switch: the current tapers within the step).
    EXPECT_TRUE(est::stale_current_rows(rows({4.5, 4.5, 4.5, 1.15}, {4.1106, 4.1106, 4.1028, 4.1026})).empty());
}

// The synthetic HPPC with every step from rest starting on a stale row (its current set back to 0 A, its voltage
// kept): the fit says so and gives the parameters of the clean recording. Read as they stand, the pulses start a
// row late and no per-pulse-set fit is usable (each rest ends in a 34 mV ohmic drop).
TEST(StaleCurrentRows, TheFitOfAnHppcWithStaleStepRowsMatchesTheCleanOne) {
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    const Recording clean = cellbench::test::synthesize(cellbench::test::hppc_program(4), so);
    Recording stale = clean;
    std::size_t corrupted = 0;
    for (std::size_t k = 1; k + 1 < stale.size(); ++k)
        if (std::abs(stale.current_a[k - 1]) < 1e-6 && std::abs(stale.current_a[k]) > 1.0) {
            stale.current_a[k] = 0.0;
            ++corrupted;
            ++k;
        }
    ASSERT_GE(corrupted, 8u);
    ASSERT_EQ(est::stale_current_rows(stale).size(), corrupted);

    const auto options = cellbench::test::characterization_options();
    const auto a = est::characterize({clean}, options);
    const auto b = est::characterize({stale}, options);
    bool said = false;
    for (const auto& w : b.warnings) said = said || w.find("show the step's new voltage") != std::string::npos;
    EXPECT_TRUE(said);
    ASSERT_TRUE(a.global && b.global);
    EXPECT_EQ(b.params.capacity_ah, a.params.capacity_ah);
    EXPECT_EQ(b.pulse_fits.size(), a.pulse_fits.size());
    EXPECT_NEAR(b.global->rms_v, a.global->rms_v, 0.01 * a.global->rms_v);
    ASSERT_EQ(a.params.discharge.r0_ohm.size(), b.params.discharge.r0_ohm.size());
    for (std::size_t k = 0; k < a.params.discharge.r0_ohm.size(); ++k) {
        EXPECT_NEAR(b.params.discharge.r0_ohm[k], a.params.discharge.r0_ohm[k], 1e-3 * a.params.discharge.r0_ohm[k])
            << "row " << k << " (SOC " << a.params.soc[k] << ")";
        EXPECT_NEAR(b.params.discharge.r1_ohm[k], a.params.discharge.r1_ohm[k], 1e-3 * a.params.discharge.r1_ohm[k])
            << "row " << k << " (SOC " << a.params.soc[k] << ")";
    }
}

}  // namespace
