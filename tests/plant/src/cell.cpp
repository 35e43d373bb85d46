// The cell's closed-form parameter functions, their randomization by seed, and the truth tables.
#include <algorithm>
#include <cmath>
#include <numbers>
#include <random>
#include <stdexcept>

#include "cellbench/plant/plant.hpp"
#include "rng.hpp"

namespace cellbench::plant {

namespace {

double raw_ocv(Chemistry chem, const std::array<double, 8>& c, double s) {
    switch (chem) {
        case Chemistry::nmc:  // smooth rise, knee at low SOC, a mild step (phase transition) mid-range
            return c[0] + c[1] * s - c[2] * std::exp(-s / c[3]) + c[4] * std::tanh((s - c[5]) / c[6]) + c[7] * s * s;
        case Chemistry::nca:  // steeper at low SOC, concave at the top
            return c[0] + c[1] * s - c[2] * std::exp(-s / c[3]) + c[4] * std::tanh((s - c[5]) / c[6]) -
                   c[7] * s * s;
        case Chemistry::lfp:  // flat plateau with two small steps, sharp ends
            return c[0] + c[1] * s - c[2] * std::exp(-s / c[3]) + c[4] * std::tanh((s - c[5]) / c[6]) +
                   c[4] * 0.8 * std::tanh((s - 0.72) / c[6]) + c[7] * std::exp((s - 1.0) / 0.035);
        case Chemistry::lmo:  // high plateau, two-stage shape near the middle
            return c[0] + c[1] * s - c[2] * std::exp(-s / c[3]) + c[4] * std::tanh((s - c[5]) / c[6]) +
                   c[7] * std::exp((s - 1.0) / 0.06);
    }
    return 0.0;
}

double low_soc_rise(double s, double amp, double width) { return 1.0 + amp * std::exp(-std::clamp(s, 0.0, 1.0) / width); }

}  // namespace

std::string_view effect_id(Effect e) {
    switch (e) {
        case Effect::none: return "none";
        case Effect::resistance_temperature: return "resistance_temperature";
        case Effect::resistance_current: return "resistance_current";
        case Effect::thermal_second_order: return "thermal_second_order";
        case Effect::ocv_hysteresis: return "ocv_hysteresis";
        case Effect::extra_rc: return "extra_rc";
        case Effect::series_resistance_offset: return "series_resistance_offset";
        case Effect::heat_flux_sensor_gain: return "heat_flux_sensor_gain";
        case Effect::capacity_error: return "capacity_error";
        case Effect::ambient_drift: return "ambient_drift";
    }
    return "none";
}

const std::vector<Effect>& all_effects() {
    static const std::vector<Effect> v{Effect::resistance_temperature, Effect::resistance_current,
                                       Effect::thermal_second_order,   Effect::ocv_hysteresis,
                                       Effect::extra_rc,               Effect::series_resistance_offset,
                                       Effect::heat_flux_sensor_gain,  Effect::capacity_error,
                                       Effect::ambient_drift};
    return v;
}

std::optional<Effect> parse_effect(std::string_view id) {
    if (id == "none") return Effect::none;
    for (Effect e : all_effects())
        if (effect_id(e) == id) return e;
    return std::nullopt;
}

bool is_bench_effect(Effect e) {
    return e == Effect::series_resistance_offset || e == Effect::heat_flux_sensor_gain ||
           e == Effect::capacity_error || e == Effect::ambient_drift;
}

std::string_view chemistry_name(Chemistry c) {
    switch (c) {
        case Chemistry::nmc: return "nmc";
        case Chemistry::nca: return "nca";
        case Chemistry::lfp: return "lfp";
        case Chemistry::lmo: return "lmo";
    }
    return "nmc";
}

std::string_view layout_name(Layout l) {
    switch (l) {
        case Layout::thesis: return "thesis";
        case Layout::usabc: return "usabc";
        case Layout::multi: return "multi";
        case Layout::random: return "random";
        case Layout::gitt: return "gitt";
    }
    return "thesis";
}

std::optional<Layout> parse_layout(std::string_view name) {
    for (Layout l : {Layout::thesis, Layout::usabc, Layout::multi, Layout::random, Layout::gitt})
        if (layout_name(l) == name) return l;
    return std::nullopt;
}

// ---------------------------------------------------------------------------------------------------------------
double CellSpec::ocv_ref_v(double s) const {
    auto inside = [&](double x) { return raw_ocv(chemistry, ocv_coef, x) + ocv_lin_a + ocv_lin_b * x; };
    constexpr double h = 1e-6;
    if (s < 0.0) return inside(0.0) + s * (inside(h) - inside(0.0)) / h;  // linear beyond the ends
    if (s > 1.0) return inside(1.0) + (s - 1.0) * (inside(1.0) - inside(1.0 - h)) / h;
    return inside(s);
}

double CellSpec::entropic_v_per_k(double s) const {
    const double x = std::clamp(s, 0.0, 1.0);
    const double raw = 1e-4 * (entropic_coef[0] + entropic_coef[1] * std::sin(2.0 * std::numbers::pi * 0.8 * x + entropic_coef[2]) +
                               entropic_coef[3] * (x - 0.5));
    return 3e-4 * std::tanh(raw / 3e-4);  // smooth, within +-0.3 mV/K
}

namespace {
double charge_scale(const std::array<double, 2>& c, double s, Direction d) {
    return d == Direction::charge ? 1.0 + c[0] + c[1] * (std::clamp(s, 0.0, 1.0) - 0.5) : 1.0;
}
}  // namespace

double CellSpec::r0_ohm(double s, Direction d) const {
    const double x = std::clamp(s, 0.0, 1.0);
    return r0_ref_ohm * (low_soc_rise(x, r0_low_amp, r0_low_width) + r0_bowl * (x - 0.6) * (x - 0.6)) *
           charge_scale(charge_r_offset, x, d);
}
double CellSpec::r1_ohm(double s, Direction d) const {
    const double x = std::clamp(s, 0.0, 1.0);
    return r1_ref_ohm * (low_soc_rise(x, r1_low_amp, r1_low_width) + r1_slope * (x - 0.5)) * charge_scale(charge_r_offset, x, d);
}
double CellSpec::r2_ohm(double s, Direction d) const {
    const double x = std::clamp(s, 0.0, 1.0);
    return r2_ref_ohm * (low_soc_rise(x, r2_low_amp, r2_low_width) + r2_slope * (x - 0.5)) * charge_scale(charge_r_offset, x, d);
}
double CellSpec::tau1_s(double s, Direction d) const {
    const double x = std::clamp(s, 0.0, 1.0);
    return tau1_base_s * std::exp(0.2 * std::sin(std::numbers::pi * 1.3 * x + tau1_phase)) * charge_scale(charge_tau_offset, x, d);
}
double CellSpec::tau2_s(double s, Direction d) const {
    const double x = std::clamp(s, 0.0, 1.0);
    return tau2_base_s * std::exp(0.2 * std::sin(std::numbers::pi * 0.9 * x + tau2_phase)) * charge_scale(charge_tau_offset, x, d);
}

double CellSpec::resistance_factor(double t_c) const {
    const double dt = t_c - reference_temperature_c;
    switch (temperature_dependence.form) {
        case TemperatureDependence::Form::none: return 1.0;
        case TemperatureDependence::Form::exponential: return std::exp(-temperature_dependence.coefficient_per_k * dt);
        case TemperatureDependence::Form::linear: return std::max(0.2, 1.0 - temperature_dependence.coefficient_per_k * dt);
    }
    return 1.0;
}

// ---------------------------------------------------------------------------------------------------------------
CellSpec make_cell(const PlantOptions& options) {
    CellSpec c;
    c.seed = options.seed;
    Rng rng(options.seed, 1);

    c.chemistry = static_cast<Chemistry>(rng.index(4));
    c.capacity_ah = rng.uniform(2.0, 5.0);
    c.nominal_capacity_ah = std::round(c.capacity_ah * rng.uniform(0.97, 1.03) * 20.0) / 20.0;  // rated, 0.05 Ah
    c.format = c.capacity_ah < 3.6 ? "18650" : "21700";
    const double d = c.format == "18650" ? 0.018 : 0.021, len = c.format == "18650" ? 0.065 : 0.070;
    c.area_m2 = std::numbers::pi * d * len + 2.0 * std::numbers::pi * (d / 2) * (d / 2);
    c.reference_temperature_c = std::round(rng.uniform(20.0, 35.0));

    auto& k = c.ocv_coef;
    switch (c.chemistry) {
        case Chemistry::nmc:
            k = {rng.uniform(3.42, 3.48), rng.uniform(0.55, 0.65), rng.uniform(0.3, 0.4), rng.uniform(0.05, 0.08),
                 rng.uniform(0.03, 0.05), rng.uniform(0.55, 0.65), rng.uniform(0.06, 0.1), rng.uniform(0.05, 0.1)};
            c.v_min_v = rng.uniform(2.85, 3.0);
            c.v_max_v = rng.uniform(4.1, 4.2);
            break;
        case Chemistry::nca:
            k = {rng.uniform(3.3, 3.4), rng.uniform(1.0, 1.1), rng.uniform(0.4, 0.5), rng.uniform(0.04, 0.06),
                 rng.uniform(0.02, 0.04), rng.uniform(0.25, 0.35), rng.uniform(0.04, 0.07), rng.uniform(0.15, 0.25)};
            c.v_min_v = rng.uniform(2.7, 2.9);
            c.v_max_v = rng.uniform(4.15, 4.2);
            break;
        case Chemistry::lfp:
            k = {rng.uniform(3.25, 3.27), rng.uniform(0.04, 0.07), rng.uniform(0.55, 0.7), rng.uniform(0.025, 0.04),
                 rng.uniform(0.015, 0.025), rng.uniform(0.3, 0.4), rng.uniform(0.025, 0.04), rng.uniform(0.2, 0.3)};
            c.v_min_v = rng.uniform(2.5, 2.6);
            c.v_max_v = rng.uniform(3.6, 3.65);
            break;
        case Chemistry::lmo:
            k = {rng.uniform(3.8, 3.86), rng.uniform(0.22, 0.3), rng.uniform(0.6, 0.7), rng.uniform(0.04, 0.06),
                 rng.uniform(0.04, 0.06), rng.uniform(0.45, 0.55), rng.uniform(0.04, 0.06), rng.uniform(0.06, 0.1)};
            c.v_min_v = rng.uniform(3.0, 3.1);
            c.v_max_v = rng.uniform(4.15, 4.25);
            break;
    }
    const double r_lo = raw_ocv(c.chemistry, k, 0.0), r_hi = raw_ocv(c.chemistry, k, 1.0);
    c.ocv_lin_a = c.v_min_v - r_lo;
    c.ocv_lin_b = (c.v_max_v - r_hi) - c.ocv_lin_a;
    for (int i = 0; i < 1000; ++i) {  // the corrected curve must rise everywhere
        const double s = i / 1000.0;
        if (c.ocv_ref_v(s + 0.001) <= c.ocv_ref_v(s))
            throw std::logic_error("plant: OCV curve not monotonic for seed " + std::to_string(options.seed));
    }
    c.entropic_coef = {rng.uniform(-1.0, 1.0), rng.uniform(0.5, 1.5), rng.uniform(0.0, 2.0 * std::numbers::pi),
                       rng.uniform(-2.0, 2.0)};

    c.r0_ref_ohm = std::clamp(rng.uniform(0.03, 0.09) / c.capacity_ah, 0.008, 0.06);
    c.r0_low_amp = rng.uniform(0.2, 0.8);
    c.r0_low_width = rng.uniform(0.05, 0.15);
    c.r0_bowl = rng.uniform(0.0, 0.5);
    c.r1_ref_ohm = c.r0_ref_ohm * rng.uniform(0.25, 0.8);
    c.r1_low_amp = rng.uniform(0.5, 2.0);
    c.r1_low_width = rng.uniform(0.08, 0.2);
    c.r1_slope = rng.uniform(-0.2, 0.2);
    c.r2_ref_ohm = c.r0_ref_ohm * rng.uniform(0.3, 1.0);
    c.r2_low_amp = rng.uniform(0.5, 2.0);
    c.r2_low_width = rng.uniform(0.08, 0.2);
    c.r2_slope = rng.uniform(-0.2, 0.2);
    c.tau1_base_s = rng.uniform(1.35, 7.5);  // x [0.82, 1.22] by SOC, x [0.95, 1.075] charge: 1-10 s
    c.tau1_phase = rng.uniform(0.0, 2.0 * std::numbers::pi);
    c.tau2_base_s = rng.uniform(std::max(27.0, 8.0 * c.tau1_base_s), 225.0);  // 20-300 s, tau2/tau1 >= 5.3
    c.tau2_phase = rng.uniform(0.0, 2.0 * std::numbers::pi);
    c.charge_r_offset = {rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)};
    c.charge_tau_offset = {rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05)};  // keeps tau2/tau1 >= 5
    c.c_th_j_per_k = rng.uniform(40.0, 120.0);
    c.r_th_k_per_w = rng.uniform(3.0, 15.0);
    double current_noise_scale = 1.0;
    if (options.capacity_ah) {
        if (!(*options.capacity_ah > 0.0)) throw std::invalid_argument("plant: capacity must be positive");
        const double f = *options.capacity_ah / c.capacity_ah, f_area = std::cbrt(f * f);
        c.capacity_ah = *options.capacity_ah;
        c.nominal_capacity_ah = std::round(c.nominal_capacity_ah * f * 20.0) / 20.0;
        if (c.capacity_ah > 10.0) c.format = "pouch";
        c.area_m2 *= f_area;
        c.r0_ref_ohm /= f;
        c.r1_ref_ohm /= f;
        c.r2_ref_ohm /= f;
        c.c_th_j_per_k *= f;
        c.r_th_k_per_w /= f_area;
        current_noise_scale = f;
    }

    // Measurement.
    Measurement& m = c.measurement;
    static constexpr double kSampling[] = {0.1, 0.2, 0.5, 1.0};
    const double seed_sample = kSampling[rng.index(4)];
    m.sample_s = options.sample_s.value_or(seed_sample);
    if (!(m.sample_s > 0.0)) throw std::invalid_argument("plant: sample interval must be positive");
    m.coarse_sample_s = std::max(1.0, m.sample_s);
    m.voltage_noise_v = rng.uniform(1e-4, 5e-4);
    m.current_noise_a = rng.uniform(1e-3, 5e-3) * current_noise_scale;

    // The drive profile's heating, roughly (RMS current about 1.6C): thermal effects are scaled so that they matter
    // on a cell that heats little.
    const double r_total = c.r0_ohm(0.5, Direction::discharge) + c.r1_ohm(0.5, Direction::discharge) +
                           c.r2_ohm(0.5, Direction::discharge);
    const double drive_heat_w = std::pow(1.6 * c.nominal_capacity_ah, 2) * r_total;
    const double drive_rise_k =
        drive_heat_w * c.r_th_k_per_w * (1.0 - std::exp(-3600.0 / (c.r_th_k_per_w * c.c_th_j_per_k)));

    // Base-cell options with known truth.
    Rng opt(options.seed, 2);
    const bool exp_form = opt.index(2) == 0;
    const double k_exp = opt.uniform(0.012, 0.03), k_lin = opt.uniform(0.012, 0.025);
    const double k_floor = 0.12 / std::max(drive_rise_k, 1e-3);  // at least ~12 % over the drive's rise
    const double kappa = opt.uniform(1.5, 3.0);
    auto set_temperature = [&] {
        c.temperature_dependence.form = exp_form ? TemperatureDependence::Form::exponential : TemperatureDependence::Form::linear;
        c.temperature_dependence.coefficient_per_k =
            exp_form ? std::clamp(k_floor, k_exp, 0.06) : std::clamp(k_floor, k_lin, 0.04);
    };
    auto set_current = [&] {
        c.current_dependence.enabled = true;
        c.current_dependence.saturation_current_a = kappa * c.nominal_capacity_ah;
    };
    if (options.temperature_dependence) set_temperature();
    if (options.current_dependence) set_current();

    // Hidden effects: magnitude from (seed, effect).
    for (Effect e : options.effects) {
        if (e == Effect::none) continue;
        if (std::find(c.effects.begin(), c.effects.end(), e) != c.effects.end()) continue;
        c.effects.push_back(e);
        Rng r(options.seed, 100 + static_cast<std::uint64_t>(e));
        switch (e) {
            case Effect::none: break;
            case Effect::resistance_temperature: set_temperature(); break;
            case Effect::resistance_current: set_current(); break;
            case Effect::thermal_second_order:
                c.thermal3 = {true, r.uniform(0.6, 0.85), std::clamp(1.0 / drive_heat_w, r.uniform(0.6, 2.0), 4.0),
                              r.uniform(10.0, 40.0)};
                break;
            case Effect::ocv_hysteresis: {
                const double m_total = r.uniform(0.008, 0.02), fast = r.uniform(0.3, 0.7);
                c.hysteresis = {true, m_total * fast, m_total * (1.0 - fast), r.uniform(0.005, 0.02), r.uniform(0.05, 0.15),
                                r.uniform(0.5, 2.0)};
                break;
            }
            case Effect::extra_rc: {
                const double tau3 = r.uniform(400.0, 1200.0);
                c.extra_rc = {true, c.r2_ref_ohm * r.uniform(0.4, 0.8), tau3, c.r2_ref_ohm * r.uniform(0.3, 0.6),
                              tau3 * r.uniform(3.0, 5.0)};
                break;
            }
            case Effect::series_resistance_offset:
                c.bench.series_resistance_ohm = std::max(0.003, c.r0_ref_ohm * r.uniform(0.2, 0.5));
                break;
            case Effect::heat_flux_sensor_gain:
                c.bench.heat_flux_gain = r.index(2) == 0 ? r.uniform(0.6, 0.8) : r.uniform(1.2, 1.45);
                c.bench.heat_flux_offset_w_per_m2 = (r.index(2) == 0 ? -1.0 : 1.0) * r.uniform(3.0, 10.0);
                break;
            case Effect::capacity_error:
                c.bench.capacity_scale = 1.0 + (r.index(2) == 0 ? -1.0 : 1.0) * r.uniform(0.04, 0.1);
                break;
            case Effect::ambient_drift:
                c.bench.ambient_drift_k_per_h = (r.index(2) == 0 ? -1.0 : 1.0) * r.uniform(1.0, 3.0);
                c.bench.ambient_ripple_k = r.uniform(0.3, 1.0);
                c.bench.ambient_ripple_period_s = r.uniform(900.0, 2400.0);
                break;
        }
    }
    return c;
}

// ---------------------------------------------------------------------------------------------------------------
Truth make_truth(const CellSpec& c, Layout layout) {
    Truth t;
    t.seed = c.seed;
    t.chemistry = std::string(chemistry_name(c.chemistry));
    t.format = c.format;
    t.layout = std::string(layout_name(layout));
    t.capacity_ah = c.capacity_ah;
    t.nominal_capacity_ah = c.nominal_capacity_ah;
    t.drive_capacity_ah = c.capacity_ah * c.bench.capacity_scale;
    t.v_min_v = c.v_min_v;
    t.v_max_v = c.v_max_v;
    t.reference_temperature_c = c.reference_temperature_c;
    t.area_m2 = c.area_m2;
    for (int i = 1; i <= 19; ++i) {
        const double s = i / 20.0;
        t.soc.push_back(s);
        t.ocv_v.push_back(c.ocv_ref_v(s));
        t.entropic_v_per_k.push_back(c.entropic_v_per_k(s));
        for (auto [dir, tab] : {std::pair{Direction::discharge, &t.discharge}, std::pair{Direction::charge, &t.charge}}) {
            tab->r0_ohm.push_back(c.r0_ohm(s, dir));
            tab->r1_ohm.push_back(c.r1_ohm(s, dir));
            tab->r2_ohm.push_back(c.r2_ohm(s, dir));
            tab->tau1_s.push_back(c.tau1_s(s, dir));
            tab->tau2_s.push_back(c.tau2_s(s, dir));
        }
    }
    t.c_th_j_per_k = c.c_th_j_per_k;
    t.r_th_k_per_w = c.r_th_k_per_w;
    for (Effect e : c.effects) t.effects.emplace_back(effect_id(e));

    using nlohmann::json;
    json o;
    const auto& td = c.temperature_dependence;
    o["resistance_temperature"] = {
        {"enabled", td.form != TemperatureDependence::Form::none},
        {"form", td.form == TemperatureDependence::Form::exponential ? "exponential"
                 : td.form == TemperatureDependence::Form::linear    ? "linear"
                                                                     : "none"},
        {"coefficient_per_k", td.coefficient_per_k},
        {"equation", "R(T) = R_ref*exp(-k*(T - T_ref)) or R_ref*max(0.2, 1 - k*(T - T_ref)); applies to R0, R1, R2 "
                     "(time constants held), T = core temperature"}};
    o["resistance_current"] = {{"enabled", c.current_dependence.enabled},
                               {"saturation_current_a", c.current_dependence.saturation_current_a},
                               {"equation", "dv1/dt = -v1/tau1 + R1*I_c*tanh(I/I_c)/tau1 (RC1 only)"}};
    o["thermal_second_order"] = {{"enabled", c.thermal3.enabled},
                                 {"core_fraction", c.thermal3.core_fraction},
                                 {"r_core_can_k_per_w", c.thermal3.r_core_can_k_per_w},
                                 {"sensor_time_constant_s", c.thermal3.sensor_time_constant_s},
                                 {"equation", "core (f*C_th, heat source) -(R_cc)- can ((1-f)*C_th, to ambient via R_th; "
                                              "heat flux = (T_can - T_amb)/R_th/area) - sensor node (first-order lag)"}};
    o["ocv_hysteresis"] = {{"enabled", c.hysteresis.enabled},
                           {"m_fast_v", c.hysteresis.m_fast_v},
                           {"m_slow_v", c.hysteresis.m_slow_v},
                           {"eps_fast", c.hysteresis.eps_fast},
                           {"eps_slow", c.hysteresis.eps_slow},
                           {"low_soc_gain", c.hysteresis.low_soc_gain},
                           {"equation", "h = h_f + h_s, dh_i/dt = |I|/(3600*Q*eps_i)*(sign(I)*M_i*w(soc) - h_i), "
                                        "w = 1 + g*exp(-soc/0.15)"}};
    o["extra_rc"] = {{"enabled", c.extra_rc.enabled}, {"r3_ohm", c.extra_rc.r3_ohm}, {"tau3_s", c.extra_rc.tau3_s},
                     {"r4_ohm", c.extra_rc.r4_ohm}, {"tau4_s", c.extra_rc.tau4_s}};
    o["series_resistance_offset"] = {{"ohm", c.bench.series_resistance_ohm}, {"scope", "drive only"}};
    o["heat_flux_sensor_gain"] = {{"gain", c.bench.heat_flux_gain},
                                  {"offset_w_per_m2", c.bench.heat_flux_offset_w_per_m2},
                                  {"scope", "drive only"}};
    o["capacity_error"] = {{"scale", c.bench.capacity_scale}, {"scope", "drive only"}};
    o["ambient_drift"] = {{"k_per_h", c.bench.ambient_drift_k_per_h},
                          {"ripple_k", c.bench.ambient_ripple_k},
                          {"ripple_period_s", c.bench.ambient_ripple_period_s},
                          {"scope", "drive only; the Ambient column keeps reporting the set point"}};
    const auto& m = c.measurement;
    o["measurement"] = {{"sample_s", m.sample_s},
                        {"coarse_sample_s", m.coarse_sample_s},
                        {"voltage_noise_v", m.voltage_noise_v},
                        {"current_noise_a", m.current_noise_a},
                        {"temperature_noise_c", m.temperature_noise_c},
                        {"heat_flux_noise_w_per_m2", m.heat_flux_noise_w_per_m2},
                        {"voltage_resolution_v", std::pow(10.0, -m.voltage_decimals)},
                        {"current_resolution_a", std::pow(10.0, -m.current_decimals)},
                        {"temperature_resolution_c", std::pow(10.0, -m.temperature_decimals)}};
    t.options = o;
    return t;
}

nlohmann::json to_json(const Truth& t) {
    auto dir = [](const DirectionTable& d) {
        std::vector<double> c1, c2;  // C = tau / R, for comparison with cellbench.params/1 tables
        for (std::size_t k = 0; k < d.r1_ohm.size(); ++k) {
            c1.push_back(d.tau1_s[k] / d.r1_ohm[k]);
            c2.push_back(d.tau2_s[k] / d.r2_ohm[k]);
        }
        return nlohmann::json{{"r0_ohm", d.r0_ohm}, {"r1_ohm", d.r1_ohm}, {"r2_ohm", d.r2_ohm}, {"tau1_s", d.tau1_s},
                              {"tau2_s", d.tau2_s}, {"c1_f", c1},         {"c2_f", c2}};
    };
    return {{"schema", "cellbench.plant-truth/1"},
            {"seed", t.seed},
            {"chemistry", t.chemistry},
            {"format", t.format},
            {"layout", t.layout},
            {"capacity_ah", t.capacity_ah},
            {"capacity_definition",
             "charge between OCV = v_min_v (SOC 0) and OCV = v_max_v (SOC 1); a discharge to the v_min_v cut-off under "
             "load delivers less (the cut-off's share), a CCCV charge ends just below SOC 1"},
            {"nominal_capacity_ah", t.nominal_capacity_ah},
            {"drive_capacity_ah", t.drive_capacity_ah},
            {"v_min_v", t.v_min_v},
            {"v_max_v", t.v_max_v},
            {"reference_temperature_c", t.reference_temperature_c},
            {"area_m2", t.area_m2},
            {"soc", t.soc},
            {"ocv_v", t.ocv_v},
            {"entropic_v_per_k", t.entropic_v_per_k},
            {"discharge", dir(t.discharge)},
            {"charge", dir(t.charge)},
            {"thermal", {{"c_th_j_per_k", t.c_th_j_per_k}, {"r_th_k_per_w", t.r_th_k_per_w}}},
            {"effects", t.effects},
            {"options", t.options}};
}

}  // namespace cellbench::plant
