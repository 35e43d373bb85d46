#pragma once
// Fit of one HPPC pulse set (segment.hpp) to the Thevenin 2RC model, two ways:
//
//  1. The thesis' method (section 3.2.2): OCV = V_A (eq. 3.1), R0 from the four voltage steps (eq. 3.2), and
//     four independent 5-parameter exponential fits (a, tau1, b, tau2, c) on the discharge pulse (eq. 3.6),
//     the discharge relaxation (eq. 3.10), the charge pulse (eq. 3.14) and the charge relaxation (eq. 3.18),
//     carrying the initial RC voltages from segment to segment exactly as Scripts 3.3-3.6 do, with their bounds
//     and start point; R1, C1, R2, C2 per segment from eqs. 3.7, 3.11, 3.15, 3.19; direction averages as in
//     Table 3.2 (discharge = mean of D and DR, charge = mean of C and CR). Faithful also where the scripts
//     approximate: t = 0 at the first row of each segment (one sample after the step, so the fast pair reads
//     exp(-dt/tau1) low, ~5 % at 0.1 s), I_d and I_c from the first row of each pulse, OCV constant within a
//     segment (so a falling OCV during the discharge pulse ends up in R2 D).
//
//  2. A joint fit of the whole pulse set (from row A, just before the discharge pulse, to the end of the charge
//     relaxation) with the exact ZOH model of electrical.hpp: R0, R1, tau1, R2, tau2 per direction plus an
//     OCV offset c, with OCV(t) = ocv_v + c + docv_dah_v_per_ah * (Ah throughput since A). The RC voltages
//     are carried across the segments by the simulation itself. For fixed time constants the model is linear
//     in (R0, R1, R2 of both directions, c) (variable projection): (a) a grid search over log-spaced
//     (tau1, tau2) of one direction at a time, the other held, twice round, each grid point a 7x7 linear
//     least-squares solve; (b) from the best grid point(s), Ceres on the four log time constants alone with the
//     linear parameters projected out (Kaufman's Jacobian); (c) Ceres on all 11 parameters of the exact model
//     (analytic Jacobian from the forward sensitivities of the ZOH recursion) under bounds (R >= 0, tau1 in
//     [0.05, 20] s, tau2 in [5, 500] s, tau1 < tau2); 1-sigma uncertainties from (J'J)^-1 at the optimum (Ceres'
//     Jacobian; the inverse taken by Eigen with J'J's columns scaled to unit norm, so that the rank check does not
//     depend on the cell's size or the units), scaled by the residual variance, when the scaled J'J is not rank
//     deficient (they ignore the correlation of neighbouring residuals, so they are optimistic).
//
// Both results are simulated with simulate_overpotential over the same rows, with OCV(t) = ocv_v +
// docv_dah * Ah (no offset: that is how a parameter set is used), and `chosen` is the one with the smaller
// RMS voltage error among the results whose parameters are all finite and positive and off the bounds of their
// method (`*_at_bound`); only when neither (or both) qualifies does the RMS alone decide. A time constant
// pinned on a bound means the pulse set does not determine it, and such a pair (e.g. tau2 = 500 s with
// R2 = 75 mOhm, which fits 50 s of charge data as a ramp) must not win on a few tenths of a millivolt: it
// would wreck any longer simulation.
//
// Signs: the thesis writes its equations with discharge-positive current and magnitudes |I_d|, |I_c|; here the
// recording's current is BDF (+ = charge), and every parameter is a positive resistance / time constant.
#include <cstddef>
#include <limits>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/electrical.hpp"
#include "cellbench/estimator/segment.hpp"

namespace cellbench::estimator {

struct PulseFitOptions {
    // Local OCV slope per Ah of charge throughput (V/Ah, positive: charging raises the OCV), from the OCV
    // table: dOCV/dSOC / capacity_ah. 0 = unknown (OCV held constant apart from the offset c).
    double docv_dah_v_per_ah = 0.0;
    // With docv_dah_v_per_ah = 0 (and no extended window): estimate the slope from the pulse set itself, the
    // slope with which the joint model fits its rows best (golden-section search; the online fit of the first
    // pulse set of a run, which has no earlier rest to take a chord from). false: hold the OCV at V_A.
    bool estimate_unknown_ocv_slope = true;
    // The charge relaxation used in the fits is cut after this long (a pulse set followed by a long rest).
    double max_relaxation_s = 300.0;
    // Extended window (offline): when extended_end > the pulse set's end, the joint fit and both RMS values
    // also cover the rows up to extended_end (the SOC-step discharge and the long rest after it), where the
    // slow pair's time constant shows; a 70 s pulse set cannot tell tau2 = 100 s from 500 s. Over that span the
    // OCV runs linearly in charge throughput from ocv_v to extended_end_ocv_v (the next rest's OCV), as the
    // parameter set's OCV table does, and rows are merged where the current holds (exact under ZOH; the merged
    // row carries the mean current, so charge is conserved).
    std::size_t extended_end = 0;
    // Hold R0 of each direction at its eq. 3.2 step value (mean of the two steps) in the joint fit's final
    // refinement: with 0.1 s sampling a fast RC pair and R0 trade off (the fit can move part of R0 into a
    // sub-second pair), while the steps measure R0 directly.
    bool r0_from_steps = true;
    // With r0_from_steps: take out of each step what the fitted RC pairs moved in the sampling interval
    // between the rows either side of it (eq. 3.2's V_B is one interval, 0.1 s, after the step and carries
    // R1 (1 - exp(-dt/tau1)) + ... of relaxation: +1-2 % for the thesis cell). The held R0 is then the one with
    // which the exact ZOH model reproduces the measured steps; held R0 and pairs are refined alternately.
    // R0Steps keeps the uncorrected eq. 3.2 values.
    bool r0_step_sampling_correction = true;
    double extended_end_ocv_v = kNaN;
    bool thesis_method = true;     // run the per-segment fits (method 1)
    bool joint_method = true;      // run the joint fit (method 2)
    bool compute_covariance = true;
    // Bounds of the joint fit's time constants (tau1 < tau2 is enforced as well).
    double tau1_min_s = 0.05, tau1_max_s = 20.0;
    double tau2_min_s = 5.0, tau2_max_s = 500.0;
    std::size_t tau1_grid = 12;    // grid points of the variable-projection search (log-spaced)
    std::size_t tau2_grid = 12;
    std::size_t refine_starts = 1; // distinct grid optima refined (the best final cost wins)
    int max_iterations = 60;       // per Ceres solve
};

// Series resistance from the four voltage steps, thesis eq. 3.2 / Script 3.2 (rows adjacent to each step).
struct R0Steps {
    double ab_ohm = kNaN;  // (V_A - V_B) / |I_d|: discharge pulse start
    double cd_ohm = kNaN;  // (V_D - V_C) / |I_d|: discharge pulse end
    double ef_ohm = kNaN;  // (V_F - V_E) / |I_c|: charge pulse start
    double gh_ohm = kNaN;  // (V_G - V_H) / |I_c|: charge pulse end
    double discharge_ohm = kNaN;  // "R0 DA" = mean(AB, CD)
    double charge_ohm = kNaN;     // "R0 CA" = mean(EF, GH)
    // The same steps less the RC pairs' movement over the sampling interval, from the joint fit
    // (PulseFitOptions::r0_step_sampling_correction); NaN when not computed. The joint result holds these.
    double discharge_corrected_ohm = kNaN;
    double charge_corrected_ohm = kNaN;
};

// One 5-parameter exponential fit of the thesis (eqs. 3.6, 3.10, 3.14, 3.18) and what it gives.
struct ExpSegmentFit {
    std::size_t begin = 0, end = 0;  // rows fitted
    double a_v = kNaN, tau1_s = kNaN, b_v = kNaN, tau2_s = kNaN, c_v = kNaN;
    double r1_ohm = kNaN, c1_f = kNaN, r2_ohm = kNaN, c2_f = kNaN;
    double rms_v = kNaN;   // RMS residual of the segment fit
    bool converged = false;
    bool at_bound = false; // a or b, tau1 or tau2 ended on a bound of Scripts 3.3-3.6
};

struct SegmentFits {
    ExpSegmentFit discharge;              // B..C, eq. 3.6 / 3.7
    ExpSegmentFit discharge_relaxation;   // D..E, eq. 3.10 / 3.11
    ExpSegmentFit charge;                 // F..G, eq. 3.14 / 3.15
    ExpSegmentFit charge_relaxation;      // H..I, eq. 3.18 / 3.19
    double v1_residual_v = kNaN, v2_residual_v = kNaN;  // V1(0), V2(0) at F, eq. 3.13 (thesis sign: > 0)
    double current_discharge_a = kNaN;  // |I_d| as the scripts take it (first discharge row)
    double current_charge_a = kNaN;     // |I_c| (first charge row)
};

// R0, R1, C1, R2, C2 of one direction (the parameter-set vocabulary).
struct RcValues {
    double r0_ohm = kNaN, r1_ohm = kNaN, c1_f = kNaN, r2_ohm = kNaN, c2_f = kNaN;
};
RcValues to_rc_values(const Rc2Params<double>& p);  // C = tau / R

inline constexpr Rc2Params<double> kNaNRc2{kNaN, kNaN, kNaN, kNaN, kNaN};

struct PulseSetFit {
    enum class Method { Thesis, Joint };

    PulseSet pulse_set;
    double soc = kNaN;            // assigned by the caller (Coulomb counting)
    double ocv_v = kNaN;          // V_A, eq. 3.1
    double temperature_c = kNaN;  // mean surface (else ambient) temperature over the pulse set
    std::size_t begin = 0, end = 0;  // rows used by the joint fit and by both RMS values (A .. capped end)

    R0Steps r0;
    SegmentFits thesis;
    // Thesis direction averages (Table 3.2 DA / CA); R0 from eq. 3.2, tau = R_avg * C_avg.
    Rc2Params<double> thesis_discharge = kNaNRc2, thesis_charge = kNaNRc2;

    Rc2Params<double> joint_discharge = kNaNRc2, joint_charge = kNaNRc2;
    Rc2Params<double> joint_discharge_sigma = kNaNRc2, joint_charge_sigma = kNaNRc2;  // NaN: not computable
    double joint_ocv_offset_v = kNaN, joint_ocv_offset_sigma_v = kNaN;  // c
    double joint_fit_rms_v = kNaN;  // joint fit residual, offset c included
    bool joint_converged = false;

    // RMS voltage error of each result simulated over rows [begin, end) with OCV(t) = ocv_v + docv_dah * Ah.
    double thesis_rms_v = kNaN, joint_rms_v = kNaN;
    // Parameters unusable for a parameter set: non-finite or non-positive, or a fit ended on a bound (thesis:
    // any segment of Scripts 3.3-3.6; joint: a time constant on its box bound).
    bool thesis_at_bound = false, joint_at_bound = false;
    Method chosen = Method::Joint;

    std::vector<std::string> warnings;  // quality problems, in plain words

    [[nodiscard]] Rc2Params<double> chosen_discharge() const {
        return chosen == Method::Joint ? joint_discharge : thesis_discharge;
    }
    [[nodiscard]] Rc2Params<double> chosen_charge() const {
        return chosen == Method::Joint ? joint_charge : thesis_charge;
    }
};

const char* to_string(PulseSetFit::Method method);

// Fits one pulse set of `rec` (indices from segment_recording on the same rows). Never throws on bad data:
// what cannot be computed is NaN and explained in `warnings`.
PulseSetFit fit_pulse_set(const Recording& rec, const PulseSet& ps, const PulseFitOptions& options = {});

}  // namespace cellbench::estimator
