// Rows a cycler writes at the start of a step with the new voltage and the old current (a published Digatron
// HPPC starts every pulse so): found by what they show, given the step's current, said in the fit's warnings.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "cellbench/estimator/stale_current.hpp"
#include "unit/hppc_synthetic.hpp"
#include "unit/same_fit.hpp"
#include "unit/thesis_params.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;

Recording rows(const std::vector<double>& current_a, const std::vector<double>& voltage_v) {
    return cellbench::test::rows_one_second_apart(current_a, voltage_v);
}

// Every row where the current steps away from a rest reads the rest's 0 A; returns how many.
std::size_t make_steps_from_rest_stale(Recording& r) {
    std::size_t n = 0;
    for (std::size_t k = 1; k + 1 < r.size(); ++k)
        if (std::abs(r.current_a[k - 1]) < 1e-6 && std::abs(r.current_a[k]) > 1.0) {
            r.current_a[k] = 0.0;
            ++n;
            ++k;
        }
    return n;
}

// 40 minutes at 1 s of 1C-4C pulses and rests, simulated by the thesis cell, voltage quantized to 0.1 mV.
Recording thesis_pulses(const char* source, int phase) {
    const auto truth = cellbench::test::thesis_parameter_set();
    Recording r;
    r.source = source;
    const double pattern[] = {-1.0, 0.0, 2.0, 0.0, -4.0, 0.0, -2.0, 1.0, 0.0, -3.0, 0.0};
    for (int k = 0; k <= 2400; ++k) {
        r.time_s.push_back(k);
        r.current_a.push_back(k < 60 ? 0.0 : pattern[(k / 45 + phase) % 11] * truth.capacity_ah);
        r.voltage_v.push_back(0.0);
    }
    est::SimulationOptions so;
    so.initial_soc = 0.8;
    so.ambient_c = 25.0;
    const auto tr = est::simulate(est::CellModel(truth), r, so);
    for (std::size_t k = 0; k < r.size(); ++k) r.voltage_v[k] = std::round(tr.voltage_v[k] * 1e4) / 1e4;
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
    const Recording clean = cellbench::test::synthetic_hppc_one_second();
    Recording stale = clean;
    const std::size_t corrupted = make_steps_from_rest_stale(stale);
    ASSERT_GE(corrupted, 8u);
    ASSERT_EQ(est::stale_current_rows(stale).size(), corrupted);

    const auto options = cellbench::test::characterization_options();
    const auto a = est::characterize({clean}, options);
    const auto b = est::characterize({stale}, options);
    EXPECT_TRUE(cellbench::test::warns(b.warnings, "show the step's new voltage"));
    ASSERT_TRUE(a.global && b.global);
    EXPECT_EQ(b.params.capacity_ah, a.params.capacity_ah);
    EXPECT_EQ(b.pulse_fits.size(), a.pulse_fits.size());
    EXPECT_NEAR(b.global->rms_v, a.global->rms_v, 0.01 * a.global->rms_v);
    cellbench::test::expect_discharge_column_near(a, b, &est::RcTable::r0_ohm, 1e-3);
    cellbench::test::expect_discharge_column_near(a, b, &est::RcTable::r1_ohm, 1e-3);
}

// diagnose reads the recordings as the fit does: with the stale rows given their step's current, the diagnosis
// (and its confirmation on another recording) is the clean recording's, and its notes say what was read so.
TEST(StaleCurrentRows, DiagnoseReadsStaleStepRowsAsTheFitDoes) {
    const Recording clean = thesis_pulses("walk", 0), clean_other = thesis_pulses("other", 5);
    Recording stale = clean, stale_other = clean_other;
    ASSERT_GE(make_steps_from_rest_stale(stale), 10u);
    ASSERT_GE(make_steps_from_rest_stale(stale_other), 10u);
    est::DiagnoseOptions o;
    o.effects = {"series_resistance_offset"};
    o.max_accepted = 1;
    o.threads = 1;
    const auto params = cellbench::test::thesis_parameter_set();
    o.confirm = {&clean_other};
    const auto a = est::diagnose(params, clean, o);
    o.confirm = {&stale_other};
    const auto b = est::diagnose(params, stale, o);
    EXPECT_TRUE(a.notes.empty());
    ASSERT_EQ(b.notes.size(), 2u);
    EXPECT_NE(b.notes[0].find("walk: "), std::string::npos) << b.notes[0];
    EXPECT_NE(b.notes[1].find("other: "), std::string::npos) << b.notes[1];
    ASSERT_TRUE(a.baseline.voltage_v && b.baseline.voltage_v);
    EXPECT_DOUBLE_EQ(*b.baseline.voltage_v, *a.baseline.voltage_v);
    ASSERT_EQ(a.findings.size(), b.findings.size());
    for (std::size_t k = 0; k < a.findings.size(); ++k) EXPECT_DOUBLE_EQ(b.findings[k].score, a.findings[k].score);
    EXPECT_EQ(est::diagnosis_to_json(b).at("notes").size(), 2u);
    EXPECT_FALSE(est::diagnosis_to_json(a).contains("notes"));
}

}  // namespace
