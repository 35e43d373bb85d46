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

    // Parameters are frozen over the interval at the state it starts from (SOC, temperature).
    Rc2Params<double> pd = params_.rc_at(s.soc, -1), pc = params_.rc_at(s.soc, +1);
    const double f = resistance_factor(s.temperature_c);
    for (auto* p : {&pd, &pc}) {  // C is held, so tau = R*C scales with R
        p->r0_ohm *= f;
        p->r1_ohm *= f;
        p->tau1_s *= f;
        p->r2_ohm *= f;
        p->tau2_s *= f;
    }
    const double ehc = params_.ehc_at(s.soc);
    const double i = current_a;
    const double ohmic_v = ohmic_drop_v(pd, pc, i);

    CellOutputs out;
    if (dt_s > 0) {
        // Each RC voltage: v_j(t) = vss_j + (v0_j - vss_j) * exp(-a_j t)   (exact under the held current)
        const double id = discharge_part(i), ic = charge_part(i);
        double* v[4] = {&s.rc.v1_discharge_v, &s.rc.v2_discharge_v, &s.rc.v1_charge_v, &s.rc.v2_charge_v};
        const double vss[4] = {pd.r1_ohm * id, pd.r2_ohm * id, pc.r1_ohm * ic, pc.r2_ohm * ic};
        const double rate[4] = {1.0 / pd.tau1_s, 1.0 / pd.tau2_s, 1.0 / pc.tau1_s, 1.0 / pc.tau2_s};
        double d[4], vss_sum = 0;
        for (int j = 0; j < 4; ++j) {
            d[j] = *v[j] - vss[j];
            vss_sum += vss[j];
        }

        // Thermal: C dT/dt = I*(R0*I + sum v_j) + I*EHC*(T + 273.15) - (T - Ta)/Rth
        //        dT/dt = -beta*T + c0 + sum_j c_j*exp(-a_j t)
        const double beta = (1.0 / th.r_th_k_per_w - i * ehc) / th.c_th_j_per_k;
        const double c0 =
            (i * (ohmic_v + vss_sum) + i * ehc * kZeroCelsiusK + ambient_c / th.r_th_k_per_w) / th.c_th_j_per_k;
        const double t0 = s.temperature_c;
        // integral_0^dt exp(-beta (dt - u)) exp(-a u) du = exp(-a dt) * (1 - exp(-(beta - a) dt)) / (beta - a)
        double t1 = t0 * std::exp(-beta * dt_s) + c0 * integral_of_decay(beta, dt_s);
        double transient_heat_j = 0;
        for (int j = 0; j < 4; ++j) {
            if (d[j] == 0.0) continue;
            t1 += i * d[j] / th.c_th_j_per_k * std::exp(-rate[j] * dt_s) * integral_of_decay(beta - rate[j], dt_s);
            transient_heat_j += i * d[j] * integral_of_decay(rate[j], dt_s);
        }

        // Mean heats over the interval (outputs only).
        out.heat_irreversible_w = i * (ohmic_v + vss_sum) + transient_heat_j / dt_s;
        out.heat_reversible_w = i * ehc * (0.5 * (t0 + t1) + kZeroCelsiusK);

        for (int j = 0; j < 4; ++j) *v[j] = vss[j] + d[j] * std::exp(-rate[j] * dt_s);
        s.temperature_c = t1;
        s.soc += i * dt_s / (3600.0 * params_.capacity_ah);
    } else {
        out.heat_irreversible_w = i * (ohmic_v + s.rc.sum());
        out.heat_reversible_w = i * ehc * (s.temperature_c + kZeroCelsiusK);
    }
    out.ocv_v = params_.ocv_at(s.soc);
    out.voltage_v = out.ocv_v + ohmic_v + s.rc.sum();
    out.heat_flow_out_w = (s.temperature_c - ambient_c) / th.r_th_k_per_w;
    return out;
}

}  // namespace cellbench::estimator
