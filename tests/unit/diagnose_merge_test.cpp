// diagnose's searches run on a merged copy of the recording (merge_intervals: rows at least search_step_s apart,
// mean current over each interval, values at its end). The copy must describe the same experiment: a merged
// interval that averaged two set currents would pair the voltage at its end with a current the cell never
// carried, an error no candidate can remove (on a 0.1 s drive profile: 21 mV RMS against 6.6 mV on the rows).
#include <gtest/gtest.h>

#include <cmath>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "unit/thesis_params.hpp"

using namespace cellbench;

namespace {

estimator::ParameterSet thesis() { return test::thesis_parameter_set(); }

// 0.1 s rows; the set current changes between rows at times that are not multiples of the 1 s merge step.
Recording stepped_profile() {
    struct Segment {
        double until_s, current_a;
    };
    const Segment profile[] = {{12.3, 0.0}, {40.0, -4.0}, {41.7, 3.0}, {77.7, -8.0}, {95.2, 0.0}, {130.5, 5.0}, {200.0, -2.5}};
    Recording r;
    r.source = "stepped";
    std::size_t seg = 0;
    for (int k = 0; k <= 2000; ++k) {
        const double t = 0.1 * k;
        while (t > profile[seg].until_s + 1e-9) ++seg;  // row k carries the current held over (t - 0.1, t]
        r.time_s.push_back(t);
        r.current_a.push_back(profile[seg].current_a);
        r.voltage_v.push_back(0.0);
    }
    return r;
}

}  // namespace

TEST(DiagnoseMerge, TheMergedCopySimulatesToTheRecordingsOwnVoltagesAcrossCurrentSteps) {
    const estimator::CellModel model(thesis());
    Recording rec = stepped_profile();
    estimator::SimulationOptions so;
    so.initial_soc = 0.6;
    so.ambient_c = 25.0;
    rec.voltage_v = estimator::simulate(model, rec, so).voltage_v;  // the model's own voltage: exact reference

    const Recording merged = estimator::merge_intervals(rec, 1.0);
    // It still merges: about one row per second plus one per current step.
    EXPECT_LT(merged.size(), rec.size() / 10 + 2 * 7 + 2);
    EXPECT_GT(merged.size(), rec.size() / 10 - 2);
    // Every merged row carries a current the profile set (never a blend of two).
    for (double i : merged.current_a) {
        bool set = false;
        for (double v : {0.0, -4.0, 3.0, -8.0, 5.0, -2.5}) set = set || std::abs(i - v) < 1e-9;
        EXPECT_TRUE(set) << "merged current " << i << " A was never set";
    }
    // The model on the merged copy reproduces the voltage at each merged row's time (zero-order hold is exact
    // over a held current; the lumped temperature, whose step depends on the interval, moves the voltage by
    // microvolts): a blended interval would be off by about dI * R0 (tens of mV here).
    const auto sim = estimator::simulate(model, merged, so);
    ASSERT_EQ(sim.voltage_v.size(), merged.size());
    double worst_v = 0;
    for (std::size_t k = 0; k < merged.size(); ++k) worst_v = std::max(worst_v, std::abs(sim.voltage_v[k] - merged.voltage_v[k]));
    EXPECT_LT(worst_v, 1e-4) << "largest voltage difference between the merged copy's simulation and the recording";
}

TEST(DiagnoseMerge, CurrentNoiseDoesNotSplitTheIntervals) {
    Recording rec = stepped_profile();
    // +-2 mA of alternating noise on every row (a cycler's current reading): no row boundary is a step.
    for (std::size_t k = 0; k < rec.size(); ++k) rec.current_a[k] += (k % 2 ? 2e-3 : -2e-3);
    const Recording merged = estimator::merge_intervals(rec, 1.0);
    EXPECT_LT(merged.size(), rec.size() / 10 + 2 * 7 + 2);
}
