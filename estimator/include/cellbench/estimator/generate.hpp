#pragma once
// Recordings with a known truth, for proving `diagnose`: a cell (the thesis parameter set, varied by seed)
// with at most one hidden effect from the catalogue, put through a characterization program (thesis Table
// 2.12 HPPC with its pilot discharge) and a randomized drive profile in the spirit of Table 5.1. The cell is
// the same CellModel the simulated bench plant wraps; the programs run as the tester runs them (CC, CCCV with
// the CV phase held at the limit, voltage/time/current cut-offs), with sensor noise.
//
// Effects that exist only in use are present only in the validation recording: series_resistance_offset
// (harness), capacity_error (the cell aged), heat_flux_sensor_gain (another sensor), ambient_drift (the
// chamber). The others belong to the cell and are present in both, at magnitudes where the 1C HPPC cannot
// show them (it runs at 1C near ambient temperature, discharge-direction OCV, 30 s pulses).
#include <cstdint>
#include <string>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"

namespace cellbench::estimator {

struct GeneratorOptions {
    std::uint32_t seed = 1;
    std::string hidden_effect;   // "" = control cell (no hidden effect)
    double magnitude = 1.0;      // scales the effect's strength around its nominal value
    bool vary_base = true;       // perturb the base parameters by seed
    // Sensor noise (white, per sample): cycler voltage and current; Type-T (a DEWE-43A resolves ~1 mK; the
    // thesis data are smoother still); heat flux density.
    double voltage_noise_v = 0.0005, current_noise_a = 0.005, temperature_noise_c = 0.005;
    double heat_flux_noise_w_per_m2 = 0.5;
};

struct GeneratedCase {
    ParameterSet truth_characterization;  // the cell as it is during characterization
    ParameterSet truth_validation;        // ... and during the drive profile (use-only effects added)
    Recording characterization;           // HPPC with pilot discharge (Table 2.12)
    Recording validation;                 // randomized drive profile (Table 5.1 spirit)
    nlohmann::json truth;                 // what was hidden, for the report (never given to diagnose)
};

// base: the nominal cell (e.g. config/cells/p45b-thesis.json). Deterministic for a seed.
GeneratedCase generate_case(const ParameterSet& base, const GeneratorOptions& options);

}  // namespace cellbench::estimator
