// Bad input to the characterization (issue 11): a recording with no pulses, a single pulse, pulses at 0 A, or NaN
// in the middle gives one clear error or a flagged partial result, never a silent table.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/logger_timing.hpp"
#include "unit/hppc_synthetic.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;
using cellbench::test::Step;

est::CharacterizationOptions options() { return cellbench::test::characterization_options(); }

Recording synth(const std::vector<Step>& program) {
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    return cellbench::test::synthesize(program, so);
}

// The message of the InputError characterize() throws ("" when it returns).
std::string error_of(const std::vector<Recording>& recs) {
    try {
        (void)est::characterize(recs, options());
    } catch (const cellbench::InputError& e) {
        return e.what();
    }
    return {};
}

TEST(CharacterizeBadInput, NoPulsesIsOneClearError) {
    // Rest, a CC discharge, rest: nothing to identify a resistance from.
    const auto rec = synth({{700, 0.0, "Rest"}, {1800, -1.9, "CC DChg"}, {700, 0.0, "Rest"}});
    const std::string e = error_of({rec});
    EXPECT_NE(e.find("pulses"), std::string::npos) << e;
}

TEST(CharacterizeBadInput, PulsesAtZeroAmpereAreNoPulses) {
    // The program of an HPPC whose pulses carry no current (a cycler channel left open): rests only, with SOC
    // steps, so there are long rests but nothing that excites the polarization.
    std::vector<Step> p;
    for (int k = 0; k < 3; ++k) {
        for (const auto& s : cellbench::test::pulse_set_program(700.0, 0.0)) p.push_back(s);
        p.push_back({300, -4.5, "CC DChg"});
    }
    p.push_back({700, 0.0, "Rest"});
    const std::string e = error_of({synth(p)});
    EXPECT_NE(e.find("pulses"), std::string::npos) << e;
}

TEST(CharacterizeBadInput, SinglePulseIsAnErrorOrFlagged) {
    // One discharge pulse between two long rests: one SOC level, no charge pulse.
    const auto rec = synth({{700, 0.0, "Rest"}, {30, -4.5, "CC DChg"}, {700, 0.0, "Rest"}});
    try {
        const auto c = est::characterize({rec}, options());
        // Not refused: then the result must say what it could not identify.
        EXPECT_FALSE(c.warnings.empty());
        ASSERT_TRUE(c.global.has_value());
        EXPECT_GT(c.global->flagged_count(), 0u) << "a single pulse identifies one SOC level, not a table";
    } catch (const cellbench::InputError& e) {
        EXPECT_FALSE(std::string(e.what()).empty());
    }
}

TEST(CharacterizeBadInput, DischargeOnlyPulseSetsAreFittedForTheDischargeDirectionAlone) {
    // Discharge-only pulses (two currents per level, 60 s apart, no charge pulse) at three SOC levels: the two
    // pulses after each long rest, up to the SOC step, are one pulse set (the Other form: more than one pulse
    // before the SOC step). Its discharge values are fitted (R0 of the synthetic cell within 3 %), its charge
    // values are null and said to be, never a made-up number; the global fit takes every pulse.
    std::vector<Step> p = {{700, 0.0, "Rest"}};
    for (int level = 0; level < 3; ++level) {
        p.push_back({10, -4.5, "CC DChg"});
        p.push_back({60, 0.0, "Rest"});
        p.push_back({10, -9.0, "CC DChg"});
        p.push_back({60, 0.0, "Rest"});
        p.push_back({400, -4.5, "CC DChg"});
        p.push_back({700, 0.0, "Rest"});
    }
    try {
        const auto c = est::characterize({synth(p)}, options());
        ASSERT_EQ(c.pulse_fits.size(), 3u);
        const double truth = cellbench::test::p45b_discharge().r0_ohm;
        for (const auto& f : c.pulse_fits) {
            EXPECT_EQ(f.pulse_set.form, est::PulseSetForm::Other);
            EXPECT_FALSE(f.pulse_set.has_charge_pulse());
            EXPECT_NEAR(f.chosen_discharge().r0_ohm, truth, 0.03 * truth) << "SOC " << f.soc;
            EXPECT_TRUE(std::isfinite(f.chosen_discharge().tau1_s)) << "SOC " << f.soc;
            EXPECT_TRUE(std::isnan(f.chosen_charge().r0_ohm)) << "SOC " << f.soc;
            bool said = false;
            for (const auto& w : f.warnings) said = said || w.find("no charge pulse") != std::string::npos;
            EXPECT_TRUE(said) << "SOC " << f.soc;
        }
    } catch (const cellbench::InputError& e) {
        ADD_FAILURE() << "three SOC levels of pulses are a characterization: " << e.what();
    }
}

TEST(CharacterizeBadInput, PulsesOutsideThePulseSetFormsSaySoInsteadOfASilentlyMissingComparison) {
    // Pulses after rests too short to read an OCV at (300 s; the long rest of each level is followed by a 2 min
    // discharge first): no pulse set of any form, so the per-pulse-set comparison is absent and an online fit of
    // such a program would find nothing. The summary says so rather than showing an empty comparison.
    std::vector<Step> p;
    for (int level = 0; level < 4; ++level) {
        p.push_back({700, 0.0, "Rest"});
        p.push_back({120, -1.0, "CC DChg"});
        p.push_back({300, 0.0, "Rest"});
        p.push_back({10, -9.0, "CC DChg"});
        p.push_back({60, 0.0, "Rest"});
        p.push_back({10, 4.5, "CC Chg"});
        p.push_back({60, 0.0, "Rest"});
        p.push_back({400, -4.5, "CC DChg"});
    }
    p.push_back({700, 0.0, "Rest"});
    try {
        const auto c = est::characterize({synth(p)}, options());
        EXPECT_TRUE(c.pulse_fits.empty());
        bool said = false;
        for (const auto& w : c.warnings) said = said || w.find("no pulse set (a long rest") != std::string::npos;
        EXPECT_TRUE(said) << "warnings: " << c.warnings.size();
    } catch (const cellbench::InputError& e) {
        ADD_FAILURE() << "four SOC levels of pulses between long rests are a characterization: " << e.what();
    }
}

TEST(CharacterizeBadInput, NanInTheMiddleIsAnErrorOrFlagged) {
    auto rec = synth(cellbench::test::hppc_program(3));
    // A dropout of the voltage channel in the middle of the second pulse set's discharge pulse.
    const std::size_t mid = rec.size() / 2;
    for (std::size_t k = mid; k < mid + 20 && k < rec.size(); ++k) rec.voltage_v[k] = std::numeric_limits<double>::quiet_NaN();
    try {
        const auto c = est::characterize({rec}, options());
        for (double v : c.params.ocv_v) EXPECT_TRUE(std::isfinite(v));
        for (double v : c.params.discharge.r0_ohm) EXPECT_TRUE(std::isfinite(v));
        // The fit ran around the gap; it must say so.
        bool told = false;
        for (const auto& w : c.warnings) told = told || w.find("NaN") != std::string::npos || w.find("missing") != std::string::npos;
        EXPECT_TRUE(told) << "the rows without a voltage are not mentioned in the warnings";
    } catch (const cellbench::InputError& e) {
        EXPECT_FALSE(std::string(e.what()).empty());
    }
}

}  // namespace

namespace {

TEST(CharacterizeBadInput, NanCurrentInTheMiddleIsOneClearError) {
    auto rec = synth(cellbench::test::hppc_program(3));
    rec.current_a[rec.size() / 2] = std::numeric_limits<double>::quiet_NaN();
    const std::string e = error_of({rec});
    EXPECT_NE(e.find("NaN"), std::string::npos) << e;
}

}  // namespace

// A cycler export that counts discharging current as positive (converted without negating it): the fit found "no
// recording measures the capacity", and simulate and diagnose reported an 807 mV error and a logger lag on the
// P45B HPPC so converted. The voltage moves against the current at every step: one error that names the cause,
// from every command that reads a recording; the same recording the right way round passes.
TEST(CharacterizeBadInput, ACurrentCountingDischargeAsPositiveIsOneClearError) {
    const auto right = synth(cellbench::test::hppc_program(3, 900.0, 4.5));
    auto reversed = right;
    for (double& i : reversed.current_a) i = -i;
    reversed.source = "exported";
    EXPECT_FALSE(est::current_sign(right).reversed());
    EXPECT_GE(est::current_sign(right).steps, 5u);
    EXPECT_TRUE(est::reversed_current_text(right).empty());
    const auto fit_error = error_of({reversed});
    EXPECT_NE(fit_error.find("exported: its current counts discharging as positive"), std::string::npos) << fit_error;
    EXPECT_NE(fit_error.find("negate the current column"), std::string::npos) << fit_error;
    // diagnose reads it the same way, as the recording diagnosed and as a --confirm recording
    const auto c = est::characterize({right}, options());
    est::DiagnoseOptions o;
    EXPECT_THROW((void)est::diagnose(c.params, reversed, o), cellbench::InputError);
    o.confirm = {&reversed};
    EXPECT_THROW((void)est::diagnose(c.params, right, o), cellbench::InputError);
}
