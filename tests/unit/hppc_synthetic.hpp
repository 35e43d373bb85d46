#pragma once
// Synthetic HPPC recordings for the segmentation and pulse-fit tests: a current program of timed steps,
// voltage = OCV(SOC) + the exact ZOH 2RC overpotential of electrical.hpp (simulate_overpotential), plus
// optional Gaussian noise on voltage and current. Sampling convention of electrical.hpp: the current of row
// k flowed during (t[k-1], t[k]].
#include <cmath>
#include <cstddef>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/electrical.hpp"
#include "cellbench/estimator/fit.hpp"

namespace cellbench::test {

struct Step {
    double duration_s;
    double current_a;      // + = charge
    std::string type;      // Step Type label
    double cv_limit_v = 0; // > 0: constant voltage at this limit once reached (current tapers, CCCV)
};

// P45B-like magnitudes (thesis Table 3.2), different for charge and discharge.
inline estimator::Rc2Params<double> p45b_discharge() { return {7.5e-3, 1.5e-3, 2.0, 8.0e-3, 30.0}; }
inline estimator::Rc2Params<double> p45b_charge() { return {7.8e-3, 1.2e-3, 1.5, 10.0e-3, 24.0}; }

inline constexpr double kCapacityAh = 3.82;

// What a user would give `characterize` for this cell when a recording does not measure it (--capacity-ah, and
// thermal values a recording without a heat flux sensor cannot identify).
inline estimator::CharacterizationOptions characterization_options() {
    estimator::CharacterizationOptions o;
    o.fallback_capacity_ah = kCapacityAh;
    o.fallback_c_th_j_per_k = 70.0;
    o.fallback_r_th_k_per_w = 8.0;
    return o;
}

// Smooth, monotone OCV(SOC) of roughly the P45B's shape between 2.9 and 4.1 V.
inline double synthetic_ocv(double soc) { return 3.25 + 0.80 * soc + 0.06 * std::tanh((soc - 0.1) * 12.0); }
inline double synthetic_docv_dsoc(double soc) {
    const double c = std::cosh((soc - 0.1) * 12.0);
    return 0.80 + 0.06 * 12.0 / (c * c);
}

struct SyntheticOptions {
    double dt_s = 0.1;
    double voltage_noise_v = 0.0;
    double current_noise_a = 0.0;
    double soc0 = 1.0;
    unsigned seed = 1;
    bool flat_ocv = false;  // OCV constant at synthetic_ocv(soc0) (the thesis' segment equations assume it)
    estimator::Rc2Params<double> discharge = p45b_discharge();
    estimator::Rc2Params<double> charge = p45b_charge();
};

// Simulates a step program. CV steps are simulated by bisection on the current at each row so that the
// terminal voltage stays at the limit (current tapers), the way a CCCV step of a cycler does.
// A few hand-written rows, one second apart (the row-rule tests of stale_current.hpp and voltage_spikes.hpp).
inline Recording rows_one_second_apart(const std::vector<double>& current_a, const std::vector<double>& voltage_v) {
    Recording r;
    r.source = "rows";
    for (std::size_t k = 0; k < current_a.size(); ++k) r.time_s.push_back(static_cast<double>(k));
    r.current_a = current_a;
    r.voltage_v = voltage_v;
    return r;
}

inline Recording synthesize(const std::vector<Step>& program, const SyntheticOptions& o = {}) {
    Recording rec;
    rec.source = "synthetic";
    std::mt19937 rng(o.seed);
    std::normal_distribution<double> vn(0.0, o.voltage_noise_v > 0 ? o.voltage_noise_v : 1.0);
    std::normal_distribution<double> in(0.0, o.current_noise_a > 0 ? o.current_noise_a : 1.0);
    double soc = o.soc0, t = 0;
    estimator::RcVoltages<double> rc;
    // The model of electrical.hpp: each direction's RC pairs driven by its own part of the current.
    auto step_model = [&](double i, double dt, estimator::RcVoltages<double>& nrc, double& nsoc) {
        nrc = rc;
        estimator::rc_step(nrc, o.discharge, o.charge, i, dt);
        nsoc = soc + i * dt / 3600.0 / kCapacityAh;
        return (o.flat_ocv ? synthetic_ocv(o.soc0) : synthetic_ocv(nsoc)) +
               estimator::ohmic_drop_v(o.discharge, o.charge, i) + nrc.sum();
    };
    // Row 0: rest state.
    auto push = [&](double time, double v, double i, const std::string& type) {
        rec.time_s.push_back(time);
        rec.voltage_v.push_back(v + (o.voltage_noise_v > 0 ? vn(rng) : 0.0));
        rec.current_a.push_back(i + (o.current_noise_a > 0 ? in(rng) : 0.0));
        rec.step_type.push_back(type);
        rec.step_count.push_back(0);
    };
    push(0.0, synthetic_ocv(soc), 0.0, program.empty() ? "Rest" : program.front().type);
    double step_no = 1;
    for (const Step& s : program) {
        const auto rows = static_cast<std::size_t>(std::llround(s.duration_s / o.dt_s));
        for (std::size_t r = 0; r < rows; ++r) {
            t += o.dt_s;
            double i = s.current_a, nsoc;
            estimator::RcVoltages<double> nrc;
            double v = step_model(i, o.dt_s, nrc, nsoc);
            if (s.cv_limit_v > 0 && ((s.current_a > 0 && v > s.cv_limit_v) || (s.current_a < 0 && v < s.cv_limit_v))) {
                double lo = 0, hi = s.current_a;  // bisection on the current magnitude
                for (int it = 0; it < 60; ++it) {
                    const double mid = 0.5 * (lo + hi);
                    const double vm = step_model(mid, o.dt_s, nrc, nsoc);
                    if ((s.current_a > 0) == (vm > s.cv_limit_v)) hi = mid; else lo = mid;
                }
                i = lo;
                v = step_model(i, o.dt_s, nrc, nsoc);
            }
            rc = nrc;
            soc = nsoc;
            push(t, v, i, s.type);
            rec.step_count.back() = step_no;
        }
        step_no += 1;
    }
    rec.pad_optional_channels();
    return rec;
}

// One pulse set of Table 2.12 (30 s discharge, 40 s rest, 10 s charge, 40 s rest), preceded by a rest.
inline std::vector<Step> pulse_set_program(double rest_s = 700.0, double current_a = 4.5) {
    return {{rest_s, 0.0, "Rest"},
            {30.0, -current_a, "CCCV DChg"},
            {40.0, 0.0, "Rest"},
            {10.0, current_a, "CCCV Chg"},
            {40.0, 0.0, "Rest"}};
}

// Multi-SOC HPPC from soc0 down by 10 % steps: n_sets pulse sets, each followed by a 10 % CC discharge.
inline std::vector<Step> hppc_program(std::size_t n_sets, double rest_s = 700.0, double current_a = 4.5) {
    std::vector<Step> p;
    for (std::size_t j = 0; j < n_sets; ++j) {
        for (const auto& s : pulse_set_program(rest_s, current_a)) p.push_back(s);
        // Drain 10 % of the capacity net of the pulses (eq. 2.4): 0.1*C - 30 s*I + 10 s*I.
        const double ah = 0.1 * kCapacityAh - 30.0 * current_a / 3600.0 + 10.0 * current_a / 3600.0;
        p.push_back({std::round(ah / current_a * 3600.0 * 10.0) / 10.0, -current_a, "CC DChg"});
    }
    p.push_back({rest_s, 0.0, "Rest"});
    return p;
}

}  // namespace cellbench::test
