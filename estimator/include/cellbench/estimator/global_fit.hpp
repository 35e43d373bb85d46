#pragma once
// One global identification of the electrical model from every characterization recording at once.
//
// The per-pulse-set fits (pulse_fit.hpp) see 70-100 s of data each and cannot tell a slow pair's time constant,
// the OCV between rest points, or a temperature or current dependence; fitted independently per SOC level they
// jump between neighbours. Here every stretch of every recording between two long rests (a "window": pulse sets,
// SOC-step discharges, pilot and full discharges, charges) is simulated with the exact ZOH model of
// electrical.hpp, and all windows are fitted together in one non-linear least-squares problem (Ceres):
//
//  - Parameters are values at SOC knots (`knot_soc`, e.g. the test's levels, or a uniform `knot_spacing`)
//    interpolated linearly, exactly as
//    ParameterSet::rc_at and ocv_at interpolate them, so the fitted tables ARE the model that was fitted:
//    per direction log R0, log R1, log tau1, log R2, log(tau2/tau1 - 1) (so 0 < tau1 < tau2 by construction,
//    never by swapping), and OCV per knot.
//  - Smoothness: a penalty on the second differences of every log-parameter along SOC (and a weak one on the
//    OCV), its weight chosen by cross-validation over windows (fit on half the windows, predict the others).
//  - Temperature dependence (Arrhenius on R0, R1, R2, as CellModel applies resistance_temperature) when the
//    recordings span more than `min_temperature_span_k` of measured cell temperature, and current dependence
//    of the polarization (asinh/Butler-Volmer, as CellModel applies resistance_current) when their currents
//    span a ratio above `min_current_ratio`: both identified from characterization data alone.
//  - A window that does not start rested on a known SOC (e.g. a CC discharge recorded on its own) gets its own
//    initial SOC as a parameter.
//  - Uncertainty of every value from the Jacobian at the optimum (ceres::Covariance), scaled by the residual
//    variance and inflated for the residuals' lag-1 autocorrelation; values outside physical bounds, with an
//    uncertainty above the value itself, or without data near their knot are flagged.
//
// Pure computation: no I/O.
#include <array>
#include <cstddef>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/estimator/progress.hpp"

namespace cellbench::estimator {

struct GlobalFitOptions {
    double knot_spacing = kNaN;  // SOC spacing of a uniform grid of table breakpoints (used when knot_soc is empty)
    // The table breakpoints themselves (increasing SOC, at least 3): characterize() puts them at the test's SOC
    // levels, so every knot sits where a pulse set measured it, whatever the layout's spacing. Empty: the uniform
    // grid of knot_spacing (0.1 when that is NaN) over the SOC the recordings visit.
    std::vector<double> knot_soc;
    // The OCV is fitted on a grid finer than the resistances and capacitances: low-rate stretches (pilot, SOC-step
    // and CC discharges) pin it between the pulse levels, while a pulse set pins the RC pairs only at its own level.
    // Each knot interval is divided into ocv_knots_per_interval equal parts; 0 derives that number from the typical
    // knot spacing so that the OCV knots are at most ocv_spacing_soc apart (at least 2 parts). An OCV knot no
    // low-rate data pass stays on the line between its neighbours, so a finer grid costs parameters, not
    // freedom. The tables come out on the finer grid, the RC values interpolated as the model does.
    // 2 % of SOC: an LFP's or LMO's OCV bends within a few % of SOC at its ends and its plateau steps; at 5 % the
    // fitted OCV of the independent plant's LFP (seed 15) was 95 mV high at 6 % SOC and the second RC pair turned
    // into an integrator standing in for the missing slope (docs/model.md).
    int ocv_knots_per_interval = 0;
    double ocv_spacing_soc = 0.02;
    std::vector<double> smoothness_candidates = {100.0, 300.0, 1000.0, 3000.0};  // cross-validated
    double smoothness = kNaN;                // given: no cross-validation
    double ocv_smoothness = 0.005;           // relative weight of the OCV's second-difference penalty
    // Weight of the prior that charge and discharge values at one knot are alike (per unit log difference, against
    // voltage residuals in units of voltage_noise_v; 0: none).
    double direction_prior = 10.0;
    double voltage_noise_v = 1e-3;           // residual scale (only the relative weights depend on it)
    // The voltage jump across every current step is a residual of its own, weighted by the noise of a difference
    // of two samples (estimated per recording from its rests), not below this floor (quantization, a logger's
    // rounding that shows no noise in the rests).
    double step_noise_floor_v = 0.1e-3;
    bool temperature_dependence = true;
    bool current_dependence = true;
    double min_temperature_span_k = 3.0;
    double min_current_ratio = 2.5;
    // A third RC pair, the same at every SOC and in both directions (the `extra_rc` extension: R3, tau3 from 5 min
    // to the longest rest, at most 3 h), for the slow relaxation a long rest shows after a discharge (solid-state diffusion), identified when a
    // rest of at least 20 min is in the recordings. Without it the second pair has to serve both the pulses and the
    // rests' tail (Panasonic 0 degC: tau2 about 45 s while the rests relax for 25 min; docs/model.md).
    bool slow_relaxation = true;
    double long_rest_s = 600.0;              // windows break at rests at least this long
    // A window's voltage residuals, on average over its duration, at most this many per second: beyond it (a drive
    // cycle logged at 10 Hz, its current changing at every row, so that every row is a tick) only every m-th tick's
    // voltage is a residual, the model still stepping through every tick. A recording's weight in the fit and the
    // fit's time then follow how long it lasts, not how often it was logged (Panasonic US06 at 0.1 s among the
    // characterization files: 37 877 of the fit's 44 990 residuals, 14 times the fit's time without it). Pulses
    // logged every 0.1 s are not touched: their ticks lengthen after each step, to a few per second on average
    // over a window. 0: no limit.
    double max_residual_rate_hz = 1.0;
    // Windows of pulses lying wholly below this SOC are left out (and named in the notes). At the test's last
    // level, after the SOC step has stopped at the cut-off, the pulses run into the cut-off again: the cycler's
    // voltage limit ends them, where the OCV is at its steepest, and no table value can fit them. Fitted
    // anyway, those few windows (30-50 mV RMS against 1-2 mV elsewhere) outweighed the rest of the test: on the
    // independent plant they turned the second RC pair into an integrator along the whole SOC axis (thesis layout
    // seed 12, tau2 off by a factor 300) or moved R0 10 % (seed 15). The tables at the lowest level then come
    // from the SOC-step discharges and the smoothness.
    double min_pulse_window_soc = 0.02;
    double step_lag = 0.0;                   // start value of the fitted current-step timing (0: at the row)
    // A step lag the data do not identify (its sd over a quarter of the sample interval) is held at 0 and the
    // tables refitted (global_fit.cpp); false leaves it where the fit put it (diagnostics).
    bool hold_unidentified_step_lag = true;
    int max_iterations = 80;
    // Starts besides the initial parameter set: uniform (tau1, tau2) in s over SOC, R0 and the OCV from the initial
    // set, its R1 + R2 split 1 : 2. Each is fitted start_iterations on every window; the lowest of them is fitted to
    // the end and wins where its objective is below the fit from the initial set. Empty: the initial set only.
    std::vector<std::array<double, 2>> start_time_constants_s = {{1.0, 20.0}, {5.0, 100.0}, {10.0, 300.0}};
    int start_iterations = 20;
    bool compute_uncertainty = true;  // also what tells an unidentified step lag (then held at 0 and refitted)
    // Tests: compare every window's Jacobian with Ceres' dynamic autodiff over the whole window (the reference the
    // fit's cheaper derivative passes must reproduce) at the start and at the fitted values; the largest relative
    // difference lands in GlobalFitResult::jacobian_mismatch. Costs several reference evaluations per window.
    bool check_jacobian = false;
    Progress progress;
};

// A stretch of one recording fitted as one simulation from a rested state.
struct GlobalWindow {
    std::size_t recording = 0;
    std::size_t begin = 0, end = 0;  // rows [begin, end)
    bool rested_start = true;        // starts at the end of a long rest (RC voltages ~ 0, SOC known)
    // "pulses" (current phases of at most a minute between rests), "step" (one current phase from a long rest into
    // the next that moves less than a quarter of the capacity: a GITT's or incremental-OCV test's titration step),
    // "discharge", "charge", "mixed". Pulses and steps are the windows the RC pairs are identified from.
    std::string kind;
    [[nodiscard]] bool identifies_rc() const { return kind == "pulses" || kind == "step"; }
    // Filled by the fit:
    double soc_min = kNaN, soc_max = kNaN;
    double soc_offset = 0.0;         // fitted initial-SOC correction (windows without a rested start)
    double capacity_scale = 1.0;     // fitted ratio of the window's charge scale (its own rate, its own day)
    bool capacity_scale_fitted = false;  // free (a slow discharge not anchored to the test's full charge), else 1
    double rms_v = kNaN;
    std::size_t residuals = 0;
};

// One fitted table value with its uncertainty and flags ("implausible", "uncertain", "unidentified").
struct FittedValue {
    double value = kNaN, sd = kNaN;
    std::vector<std::string> flags;
};

struct GlobalFitResult {
    ParameterSet params;  // electrical part (soc, ocv_v, discharge, charge, reference temperature, extensions)
    // Per knot, per direction: r0_ohm, r1_ohm, c1_f, r2_ohm, c2_f, tau1_s, tau2_s; and ocv_v.
    std::vector<std::vector<FittedValue>> discharge, charge;  // [knot][quantity]
    std::vector<FittedValue> ocv;
    FittedValue activation_energy_j_per_mol, exchange_current_a;
    bool slow_relaxation = false;         // a slow pair was fitted (GlobalFitOptions::slow_relaxation)
    FittedValue slow_r_ohm, slow_tau_s;   // its R3 and tau3 (in params.extensions.extra_rc when identified)
    double reference_current_a = kNaN;
    bool temperature_dependence = false, current_dependence = false;
    double smoothness = kNaN;
    int ocv_knots_per_interval = 0;  // the OCV grid's parts per knot interval (the table's RC rows are every m-th)
    // Where the fit that won started: the initial parameter set (NaN here) or uniform time constants in s
    // (GlobalFitOptions::start_time_constants_s).
    std::array<double, 2> start_time_constants_s = {kNaN, kNaN};
    std::vector<std::pair<double, double>> cross_validation;  // (weight, held-out RMS V)
    std::vector<GlobalWindow> windows;
    // Per recording, the SOC of every row as the fit ends with it: the Coulomb count, or for a recording not
    // anchored to the test's full charge the count from its first rested voltage, with each window's fitted SOC
    // offset and charge scale applied (rows outside every window keep the shift of the window before them, or
    // after them at the start). What the thermal identification reads the OCV at.
    std::vector<std::vector<double>> soc_of_row;
    double rms_v = kNaN;
    double residual_autocorrelation = kNaN;
    FittedValue step_lag;  // fitted fraction of a step's sample interval the new current flowed before its row
    double jacobian_mismatch = kNaN;  // GlobalFitOptions::check_jacobian: the largest relative difference found
    std::vector<std::string> notes;

    static constexpr const char* kQuantities[7] = {"r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "tau1_s", "tau2_s"};
    [[nodiscard]] nlohmann::json to_json() const;
    [[nodiscard]] std::size_t flagged_count() const;
};

// soc_of_row: per recording, the Coulomb-counted SOC of every row (empty: the recording's windows get a fitted
// initial SOC from `initial` below). `initial` provides starting values (and the OCV / SOC of unanchored
// windows); its grid need not match. long_rest_ranges: per recording, the long rests [begin, end).
GlobalFitResult fit_global(const std::vector<const Recording*>& recordings,
                           const std::vector<std::vector<double>>& soc_of_row,
                           const std::vector<std::vector<std::pair<std::size_t, std::size_t>>>& long_rest_ranges,
                           double capacity_ah, const ParameterSet& initial, const GlobalFitOptions& options = {});

// Where the model fits the characterization worst: the SOC ranges of the pulse windows whose RMS residual exceeds
// kPoorFitRatio times the median pulse window's (adjacent ones joined), one note each, or none. The tables there
// rest on data the model does not reproduce (on the P45B HPPC without the cycler's export: 10.4 mV RMS at 0-10 %
// SOC against a median of 2.7 mV, where its Random Walk prediction is 50-76 mV off), a fact about the model's
// structure that the values' own uncertainties do not carry. Fewer than four pulse windows: none (no median to
// judge by).
inline constexpr double kPoorFitRatio = 3.0;
std::vector<std::string> poorly_fitted_notes(const std::vector<GlobalWindow>& windows);

}  // namespace cellbench::estimator
