// Current glitches (a current reading that leaves and returns within one to three samples while the voltage does
// not follow) are found by what they show, never where the voltage answers the current, and the fit reads a
// recording with them as it reads the clean one.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/current_glitches.hpp"
#include "cellbench/estimator/voltage_spikes.hpp"
#include "unit/hppc_synthetic.hpp"
#include "unit/same_fit.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;

// Three 10 A pulses of a cell whose ohmic drop is 10 mOhm (0.1 V), then the rows under test: the recording's own
// steps are what tells a glitch from a current that flowed.
Recording with_pulses(const std::vector<double>& current_a, const std::vector<double>& voltage_v) {
    std::vector<double> i, v;
    for (int p = 0; p < 3; ++p)
        for (double c : {0.0, 0.0, -10.0, -10.0, -10.0, 0.0, 0.0}) {
            i.push_back(c);
            v.push_back(c == 0.0 ? 3.700 : 3.600);
        }
    i.insert(i.end(), current_a.begin(), current_a.end());
    v.insert(v.end(), voltage_v.begin(), voltage_v.end());
    return cellbench::test::rows_one_second_apart(i, v);
}

constexpr std::size_t kBase = 21;  // rows with_pulses puts before the rows under test

TEST(CurrentGlitches, TheRecordingsOwnStepsGiveItsOhmicResistance) {
    EXPECT_NEAR(est::apparent_step_resistance_ohm(with_pulses({}, {})), 0.010, 1e-12);
    // Fewer than three held steps: not measured, and then nothing is called a glitch.
    const Recording bare = cellbench::test::rows_one_second_apart({0, 0, -18, 0, 0}, {3.7, 3.7, 3.7, 3.7, 3.7});
    EXPECT_TRUE(std::isnan(est::apparent_step_resistance_ohm(bare)));
    EXPECT_TRUE(est::current_glitch_rows(bare).empty());
}

TEST(CurrentGlitches, ACurrentTheVoltageDoesNotFollowIsAGlitch) {
    // -18 A for one row in a rest; a dropout to 0 A for two rows in a 10 A discharge (the voltage stays 0.1 V down).
    Recording r = with_pulses({0, 0, -18, 0, 0, -10, -10, 0, 0, -10, -10},
                              {3.700, 3.700, 3.700, 3.699, 3.699, 3.600, 3.599, 3.599, 3.598, 3.598, 3.700});
    EXPECT_EQ(est::current_glitch_rows(r), (std::vector<std::size_t>{kBase + 2, kBase + 7, kBase + 8}));
    const std::string note = est::correct_current_glitches(r);
    EXPECT_EQ(note, "rows: 3 rows show a current glitch (the first at t = 23.000 s: -18.000 A) that leaves and returns "
                    "within at most 3 samples while the voltage does not follow, which no cell does: their current is "
                    "taken between the rows either side");
    EXPECT_NEAR(r.current_a[kBase + 2], 0.0, 1e-12);
    EXPECT_NEAR(r.current_a[kBase + 7], -10.0, 1e-12);
    EXPECT_NEAR(r.current_a[kBase + 8], -10.0, 1e-12);
    EXPECT_TRUE(est::current_glitch_rows(r).empty());
    // correct_logging_artifacts, which fit, simulate and diagnose read every recording through, applies it.
    Recording again = with_pulses({0, 0, -18, 0, 0}, {3.700, 3.700, 3.700, 3.700, 3.700});
    const auto notes = est::correct_logging_artifacts(again);
    ASSERT_EQ(notes.size(), 1u);
    EXPECT_NE(notes[0].find("current glitch"), std::string::npos);
}

TEST(CurrentGlitches, CurrentsTheVoltageFollowsAndSmallOrLastingChangesAreLeftAlone) {
    // A one-row pulse the voltage follows (0.18 V for 18 A): a current that flowed.
    EXPECT_TRUE(est::current_glitch_rows(with_pulses({0, 0, -18, 0, 0}, {3.70, 3.70, 3.52, 3.69, 3.70})).empty());
    // Followed in part (a DAQ sampling the drop half-way through the row): still the cell's answer.
    EXPECT_TRUE(est::current_glitch_rows(with_pulses({0, 0, -18, 0, 0}, {3.70, 3.70, 3.61, 3.69, 3.70})).empty());
    // A step that lasts: the rows either side disagree.
    EXPECT_TRUE(est::current_glitch_rows(with_pulses({0, 0, -10, -10, -10}, {3.70, 3.70, 3.70, 3.60, 3.60})).empty());
    // 0.1 A off: a cycler's regulation, not a glitch worth a correction.
    EXPECT_TRUE(est::current_glitch_rows(with_pulses({0, 0, -0.1, 0, 0}, {3.70, 3.70, 3.70, 3.70, 3.70})).empty());
    // Four rows off: left alone.
    EXPECT_TRUE(
        est::current_glitch_rows(with_pulses({0, 0, -18, -18, -18, -18, 0}, {3.7, 3.7, 3.7, 3.7, 3.7, 3.7, 3.7})).empty());
}

// The synthetic HPPC with a current glitch every 5 minutes (-18 A or 0 A, in rests and under current alike): the
// fit says so and gives the clean recording's parameters. Read as they stand, one -18 A row in a rest of the P45B
// HPPC moved its discharge R0 by up to 74 % (current_glitches.hpp).
TEST(CurrentGlitches, TheFitOfAnHppcWithCurrentGlitchesMatchesTheCleanOne) {
    const Recording clean = cellbench::test::synthetic_hppc_one_second();
    Recording glitched = clean;
    const auto planted = cellbench::test::corrupt_every_300th_held_row(
        glitched, [](Recording& r, std::size_t k) { r.current_a[k] = r.current_a[k] == 0.0 ? -18.0 : 0.0; });
    ASSERT_GE(planted.size(), 8u);
    ASSERT_EQ(est::current_glitch_rows(glitched), planted);
    EXPECT_TRUE(est::current_glitch_rows(clean).empty());
    cellbench::test::expect_fits_as_clean(clean, glitched, "show a current glitch");
}

}  // namespace
