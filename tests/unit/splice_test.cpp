// Splicing a cycler's coarse export and a finer file of the same test: nothing of the coarse export outside the
// finer file is lost, and the finer rows land on the clock a BDF writer round-trips.
#include <gtest/gtest.h>

#include <cmath>
#include <sstream>
#include <string>

#include "cellbench/estimator/merge.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

// 1 s cycler record of 0..100 s: rest (step 1), 10 A discharge from 20 to 60 s (step 2), rest (step 3).
Recording coarse() {
    Recording a;
    a.source = "coarse";
    for (int k = 0; k <= 100; ++k) {
        const double t = k;
        const bool on = t >= 20 && t < 60;
        a.time_s.push_back(t);
        a.current_a.push_back(on ? -10.0 : 0.0);
        a.voltage_v.push_back(on ? 3.6 : 3.7);
        a.step_count.push_back(t < 20 ? 1 : on ? 2 : 3);
        a.step_type.push_back(on ? "CC DChg" : "Rest");
    }
    return a;
}

// The same test at 0.1 s on its own clock (0 = 15.1 s of the cycler's), 15.1..70.1 s, with a surface temperature.
Recording fine() {
    Recording b;
    b.source = "fine";
    for (int k = 0; k <= 550; ++k) {
        const double t = 0.1 * k, tc = t + 15.1;
        const bool on = tc >= 20 && tc < 60;
        b.time_s.push_back(t);
        b.current_a.push_back(on ? -10.0 : 0.0);
        b.voltage_v.push_back(on ? 3.6 : 3.7);
        b.step_type.push_back(on ? "CC DChg" : "Rest");
        b.surface_c.push_back(25.0);
    }
    return b;
}

}  // namespace

TEST(Splice, CoarseRowsBeforeAndAfterTheFinerFileAreKept) {
    const auto a = coarse(), b = fine();
    const auto s = splice_recordings(a, b, 15.1);
    // 0..15 s of a (16 rows), b's 551 rows, then a's 71..100 s (30 rows).
    ASSERT_EQ(s.size(), 16u + 551u + 30u);
    EXPECT_DOUBLE_EQ(s.time_s.front(), 0.0);
    EXPECT_DOUBLE_EQ(s.time_s.back(), 100.0);
    for (std::size_t k = 1; k < s.size(); ++k) ASSERT_GT(s.time_s[k], s.time_s[k - 1]) << "row " << k;
    // Channels only the finer file holds are empty (NaN) outside it, its values inside.
    EXPECT_TRUE(std::isnan(s.surface_c.front()));
    EXPECT_TRUE(std::isnan(s.surface_c.back()));
    EXPECT_EQ(s.surface_c[16], 25.0);
    // Steps stay distinct and in order across both seams: rest, discharge, rest.
    EXPECT_EQ(s.step_count.front(), 1.0);
    EXPECT_EQ(s.step_type.back(), "Rest");
    for (std::size_t k = 1; k < s.size(); ++k) ASSERT_GE(s.step_count[k], s.step_count[k - 1]) << "row " << k;
    EXPECT_EQ(s.step_count.back(), s.step_count[16 + 550]) << "the last rest continues past the finer file's end";
}

TEST(Splice, ShiftedTimesAreWhatABdfFileOfTheSpliceReadsBack) {
    const auto s = splice_recordings(coarse(), fine(), 15.1);
    std::ostringstream text;
    protocol::write_bdf_csv(text, s);
    const auto back = protocol::parse_bdf_csv(text.str(), "spliced.bdf.csv");
    ASSERT_EQ(back.size(), s.size());
    // 0.1 + 15.1 is not 15.2 in binary; the splice must hold the value a written file gives back, or a fit of
    // the files handed in separately and one of `import`'s merged file would resample into different bins.
    for (std::size_t k = 0; k < s.size(); ++k) ASSERT_EQ(back.time_s[k], s.time_s[k]) << "row " << k;
}
