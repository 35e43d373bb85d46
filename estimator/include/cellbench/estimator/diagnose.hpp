#pragma once
// `cellbench diagnose`: where does the simulation miss the recording, which physics did the model leave out,
// and how much does adding it help — decided on data the candidate was not fitted to.
//
// 1. Locate: simulate with the given parameters; split the residuals of voltage, surface temperature and heat
//    flux by operating condition (direction, C-rate band, SOC band, temperature rise, time since the last
//    current step, charge throughput) and rank where the error concentrates.
// 2. Name and model: every candidate of the catalogue (params.hpp ModelExtensions, the effect ids of
//    INTERFACES.md) is fitted to the recording with the base parameters held. The objective is the sum over
//    the measured quantities of their mean squared error relative to the baseline's, so each quantity's
//    relative improvement counts alike. Searches run on a copy merged to 1 s intervals (charge conserved);
//    every figure reported is measured at full resolution.
// 3. Evidence: K-fold cross-validation over interleaved time blocks (block b belongs to fold b mod K, blocks
//    short against the recording, so every fold spans the SOC, current and temperature range of a drifting
//    recording; fit on K-1 folds, score on the held-out one; the simulation always runs the whole recording so
//    the states stay continuous) and BIC with an
//    effective sample count (residuals 10 s apart are taken as independent). A finding is significant when
//    (a) it removes at least min_cv_improvement of the held-out error on average, (b) it improves at least
//    K-1 of the K held-out blocks, and (c) its BIC improves by more than bic_threshold.
// 4. Combinations: after accepting the strongest significant finding, the remaining candidates are fitted
//    again on top of it (a recording may hide two effects), up to max_accepted. A candidate the parameter set
//    already holds (the global fit identifies resistance_temperature and resistance_current) is not proposed
//    again as missing.
// 5. Kinds: a finding is "physics_missing" (an effect of the catalogue) or "parameters_wrong" (the base set is
//    off: OCV table offset in a SOC band, capacity; re-identified on this recording). A capacity correction
//    within twice the parameter set's capacity_ah_sd (the characterization's own uncertainty) is not significant.
//    With other recordings of the cell (DiagnoseOptions::confirm), a candidate is fitted to them together with the
//    diagnosed one (each recording's error relative to the parameter set's), and one that still makes one of them
//    worse is contradicted and never significant (confirmation_verdict). The diagnosed recording itself is held
//    to the same rule for the quantities its evidence leaves out: a candidate that pushes a quantity the base gets
//    within the instrument's accuracy beyond it (a second RC pair that mends the voltage and spoils a heat flux the
//    base had right) is never significant either (Finding::worsens).
// 6. No false reassurance: the measurement noise is estimated from the recording itself (sample-to-sample
//    scatter in rests); when a quantity's residual after the accepted findings stays above noise_factor times
//    its noise, `unexplained` says where, how large, what it correlates with and which terms a sparse
//    regression of the residual keeps (residual_regression.cpp). The summary never says "adequate" then.
#include <atomic>
#include <cstddef>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/estimator/progress.hpp"
#include "cellbench/estimator/simulate.hpp"

namespace cellbench::estimator {

// The surface the default heat flux floor is given for: a 21700 cell's (m^2).
inline constexpr double kHeatFluxFloorAreaM2 = 0.005311;

struct DiagnoseOptions {
    std::size_t folds = 4;
    double min_cv_improvement = 0.25;  // fraction of the held-out error removed, averaged over the folds
    double bic_threshold = -10.0;      // required BIC change (negative = better)
    std::size_t max_accepted = 3;
    double search_step_s = 1.0;        // interval of the merged copy used by the searches
    std::vector<std::string> effects;  // candidates to try; empty = the whole catalogue
    std::size_t threads = 0;           // worker threads for the candidates (0 = one per core)
    // Errors below these RMS levels are not worth modelling (instrument accuracy): each quantity's error is
    // normalised by max(its baseline RMS, this floor), so a 30 % gain on a 0.1 degC error does not count as
    // much as a 30 % gain on a 2 degC one; and a quantity the current base already meets within its floor
    // gives no evidence at all (it leaves the held-out scores and the BIC; with none left, nothing is
    // significant, though `unexplained` still reports a residual above the noise).
    double voltage_floor_v = 0.005;       // cycler voltage accuracy class (0.05 % of a 10 V range)
    double temperature_floor_c = 0.3;     // thermocouple-grade agreement
    double heat_flux_floor_w = 0.05;      // ~10 W/m^2 over a 21700 cell's surface
    // The heat flux floor above is a 21700's: a larger cell (the parameter set's thermal.area_m2 above
    // kHeatFluxFloorAreaM2) gets it scaled by its surface, the sensor's accuracy per m^2 being the same. False: the
    // floor as given (the CLI's --heat-flux-floor-w).
    bool scale_heat_flux_floor_with_area = true;
    // A thermocouple's accuracy is mostly an offset: when no quantity exceeds its floor, a temperature error whose
    // part about its mean exceeds this multiple of the recording's temperature noise is evidence nonetheless.
    double temperature_shape_noise_factor = 3.0;
    // Held-out folds: interleaved blocks of this length (0: duration / (folds * 8), at least 60 s).
    double holdout_block_s = 0.0;
    // `unexplained` is reported while a residual RMS exceeds this multiple of the quantity's measurement noise.
    double noise_factor = 2.0;
    // Progress of diagnose() (baseline, round r candidate k of n, final simulation); empty = none.
    Progress progress;
    // Set by another thread to give up: diagnose() stops after the candidate fits under way and throws
    // DiagnoseCancelled (cellbenchd's shutdown). nullptr = never.
    const std::atomic<bool>* cancel = nullptr;
    // Other recordings of the same cell on the same bench set-up, best ones the parameter set was not fitted to
    // (another drive cycle): every candidate is fitted to them together with the diagnosed recording (the held-out
    // evidence stays the diagnosed recording's), then simulated on each with the current base and with its
    // correction. One that it makes worse (confirmation_verdict) contradicts it: a finding a recording contradicts
    // is not significant, whatever the diagnosed recording says. Effects that are a state of the diagnosed
    // recording (initial_soc, ambient_drift) do not carry over to another one and are not fitted to nor checked on
    // them. Not owned: they must outlive the call.
    std::vector<const Recording*> confirm;
};

// Thrown by diagnose() when DiagnoseOptions::cancel was set.
class DiagnoseCancelled : public std::runtime_error {
public:
    DiagnoseCancelled() : std::runtime_error("diagnosis cancelled") {}
};

struct QuantityRms {
    std::optional<double> voltage_v, temperature_c, heat_flux_w;
};

// One operating condition and how much of the error it carries.
struct ConditionError {
    std::string dimension;  // "direction", "c_rate", "soc", "temperature_rise", "since_step", "throughput", "combined"
    std::string condition;  // in words, e.g. "discharge above 3C, SOC 10-30 %"
    double time_share = 0.0;
    double share_of_voltage_error = 0.0;  // of the total squared voltage error (time-weighted)
    double voltage_rms_v = 0.0, voltage_bias_v = 0.0;
    std::optional<double> temperature_rms_c, temperature_bias_c;
};

// What another recording of the cell says about a finding (DiagnoseOptions::confirm).
struct Confirmation {
    std::string recording;                   // its source
    QuantityRms before, after;               // RMS with the current base, and with the finding added
    std::vector<std::string> better, worse;  // "voltage", "temperature", "heat_flux"
    std::string verdict;                     // "confirms" (better, none worse), "neutral", "contradicts" (a worse)
};

// A quantity is worse when its RMS rises above the instrument's accuracy and by more than 5 % and a tenth of that
// accuracy; better when it falls by as much from above the accuracy (changes inside the accuracy are no evidence).
// Fills better, worse and verdict from before and after.
void confirmation_verdict(Confirmation& c, double voltage_floor_v, double temperature_floor_c, double heat_flux_floor_w);

struct Finding {
    std::string effect;
    std::string kind = "physics_missing";  // or "parameters_wrong"
    bool significant = false;
    bool implausible = false;     // a correction on its plausible limit (its parameter's flags say which)
    double score = 0.0;           // mean held-out error reduction (fraction), the ranking key
    std::size_t folds_improved = 0;
    double delta_bic = 0.0;
    std::size_t parameters_count = 0;
    nlohmann::json parameters = nlohmann::json::object();
    QuantityRms improved;         // full-resolution RMS with this effect added to the accepted ones
    std::string explanation;
    // On each DiagnoseOptions::confirm recording (empty: none given, or a state of the diagnosed recording).
    std::vector<Confirmation> confirmation;
    bool contradicted = false;    // a confirm recording contradicts it: never significant
    bool withdrawn = false;       // it passed the significance test here, and a confirm recording contradicts it
    // Quantities of the diagnosed recording that the base gets within the instrument's accuracy (so not part of
    // the evidence) and this candidate makes worse beyond it, as confirmation_verdict judges: never significant.
    std::vector<std::string> worsens;
};

// Measurement noise (1 sigma) estimated from the recording: robust sample-to-sample scatter in rests.
struct NoiseEstimate {
    QuantityRms sigma;
    std::size_t rest_pairs = 0;  // consecutive rest rows the estimate rests on
};
NoiseEstimate estimate_noise(const Recording& rec, double capacity_ah);

// Sparse regression of a residual over a library of candidate terms (sequentially thresholded least squares on
// standardised columns): I, |I|, I*|I|, I low-passed at 10/100/1000 s, a throughput-driven direction state,
// temperature rise, SOC, and products. `explained` is the share of the residual variance the kept terms remove.
struct SparseTerm {
    std::string term;        // e.g. "I_lp100s" or "I*dT"
    std::string meaning;     // plain words
    double coefficient = 0;  // natural units: residual unit per term unit
    double share = 0;        // share of the residual variance this term alone carries (standardised beta^2)
};
struct ResidualModel {
    std::string quantity;    // "voltage_v" or "temperature_c"
    std::vector<SparseTerm> terms;
    double explained = 0.0;
    std::vector<std::pair<std::string, double>> correlations;  // strongest Pearson r of the residual per term
};
ResidualModel sparse_residual_model(const Recording& rec, const SimulationTrace& trace, const ParameterSet& params,
                                    bool temperature = false);

struct Unexplained {
    QuantityRms rms, noise;                  // residual after the accepted findings; estimated noise
    std::vector<std::string> above_noise;    // quantities above noise_factor x noise
    std::vector<ConditionError> where;       // largest shares of the remaining voltage error
    ResidualModel voltage, temperature;      // sparse models of the remaining residuals
    std::string summary;
};

struct Diagnosis {
    QuantityRms baseline;
    std::vector<ConditionError> where;       // the largest shares of the voltage error, strongest first
    std::vector<ConditionError> breakdown;   // every condition of every dimension (report)
    std::vector<Finding> findings;           // ordered by score, strongest first
    std::vector<std::string> accepted;       // effects accepted, in order
    ParameterSet improved_params;            // base + accepted extensions
    QuantityRms improved;                    // with all accepted effects
    SimulationTrace baseline_trace, improved_trace;
    std::string summary;                     // plain words
    NoiseEstimate noise;
    std::optional<Unexplained> unexplained;  // null: residual at the noise level or explained
    std::vector<std::string> skipped;        // candidates the parameter set already holds
    nlohmann::json holdout;                  // the hold-out scheme ({"scheme": "interleaved_blocks", ...})
    std::vector<std::string> confirm_recordings;  // sources of DiagnoseOptions::confirm
    // What was read differently from the file (rows at current steps with a stale current), in plain words.
    std::vector<std::string> notes;
};

// Which of one round's candidate findings diagnose accepts (an index; round.size() when none is significant): the
// strongest significant one, plausible before implausible; a significant base correction (parameters_wrong)
// scoring at least 80 % of it goes first instead, unless the physics is better by BIC.
std::size_t accepted_in_round(const std::vector<Finding>& round);

// Throws InputError if the recording is too short to cross-validate (fewer than folds * 60 s).
Diagnosis diagnose(const ParameterSet& params, const Recording& rec, const DiagnoseOptions& options = {});

// "cellbench.diagnosis/1" (INTERFACES.md).
nlohmann::json diagnosis_to_json(const Diagnosis& d);

// Residuals by condition (step 1 alone).
std::vector<ConditionError> locate_errors(const ParameterSet& params, const Recording& rec, const SimulationTrace& trace);

// The catalogue of effect ids this build can fit.
const std::vector<std::string>& effect_catalogue();

// Copy of rec merged into intervals of at least step_s (mean current, values at the interval end).
Recording merge_intervals(const Recording& rec, double step_s);

// Rows to plot: the span of t is cut into max(1, max_points / (2 * series.size())) equal time buckets and
// each bucket keeps the rows of the minimum and the maximum of every series (NaN skipped), so spikes survive.
// Ascending, without duplicates, at most max_points (>= 2 * series.size()) rows. Series shorter than t are
// read as far as they go.
std::vector<std::size_t> decimate_rows(const std::vector<double>& t, const std::vector<const std::vector<double>*>& series,
                                       std::size_t max_points);

// The traces of a diagnosis for plotting (the dashboard's Diagnosis page, `diagnose --report`): measured
// against simulated, at the rows decimate_rows keeps of measured voltage, the voltage errors and measured
// surface temperature. Errors are simulated minus measured.
struct DiagnosisTraces {
    std::size_t rows = 0;                  // rows of the recording
    std::vector<double> time_s;            // test time of each kept row
    std::vector<double> voltage_measured_v, voltage_baseline_v, voltage_improved_v;   // improved: empty when
    std::vector<double> voltage_error_baseline_v, voltage_error_improved_v;           // nothing was accepted
    std::vector<double> surface_measured_c, surface_baseline_c, surface_improved_c;   // empty: no surface column
};
DiagnosisTraces diagnosis_traces(const Diagnosis& d, const Recording& rec, std::size_t max_points = 2000);

// {"rows": N, "points": n, "time_s": [...],
//  "voltage_v": {"measured": [...], "baseline": [...], "improved": [...]},
//  "voltage_error_v": {"baseline": [...], "improved": [...]},
//  "surface_c": {"measured": [...], "baseline": [...], "improved": [...]}}
// "improved" members only when the diagnosis accepted an effect; "surface_c" only when the recording measures
// surface temperature; NaN (no value) is null.
nlohmann::json traces_to_json(const DiagnosisTraces& t);

}  // namespace cellbench::estimator
