#pragma once
// Characterization: turn recordings of one cell into a parameter set, using each recording for what it
// contains (pilot discharge -> capacity; long rests -> OCV and thermal capacity; HPPC pulse sets -> R0, R1,
// C1, R2, C2 per direction; CC discharge -> entropic heat coefficient; cooling and heat flux -> thermal
// resistance). The same pieces serve the daemon's online fitting: it feeds fit_pulse_set() one pulse set at
// a time and calls assemble_parameter_set() at the end of the run.
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/estimator/global_fit.hpp"
#include "cellbench/estimator/progress.hpp"
#include "cellbench/estimator/pulse_fit.hpp"
#include "cellbench/estimator/segment.hpp"

namespace cellbench::estimator {

struct CharacterizationOptions {
    std::string cell = "Molicel INR-21700-P45B";
    double area_m2 = 5.311e-3;  // total surface of a 21700 cell: pi*d*L + 2*pi*(d/2)^2
    // Used only where no recording measures them.
    double fallback_capacity_ah = 0.0;  // `fit --capacity-ah`, or the cell config's capacity
    std::string fallback_capacity_source = "given capacity";
    double fallback_c_th_j_per_k = 0.0;
    double fallback_r_th_k_per_w = 0.0;
    // The global identification (global_fit.hpp) gives the tables; false: the per-pulse-set assembly as before
    // (kept as the reported comparison either way).
    bool global_fit = true;
    GlobalFitOptions global;
    // Progress of characterize() (segmenting, pulse set k of n, thermal parameters); empty = none.
    Progress progress;
};

struct OcvPoint {
    double soc = kNaN;
    double ocv_v = kNaN;
    double rest_s = 0.0;      // length of the rest it ends
    std::string source;
};

struct CapacityMeasurement {
    double capacity_ah = kNaN;
    std::string method;  // "pilot discharge", "HPPC throughput to cut-off", "fallback"
    std::string source;
    // 1 sigma: how far the characterization's recordings disagree on the charge scale (the global fit's charge
    // scale of each slow discharge it was free to rescale, spanning at least half the SOC range); NaN where no
    // such recording was handed in.
    double capacity_ah_sd = kNaN;
    // Of capacity_ah: the charge a slow discharge (C/10 or slower, a rest after it) left between its cut-off under
    // load and OCV = cut-off, from the relaxation after it and the voltage's slope at its end; 0 where none.
    double below_cutoff_ah = 0.0;
};

// What the thermal fits gave, with the choice made and why (filled by fit_thermal_parameters).
struct ThermalCharacterization {
    double c_th_j_per_k = kNaN, c_th_sigma_j_per_k = kNaN, c_th_r_squared = kNaN;
    double r_th_k_per_w = kNaN, r_th_sigma_k_per_w = kNaN;
    std::string r_th_method;
    // Plausibility ("implausible", "uncertain", "at_bound"), as the global fit's table values carry them.
    std::vector<std::string> c_th_flags, r_th_flags;
    nlohmann::json details = nlohmann::json::object();
    std::vector<double> ehc_soc, ehc_v_per_k;
    std::vector<std::string> notes;
};

struct Characterization {
    ParameterSet params;
    CapacityMeasurement capacity;
    std::vector<OcvPoint> ocv_points;
    std::vector<PulseSetFit> pulse_fits;
    std::optional<ParameterSet> per_pulse_set_params;  // the per-pulse-set assembly (comparison)
    std::optional<GlobalFitResult> global;
    ThermalCharacterization thermal;
    std::vector<std::string> warnings;

    [[nodiscard]] nlohmann::json summary_json() const;
};

Characterization characterize(const std::vector<Recording>& recordings, const CharacterizationOptions& options = {});

// Builds the SOC-indexed tables from per-pulse-set fits and OCV points (daemon end-of-run and CLI alike).
// Breakpoints are the OCV points' SOCs; RC values come from the pulse set nearest in SOC whose fit of that
// direction is usable (a charge pulse that turned CV at 100 % SOC is not).
ParameterSet assemble_parameter_set(const std::vector<PulseSetFit>& fits, const std::vector<OcvPoint>& ocv_points,
                                    double capacity_ah, const ThermalCharacterization& thermal,
                                    const CharacterizationOptions& options);

}  // namespace cellbench::estimator
