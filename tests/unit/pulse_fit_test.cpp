// Pulse-set fitter: thesis per-segment method and joint exact-ZOH fit on synthetic HPPC recordings with known
// parameters (different for charge and discharge), voltage noise and an OCV slope.
#include "cellbench/estimator/pulse_fit.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <tuple>
#include <cstdio>

#include "unit/hppc_synthetic.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

double rel(double got, double want) { return std::abs(got - want) / std::abs(want); }

void expect_params(const Rc2Params<double>& got, const Rc2Params<double>& want, double tol_r0, double tol_r,
                   double tol_tau, const char* what) {
    SCOPED_TRACE(what);
    EXPECT_LT(rel(got.r0_ohm, want.r0_ohm), tol_r0) << got.r0_ohm;
    EXPECT_LT(rel(got.r1_ohm, want.r1_ohm), tol_r) << got.r1_ohm;
    EXPECT_LT(rel(got.tau1_s, want.tau1_s), tol_tau) << got.tau1_s;
    EXPECT_LT(rel(got.r2_ohm, want.r2_ohm), tol_r) << got.r2_ohm;
    EXPECT_LT(rel(got.tau2_s, want.tau2_s), tol_tau) << got.tau2_s;
}

struct Hppc {
    Recording rec;
    RecordingSegments seg;
    std::vector<double> soc;  // at A of each pulse set
};

Hppc make_hppc(std::size_t n_sets, const test::SyntheticOptions& o) {
    Hppc h;
    h.rec = test::synthesize(test::hppc_program(n_sets), o);
    h.seg = segment_recording(h.rec);
    // SOC at each pulse set by Coulomb counting (what the caller does).
    for (const auto& ps : h.seg.pulse_sets) {
        double q = 0;
        for (std::size_t k = 1; k < ps.pulse_begin; ++k)
            q += h.rec.current_a[k] * (h.rec.time_s[k] - h.rec.time_s[k - 1]) / 3600.0;
        h.soc.push_back(o.soc0 + q / test::kCapacityAh);
    }
    return h;
}

// The free joint fit (R0 estimated with the rest): the model is identifiable from one pulse set.
PulseFitOptions options_at(double soc) {
    PulseFitOptions po;
    po.docv_dah_v_per_ah = test::synthetic_docv_dsoc(soc) / test::kCapacityAh;
    po.r0_from_steps = false;
    return po;
}

PulseFitOptions free_r0() {
    PulseFitOptions po;
    po.r0_from_steps = false;
    return po;
}

}  // namespace

TEST(PulseFit, JointFitRecoversKnownParametersWithNoise) {
    test::SyntheticOptions o;
    o.voltage_noise_v = 3e-4;
    o.soc0 = 0.95;
    o.seed = 42;
    const auto h = make_hppc(5, o);
    ASSERT_EQ(h.seg.pulse_sets.size(), 5u);
    double total_ms = 0;
    for (std::size_t j = 0; j < h.seg.pulse_sets.size(); ++j) {
        SCOPED_TRACE("pulse set " + std::to_string(j));
        const auto t0 = std::chrono::steady_clock::now();
        auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[j], options_at(h.soc[j]));
        total_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        fit.soc = h.soc[j];

        expect_params(fit.joint_discharge, o.discharge, 0.01, 0.10, 0.15, "joint discharge");
        expect_params(fit.joint_charge, o.charge, 0.01, 0.10, 0.20, "joint charge");
        EXPECT_TRUE(fit.joint_converged);
        // V_A is one noisy row: the offset c takes up its noise.
        EXPECT_NEAR(fit.joint_ocv_offset_v, 0.0, 1.2e-3);
        // Residual at the noise level; the prediction (no offset) close to it.
        EXPECT_LT(fit.joint_fit_rms_v, 3.5e-4);
        EXPECT_LT(fit.joint_rms_v, 1.3e-3);
        // Uncertainties exist and the errors are within a few sigma (sigma is optimistic, hence 6).
        for (auto [got, sig, want] : {std::tuple{fit.joint_discharge.r0_ohm, fit.joint_discharge_sigma.r0_ohm,
                                                 o.discharge.r0_ohm},
                                      std::tuple{fit.joint_charge.r2_ohm, fit.joint_charge_sigma.r2_ohm,
                                                 o.charge.r2_ohm},
                                      std::tuple{fit.joint_discharge.tau2_s, fit.joint_discharge_sigma.tau2_s,
                                                 o.discharge.tau2_s}}) {
            ASSERT_TRUE(std::isfinite(sig));
            EXPECT_GT(sig, 0.0);
            EXPECT_LT(std::abs(got - want), 6 * sig + 1e-12);
        }
        // Thesis method: R0 from the steps within a few %, finite segment results, prediction RMS reported.
        EXPECT_LT(rel(fit.r0.discharge_ohm, o.discharge.r0_ohm), 0.05);
        EXPECT_LT(rel(fit.r0.charge_ohm, o.charge.r0_ohm), 0.05);
        EXPECT_TRUE(std::isfinite(fit.thesis_rms_v));
        EXPECT_TRUE(std::isfinite(fit.thesis_discharge.r1_ohm));
        EXPECT_TRUE(std::isfinite(fit.thesis_charge.r2_ohm));
        // The better predictor is chosen.
        const double best = std::min(fit.thesis_rms_v, fit.joint_rms_v);
        EXPECT_EQ(fit.chosen == PulseSetFit::Method::Joint ? fit.joint_rms_v : fit.thesis_rms_v, best);
        EXPECT_TRUE(std::isnan(fit.temperature_c));  // no temperature channel
    }
    std::printf("joint+thesis fit: %.2f ms per pulse set\n", total_ms / 5.0);
}

TEST(PulseFit, NoiseFreeDataIsFitExactly) {
    test::SyntheticOptions o;
    o.soc0 = 0.7;
    const auto h = make_hppc(1, o);
    ASSERT_EQ(h.seg.pulse_sets.size(), 1u);
    const auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[0], options_at(h.soc[0]));
    expect_params(fit.joint_discharge, o.discharge, 1e-4, 1e-3, 1e-3, "joint discharge");
    expect_params(fit.joint_charge, o.charge, 1e-4, 1e-3, 1e-3, "joint charge");
    EXPECT_LT(fit.joint_rms_v, 1e-6);
    EXPECT_EQ(fit.chosen, PulseSetFit::Method::Joint);
    // R0 steps: V_A - V_B includes 0.1 s of RC response, so they read slightly high (< 2 %).
    for (double r0 : {fit.r0.ab_ohm, fit.r0.cd_ohm}) {
        EXPECT_GT(r0, o.discharge.r0_ohm);
        EXPECT_LT(rel(r0, o.discharge.r0_ohm), 0.02);
    }
    for (double r0 : {fit.r0.ef_ohm, fit.r0.gh_ohm}) EXPECT_LT(rel(r0, o.charge.r0_ohm), 0.02);
    // Capacitances are tau / R.
    const auto rc = to_rc_values(fit.joint_discharge);
    EXPECT_NEAR(rc.c1_f, o.discharge.tau1_s / o.discharge.r1_ohm, 2.0);
    EXPECT_NEAR(rc.c2_f, o.discharge.tau2_s / o.discharge.r2_ohm, 5.0);
}

TEST(PulseFit, ThesisSegmentsAreExactOnFlatOcv) {
    // The thesis' segment equations (3.3-3.19) hold the OCV constant within each segment; on such data they
    // must give back the model's parameters.
    test::SyntheticOptions o;
    o.soc0 = 0.7;
    o.flat_ocv = true;
    const auto h = make_hppc(1, o);
    ASSERT_EQ(h.seg.pulse_sets.size(), 1u);
    const auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[0], free_r0());
    const auto& s = fit.thesis;
    // Scripts 3.3-3.6 put t = 0 at the first row of each segment, 0.1 s after the current step, so the fast
    // pair's amplitude reads exp(-0.1 s / tau1) low: 4.9 % for tau1 = 2 s, 6.5 % for 1.5 s. Faithful to the
    // thesis, and the reason for the joint fit.
    const double bias_d = 1.0 - std::exp(-0.1 / o.discharge.tau1_s);
    const double bias_c = 1.0 - std::exp(-0.1 / o.charge.tau1_s);
    for (const auto* f : {&s.discharge, &s.discharge_relaxation}) {
        EXPECT_NEAR(f->r1_ohm / o.discharge.r1_ohm, 1.0 - bias_d, 0.01);
        EXPECT_LT(rel(f->tau1_s, o.discharge.tau1_s), 0.02);
        EXPECT_LT(rel(f->r2_ohm, o.discharge.r2_ohm), 0.02);
        EXPECT_LT(rel(f->tau2_s, o.discharge.tau2_s), 0.02);
    }
    // Charge pulse and relaxation carry the initial RC voltages (eqs. 3.13, 3.17). Those equations let the
    // discharge's leftover polarization decay with the CHARGE time constants; in the model (electrical.hpp)
    // it keeps its own, so the charge segments are only approximately exact: within 10 %.
    EXPECT_GT(s.v1_residual_v, 0.0);  // discharge polarization left at F (thesis sign)
    EXPECT_GT(s.v2_residual_v, 0.0);
    for (const auto* f : {&s.charge, &s.charge_relaxation}) {
        EXPECT_NEAR(f->r1_ohm / o.charge.r1_ohm, 1.0 - bias_c, 0.02);
        EXPECT_LT(rel(f->tau1_s, o.charge.tau1_s), 0.05);
        EXPECT_LT(rel(f->r2_ohm, o.charge.r2_ohm), 0.10);
        EXPECT_LT(rel(f->tau2_s, o.charge.tau2_s), 0.10);
    }
    EXPECT_NEAR(fit.thesis_discharge.r1_ohm / o.discharge.r1_ohm, 1.0 - bias_d, 0.01);
    EXPECT_LT(rel(fit.thesis_charge.r2_ohm, o.charge.r2_ohm), 0.05);
    EXPECT_LT(fit.thesis_rms_v, 3e-4);
    expect_params(fit.joint_discharge, o.discharge, 1e-4, 1e-3, 1e-3, "joint discharge");
}

TEST(PulseFit, ThesisSegmentsAbsorbTheOcvSlope) {
    // With the OCV falling during the discharge pulse, the thesis' eq. 3.6 (constant OCV) puts the slope
    // into the slow pair, while the joint fit, given the slope, does not.
    test::SyntheticOptions o;
    o.soc0 = 0.7;
    const auto h = make_hppc(1, o);
    const auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[0], options_at(h.soc[0]));
    EXPECT_GT(fit.thesis.discharge.r2_ohm, 1.2 * o.discharge.r2_ohm);
    EXPECT_LT(rel(fit.joint_discharge.r2_ohm, o.discharge.r2_ohm), 1e-3);
    EXPECT_LT(fit.joint_rms_v, fit.thesis_rms_v);
}

TEST(PulseFit, UnknownOcvSlopeStillGivesR0) {
    test::SyntheticOptions o;
    o.voltage_noise_v = 3e-4;
    o.soc0 = 0.5;
    const auto h = make_hppc(1, o);
    const auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[0]);  // docv = 0
    EXPECT_LT(rel(fit.joint_discharge.r0_ohm, o.discharge.r0_ohm), 0.05);
    EXPECT_LT(rel(fit.joint_charge.r0_ohm, o.charge.r0_ohm), 0.05);
    EXPECT_TRUE(std::any_of(fit.warnings.begin(), fit.warnings.end(),
                            [](const std::string& w) { return w.find("OCV slope unknown") != std::string::npos; }));
}

TEST(PulseFit, ChargePulseAtVoltageLimitIsFlagged) {
    using test::Step;
    // Fully charged cell: the charge pulse reaches 4.1 V at once and turns CV (thesis 100 % SOC pulse set).
    std::vector<Step> prog{{700, 0, "Rest"}, {30, -4.5, "CCCV DChg"}, {40, 0, "Rest"},
                           {10, 4.5, "CCCV Chg", 4.1}, {40, 0, "Rest"}};
    test::SyntheticOptions o;
    o.soc0 = 0.99;
    o.voltage_noise_v = 3e-4;
    const auto rec = test::synthesize(prog, o);
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.pulse_sets.size(), 1u);
    ASSERT_TRUE(seg.pulse_sets[0].charge_cv);
    const auto fit = fit_pulse_set(rec, seg.pulse_sets[0], options_at(0.99));
    EXPECT_TRUE(std::any_of(fit.warnings.begin(), fit.warnings.end(),
                            [](const std::string& w) { return w.find("turned CV") != std::string::npos; }));
    // The discharge side is unaffected.
    EXPECT_LT(rel(fit.joint_discharge.r0_ohm, o.discharge.r0_ohm), 0.01);
}

TEST(PulseFit, InvalidPulseSetDoesNotCrash) {
    const auto rec = test::synthesize(test::pulse_set_program());
    PulseSet bad;  // all zero
    const auto fit = fit_pulse_set(rec, bad);
    EXPECT_FALSE(fit.warnings.empty());
    EXPECT_TRUE(std::isnan(fit.joint_discharge.r0_ohm));
    PulseSet beyond = segment_recording(rec).pulse_sets.at(0);
    beyond.end = rec.size() + 10;
    EXPECT_FALSE(fit_pulse_set(rec.slice(0, rec.size()), beyond).warnings.empty());
}

TEST(PulseFit, DefaultJointFitHoldsR0AtTheSamplingCorrectedSteps) {
    // By default R0 is measured by the steps (eq. 3.2) and the joint fit finds the rest. The raw steps read R0
    // high (V_B is 0.1 s after the step and carries that much RC response); the held value has the fitted
    // pairs' movement over that interval taken out, so on noise-free data it is the cell's R0.
    test::SyntheticOptions o;
    o.soc0 = 0.7;
    const auto h = make_hppc(1, o);
    ASSERT_EQ(h.seg.pulse_sets.size(), 1u);
    PulseFitOptions po;
    po.docv_dah_v_per_ah = test::synthetic_docv_dsoc(h.soc[0]) / test::kCapacityAh;
    const auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[0], po);
    EXPECT_GT(rel(fit.r0.discharge_ohm, o.discharge.r0_ohm), 0.005);  // the raw steps' bias
    EXPECT_GT(fit.r0.discharge_ohm, o.discharge.r0_ohm);
    EXPECT_DOUBLE_EQ(fit.joint_discharge.r0_ohm, fit.r0.discharge_corrected_ohm);
    EXPECT_DOUBLE_EQ(fit.joint_charge.r0_ohm, fit.r0.charge_corrected_ohm);
    EXPECT_LT(rel(fit.joint_discharge.r0_ohm, o.discharge.r0_ohm), 1e-3);
    EXPECT_LT(rel(fit.joint_charge.r0_ohm, o.charge.r0_ohm), 1e-3);
    EXPECT_TRUE(std::isnan(fit.joint_discharge_sigma.r0_ohm));  // held, not estimated
    EXPECT_LT(fit.joint_rms_v, 1e-5);
    EXPECT_NEAR(fit.joint_discharge.r2_ohm, o.discharge.r2_ohm, 0.01 * o.discharge.r2_ohm);

    // Without the correction the joint fit holds the raw eq. 3.2 values and predicts a little worse.
    po.r0_step_sampling_correction = false;
    const auto raw = fit_pulse_set(h.rec, h.seg.pulse_sets[0], po);
    EXPECT_DOUBLE_EQ(raw.joint_discharge.r0_ohm, raw.r0.discharge_ohm);
    EXPECT_DOUBLE_EQ(raw.joint_charge.r0_ohm, raw.r0.charge_ohm);
    EXPECT_TRUE(std::isnan(raw.r0.discharge_corrected_ohm));
    EXPECT_GT(raw.joint_rms_v, fit.joint_rms_v);
}

TEST(PulseFit, UnknownOcvSlopeIsEstimatedAndTheSlowPairRecovered) {
    // The first pulse set of an online run has no earlier rest to take the OCV slope from (docv = 0). Held flat,
    // the OCV's fall during the discharge pulse lands in the slow pair; estimated from the pulse set itself, the
    // slope comes out near the truth and the pairs with it. Noise as on the simulated tester.
    test::SyntheticOptions o;
    o.soc0 = 0.7;
    o.voltage_noise_v = 2e-4;
    const auto h = make_hppc(1, o);
    ASSERT_EQ(h.seg.pulse_sets.size(), 1u);
    PulseFitOptions held = free_r0();
    held.estimate_unknown_ocv_slope = false;
    const auto flat = fit_pulse_set(h.rec, h.seg.pulse_sets[0], held);
    const auto fit = fit_pulse_set(h.rec, h.seg.pulse_sets[0], free_r0());
    EXPECT_GT(rel(flat.joint_discharge.r2_ohm, o.discharge.r2_ohm), 0.15);  // what the estimate repairs
    expect_params(fit.joint_discharge, o.discharge, 0.03, 0.10, 0.10, "estimated slope, discharge");
    expect_params(fit.joint_charge, o.charge, 0.03, 0.10, 0.15, "estimated slope, charge");
    EXPECT_TRUE(std::any_of(fit.warnings.begin(), fit.warnings.end(),
                            [](const std::string& w) { return w.find("estimated from the pulse set") != std::string::npos; }));
}

// A discharge-only pulse set (long rest, 30 s discharge pulse, rest, then the SOC step): the joint fit identifies
// the discharge direction alone, with uncertainties; the charge direction, which no row excites, is null and said
// to be, never a value; the thesis' per-segment fits, which need its four segments, are not run.
TEST(PulseFit, DischargeOnlyPulseSetFitsTheDischargeDirectionAlone) {
    test::SyntheticOptions o;
    o.soc0 = 0.7;
    o.voltage_noise_v = 2e-4;
    const std::vector<test::Step> prog = {
        {700, 0, "Rest"}, {30, -9.0, "CC DChg"}, {120, 0, "Rest"}, {300, -4.5, "CC DChg"}, {700, 0, "Rest"}};
    const auto rec = test::synthesize(prog, o);
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.pulse_sets.size(), 1u);
    ASSERT_EQ(seg.pulse_sets[0].form, PulseSetForm::DischargeOnly);
    for (const bool from_steps : {false, true}) {
        SCOPED_TRACE(from_steps ? "R0 held at the steps" : "R0 fitted");
        PulseFitOptions po = options_at(0.7);
        po.r0_from_steps = from_steps;
        const auto fit = fit_pulse_set(rec, seg.pulse_sets[0], po);
        expect_params(fit.chosen_discharge(), o.discharge, 0.02, 0.10, 0.25, "discharge");
        EXPECT_EQ(fit.chosen, PulseSetFit::Method::Joint);
        EXPECT_FALSE(fit.joint_at_bound);
        EXPECT_TRUE(std::isnan(fit.chosen_charge().r0_ohm));
        EXPECT_TRUE(std::isnan(fit.chosen_charge().tau2_s));
        EXPECT_TRUE(std::isnan(fit.r0.charge_ohm));
        EXPECT_TRUE(std::isnan(fit.thesis_rms_v));
        EXPECT_LT(fit.joint_rms_v, 1e-3);
        if (!from_steps) {
            EXPECT_GT(fit.joint_discharge_sigma.r1_ohm, 0.0);
        }
        bool said = false;
        for (const auto& w : fit.warnings) said = said || w.find("charge parameters not identified") != std::string::npos;
        EXPECT_TRUE(said);
    }
}

// The USABC layout's pulse set (regen pulse straight into the SOC step): both directions fitted; the step at the
// regen pulse's end is a step into the SOC step's current, not into a rest, so it is not read as R0 (eq. 3.2's GH),
// and the charge R0 comes from the step at its start alone.
TEST(PulseFit, UsabcPulseSetFitsBothDirectionsWithoutTheStepIntoTheSocStep) {
    test::SyntheticOptions o;
    o.soc0 = 0.6;
    o.voltage_noise_v = 2e-4;
    const std::vector<test::Step> prog = {{700, 0, "Rest"}, {30, -9.0, "CC DChg"}, {40, 0, "Rest"},
                                          {10, 6.75, "CC Chg"},  {300, -4.5, "CC DChg"}, {700, 0, "Rest"}};
    const auto rec = test::synthesize(prog, o);
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.pulse_sets.size(), 1u);
    ASSERT_EQ(seg.pulse_sets[0].form, PulseSetForm::NoChargeRelaxation);
    const auto fit = fit_pulse_set(rec, seg.pulse_sets[0], options_at(0.6));
    EXPECT_TRUE(std::isnan(fit.r0.gh_ohm));
    EXPECT_LT(rel(fit.r0.ef_ohm, o.charge.r0_ohm), 0.03);
    EXPECT_LT(rel(fit.r0.charge_ohm, o.charge.r0_ohm), 0.03);
    expect_params(fit.chosen_discharge(), o.discharge, 0.02, 0.10, 0.25, "discharge");
    EXPECT_LT(rel(fit.chosen_charge().r0_ohm, o.charge.r0_ohm), 0.03);
    EXPECT_TRUE(std::isfinite(fit.chosen_charge().r1_ohm));
    EXPECT_TRUE(std::isnan(fit.thesis_rms_v));
}

// A pulse set of the Other form (a 2 s charge pulse, then at once a 30 s discharge pulse, a rest, the SOC step):
// both directions fitted; R0 only from the steps with a rest on their other side (EF into the charge pulse, CD out
// of the discharge pulse), never from the step between the pulses, which moves both directions' R0.
TEST(PulseFit, ChargeFirstPulseSetWithoutARestBetweenReadsOnlyTheStepsAtARest) {
    test::SyntheticOptions o;
    o.soc0 = 0.6;
    o.voltage_noise_v = 2e-4;
    const std::vector<test::Step> prog = {{700, 0, "Rest"},  {2, 2.25, "CC Chg"},      {30, -9.0, "CC DChg"},
                                          {40, 0, "Rest"},   {300, -4.5, "CC DChg"},   {700, 0, "Rest"}};
    const auto rec = test::synthesize(prog, o);
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.pulse_sets.size(), 1u);
    ASSERT_EQ(seg.pulse_sets[0].form, PulseSetForm::Other);
    const auto fit = fit_pulse_set(rec, seg.pulse_sets[0], options_at(0.6));
    EXPECT_TRUE(std::isnan(fit.r0.ab_ohm));
    EXPECT_TRUE(std::isnan(fit.r0.gh_ohm));
    EXPECT_LT(rel(fit.r0.cd_ohm, o.discharge.r0_ohm), 0.03);
    EXPECT_LT(rel(fit.r0.ef_ohm, o.charge.r0_ohm), 0.05);
    expect_params(fit.chosen_discharge(), o.discharge, 0.02, 0.10, 0.25, "discharge");
    EXPECT_TRUE(std::isfinite(fit.chosen_charge().r0_ohm));
    EXPECT_TRUE(std::isnan(fit.thesis_rms_v));
}

// The joint fit's uncertainties do not depend on the cell's size: the same pulse set on a cell with a hundredth of
// the resistances, a hundred times the capacitances (the same time constants) and a hundred times the current (the same
// voltages, the same noise) has the same relative uncertainties. In raw units J'J then spreads its eigenvalues by
// 1e4 more (ohms against seconds), which the covariance's rank check read as rank deficient: a 40 Ah cell on the
// simulated bench got no uncertainty at all for the first pulse set of its run.
TEST(PulseFit, JointUncertaintiesAreTheSameOnACellAHundredTimesLarger) {
    constexpr double kScale = 100.0;
    auto fit_of = [&](double scale) {
        test::SyntheticOptions o;
        o.flat_ocv = true;  // the same voltages at any current: the SOC the larger current moves does not show
        o.soc0 = 0.8;
        o.voltage_noise_v = 2e-4;
        o.seed = 7;
        for (auto* p : {&o.discharge, &o.charge}) p->r0_ohm /= scale, p->r1_ohm /= scale, p->r2_ohm /= scale;
        auto program = test::pulse_set_program(700.0, 4.5 * scale);
        program.push_back({300.0, -4.5 * scale, "CC DChg"});  // the SOC step, then the next level's rest
        program.push_back({700.0, 0.0, "Rest"});
        const auto rec = test::synthesize(program, o);
        const auto seg = segment_recording(rec);
        EXPECT_EQ(seg.pulse_sets.size(), 1u);
        PulseFitOptions po;
        po.docv_dah_v_per_ah = 0.0;
        return fit_pulse_set(rec, seg.pulse_sets.at(0), po);
    };
    const auto small = fit_of(1.0), large = fit_of(kScale);
    for (const auto& [name, s, l] :
         {std::tuple{"discharge R1", small.joint_discharge_sigma.r1_ohm / small.joint_discharge.r1_ohm,
                     large.joint_discharge_sigma.r1_ohm / large.joint_discharge.r1_ohm},
          std::tuple{"discharge tau2", small.joint_discharge_sigma.tau2_s / small.joint_discharge.tau2_s,
                     large.joint_discharge_sigma.tau2_s / large.joint_discharge.tau2_s},
          std::tuple{"charge R2", small.joint_charge_sigma.r2_ohm / small.joint_charge.r2_ohm,
                     large.joint_charge_sigma.r2_ohm / large.joint_charge.r2_ohm},
          std::tuple{"charge tau1", small.joint_charge_sigma.tau1_s / small.joint_charge.tau1_s,
                     large.joint_charge_sigma.tau1_s / large.joint_charge.tau1_s}}) {
        SCOPED_TRACE(name);
        ASSERT_TRUE(std::isfinite(s) && s > 0.0) << "no uncertainty on the small cell";
        ASSERT_TRUE(std::isfinite(l) && l > 0.0) << "no uncertainty on the large cell";
        EXPECT_NEAR(l, s, 0.05 * s);
    }
    EXPECT_NEAR(large.joint_discharge.r1_ohm * kScale, small.joint_discharge.r1_ohm, 0.01 * small.joint_discharge.r1_ohm);
}
