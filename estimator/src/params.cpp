#include "cellbench/estimator/params.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "cellbench/core/json_fields.hpp"
#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

namespace {

using nlohmann::json;

using json_fields::fail, json_fields::finite_number, json_fields::member;  // errors read "SOURCE: PATH: what"

double number_member(const json& j, const std::string& key, const std::string& source, const std::string& path) {
    return finite_number(member(j, key, source, path), source, path + "." + key);
}

std::vector<double> number_array(const json& j, const std::string& source, const std::string& path) {
    if (!j.is_array()) fail(source, path, "expected an array of numbers");
    std::vector<double> out;
    out.reserve(j.size());
    for (std::size_t i = 0; i < j.size(); ++i)
        out.push_back(finite_number(j[i], source, path + "[" + std::to_string(i) + "]"));
    return out;
}

std::vector<double> array_member(const json& j, const std::string& key, const std::string& source,
                                 const std::string& path) {
    return number_array(member(j, key, source, path), source, path + "." + key);
}

RcTable rc_table(const json& j, const std::string& source, const std::string& path) {
    RcTable t;
    t.r0_ohm = array_member(j, "r0_ohm", source, path);
    t.r1_ohm = array_member(j, "r1_ohm", source, path);
    t.c1_f = array_member(j, "c1_f", source, path);
    t.r2_ohm = array_member(j, "r2_ohm", source, path);
    t.c2_f = array_member(j, "c2_f", source, path);
    return t;
}

json rc_json(const RcTable& t) {
    return json{{"r0_ohm", t.r0_ohm}, {"r1_ohm", t.r1_ohm}, {"c1_f", t.c1_f}, {"r2_ohm", t.r2_ohm}, {"c2_f", t.c2_f}};
}

std::size_t segment_index(const std::vector<double>& x, double xq) {
    // index i such that x[i] <= xq < x[i+1], clamped to [0, n-2]
    auto it = std::upper_bound(x.begin(), x.end(), xq);
    std::size_t i = it == x.begin() ? 0 : static_cast<std::size_t>(it - x.begin()) - 1;
    return std::min(i, x.size() - 2);
}


}  // namespace

double interp_hold(const std::vector<double>& x, const std::vector<double>& y, double xq) {
    if (x.empty()) return kNaN;
    if (x.size() == 1 || xq <= x.front()) return y.front();
    if (xq >= x.back()) return y.back();
    const std::size_t i = segment_index(x, xq);
    const double w = (xq - x[i]) / (x[i + 1] - x[i]);
    return y[i] + w * (y[i + 1] - y[i]);
}

double interp_extrap(const std::vector<double>& x, const std::vector<double>& y, double xq) {
    if (x.empty()) return kNaN;
    if (x.size() == 1) return y.front();
    const std::size_t i = segment_index(x, xq);
    const double w = (xq - x[i]) / (x[i + 1] - x[i]);
    return y[i] + w * (y[i + 1] - y[i]);
}

bool ModelExtensions::empty() const { return to_json().empty(); }

json ModelExtensions::to_json() const {
    json j = other;
    if (entropic_heat)
        j["entropic_heat"] = {{"ehc_v_per_k", entropic_heat->ehc_v_per_k},
                              {"ehc_slope_v_per_k", entropic_heat->ehc_slope_v_per_k}};
    if (thermal_second_order)
        j["thermal_second_order"] = {{"core_fraction", thermal_second_order->core_fraction},
                                     {"r_core_surface_k_per_w", thermal_second_order->r_core_surface_k_per_w}};
    if (resistance_temperature)
        j["resistance_temperature"] = {{"activation_energy_j_per_mol", resistance_temperature->activation_energy_j_per_mol}};
    if (resistance_current)
        j["resistance_current"] = {{"exchange_current_a", resistance_current->exchange_current_a},
                                   {"reference_current_a", resistance_current->reference_current_a}};
    if (ocv_hysteresis)
        j["ocv_hysteresis"] = {{"magnitude_v", ocv_hysteresis->magnitude_v},
                               {"rate_per_capacity", ocv_hysteresis->rate_per_capacity}};
    if (extra_rc) j["extra_rc"] = {{"r_ohm", extra_rc->r_ohm}, {"tau_s", extra_rc->tau_s}};
    if (capacity_error) j["capacity_error"] = {{"capacity_scale", capacity_error->capacity_scale}};
    if (series_resistance_offset) j["series_resistance_offset"] = {{"r_ohm", series_resistance_offset->r_ohm}};
    if (heat_flux_sensor_gain) j["heat_flux_sensor_gain"] = {{"gain", heat_flux_sensor_gain->gain}};
    if (ambient_drift)
        j["ambient_drift"] = {{"offset_c", ambient_drift->offset_c}, {"rate_c_per_h", ambient_drift->rate_c_per_h}};
    return j;
}

std::vector<std::string> ModelExtensions::unknown_ids() const {
    std::vector<std::string> ids;
    for (const auto& item : other.items()) ids.push_back(item.key());
    return ids;
}

ModelExtensions ModelExtensions::from_json(const json& j, const std::string& source) {
    if (!j.is_object()) fail(source, "$.extensions", "expected an object keyed by effect id");
    ModelExtensions e;
    for (const auto& item : j.items()) {
        // Not a structured binding: clang 14 (the fuzz build) cannot capture one in the lambdas below.
        const std::string& key = item.key();
        const json& v = item.value();
        const std::string path = "$.extensions." + key;
        auto num = [&](const char* name) { return number_member(v, name, source, path); };
        auto positive = [&](const char* name) {
            const double x = num(name);
            if (!(x > 0)) fail(source, path + "." + name, "expected a positive number");
            return x;
        };
        // The same for values no cell or bench has by orders of magnitude (ParameterSet::validate's rule).
        auto at_most = [&](const char* name, double x, double limit, const char* expected) {
            if (!(std::abs(x) <= limit)) fail(source, path + "." + name, expected);
            return x;
        };
        if (key == "entropic_heat") {
            e.entropic_heat = EntropicHeatExt{
                at_most("ehc_v_per_k", num("ehc_v_per_k"), kMaxEntropicVPerK,
                        "expected an entropic coefficient within +-10 mV/K (a cell's is within +-1 mV/K)"),
                at_most("ehc_slope_v_per_k", num("ehc_slope_v_per_k"), 10 * kMaxEntropicVPerK,
                        "expected a slope within +-100 mV/K per unit SOC")};
        } else if (key == "thermal_second_order") {
            const double f = num("core_fraction");
            if (!(f > 0 && f < 1)) fail(source, path + ".core_fraction", "expected a fraction strictly between 0 and 1");
            e.thermal_second_order = ThermalSecondOrderExt{
                f, at_most("r_core_surface_k_per_w", positive("r_core_surface_k_per_w"), kMaxThermalResistanceKPerW,
                           "expected a thermal resistance below 10 000 K/W")};
        } else if (key == "resistance_temperature") {
            e.resistance_temperature = ResistanceTemperatureExt{
                at_most("activation_energy_j_per_mol", num("activation_energy_j_per_mol"), 5e5,
                        "expected an activation energy within +-500 kJ/mol (a cell's is 10-60 kJ/mol)")};
        } else if (key == "resistance_current") {
            e.resistance_current = ResistanceCurrentExt{
                at_most("exchange_current_a", positive("exchange_current_a"), 1e6, "expected a current below 1 MA"),
                at_most("reference_current_a", positive("reference_current_a"), 1e6, "expected a current below 1 MA")};
        } else if (key == "ocv_hysteresis") {
            e.ocv_hysteresis = OcvHysteresisExt{
                at_most("magnitude_v", num("magnitude_v"), 1.0, "expected a hysteresis within +-1 V"),
                at_most("rate_per_capacity", positive("rate_per_capacity"), 1e6,
                        "expected a rate below 1e6 per capacity")};
        } else if (key == "extra_rc") {
            const double r = num("r_ohm");
            if (r < 0) fail(source, path + ".r_ohm", "expected a non-negative resistance");
            e.extra_rc = ExtraRcExt{at_most("r_ohm", r, kMaxResistanceOhm, "expected a resistance below 1 kOhm"),
                                    positive("tau_s")};
        } else if (key == "capacity_error") {
            e.capacity_error = CapacityErrorExt{
                at_most("capacity_scale", positive("capacity_scale"), 100.0, "expected a scale below 100")};
        } else if (key == "series_resistance_offset") {
            e.series_resistance_offset = SeriesResistanceOffsetExt{
                at_most("r_ohm", num("r_ohm"), kMaxResistanceOhm, "expected a resistance within +-1 kOhm")};
        } else if (key == "heat_flux_sensor_gain") {
            e.heat_flux_sensor_gain =
                HeatFluxSensorGainExt{at_most("gain", positive("gain"), 100.0, "expected a gain below 100")};
        } else if (key == "ambient_drift") {
            e.ambient_drift = AmbientDriftExt{
                at_most("offset_c", num("offset_c"), 100.0, "expected an offset within +-100 K"),
                at_most("rate_c_per_h", num("rate_c_per_h"), 1000.0, "expected a drift within +-1000 K/h")};
        } else {
            e.other[key] = v;
        }
    }
    return e;
}

ParameterSet ParameterSet::from_json(const json& j, const std::string& source) {
    if (!j.is_object()) fail(source, "$", "expected a JSON object");
    const auto& schema = member(j, "schema", source, "$");
    if (!schema.is_string() || schema.get<std::string>() != kParamsSchema)
        fail(source, "$.schema", std::string("expected \"") + kParamsSchema + "\"");
    ParameterSet p;
    if (auto it = j.find("cell"); it != j.end() && it->is_string()) p.cell = it->get<std::string>();
    p.capacity_ah = number_member(j, "capacity_ah", source, "$");
    if (auto it = j.find("capacity_ah_sd"); it != j.end() && !it->is_null())
        p.capacity_ah_sd = number_member(j, "capacity_ah_sd", source, "$");
    if (j.contains("reference_temperature_c"))
        p.reference_temperature_c = number_member(j, "reference_temperature_c", source, "$");
    p.soc = array_member(j, "soc", source, "$");
    p.ocv_v = array_member(j, "ocv_v", source, "$");
    if (auto it = j.find("ocv_v_sd"); it != j.end() && !it->is_null()) p.ocv_v_sd = array_member(j, "ocv_v_sd", source, "$");
    p.discharge = rc_table(member(j, "discharge", source, "$"), source, "$.discharge");
    p.charge = rc_table(member(j, "charge", source, "$"), source, "$.charge");
    const auto& th = member(j, "thermal", source, "$");
    p.thermal.c_th_j_per_k = number_member(th, "c_th_j_per_k", source, "$.thermal");
    p.thermal.r_th_k_per_w = number_member(th, "r_th_k_per_w", source, "$.thermal");
    p.thermal.area_m2 = number_member(th, "area_m2", source, "$.thermal");
    if (th.contains("ehc_soc")) p.thermal.ehc_soc = array_member(th, "ehc_soc", source, "$.thermal");
    if (th.contains("ehc_v_per_k")) p.thermal.ehc_v_per_k = array_member(th, "ehc_v_per_k", source, "$.thermal");
    if (auto it = j.find("extensions"); it != j.end()) p.extensions = ModelExtensions::from_json(*it, source);
    p.validate(source);
    return p;
}

json ParameterSet::to_json() const {
    const json ext = extensions.to_json();
    json j{{"schema", kParamsSchema},
           {"cell", cell},
           {"capacity_ah", capacity_ah},
           {"reference_temperature_c", reference_temperature_c},
           {"soc", soc},
           {"ocv_v", ocv_v},
           {"discharge", rc_json(discharge)},
           {"charge", rc_json(charge)},
           {"thermal",
            {{"c_th_j_per_k", thermal.c_th_j_per_k},
             {"r_th_k_per_w", thermal.r_th_k_per_w},
             {"area_m2", thermal.area_m2},
             {"ehc_soc", thermal.ehc_soc},
             {"ehc_v_per_k", thermal.ehc_v_per_k}}},
           {"extensions", ext}};
    if (std::isfinite(capacity_ah_sd)) j["capacity_ah_sd"] = capacity_ah_sd;
    if (!ocv_v_sd.empty()) j["ocv_v_sd"] = ocv_v_sd;
    return j;
}

void ParameterSet::validate(const std::string& source) const {
    if (!(capacity_ah > 0)) fail(source, "$.capacity_ah", "expected a positive capacity in Ah");
    if (!std::isnan(capacity_ah_sd) && !(capacity_ah_sd >= 0 && std::isfinite(capacity_ah_sd)))
        fail(source, "$.capacity_ah_sd", "expected a non-negative uncertainty in Ah (or no member)");
    if (soc.size() < 2) fail(source, "$.soc", "expected at least two SOC breakpoints");
    for (std::size_t i = 0; i < soc.size(); ++i) {
        if (soc[i] < 0 || soc[i] > 1) fail(source, "$.soc[" + std::to_string(i) + "]", "expected a fraction 0..1");
        if (i > 0 && !(soc[i] > soc[i - 1]))
            fail(source, "$.soc[" + std::to_string(i) + "]", "expected strictly ascending SOC");
    }
    auto check_size = [&](const std::vector<double>& v, const std::string& path) {
        if (v.size() != soc.size())
            fail(source, path,
                 "expected " + std::to_string(soc.size()) + " values (one per soc entry), got " + std::to_string(v.size()));
    };
    auto check_positive = [&](const std::vector<double>& v, const std::string& path) {
        check_size(v, path);
        for (std::size_t i = 0; i < v.size(); ++i)
            if (!(v[i] > 0)) fail(source, path + "[" + std::to_string(i) + "]", "expected a positive value");
    };
    auto check_resistance = [&](const std::vector<double>& v, const std::string& path) {
        check_positive(v, path);
        for (std::size_t i = 0; i < v.size(); ++i)
            if (!(v[i] <= kMaxResistanceOhm))
                fail(source, path + "[" + std::to_string(i) + "]",
                     "expected a resistance below 1 kOhm (a cell's are milliohms)");
    };
    // Values no cell has by orders of magnitude (a typo, a unit slip) are refused, naming the member: the model
    // would follow them into an overflow or an answer that looks like a result. What a cell can have but seldom
    // does is for the fit's plausibility flags.
    if (!(capacity_ah >= kMinCapacityAh && capacity_ah <= kMaxCapacityAh))
        fail(source, "$.capacity_ah", "expected a capacity between 0.1 mAh and 100 kAh");
    if (!(reference_temperature_c >= kMinCellTemperatureC && reference_temperature_c <= kMaxCellTemperatureC))
        fail(source, "$.reference_temperature_c", "expected a cell temperature between -100 and 300 degC");
    check_size(ocv_v, "$.ocv_v");
    for (std::size_t i = 0; i < ocv_v.size(); ++i)
        if (!(ocv_v[i] > 0 && ocv_v[i] < 10))
            fail(source, "$.ocv_v[" + std::to_string(i) + "]", "expected an open-circuit voltage between 0 and 10 V");
    if (!ocv_v_sd.empty()) {
        check_size(ocv_v_sd, "$.ocv_v_sd");
        for (std::size_t i = 0; i < ocv_v_sd.size(); ++i)
            if (!(ocv_v_sd[i] >= 0 && std::isfinite(ocv_v_sd[i])))
                fail(source, "$.ocv_v_sd[" + std::to_string(i) + "]", "expected a non-negative uncertainty in V");
    }
    for (const auto& [name, t] : {std::pair<std::string, const RcTable*>{"discharge", &discharge}, {"charge", &charge}}) {
        check_resistance(t->r0_ohm, "$." + name + ".r0_ohm");
        check_resistance(t->r1_ohm, "$." + name + ".r1_ohm");
        check_positive(t->c1_f, "$." + name + ".c1_f");
        check_resistance(t->r2_ohm, "$." + name + ".r2_ohm");
        check_positive(t->c2_f, "$." + name + ".c2_f");
    }
    if (!(thermal.c_th_j_per_k > 0)) fail(source, "$.thermal.c_th_j_per_k", "expected a positive thermal capacity");
    if (!(thermal.r_th_k_per_w > 0)) fail(source, "$.thermal.r_th_k_per_w", "expected a positive thermal resistance");
    if (!(thermal.r_th_k_per_w <= kMaxThermalResistanceKPerW))
        fail(source, "$.thermal.r_th_k_per_w", "expected a thermal resistance below 10 000 K/W (a cell's is 1-20 K/W)");
    if (!(thermal.area_m2 > 0)) fail(source, "$.thermal.area_m2", "expected a positive area");
    if (!(thermal.area_m2 <= kMaxAreaM2)) fail(source, "$.thermal.area_m2", "expected a surface area below 10 m^2");
    for (std::size_t i = 0; i < thermal.ehc_soc.size(); ++i)
        if (!(thermal.ehc_soc[i] >= 0 && thermal.ehc_soc[i] <= 1))
            fail(source, "$.thermal.ehc_soc[" + std::to_string(i) + "]", "expected a fraction 0..1");
    for (std::size_t i = 0; i < thermal.ehc_v_per_k.size(); ++i)
        if (!(std::abs(thermal.ehc_v_per_k[i]) <= kMaxEntropicVPerK))
            fail(source, "$.thermal.ehc_v_per_k[" + std::to_string(i) + "]",
                 "expected an entropic coefficient within +-10 mV/K (a cell's is within +-1 mV/K)");
    if (thermal.ehc_soc.size() != thermal.ehc_v_per_k.size())
        fail(source, "$.thermal.ehc_v_per_k", "expected one value per ehc_soc entry");
    for (std::size_t i = 1; i < thermal.ehc_soc.size(); ++i)
        if (!(thermal.ehc_soc[i] > thermal.ehc_soc[i - 1]))
            fail(source, "$.thermal.ehc_soc[" + std::to_string(i) + "]", "expected strictly ascending SOC");
}

double ParameterSet::ocv_at(double s) const { return interp_extrap(soc, ocv_v, s); }

double ParameterSet::docv_dsoc_at(double s) const {
    const std::size_t i = segment_index(soc, s);
    return (ocv_v[i + 1] - ocv_v[i]) / (soc[i + 1] - soc[i]);
}

Rc2Params<double> ParameterSet::rc_at(double s, int direction) const {
    const RcTable& t = direction > 0 ? charge : discharge;
    const double r1 = interp_hold(soc, t.r1_ohm, s), r2 = interp_hold(soc, t.r2_ohm, s);
    return {interp_hold(soc, t.r0_ohm, s), r1, r1 * interp_hold(soc, t.c1_f, s), r2, r2 * interp_hold(soc, t.c2_f, s)};
}

double ParameterSet::ehc_at(double s) const {
    if (thermal.ehc_soc.empty()) return 0.0;
    return interp_hold(thermal.ehc_soc, thermal.ehc_v_per_k, s);
}

double ParameterSet::soc_from_ocv(double v) const {
    // The OCV table is monotone for a Li-ion cell; invert piecewise (with the same linear extrapolation).
    const std::size_t n = soc.size();
    if (v <= ocv_v.front()) {
        const double slope = (ocv_v[1] - ocv_v[0]) / (soc[1] - soc[0]);
        return std::clamp(soc[0] + (v - ocv_v[0]) / slope, 0.0, 1.0);
    }
    if (v >= ocv_v.back()) {
        const double slope = (ocv_v[n - 1] - ocv_v[n - 2]) / (soc[n - 1] - soc[n - 2]);
        return std::clamp(soc[n - 1] + (v - ocv_v[n - 1]) / slope, 0.0, 1.0);
    }
    for (std::size_t i = 0; i + 1 < n; ++i) {
        if (v >= ocv_v[i] && v <= ocv_v[i + 1]) {
            const double span = ocv_v[i + 1] - ocv_v[i];
            const double w = span > 0 ? (v - ocv_v[i]) / span : 0.0;
            return std::clamp(soc[i] + w * (soc[i + 1] - soc[i]), 0.0, 1.0);
        }
    }
    return kNaN;
}

}  // namespace cellbench::estimator
