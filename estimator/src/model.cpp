#include "cellbench/estimator/model.hpp"

#include <cmath>

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

}  // namespace

CellModel::CellModel(ParameterSet params) : params_(std::move(params)) { params_.validate(); }

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
    const double i0 = ext->exchange_current_a;
    return asinh_ratio(std::abs(current_a) / (2 * i0)) / asinh_ratio(ext->reference_current_a / (2 * i0));
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
        const double steady_heat_w = i * (ohmic_v + vss_sum + h_mean);
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
            const auto& so = *ext.thermal_second_order;
            const double cc = so.core_fraction * th.c_th_j_per_k, cs = th.c_th_j_per_k - cc;
            const double g_cs = 1.0 / so.r_core_surface_k_per_w, g_sa = 1.0 / th.r_th_k_per_w;
            const double a[2][2] = {{(-g_cs + i * ehc) / cc, g_cs / cc}, {g_cs / cs, (-g_cs - g_sa) / cs}};
            const double b[2] = {(out.heat_irreversible_w + i * ehc * kZeroCelsiusK) / cc, g_sa * ambient_c / cs};
            double x[2] = {tc0, t0};
            two_node_step(a, b, x, dt_s);
            s.core_temperature_c = x[0];
            s.temperature_c = x[1];
            out.heat_reversible_w = i * ehc * (0.5 * (tc0 + x[0]) + kZeroCelsiusK);
        }

        for (int j = 0; j < 5; ++j) *v[j] = vss[j] + d[j] * std::exp(-rate[j] * dt_s);
        s.soc += i * dt_s / (3600.0 * capacity);
        s.elapsed_s += dt_s;
    } else {
        out.heat_irreversible_w = i * (ohmic_v + s.rc.sum() + s.extra_rc_v + s.hysteresis_v);
        out.heat_reversible_w = i * ehc * (t_inner + kZeroCelsiusK);
    }
    out.ocv_v = params_.ocv_at(s.soc);
    out.voltage_v = out.ocv_v + ohmic_v + s.rc.sum() + s.extra_rc_v + s.hysteresis_v;
    out.heat_flow_out_w = (s.temperature_c - ambient_c) / th.r_th_k_per_w;
    out.sensor_heat_flow_w = out.heat_flow_out_w * (ext.heat_flux_sensor_gain ? ext.heat_flux_sensor_gain->gain : 1.0);
    return out;
}

}  // namespace cellbench::estimator
