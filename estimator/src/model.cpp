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

}  // namespace

CellModel::CellModel(ParameterSet params) : params_(std::move(params)) { params_.validate(); }

double CellModel::resistance_factor(double temperature_c) const {
    const auto& ext = params_.extensions.resistance_temperature;
    if (!ext) return 1.0;
    const double t_k = temperature_c + kZeroCelsiusK;
    const double t_ref_k = params_.reference_temperature_c + kZeroCelsiusK;
    return std::exp(ext->activation_energy_j_per_mol / kGasConstantJPerMolK * (1.0 / t_k - 1.0 / t_ref_k));
}

CellState CellModel::rested_state(double terminal_voltage_v, double temperature_c) const {
    CellState s;
    s.soc = params_.soc_from_ocv(terminal_voltage_v);
    s.temperature_c = temperature_c;
    return s;
}

CellOutputs CellModel::step(CellState& s, double current_a, double ambient_c, double dt_s) const {
    const auto& th = params_.thermal;
    s.direction = current_direction(current_a, s.direction);

    // Parameters are frozen over the interval at the state it starts from (SOC, temperature, direction).
    Rc2Params<double> p = params_.rc_at(s.soc, s.direction);
    const double f = resistance_factor(s.temperature_c);
    p.r0_ohm *= f;
    p.r1_ohm *= f;  // C is held, so tau = R*C scales with R
    p.tau1_s *= f;
    p.r2_ohm *= f;
    p.tau2_s *= f;
    const double ehc = params_.ehc_at(s.soc);
    const double i = current_a;

    CellOutputs out;
    if (dt_s > 0) {
        // RC voltages: v_k(t) = vss_k + (v0_k - vss_k) * exp(-t/tau_k)   (exact under the held current)
        const double v1ss = p.r1_ohm * i, v2ss = p.r2_ohm * i;
        const double d1 = s.v1_v - v1ss, d2 = s.v2_v - v2ss;
        const double a1 = 1.0 / p.tau1_s, a2 = 1.0 / p.tau2_s;

        // Thermal: C dT/dt = I*(R0*I + v1 + v2) + I*EHC*(T + 273.15) - (T - Ta)/Rth
        //        dT/dt = -beta*T + c0 + c1*exp(-a1 t) + c2*exp(-a2 t)
        const double beta = (1.0 / th.r_th_k_per_w - i * ehc) / th.c_th_j_per_k;
        const double c0 =
            (i * (p.r0_ohm * i + v1ss + v2ss) + i * ehc * kZeroCelsiusK + ambient_c / th.r_th_k_per_w) /
            th.c_th_j_per_k;
        const double c1 = i * d1 / th.c_th_j_per_k, c2 = i * d2 / th.c_th_j_per_k;
        const double e_beta = std::exp(-beta * dt_s);
        // integral_0^dt exp(-beta (dt - u)) exp(-a u) du = exp(-a dt) * (1 - exp(-(beta - a) dt)) / (beta - a)
        const double t0 = s.temperature_c;
        const double t1 = t0 * e_beta + c0 * integral_of_decay(beta, dt_s) +
                          c1 * std::exp(-a1 * dt_s) * integral_of_decay(beta - a1, dt_s) +
                          c2 * std::exp(-a2 * dt_s) * integral_of_decay(beta - a2, dt_s);

        // Mean heats over the interval (outputs only).
        out.heat_irreversible_w = i * (p.r0_ohm * i + v1ss + v2ss) +
                                  i * (d1 * integral_of_decay(a1, dt_s) + d2 * integral_of_decay(a2, dt_s)) / dt_s;
        out.heat_reversible_w = i * ehc * (0.5 * (t0 + t1) + kZeroCelsiusK);

        s.v1_v = v1ss + d1 * std::exp(-a1 * dt_s);
        s.v2_v = v2ss + d2 * std::exp(-a2 * dt_s);
        s.temperature_c = t1;
        s.soc += i * dt_s / (3600.0 * params_.capacity_ah);
    } else {
        out.heat_irreversible_w = i * (p.r0_ohm * i + s.v1_v + s.v2_v);
        out.heat_reversible_w = i * ehc * (s.temperature_c + kZeroCelsiusK);
    }
    out.ocv_v = params_.ocv_at(s.soc);
    out.voltage_v = out.ocv_v + p.r0_ohm * i + s.v1_v + s.v2_v;
    out.heat_flow_out_w = (s.temperature_c - ambient_c) / th.r_th_k_per_w;
    return out;
}

}  // namespace cellbench::estimator
