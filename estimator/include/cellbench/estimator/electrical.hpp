#pragma once
// Exact zero-order-hold (ZOH) discretization of the Thevenin 2RC electrical model with direction-dependent
// parameters.
//
// Sign convention: current I is positive when charging (BDF). The current splits into its discharge part
// I- = min(I, 0) and its charge part I+ = max(I, 0). Each direction has its own two RC pairs, driven only by its
// own part of the current and always relaxing with its own time constants:
//     V = OCV(SOC) + R0_dis*I- + R0_chg*I+ + v1_dis + v2_dis + v1_chg + v2_chg
//     dv_kd/dt = -v_kd/(R_kd*C_kd) + I-/C_kd,    dv_kc/dt = -v_kc/(R_kc*C_kc) + I+/C_kc
// This is the superposition of two linear systems, so with equal parameters for both directions it is exactly
// the plain 2RC model, and the polarization a discharge pulse leaves behind relaxes with the discharge time
// constants whatever comes next (what the thesis' relaxation fits, eqs. 3.10 and 3.18, assume). Switching
// the parameters of one shared RC pair by the sign of the current would instead make a charge pulse change how
// the discharge's leftover polarization decays.
//
// Sampling convention (shared by the model, the simulator and every fitter): the current recorded at sample
// k is the current that flowed during (t[k-1], t[k]] and is held constant over that interval. The exact
// solution of the linear ODE over an interval of length dt with constant I is
//     v(t+dt) = exp(-dt/tau) * v(t) + R * (1 - exp(-dt/tau)) * I
// whatever dt is; nothing here is an Euler step.
//
// These templates work with double and with ceres::Jet (automatic differentiation).
#include <algorithm>
#include <cmath>
#include <cstddef>

namespace cellbench::estimator {

// Currents with a magnitude below this count as a rest where a phase must be named (segmentation, reports).
inline constexpr double kRestCurrentA = 0.01;

// R0, R1, tau1 = R1*C1, R2, tau2 = R2*C2 of one current direction.
template <typename T>
struct Rc2Params {
    T r0_ohm, r1_ohm, tau1_s, r2_ohm, tau2_s;
};

// The four RC voltages: pairs 1 and 2 of the discharge and of the charge direction.
template <typename T>
struct RcVoltages {
    T v1_discharge_v{0.0}, v2_discharge_v{0.0}, v1_charge_v{0.0}, v2_charge_v{0.0};
    T sum() const { return v1_discharge_v + v2_discharge_v + v1_charge_v + v2_charge_v; }
};

inline double discharge_part(double current_a) { return std::min(current_a, 0.0); }
inline double charge_part(double current_a) { return std::max(current_a, 0.0); }

// One exact ZOH step of an RC pair: state v, resistance r, time constant tau, held current i, step dt.
template <typename T>
inline T rc_zoh_step(const T& v, const T& r_ohm, const T& tau_s, const T& current_a, double dt_s) {
    using std::exp;
    const T decay = exp(-T(dt_s) / tau_s);
    return decay * v + r_ohm * (T(1.0) - decay) * current_a;
}

// Direction of a current for naming phases: +1 charge, -1 discharge; rests keep the previous direction.
inline int current_direction(double current_a, int previous_direction) {
    if (current_a > kRestCurrentA) return +1;
    if (current_a < -kRestCurrentA) return -1;
    return previous_direction;
}

// Ohmic drop R0*I with the resistance of the current's own direction.
template <typename T>
inline T ohmic_drop_v(const Rc2Params<T>& discharge, const Rc2Params<T>& charge, double current_a) {
    return current_a < 0 ? discharge.r0_ohm * T(current_a) : charge.r0_ohm * T(current_a);
}

// Advances the RC voltages over one interval dt_s during which current_a flowed.
template <typename T>
inline void rc_step(RcVoltages<T>& v, const Rc2Params<T>& discharge, const Rc2Params<T>& charge, double current_a,
                    double dt_s) {
    const T id(discharge_part(current_a)), ic(charge_part(current_a));
    v.v1_discharge_v = rc_zoh_step(v.v1_discharge_v, discharge.r1_ohm, discharge.tau1_s, id, dt_s);
    v.v2_discharge_v = rc_zoh_step(v.v2_discharge_v, discharge.r2_ohm, discharge.tau2_s, id, dt_s);
    v.v1_charge_v = rc_zoh_step(v.v1_charge_v, charge.r1_ohm, charge.tau1_s, ic, dt_s);
    v.v2_charge_v = rc_zoh_step(v.v2_charge_v, charge.r2_ohm, charge.tau2_s, ic, dt_s);
}

// Overpotential V - OCV of the model over samples [0, n) of a recording, from the RC voltages v0 at sample 0
// (sample 0's own interval is taken as empty).
template <typename T>
void simulate_overpotential(const double* time_s, const double* current_a, std::size_t n,
                            const Rc2Params<T>& discharge, const Rc2Params<T>& charge, RcVoltages<T> v, T* out_v) {
    for (std::size_t k = 0; k < n; ++k) {
        if (k > 0) rc_step(v, discharge, charge, current_a[k], time_s[k] - time_s[k - 1]);
        out_v[k] = ohmic_drop_v(discharge, charge, current_a[k]) + v.sum();
    }
}

}  // namespace cellbench::estimator
