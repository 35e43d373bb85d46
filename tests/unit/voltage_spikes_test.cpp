// Voltage spikes (an instrument's glitch: there and back within one to three samples while the current holds)
// are found by what they show, never at a current step, and the fit and diagnose read a recording with them as
// they read the clean one.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/voltage_spikes.hpp"
#include "unit/hppc_synthetic.hpp"
#include "unit/same_fit.hpp"
#include "unit/thesis_params.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;

Recording rows(const std::vector<double>& current_a, const std::vector<double>& voltage_v) {
    return cellbench::test::rows_one_second_apart(current_a, voltage_v);
}

TEST(VoltageSpikes, ARowThatLeavesAndReturnsWhileTheCurrentHoldsIsASpike) {
    // In a rest and under a 4.5 A discharge; up or down.
    Recording r = rows({0, 0, 0, 0, -4.5, -4.5, -4.5, -4.5}, {3.700, 3.700, 0.500, 3.700, 3.650, 3.649, 9.000, 3.647});
    EXPECT_EQ(est::voltage_spike_rows(r), (std::vector<std::size_t>{2, 6}));
    const std::string note = est::correct_voltage_spikes(r);
    EXPECT_EQ(note, "rows: 2 rows show a voltage spike (the first at t = 2.000 s: 0.5000 V) that leaves and returns "
                    "within at most 3 samples while the current holds, which no cell does: their voltage is taken "
                    "between the rows either side");
    EXPECT_NEAR(r.voltage_v[2], 3.700, 1e-12);
    EXPECT_NEAR(r.voltage_v[6], 3.648, 1e-12);
    EXPECT_TRUE(est::voltage_spike_rows(r).empty());
}

// A logger's dropout can last a few samples: two or three rows off together, each beyond both rows either side,
// take the line between those rows. Four are left as they are (a glitch that long is no longer told from a cell's
// own move by this rule).
TEST(VoltageSpikes, AGlitchOfTwoOrThreeRowsIsOneSpike) {
    Recording r = rows({-4.5, -4.5, -4.5, -4.5, -4.5, 0, 0, 0, 0, 0, 0},
                       {3.650, 3.649, 0.000, 0.000, 3.646, 3.700, 3.901, 3.950, 3.930, 3.703, 3.703});
    EXPECT_EQ(est::voltage_spike_rows(r), (std::vector<std::size_t>{2, 3, 6, 7, 8}));
    est::correct_voltage_spikes(r);
    EXPECT_NEAR(r.voltage_v[2], 3.648, 1e-12);
    EXPECT_NEAR(r.voltage_v[3], 3.647, 1e-12);
    EXPECT_NEAR(r.voltage_v[6], 3.70075, 1e-12);
    EXPECT_NEAR(r.voltage_v[8], 3.70225, 1e-12);
    // Four rows off: left alone. A row between that is not off ends the run: two spikes of one row.
    EXPECT_TRUE(est::voltage_spike_rows(rows({0, 0, 0, 0, 0, 0, 0}, {3.7, 3.7, 3.9, 3.9, 3.9, 3.9, 3.7})).empty());
    EXPECT_EQ(est::voltage_spike_rows(rows({0, 0, 0, 0, 0}, {3.7, 3.9, 3.7, 3.9, 3.7})), (std::vector<std::size_t>{1, 3}));
    // The current steps inside the run: a short pulse the voltage follows, not a glitch.
    EXPECT_TRUE(est::voltage_spike_rows(rows({0, 0, -20, -20, 0, 0}, {3.7, 3.7, 3.55, 3.54, 3.69, 3.7})).empty());
}

TEST(VoltageSpikes, CurrentStepsPulsesOfOneRowAndRealMovesAreLeftAlone) {
    // A one-row pulse: the voltage follows the current there and back.
    EXPECT_TRUE(est::voltage_spike_rows(rows({0, 0, -20, 0, 0}, {3.7, 3.7, 3.55, 3.69, 3.7})).empty());
    // A step: the voltage moves and stays.
    EXPECT_TRUE(est::voltage_spike_rows(rows({0, 0, -4.5, -4.5}, {3.70, 3.70, 3.64, 3.63})).empty());
    // Under 50 mV: noise or a fast relaxation, not a glitch.
    EXPECT_TRUE(est::voltage_spike_rows(rows({0, 0, 0, 0}, {3.700, 3.700, 3.740, 3.700})).empty());
    // The neighbours disagree: a move, not a spike (the end of a discharge falling towards its cut-off).
    EXPECT_TRUE(est::voltage_spike_rows(rows({-18, -18, -18, -18}, {2.95, 2.90, 2.80, 2.70})).empty());
}

// The synthetic HPPC with a glitch every 5 minutes (0.5 V, in rests and under current alike): the fit says so
// and gives the clean recording's parameters. Read as they stand, one such row moved the P45B tables by up to 7 %
// in R0 and a factor 84 in C2 (docs/command-line.md).
TEST(VoltageSpikes, TheFitOfAnHppcWithVoltageSpikesMatchesTheCleanOne) {
    const Recording clean = cellbench::test::synthetic_hppc_one_second();
    Recording spiked = clean;
    const auto planted =
        cellbench::test::corrupt_every_300th_held_row(spiked, [](Recording& r, std::size_t k) { r.voltage_v[k] = 0.5; });
    ASSERT_GE(planted.size(), 8u);
    ASSERT_EQ(est::voltage_spike_rows(spiked), planted);
    EXPECT_TRUE(est::voltage_spike_rows(clean).empty());
    cellbench::test::expect_fits_as_clean(clean, spiked, "show a voltage spike");
}

}  // namespace
