#pragma once
// The cell's parameter set ("cellbench.params/1", INTERFACES.md): the model's numbers, kept apart from the
// model equations (model.hpp) and from the step program that produced the data.
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/estimator/electrical.hpp"

namespace cellbench::estimator {

// R/C tables of one current direction, one value per SOC breakpoint.
struct RcTable {
    std::vector<double> r0_ohm, r1_ohm, c1_f, r2_ohm, c2_f;
};

struct ThermalParams {
    double c_th_j_per_k = 0.0;    // lumped thermal capacity
    double r_th_k_per_w = 0.0;    // cell surface to ambient
    double area_m2 = 0.0;         // total cell surface (heat flux density -> heat flow)
    std::vector<double> ehc_soc;  // SOC breakpoints (0..1) of the entropic heat coefficient
    std::vector<double> ehc_v_per_k;  // dU/dT
};

// Physics added by `diagnose` (effect ids of INTERFACES.md), each absent unless fitted. Every effect has few
// parameters, so that it can be identified from one recording without rewarding parameters for nothing.
struct EntropicHeatExt {  // reversible heat I*T*dU/dT with dU/dT = a + b*(SOC - 0.5), added to the table
    double ehc_v_per_k = 0.0;
    double ehc_slope_v_per_k = 0.0;
};
struct ThermalSecondOrderExt {  // core and surface nodes; heat enters the core, the sensors see the surface
    double core_fraction = 0.7;           // C_core / C_th (the rest is the can and the surface)
    double r_core_surface_k_per_w = 1.0;  // conduction core -> surface
};
struct ResistanceTemperatureExt {  // Arrhenius: R(T) = R(T_ref) * exp(Ea/Rgas * (1/T - 1/T_ref)), R0, R1, R2
    double activation_energy_j_per_mol = 0.0;
};
struct ResistanceCurrentExt {  // Butler-Volmer: polarization resistance falls with |I| like asinh(x)/x
    double exchange_current_a = 10.0;   // I0: the larger, the more linear
    double reference_current_a = 4.5;   // current at which the tables were identified (factor 1 there)
};
struct OcvHysteresisExt {  // one-state hysteresis h -> +-M with rate gamma per unit of charge throughput
    double magnitude_v = 0.0;
    double rate_per_capacity = 20.0;    // gamma: h settles after ~1/gamma of the capacity
};
struct ExtraRcExt {  // a slow diffusion pair beyond the two RC pairs, driven by the whole current
    double r_ohm = 0.0;
    double tau_s = 600.0;
};
struct CapacityErrorExt {
    double capacity_scale = 1.0;        // usable capacity / parameter set's capacity
};
struct SeriesResistanceOffsetExt {
    double r_ohm = 0.0;                 // added to R0 of both directions
};
struct HeatFluxSensorGainExt {
    double gain = 1.0;                  // measured heat flux / true heat flux
};
struct AmbientDriftExt {  // T_amb(t) = T_amb + offset + rate * t (t since the recording's start)
    double offset_c = 0.0;
    double rate_c_per_h = 0.0;
};

struct ModelExtensions {
    std::optional<EntropicHeatExt> entropic_heat;
    std::optional<ThermalSecondOrderExt> thermal_second_order;
    std::optional<ResistanceTemperatureExt> resistance_temperature;
    std::optional<ResistanceCurrentExt> resistance_current;
    std::optional<OcvHysteresisExt> ocv_hysteresis;
    std::optional<ExtraRcExt> extra_rc;
    std::optional<CapacityErrorExt> capacity_error;
    std::optional<SeriesResistanceOffsetExt> series_resistance_offset;
    std::optional<HeatFluxSensorGainExt> heat_flux_sensor_gain;
    std::optional<AmbientDriftExt> ambient_drift;
    nlohmann::json other = nlohmann::json::object();  // effects this build does not model: kept verbatim

    [[nodiscard]] bool empty() const;
    // The ids in `other`: effects a parameter set names that this build neither simulates nor fits (a typo, or a
    // newer cellbench's effect). A command that loads the set says so (tools/cli load_params, the daemon's cells).
    [[nodiscard]] std::vector<std::string> unknown_ids() const;
    [[nodiscard]] nlohmann::json to_json() const;
    // Parses the known effect ids (parameters checked for range), keeps unknown ones in `other`.
    static ModelExtensions from_json(const nlohmann::json& j, const std::string& source);
};

struct ParameterSet {
    std::string cell;
    double capacity_ah = 0.0;
    // 1 sigma of capacity_ah where the characterization could judge it (its recordings' disagreement on the
    // charge scale); NaN: not estimated. `diagnose` does not call a capacity correction within 2 sigma a finding.
    double capacity_ah_sd = std::numeric_limits<double>::quiet_NaN();
    double reference_temperature_c = 25.0;
    std::vector<double> soc;    // ascending fractions 0..1
    std::vector<double> ocv_v;  // one per soc
    // 1 sigma of each ocv_v where the characterization judged it (the global fit's uncertainty); empty: not
    // estimated.
    std::vector<double> ocv_v_sd;
    RcTable discharge, charge;
    ThermalParams thermal;
    ModelExtensions extensions;

    // Throws InputError naming the JSON path and what was expected.
    static ParameterSet from_json(const nlohmann::json& j, const std::string& source = "parameters");
    [[nodiscard]] nlohmann::json to_json() const;
    // Throws InputError if tables are inconsistent (sizes, ordering, non-positive R/C/capacity).
    void validate(const std::string& source = "parameters") const;

    // Table look-ups: linear in SOC inside the table, nearest value outside (OCV extrapolates linearly).
    [[nodiscard]] double ocv_at(double soc) const;
    [[nodiscard]] double docv_dsoc_at(double soc) const;
    [[nodiscard]] Rc2Params<double> rc_at(double soc, int direction) const;  // direction +1 charge, -1 dis.
    [[nodiscard]] double ehc_at(double soc) const;
    // SOC whose OCV is ocv_v (inverse of ocv_at on the monotone table; clamped to [0, 1]).
    [[nodiscard]] double soc_from_ocv(double ocv_v) const;
};

// Piecewise-linear interpolation with nearest-value hold outside [x.front(), x.back()].
double interp_hold(const std::vector<double>& x, const std::vector<double>& y, double xq);
// Piecewise-linear interpolation with linear extrapolation from the end segments.
double interp_extrap(const std::vector<double>& x, const std::vector<double>& y, double xq);

inline constexpr const char* kParamsSchema = "cellbench.params/1";

// What a parameter set may hold at all (ParameterSet::validate): orders of magnitude beyond any cell, so that only
// a typo or a unit slip is refused; a value a cell can have but seldom does is flagged by the fit instead.
inline constexpr double kMinCapacityAh = 1e-4, kMaxCapacityAh = 1e5;
inline constexpr double kMinCellTemperatureC = -100.0, kMaxCellTemperatureC = 300.0;  // a recording's own range
inline constexpr double kMaxResistanceOhm = 1e3;
inline constexpr double kMaxThermalResistanceKPerW = 1e4;
inline constexpr double kMaxAreaM2 = 10.0;
inline constexpr double kMaxEntropicVPerK = 0.01;

}  // namespace cellbench::estimator
