#include "cellbench/estimator/model.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

namespace {

constexpr double kGasConstantJPerMolK = 8.314462618;

// (1 - exp(-rate*dt)) / rate, continuous at rate -> 0 (where it tends to dt).
double integral_of_decay(double rate_per_s, double dt_s) {
    const double x = rate_per_s * dt_s;
    if (std::abs(x) < 1e-8) return dt_s * (1.0 - 0.5 * x);
    return -std::expm1(-x) / rate_per_s;
}

// An RC voltage that has relaxed below a femtovolt is zero. Left alone, a long rest decays it on through the
// subnormal range (below 2.2e-308 V), where every multiplication costs about a hundred cycles: a one-hour HPPC
// rest after a pulse simulated at half the speed. A femtovolt is 10^11 below the noise of any cycler.
constexpr double kRelaxedV = 1e-15;
[[gnu::always_inline]] inline double settled(double v) { return std::abs(v) < kRelaxedV ? 0.0 : v; }

// asinh(x)/x, 1 at x = 0.
double asinh_ratio(double x) { return std::abs(x) < 1e-6 ? 1.0 - x * x / 6.0 : std::asinh(x) / x; }

// x(dt) for x' = A x + b with constant b (2x2, A invertible): x_ss + exp(A dt) (x0 - x_ss).
void two_node_step(const double a[2][2], const double b[2], double x[2], double dt) {
    const double det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    const double xss[2] = {-(a[1][1] * b[0] - a[0][1] * b[1]) / det, -(-a[1][0] * b[0] + a[0][0] * b[1]) / det};
    // exp(A t) by Cayley-Hamilton: e^{s t} [ (cosh(d t) - s sinh(d t)/d) I + (sinh(d t)/d) A ], s = tr/2,
    // d^2 = s^2 - det (real for this passive network).
    const double s = 0.5 * (a[0][0] + a[1][1]);
    const double d2 = s * s - det;
    const double d = std::sqrt(std::max(d2, 0.0));
    const double e = std::exp(s * dt);
    const double sh_over_d = d * dt < 1e-8 ? dt : std::sinh(d * dt) / d;
    const double c0 = e * (std::cosh(d * dt) - s * sh_over_d), c1 = e * sh_over_d;
    const double y[2] = {x[0] - xss[0], x[1] - xss[1]};
    x[0] = xss[0] + (c0 + c1 * a[0][0]) * y[0] + c1 * a[0][1] * y[1];
    x[1] = xss[1] + c1 * a[1][0] * y[0] + (c0 + c1 * a[1][1]) * y[1];
}

// The core and surface nodes (ThermalSecondOrderExt) over dt_s with the heat held: the irreversible heat and the
// reversible heat i T dU/dT at the core's temperature enter the core, the surface exchanges with the ambient through
// R_th. Updates s's core and surface temperatures from core_c (the core at the step's start) and s.temperature_c;
// returns the reversible heat in W at the step's mean core temperature.
double two_node_thermal_step(const ThermalSecondOrderExt& so, const ThermalParams& th, double i, double ehc,
                             double heat_irreversible_w, double ambient_c, double core_c, double dt_s, CellState& s) {
    const double cc = so.core_fraction * th.c_th_j_per_k, cs = th.c_th_j_per_k - cc;
    const double g_cs = 1.0 / so.r_core_surface_k_per_w, g_sa = 1.0 / th.r_th_k_per_w;
    const double a[2][2] = {{(-g_cs + i * ehc) / cc, g_cs / cc}, {g_cs / cs, (-g_cs - g_sa) / cs}};
    const double b[2] = {(heat_irreversible_w + i * ehc * kZeroCelsiusK) / cc, g_sa * ambient_c / cs};
    double x[2] = {core_c, s.temperature_c};
    two_node_step(a, b, x, dt_s);
    s.core_temperature_c = x[0];
    s.temperature_c = x[1];
    return i * ehc * (0.5 * (core_c + x[0]) + kZeroCelsiusK);
}

}  // namespace

CellModel::CellModel(ParameterSet params) : params_(std::move(params)) {
    params_.validate();
    if (const auto& ext = params_.extensions.resistance_current)
        reference_current_ratio_ = asinh_ratio(ext->reference_current_a / (2 * ext->exchange_current_a));
}

double CellModel::resistance_factor(double temperature_c) const {
    const auto& ext = params_.extensions.resistance_temperature;
    if (!ext) return 1.0;
    const double t_k = temperature_c + kZeroCelsiusK;
    const double t_ref_k = params_.reference_temperature_c + kZeroCelsiusK;
    return std::exp(ext->activation_energy_j_per_mol / kGasConstantJPerMolK * (1.0 / t_k - 1.0 / t_ref_k));
}

double CellModel::current_factor(double current_a) const {
    const auto& ext = params_.extensions.resistance_current;
    if (!ext) return 1.0;
    return asinh_ratio(std::abs(current_a) / (2 * ext->exchange_current_a)) / reference_current_ratio_;
}

double CellModel::capacity_ah() const {
    const auto& ext = params_.extensions.capacity_error;
    return params_.capacity_ah * (ext ? ext->capacity_scale : 1.0);
}

CellState CellModel::rested_state(double terminal_voltage_v, double temperature_c) const {
    CellState s;
    s.soc = params_.soc_from_ocv(terminal_voltage_v);
    s.temperature_c = temperature_c;
    if (params_.extensions.thermal_second_order) s.core_temperature_c = temperature_c;
    return s;
}

CellOutputs CellModel::step(CellState& s, double current_a, double ambient_c, double dt_s) const {
    const auto& th = params_.thermal;
    const auto& ext = params_.extensions;
    if (ext.thermal_second_order && !std::isfinite(s.core_temperature_c)) s.core_temperature_c = s.temperature_c;
    const double t_inner = ext.thermal_second_order ? s.core_temperature_c : s.temperature_c;
    if (ext.ambient_drift)
        ambient_c += ext.ambient_drift->offset_c + ext.ambient_drift->rate_c_per_h * (s.elapsed_s + 0.5 * dt_s) / 3600.0;

    // Parameters are frozen over the interval at the state it starts from (SOC, temperature) and its current.
    Rc2Params<double> pd = params_.rc_at(s.soc, -1), pc = params_.rc_at(s.soc, +1);
    const double f_t = resistance_factor(t_inner), f_i = current_factor(current_a);
    const double dr0 = ext.series_resistance_offset ? ext.series_resistance_offset->r_ohm : 0.0;
    for (auto* p : {&pd, &pc}) {  // C is held, so tau = R*C scales with R
        p->r0_ohm = p->r0_ohm * f_t + dr0;
        p->r1_ohm *= f_t * f_i;
        p->tau1_s *= f_t * f_i;
        p->r2_ohm *= f_t * f_i;
        p->tau2_s *= f_t * f_i;
    }
    double ehc = params_.ehc_at(s.soc);
    if (ext.entropic_heat) ehc += ext.entropic_heat->ehc_v_per_k + ext.entropic_heat->ehc_slope_v_per_k * (s.soc - 0.5);
    const double i = current_a;
    const double ohmic_v = ohmic_drop_v(pd, pc, i);
    // A series resistance outside the cell (harness, contacts) drops voltage at the terminals but dissipates its
    // heat outside the cell: only the cell's own ohmic drop heats it.
    const double cell_ohmic_v = ohmic_v - dr0 * i;
    const double capacity = capacity_ah();

    CellOutputs out;
    out.ambient_c = ambient_c;
    if (dt_s > 0) {
        // Each RC voltage: v_j(t) = vss_j + (v0_j - vss_j) * exp(-a_j t)   (exact under the held current)
        const double id = discharge_part(i), ic = charge_part(i);
        const double r3 = ext.extra_rc ? ext.extra_rc->r_ohm * f_t : 0.0;
        const double tau3 = ext.extra_rc ? ext.extra_rc->tau_s * f_t : 1.0;
        double* v[5] = {&s.rc.v1_discharge_v, &s.rc.v2_discharge_v, &s.rc.v1_charge_v, &s.rc.v2_charge_v, &s.extra_rc_v};
        const double vss[5] = {pd.r1_ohm * id, pd.r2_ohm * id, pc.r1_ohm * ic, pc.r2_ohm * ic, r3 * i};
        const double rate[5] = {1.0 / pd.tau1_s, 1.0 / pd.tau2_s, 1.0 / pc.tau1_s, 1.0 / pc.tau2_s, 1.0 / tau3};
        double d[5], vss_sum = 0;
        for (int j = 0; j < 5; ++j) {
            d[j] = *v[j] - vss[j];
            vss_sum += vss[j];
        }
        // Hysteresis relaxes exponentially in charge throughput (exact for the held current).
        double h_mean = s.hysteresis_v;
        if (ext.ocv_hysteresis && i != 0.0) {
            const double k = ext.ocv_hysteresis->rate_per_capacity * std::abs(i) / (3600.0 * capacity);
            const double target = (i > 0 ? 1.0 : -1.0) * ext.ocv_hysteresis->magnitude_v;
            const double h0 = s.hysteresis_v;
            s.hysteresis_v = target + (h0 - target) * std::exp(-k * dt_s);
            h_mean = target + (h0 - target) * integral_of_decay(k, dt_s) / dt_s;
        }

        double transient_heat_j = 0;
        for (int j = 0; j < 5; ++j)
            if (d[j] != 0.0) transient_heat_j += i * d[j] * integral_of_decay(rate[j], dt_s);
        const double steady_heat_w = i * (cell_ohmic_v + vss_sum + h_mean);
        out.heat_irreversible_w = steady_heat_w + transient_heat_j / dt_s;
        const double t0 = s.temperature_c, tc0 = t_inner;

        if (!ext.thermal_second_order) {
            // C dT/dt = I*(R0*I + sum v_j + h) + I*EHC*(T + 273.15) - (T - Ta)/Rth
            //       dT/dt = -beta*T + c0 + sum_j c_j*exp(-a_j t)     (exact)
            const double beta = (1.0 / th.r_th_k_per_w - i * ehc) / th.c_th_j_per_k;
            const double c0 =
                (steady_heat_w + i * ehc * kZeroCelsiusK + ambient_c / th.r_th_k_per_w) / th.c_th_j_per_k;
            // integral_0^dt exp(-beta (dt - u)) exp(-a u) du = exp(-a dt) * (1 - exp(-(beta - a) dt)) / (beta - a)
            double t1 = t0 * std::exp(-beta * dt_s) + c0 * integral_of_decay(beta, dt_s);
            for (int j = 0; j < 5; ++j)
                if (d[j] != 0.0)
                    t1 += i * d[j] / th.c_th_j_per_k * std::exp(-rate[j] * dt_s) *
                          integral_of_decay(beta - rate[j], dt_s);
            s.temperature_c = t1;
            out.heat_reversible_w = i * ehc * (0.5 * (t0 + t1) + kZeroCelsiusK);
        } else {
            // Core (heat source, reversible heat at the core temperature) and surface nodes, mean heat held.
            out.heat_reversible_w = two_node_thermal_step(*ext.thermal_second_order, th, i, ehc, out.heat_irreversible_w,
                                                          ambient_c, tc0, dt_s, s);
        }

        for (int j = 0; j < 5; ++j) *v[j] = settled(vss[j] + d[j] * std::exp(-rate[j] * dt_s));
        s.soc += i * dt_s / (3600.0 * capacity);
        s.elapsed_s += dt_s;
    } else {
        out.heat_irreversible_w = i * (cell_ohmic_v + s.rc.sum() + s.extra_rc_v + s.hysteresis_v);
        out.heat_reversible_w = i * ehc * (t_inner + kZeroCelsiusK);
    }
    out.ocv_v = params_.ocv_at(s.soc);
    out.voltage_v = out.ocv_v + ohmic_v + s.rc.sum() + s.extra_rc_v + s.hysteresis_v;
    out.heat_flow_out_w = (s.temperature_c - ambient_c) / th.r_th_k_per_w;
    out.sensor_heat_flow_w = out.heat_flow_out_w * (ext.heat_flux_sensor_gain ? ext.heat_flux_sensor_gain->gain : 1.0);
    return out;
}

}  // namespace cellbench::estimator

namespace cellbench::estimator {

namespace {

// Index i with x[i] <= q < x[i+1], clamped to [0, n-2] (params.cpp's segment_index), starting from a guess.
std::size_t bracket_from(const std::vector<double>& x, std::size_t guess, double q) {
    const std::size_t last = x.size() - 2;
    if (guess <= last) {
        if ((guess == 0 || x[guess] <= q) && (guess == last || q < x[guess + 1])) return guess;
        if (guess < last && x[guess + 1] <= q && (guess + 1 == last || q < x[guess + 2])) return guess + 1;
        if (guess > 0 && x[guess - 1] <= q && q < x[guess]) return guess - 1;
    }
    auto it = std::upper_bound(x.begin(), x.end(), q);
    std::size_t i = it == x.begin() ? 0 : static_cast<std::size_t>(it - x.begin()) - 1;
    return std::min(i, last);
}

// Places `lines` on the segment of axis x holding q (hold: the ends' values beyond them; else the end segments'
// lines extended) for the given columns: the arithmetic of params.cpp's interp_hold / interp_extrap.
template <std::size_t K>
void place_lines(CellStepper::SegmentLines<K>& lines, const std::vector<double>& x,
                 const std::array<const std::vector<double>*, K>& columns, double q, bool hold) {
    constexpr double inf = std::numeric_limits<double>::infinity();
    auto held = [&](std::size_t at, double lo, double hi) {
        lines.lo = lo, lines.hi = hi, lines.x0 = 0.0, lines.inv_dx = 0.0;
        for (std::size_t c = 0; c < K; ++c) lines.base[c] = (*columns[c])[at], lines.slope[c] = 0.0;
    };
    if (x.size() == 1) return held(0, -inf, inf);
    if (hold && q <= x.front()) return held(0, -inf, std::nextafter(x.front(), inf));
    if (hold && q >= x.back()) return held(x.size() - 1, x.back(), inf);
    const std::size_t i = lines.bracket = bracket_from(x, lines.bracket, q);
    if (!(q == q)) {  // NaN: every value NaN, and never valid
        lines.lo = lines.hi = kNaN, lines.x0 = 0.0, lines.inv_dx = kNaN;
    } else {
        const std::size_t last = x.size() - 2;
        lines.lo = hold || i > 0 ? x[i] : -inf;
        lines.hi = hold || i < last ? x[i + 1] : inf;
        lines.x0 = x[i];
        lines.inv_dx = 1.0 / (x[i + 1] - x[i]);
    }
    for (std::size_t c = 0; c < K; ++c) {
        lines.base[c] = (*columns[c])[i];
        lines.slope[c] = (*columns[c])[i + 1] - (*columns[c])[i];
    }
}

// Weight of q on the lines' segment, re-placing them first when q lies outside it.
template <std::size_t K>
[[gnu::always_inline]] inline double line_weight(CellStepper::SegmentLines<K>& lines, const std::vector<double>& x,
                                                 const std::array<const std::vector<double>*, K>& columns, double q,
                                                 bool hold) {
    if (!(q >= lines.lo && q < lines.hi)) place_lines(lines, x, columns, q, hold);
    return (q - lines.x0) * lines.inv_dx;
}

// CellStepper::DecayCache::eval, inlined into the step (five calls per step: the four pairs and the thermal decay).
[[gnu::always_inline]] inline void decay_eval(CellStepper::DecayCache& c, double x, double& e, double& m) {
    const double d = x - c.x0;
    if (d == 0.0) {  // the same rate and interval as last time (a rest at a constant sampling interval)
        e = c.e0;
        m = c.m0;
        return;
    }
    const double ad = std::abs(d);
    if (ad <= 1e-2 && ad <= 0.5 * std::abs(c.x0)) {  // false for NaN
        // expm1(-d) by its Taylor series, then exp(-x) = exp(-x0) exp(-d). Truncation: d^5/5! < 1e-22 below
        // 1e-4 (the usual change from one sample to the next under current), d^8/8! < 2.5e-21 up to 1e-2.
        const double q = ad < 1e-4 ? -d * (1.0 - d * (1.0 / 2 - d * (1.0 / 6 - d * (1.0 / 24))))
                                   : -d * (1.0 - d * (1.0 / 2 - d * (1.0 / 6 - d * (1.0 / 24 - d * (1.0 / 120 -
                                                                     d * (1.0 / 720 - d / 5040))))));
        e = c.e0 + c.e0 * q;
        m = c.m0 + c.e0 * q;
        return;
    }
    c.x0 = x;
    c.e0 = std::exp(-x);
    c.m0 = std::expm1(-x);
    e = c.e0;
    m = c.m0;
}

// integral_of_decay(rate, dt) for |rate dt| < 1e-2, x = rate dt: dt * sum_k (-x)^k / (k + 1)! to k = 7
// (truncation below x^8 / 9! < 3e-22 relative), in place of expm1 and a division.
[[gnu::always_inline]] inline double integral_of_small_decay(double x, double dt_s) {
    constexpr double k3 = 1.0 / 3, k5 = 1.0 / 5, k6 = 1.0 / 6, k7 = 1.0 / 7;
    return dt_s * (1.0 - x * 0.5 * (1.0 - x * k3 * (1.0 - x * 0.25 * (1.0 - x * k5 * (1.0 - x * k6 *
                                                                   (1.0 - x * k7 * (1.0 - x * 0.125)))))));
}

}  // namespace

void CellStepper::DecayCache::eval(double x, double& e, double& m) { decay_eval(*this, x, e, m); }

CellStepper::CellStepper(const CellModel& model)
    : model_(model),
      p_(model.params()),
      inv_c_th_per_j_(1.0 / p_.thermal.c_th_j_per_k),
      inv_r_th_w_per_k_(1.0 / p_.thermal.r_th_k_per_w),
      soc_per_a_s_(1.0 / (3600.0 * model.capacity_ah())) {}

void CellStepper::refresh_parameters(double soc, double f_t, double f_i) {
    key_soc_ = soc;
    key_ft_ = f_t;
    key_fi_ = f_i;
    const auto& ext = p_.extensions;
    const double dr0 = ext.series_resistance_offset ? ext.series_resistance_offset->r_ohm : 0.0;
    const std::array<const std::vector<double>*, 10> columns{
        &p_.discharge.r0_ohm, &p_.discharge.r1_ohm, &p_.discharge.c1_f, &p_.discharge.r2_ohm, &p_.discharge.c2_f,
        &p_.charge.r0_ohm,    &p_.charge.r1_ohm,    &p_.charge.c1_f,    &p_.charge.r2_ohm,    &p_.charge.c2_f};
    const double w = line_weight(rc_lines_, p_.soc, columns, soc, true);
    double y[10];
    for (std::size_t c = 0; c < 10; ++c) y[c] = rc_lines_.base[c] + w * rc_lines_.slope[c];
    const double f_rc = f_t * f_i;
    auto rc = [&](const double* v, Rc2Params<double>& p) {
        p.r0_ohm = v[0] * f_t + dr0;
        p.r1_ohm = v[1] * f_rc;
        p.tau1_s = v[1] * v[2] * f_rc;
        p.r2_ohm = v[3] * f_rc;
        p.tau2_s = v[3] * v[4] * f_rc;
    };
    rc(y, pd_);
    rc(y + 5, pc_);
    ehc_ = 0.0;
    if (!p_.thermal.ehc_soc.empty()) {
        const std::array<const std::vector<double>*, 1> ehc_column{&p_.thermal.ehc_v_per_k};
        const double we = line_weight(ehc_lines_, p_.thermal.ehc_soc, ehc_column, soc, true);
        ehc_ = ehc_lines_.base[0] + we * ehc_lines_.slope[0];
    }
    if (ext.entropic_heat) ehc_ += ext.entropic_heat->ehc_v_per_k + ext.entropic_heat->ehc_slope_v_per_k * (soc - 0.5);
    const double tau3 = ext.extra_rc ? ext.extra_rc->tau_s * f_t : 1.0;
    tau_[0] = pd_.tau1_s;
    tau_[1] = pd_.tau2_s;
    tau_[2] = pc_.tau1_s;
    tau_[3] = pc_.tau2_s;
    tau_[4] = tau3;
    for (int j = 0; j < 5; ++j) rate_[j] = 1.0 / tau_[j];  // packed divisions
}

CellOutputs CellStepper::step(CellState& s, double current_a, double ambient_c, double dt_s, double output_current_a) {
    if (!(dt_s > 0)) return model_.step(s, output_current_a, ambient_c, dt_s);  // evaluation only: the reference
    const auto& th = p_.thermal;
    const auto& ext = p_.extensions;
    if (ext.thermal_second_order && !std::isfinite(s.core_temperature_c)) s.core_temperature_c = s.temperature_c;
    const double t_inner = ext.thermal_second_order ? s.core_temperature_c : s.temperature_c;
    if (ext.ambient_drift)
        ambient_c += ext.ambient_drift->offset_c + ext.ambient_drift->rate_c_per_h * (s.elapsed_s + 0.5 * dt_s) / 3600.0;

    if (ext.resistance_temperature && !(t_inner == t_inner_key_)) {
        t_inner_key_ = t_inner;
        f_t_ = model_.resistance_factor(t_inner);
    }
    if (ext.resistance_current && !(current_a == i_key_)) {
        i_key_ = current_a;
        f_i_ = model_.current_factor(current_a);
    }
    if (!(s.soc == key_soc_ && f_t_ == key_ft_ && f_i_ == key_fi_)) refresh_parameters(s.soc, f_t_, f_i_);

    const double i = current_a;
    const double ohmic_v = ohmic_drop_v(pd_, pc_, i);
    const double dr0 = ext.series_resistance_offset ? ext.series_resistance_offset->r_ohm : 0.0;
    const double cell_ohmic_v = ohmic_v - dr0 * i;  // the harness' heat stays outside the cell (as in CellModel)
    CellOutputs out;
    out.ambient_c = ambient_c;

    const double id = discharge_part(i), ic = charge_part(i);
    const double r3 = ext.extra_rc ? ext.extra_rc->r_ohm * f_t_ : 0.0;
    double* v[5] = {&s.rc.v1_discharge_v, &s.rc.v2_discharge_v, &s.rc.v1_charge_v, &s.rc.v2_charge_v, &s.extra_rc_v};
    const double vss[5] = {pd_.r1_ohm * id, pd_.r2_ohm * id, pc_.r1_ohm * ic, pc_.r2_ohm * ic, r3 * i};
    // The fifth lane (extra_rc) only with that extension (or a state that still holds its voltage).
    const int lanes = ext.extra_rc || s.extra_rc_v != 0.0 ? 5 : 4;
    double d[5], e[5], m[5], vss_sum = 0;
    for (int j = 0; j < lanes; ++j) {
        d[j] = *v[j] - vss[j];
        vss_sum += vss[j];
        if (d[j] != 0.0) decay_eval(pair_[j], rate_[j] * dt_s, e[j], m[j]);
    }
    // integral_of_decay(rate, dt) = (1 - e^{-rate dt}) / rate, given m_neg = expm1(-rate dt) and 1/rate.
    auto iod = [dt_s](double rate, double inv_rate, double m_neg) {
        const double x = rate * dt_s;
        if (std::abs(x) < 1e-8) return dt_s * (1.0 - 0.5 * x);
        return -m_neg * inv_rate;
    };

    double h_mean = s.hysteresis_v;
    if (ext.ocv_hysteresis && i != 0.0) {
        const double k = ext.ocv_hysteresis->rate_per_capacity * std::abs(i) * soc_per_a_s_;
        const double target = (i > 0 ? 1.0 : -1.0) * ext.ocv_hysteresis->magnitude_v;
        const double h0 = s.hysteresis_v;
        s.hysteresis_v = target + (h0 - target) * std::exp(-k * dt_s);
        h_mean = target + (h0 - target) * integral_of_decay(k, dt_s) / dt_s;
    }

    // At zero current the transient heat and the RC terms of the thermal step vanish (they carry a factor I).
    const bool flowing = i != 0.0;
    double transient_heat_j = 0;
    if (flowing)
        for (int j = 0; j < lanes; ++j)
            if (d[j] != 0.0) transient_heat_j += i * d[j] * iod(rate_[j], tau_[j], m[j]);
    const double steady_heat_w = i * (cell_ohmic_v + vss_sum + h_mean);
    out.heat_irreversible_w = steady_heat_w + transient_heat_j / dt_s;
    const double t0 = s.temperature_c, tc0 = t_inner;
    const double ehc = ehc_;

    if (!ext.thermal_second_order) {
        const double beta = (inv_r_th_w_per_k_ - i * ehc) * inv_c_th_per_j_;
        const double c0 = (steady_heat_w + i * ehc * kZeroCelsiusK + ambient_c * inv_r_th_w_per_k_) * inv_c_th_per_j_;
        double eb, mb;
        decay_eval(beta_, beta * dt_s, eb, mb);
        double t1 = t0 * eb + c0 * iod(beta, 1.0 / beta, mb);
        if (flowing) {
            // exp(-a dt) * integral_of_decay(beta - a, dt) = (e^{-a dt} - e^{-beta dt}) / (beta - a); the series
            // where beta and a lie close (the usual case at 0.1-1 s sampling).
            double sum = 0.0;
            for (int j = 0; j < lanes; ++j) {
                if (d[j] == 0.0) continue;
                const double gap = beta - rate_[j], x = gap * dt_s;
                sum += d[j] * (std::abs(x) < 1e-2 ? e[j] * integral_of_small_decay(x, dt_s) : (m[j] - mb) / gap);
            }
            t1 += i * inv_c_th_per_j_ * sum;
        }
        s.temperature_c = t1;
        out.heat_reversible_w = i * ehc * (0.5 * (t0 + t1) + kZeroCelsiusK);
    } else {
        out.heat_reversible_w = two_node_thermal_step(*ext.thermal_second_order, th, i, ehc, out.heat_irreversible_w,
                                                      ambient_c, tc0, dt_s, s);
    }

    for (int j = 0; j < lanes; ++j) *v[j] = settled(d[j] != 0.0 ? vss[j] + d[j] * e[j] : vss[j] + d[j]);
    s.soc += i * dt_s * soc_per_a_s_;
    s.elapsed_s += dt_s;

    const std::array<const std::vector<double>*, 1> ocv_column{&p_.ocv_v};
    const double w_ocv = line_weight(ocv_lines_, p_.soc, ocv_column, s.soc, false);
    out.ocv_v = ocv_lines_.base[0] + w_ocv * ocv_lines_.slope[0];
    // R0 does not depend on the current factor (refresh_parameters), so the row's own drop reads the same tables.
    const double row_ohmic_v = output_current_a == i ? ohmic_v : ohmic_drop_v(pd_, pc_, output_current_a);
    out.voltage_v = out.ocv_v + row_ohmic_v + s.rc.sum() + s.extra_rc_v + s.hysteresis_v;
    out.heat_flow_out_w = (s.temperature_c - ambient_c) * inv_r_th_w_per_k_;
    out.sensor_heat_flow_w = out.heat_flow_out_w * (ext.heat_flux_sensor_gain ? ext.heat_flux_sensor_gain->gain : 1.0);
    return out;
}

}  // namespace cellbench::estimator
