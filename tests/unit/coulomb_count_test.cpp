// Coulomb counting of recordings (estimator/coulomb.hpp: cumulative_charge_ah, step_logging, a phase's
// charge_ah). What a user relies on: a pulse or an SOC step moves the SOC by its own charge however the instrument
// logged around it (a cycler that writes a step's first row the moment it begins; a logger that writes a step's
// end as a row and the next step's first row one interval later), so the SOC axis of an HPPC's low levels does not
// drift with the logging intervals.
#include <gtest/gtest.h>

#include <cmath>

#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/estimator/segment.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

struct Rows {
    Recording rec;
    void add(double t, double i) {
        rec.time_s.push_back(t);
        rec.current_a.push_back(i);
        rec.voltage_v.push_back(3.7 + 0.01 * i);
    }
};

// A cycler's rows: rest logged every rest_dt_s, a pulse of current_a logged every pulse_dt_s from the instant it
// begins for pulse_s, rest again from the instant it ends.
Recording cycler_pulse(double rest_dt_s, double pulse_dt_s, double current_a, double pulse_s) {
    Rows r;
    double t = 0;
    for (int k = 0; k < 60; ++k, t += rest_dt_s) r.add(t, 0.0);
    for (int k = 0; k < static_cast<int>(std::lround(pulse_s / pulse_dt_s)); ++k, t += pulse_dt_s) r.add(t, current_a);
    for (int k = 0; k < 60; ++k, t += rest_dt_s) r.add(t, 0.0);
    return r.rec;
}

}  // namespace

TEST(CoulombCount, ACyclersPulseMovesTheChargeByItsOwnChargeHoweverSparselyTheRestWasLogged) {
    // 3 A for 30 s = 90 A s. Counting each interval at its closing row's current gave -(3 A x 10 s + 29 x 3 A x 1 s)
    // = -117 A s where the rest was logged every 10 s.
    for (const double rest_dt : {10.0, 0.1}) {
        const auto rec = cycler_pulse(rest_dt, 1.0, -3.0, 30.0);
        EXPECT_EQ(step_logging(rec.time_s, rec.current_a), StepLogging::at_step_start);
        const auto q = cumulative_charge_ah(rec);
        EXPECT_NEAR(q.back() * 3600.0, -90.0, 1e-9) << "rest logged every " << rest_dt << " s";
        EXPECT_NEAR(q[60] * 3600.0, 0.0, 1e-9);    // the pulse's first row: nothing has flowed yet
        EXPECT_NEAR(q[90] * 3600.0, -90.0, 1e-9);  // the rest's first row: all of it has
        const auto seg = segment_recording(rec);
        ASSERT_FALSE(seg.phases.empty());
        bool found = false;
        for (const auto& ph : seg.phases)
            if (ph.direction < 0) {
                EXPECT_NEAR(ph.charge_ah * 3600.0, -90.0, 1e-9);
                found = true;
            }
        EXPECT_TRUE(found);
    }
}

TEST(CoulombCount, ALoggerThatWritesTheFirstRowOneIntervalInCountsTheWholeIntervalAtTheNewCurrent) {
    // As the Panasonic 18650PF's logger: rest at 1 s; an SOC step of -0.87 A for 600 s whose first row comes 60 s
    // after it began, then every 60 s, its last row where it ended; the rest's first row 300 s later, then every
    // 300 s. Holding the old current over the interval before a new step's row gave -0.87 A x 840 s.
    Rows r;
    for (int k = 0; k <= 99; ++k) r.add(k, 0.0);
    for (int k = 1; k <= 10; ++k) r.add(99.0 + 60.0 * k, -0.87);
    for (int k = 1; k <= 5; ++k) r.add(699.0 + 300.0 * k, 0.0);
    EXPECT_EQ(step_logging(r.rec.time_s, r.rec.current_a), StepLogging::one_interval_after);
    const auto q = cumulative_charge_ah(r.rec);
    EXPECT_NEAR(q.back() * 3600.0, -0.87 * 600.0, 1e-9);
}

TEST(CoulombCount, StepsLoggedAtOneRateFollowTheConventionTheOtherStepsShow) {
    // Everything logged every 1 s, so a pulse's own steps cannot tell when they happened; the SOC steps end on a
    // limit between two rows (the rest's first row 0.5 s after the last discharge row: cut short), which only a
    // cycler writing rows at step starts does. The pulses then count from their first row, not an interval
    // earlier (the ZOH convention where nothing tells).
    Rows r;
    double t = 0;
    std::size_t pulse_row = 0;
    for (int level = 0; level < 3; ++level) {
        for (int k = 0; k < 60; ++k, t += 1.0) r.add(t, 0.0);
        if (level == 1) pulse_row = r.rec.time_s.size();
        for (int k = 0; k < 30; ++k, t += 1.0) r.add(t, -3.0);
        for (int k = 0; k < 60; ++k, t += 1.0) r.add(t, 0.0);
        for (int k = 0; k < 101; ++k, t += 1.0) r.add(t, -1.0);
        t -= 0.5;  // the limit is reached 0.5 s after the last discharge row
    }
    for (int k = 0; k < 10; ++k, t += 1.0) r.add(t, 0.0);
    EXPECT_EQ(step_logging(r.rec.time_s, r.rec.current_a), StepLogging::at_step_start);
    const auto q = cumulative_charge_ah(r.rec);
    EXPECT_NEAR(q.back() * 3600.0, -3 * (90.0 + 100.5), 1e-9);
    EXPECT_NEAR((q[pulse_row + 30] - q[pulse_row]) * 3600.0, -90.0, 1e-9);
    EXPECT_NEAR((q[pulse_row] - q[pulse_row - 1]) * 3600.0, 0.0, 1e-9);
}

TEST(CoulombCount, ATaperIsIntegratedAsACurve) {
    // A CV taper I(t) = 2 exp(-t / 600) A sampled every 1 s for 1800 s: within 1e-5 of the exact charge (a rule that
    // holds either end of every interval is 1 A s off, half the first sample).
    Rows r;
    for (int k = 0; k <= 1800; ++k) r.add(k, 2.0 * std::exp(-k / 600.0));
    const auto q = cumulative_charge_ah(r.rec);
    const double exact = 2.0 * 600.0 * (1.0 - std::exp(-3.0));
    EXPECT_NEAR(q.back() * 3600.0 / exact, 1.0, 1e-5);
}

TEST(CoulombCount, RowsWithoutACurrentOrTimeAddNothing) {
    Rows r;
    r.add(0, -1.0), r.add(1, -1.0), r.add(2, NAN), r.add(3, -1.0), r.add(NAN, -1.0), r.add(5, -1.0);
    const auto q = cumulative_charge_ah(r.rec);
    ASSERT_EQ(q.size(), 6u);
    for (double x : q) EXPECT_TRUE(std::isfinite(x));
    EXPECT_NEAR(q[1] * 3600.0, -1.0, 1e-12);
    EXPECT_NEAR(q[5] * 3600.0, -1.0, 1e-12);
}

TEST(CoulombCount, WhereNoStepTellsTheModelsHoldConventionCounts) {
    // One rate throughout and no step cut short: nothing tells when the steps happened. The count then holds each
    // row's current over the interval before it, as the electrical model's ZOH step does.
    const auto rec = cycler_pulse(1.0, 1.0, -3.0, 30.0);
    EXPECT_EQ(step_logging(rec.time_s, rec.current_a), StepLogging::unknown);
    const auto q = cumulative_charge_ah(rec);
    EXPECT_NEAR(q[60] * 3600.0, -3.0, 1e-9);
    EXPECT_NEAR(q.back() * 3600.0, -90.0, 1e-9);
}
