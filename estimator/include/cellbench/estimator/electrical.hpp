#pragma once
// Exact zero-order-hold (ZOH) discretization of the Thevenin 2RC electrical model.
//
// Sign convention: current I is positive when charging (BDF). Terminal voltage
//     V = OCV(SOC) + R0*I + v1 + v2,      dv_k/dt = -v_k/(R_k*C_k) + I/C_k
// so under a constant current each v_k tends to R_k*I.
//
// Sampling convention (shared by the model, the simulator and every fitter): the current recorded at sample
// k is the current that flowed during (t[k-1], t[k]] and is held constant over that interval. The exact
// solution of the linear ODE over an interval of length dt with constant I is
//     v_k(t+dt) = exp(-dt/tau_k) * v_k(t) + R_k * (1 - exp(-dt/tau_k)) * I
// whatever dt is; nothing here is an Euler step.
//
// These templates work with double and with ceres::Jet (automatic differentiation).
#include <cmath>
#include <cstddef>

namespace cellbench::estimator {

// Currents with a magnitude below this are a rest (the direction of the last current is kept).
inline constexpr double kRestCurrentA = 0.01;

// R0, R1, tau1 = R1*C1, R2, tau2 = R2*C2 of one current direction.
template <typename T>
struct Rc2Params {
    T r0_ohm, r1_ohm, tau1_s, r2_ohm, tau2_s;
};

// One exact ZOH step of an RC pair: state v, resistance r, time constant tau, held current i, step dt.
template <typename T>
inline T rc_zoh_step(const T& v, const T& r_ohm, const T& tau_s, const T& current_a, double dt_s) {
    using std::exp;
    const T decay = exp(-T(dt_s) / tau_s);
    return decay * v + r_ohm * (T(1.0) - decay) * current_a;
}

// Direction tracker: +1 charge, -1 discharge; rests keep the previous direction.
inline int current_direction(double current_a, int previous_direction) {
    if (current_a > kRestCurrentA) return +1;
    if (current_a < -kRestCurrentA) return -1;
    return previous_direction;
}

// Overpotential V - OCV of the 2RC model over samples [0, n) of a recording, with separate parameters for
// discharge and charge (the rest after a current keeps that current's parameters). v1_0 and v2_0 are the RC
// voltages at sample 0 (before sample 0's own current is applied: sample 0's interval is taken as empty).
// direction_0 is the direction in force before sample 0.
template <typename T>
void simulate_overpotential(const double* time_s, const double* current_a, std::size_t n,
                            const Rc2Params<T>& discharge, const Rc2Params<T>& charge, T v1, T v2,
                            int direction_0, T* out_v) {
    int dir = direction_0;
    for (std::size_t k = 0; k < n; ++k) {
        dir = current_direction(current_a[k], dir);
        const Rc2Params<T>& p = dir > 0 ? charge : discharge;
        const T i = T(current_a[k]);
        if (k > 0) {
            const double dt = time_s[k] - time_s[k - 1];
            v1 = rc_zoh_step(v1, p.r1_ohm, p.tau1_s, i, dt);
            v2 = rc_zoh_step(v2, p.r2_ohm, p.tau2_s, i, dt);
        }
        out_v[k] = p.r0_ohm * i + v1 + v2;
    }
}

}  // namespace cellbench::estimator
