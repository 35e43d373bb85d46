#pragma once
// The cell's parameter set ("cellbench.params/1", INTERFACES.md): the model's numbers, kept apart from the
// model equations (model.hpp) and from the step program that produced the data.
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

// Physics added by `diagnose` (effect ids of INTERFACES.md). Each is absent unless fitted.
struct ResistanceTemperatureExt {  // Arrhenius: R(T) = R(T_ref) * exp(Ea/Rgas * (1/T - 1/T_ref))
    double activation_energy_j_per_mol = 0.0;
};
struct ModelExtensions {
    std::optional<ResistanceTemperatureExt> resistance_temperature;
    nlohmann::json other = nlohmann::json::object();  // effects this build does not model: kept verbatim
};

struct ParameterSet {
    std::string cell;
    double capacity_ah = 0.0;
    double reference_temperature_c = 25.0;
    std::vector<double> soc;    // ascending fractions 0..1
    std::vector<double> ocv_v;  // one per soc
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

}  // namespace cellbench::estimator
