// The global fit says where the model fits the characterization worst (an honest account of where the model is
// wrong): the P45B HPPC handed in without the cycler's export is fitted at 10.4 mV RMS in its 0-10 % SOC pulse set
// against 1.4-3.0 mV elsewhere, no table value there was flagged, and the model predicts the Random Walk 50-76 mV
// off below 20 % SOC. The note names that range; a fit that is even everywhere gets none.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "cellbench/estimator/global_fit.hpp"

namespace {

namespace est = cellbench::estimator;

est::GlobalWindow window(const char* kind, double lo, double hi, double rms_mv) {
    est::GlobalWindow w;
    w.kind = kind;
    w.soc_min = lo, w.soc_max = hi;
    w.rms_v = rms_mv * 1e-3;
    return w;
}

// The P45B two-file arrangement's pulse windows (fit --json, session 29), 10 % levels from full, plus its 4C window.
std::vector<est::GlobalWindow> two_file_windows() {
    const double rms[10] = {2.72, 1.82, 2.51, 2.97, 1.43, 2.19, 2.26, 2.78, 6.27, 10.40};
    std::vector<est::GlobalWindow> w;
    for (int k = 0; k < 10; ++k) w.push_back(window("pulses", 0.9 - 0.1 * k, 1.0 - 0.1 * k, rms[k]));
    w.push_back(window("discharge", 0.0, 0.99, 9.74));  // a long window: not a place in SOC
    return w;
}

TEST(PoorFitNotes, NameTheSocRangeWhereThePulseSetsFitFarWorseThanTheMedian) {
    const auto notes = est::poorly_fitted_notes(two_file_windows());
    ASSERT_EQ(notes.size(), 1u);
    EXPECT_NE(notes[0].find("SOC 0-10 %"), std::string::npos) << notes[0];
    EXPECT_NE(notes[0].find("10.4 mV"), std::string::npos) << notes[0];
    EXPECT_NE(notes[0].find("median of 2.7 mV"), std::string::npos) << notes[0];
}

TEST(PoorFitNotes, AdjacentPoorWindowsAreOneRangeAndSeparateOnesTwo) {
    auto w = two_file_windows();
    w[8].rms_v = 9e-3;  // 10-20 % as poor as 0-10 %: one range
    auto notes = est::poorly_fitted_notes(w);
    ASSERT_EQ(notes.size(), 1u);
    EXPECT_NE(notes[0].find("SOC 0-20 %"), std::string::npos) << notes[0];
    w[0].rms_v = 12e-3;  // and the top level: a second range
    notes = est::poorly_fitted_notes(w);
    ASSERT_EQ(notes.size(), 2u);
    EXPECT_NE(notes[1].find("SOC 90-100 %"), std::string::npos) << notes[1];
}

TEST(PoorFitNotes, AnEvenFitOrTooFewPulseSetsGetNone) {
    auto w = two_file_windows();
    w[8].rms_v = 3e-3, w[9].rms_v = 3.5e-3;
    EXPECT_TRUE(est::poorly_fitted_notes(w).empty());
    const std::vector<est::GlobalWindow> three = {window("pulses", 0.8, 0.9, 1.0), window("pulses", 0.7, 0.8, 1.0),
                                                  window("pulses", 0.0, 0.1, 20.0)};
    EXPECT_TRUE(est::poorly_fitted_notes(three).empty());
}

}  // namespace
