// The simulated cycler around the continuous-time cell: each program step is integrated piecewise (a new ODE
// segment at every current breakpoint and at every CC -> CV switch), with Boost.Odeint's dense-output
// Dormand-Prince 5(4); step ends (time, voltage cut-off, CV current taper, Ah limit) are located by bisection on
// the dense output, and samples are taken from it at the logging instants.
#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

#include <boost/numeric/odeint.hpp>

#include "cellbench/plant/plant.hpp"
#include "rng.hpp"

namespace cellbench::plant {

namespace {

namespace odeint = boost::numeric::odeint;

// State: soc, v1, v2, T_core, T_can, T_sensor, h_fast, h_slow, v3, v4, heat generated (J), heat out (J).
enum : std::size_t { kSoc, kV1, kV2, kTc, kTcan, kTs, kHf, kHs, kV3, kV4, kQgen, kQout, kN };
using State = std::array<double, kN>;

constexpr double kKelvin = 273.15;

enum class Phase { rest, cc, cv };

struct Plant {
    const CellSpec& c;
    bool bench;
    double capacity_as;  // A·s

    double ambient_c(double t) const {
        double a = c.reference_temperature_c;
        if (bench) {
            a += c.bench.ambient_drift_k_per_h * t / 3600.0;
            if (c.bench.ambient_ripple_k != 0.0)
                a += c.bench.ambient_ripple_k * std::sin(2.0 * std::numbers::pi * t / c.bench.ambient_ripple_period_s);
        }
        return a;
    }
    double series_ohm() const { return bench ? c.bench.series_resistance_ohm : 0.0; }

    // Everything but the current term of the terminal voltage.
    double emf_v(const State& x) const {
        double e = c.ocv_v(x[kSoc], x[kTc]) + x[kV1] + x[kV2];
        if (c.extra_rc.enabled) e += x[kV3] + x[kV4];
        if (c.hysteresis.enabled) e += x[kHf] + x[kHs];
        return e;
    }
    double r0_internal(const State& x, Direction d) const { return c.r0_ohm(x[kSoc], d) * c.resistance_factor(x[kTc]); }

    double current_a(const State& x, Phase phase, double set_a, double cv_v, Direction d) const {
        switch (phase) {
            case Phase::rest: return 0.0;
            case Phase::cc: return set_a;
            case Phase::cv: {  // the current holding the voltage, never beyond the set value nor reversed
                const double i = (cv_v - emf_v(x)) / (r0_internal(x, d) + series_ohm());
                return set_a >= 0.0 ? std::clamp(i, 0.0, set_a) : std::clamp(i, set_a, 0.0);
            }
        }
        return 0.0;
    }
    double terminal_v(const State& x, double i, Direction d) const {
        return emf_v(x) + i * (r0_internal(x, d) + series_ohm());
    }

    void rhs(const State& x, State& dx, double t, double i, Direction d) const {
        const double s = x[kSoc];
        const double rf = c.resistance_factor(x[kTc]);
        dx.fill(0.0);
        dx[kSoc] = i / capacity_as;
        const double tau1 = c.tau1_s(s, d), tau2 = c.tau2_s(s, d);
        const double drive1 = c.current_dependence.enabled
                                  ? c.current_dependence.saturation_current_a * std::tanh(i / c.current_dependence.saturation_current_a)
                                  : i;
        dx[kV1] = (-x[kV1] + c.r1_ohm(s, d) * rf * drive1) / tau1;
        dx[kV2] = (-x[kV2] + c.r2_ohm(s, d) * rf * i) / tau2;
        double polarization = x[kV1] + x[kV2];
        if (c.extra_rc.enabled) {
            dx[kV3] = (-x[kV3] + c.extra_rc.r3_ohm * rf * i) / c.extra_rc.tau3_s;
            dx[kV4] = (-x[kV4] + c.extra_rc.r4_ohm * rf * i) / c.extra_rc.tau4_s;
            polarization += x[kV3] + x[kV4];
        }
        if (c.hysteresis.enabled) {
            const auto& h = c.hysteresis;
            const double w = 1.0 + h.low_soc_gain * std::exp(-std::clamp(s, 0.0, 1.0) / 0.15);
            const double sgn = i > 0.0 ? 1.0 : (i < 0.0 ? -1.0 : 0.0);
            const double rate = std::abs(i) / capacity_as;
            dx[kHf] = rate / h.eps_fast * (sgn * h.m_fast_v * w - x[kHf]);
            dx[kHs] = rate / h.eps_slow * (sgn * h.m_slow_v * w - x[kHs]);
            polarization += x[kHf] + x[kHs];
        }
        // Heat: irreversible I·(V_int - OCV) (V_int without the external series resistance), reversible I·T·dU/dT.
        const double q_gen = i * (i * c.r0_ohm(s, d) * rf + polarization) + i * (x[kTc] + kKelvin) * c.entropic_v_per_k(s);
        const double ta = ambient_c(t);
        dx[kQgen] = q_gen;
        if (c.thermal3.enabled) {
            const auto& th = c.thermal3;
            const double q_cc = (x[kTc] - x[kTcan]) / th.r_core_can_k_per_w;
            const double q_out = (x[kTcan] - ta) / c.r_th_k_per_w;
            dx[kTc] = (q_gen - q_cc) / (th.core_fraction * c.c_th_j_per_k);
            dx[kTcan] = (q_cc - q_out) / ((1.0 - th.core_fraction) * c.c_th_j_per_k);
            dx[kTs] = (x[kTcan] - x[kTs]) / th.sensor_time_constant_s;
            dx[kQout] = q_out;
        } else {
            const double q_out = (x[kTc] - ta) / c.r_th_k_per_w;
            dx[kTc] = (q_gen - q_out) / c.c_th_j_per_k;
            dx[kQout] = q_out;
        }
    }
    double surface_c(const State& x) const { return c.thermal3.enabled ? x[kTs] : x[kTc]; }
    double heat_out_w(const State& x, double t) const {
        return ((c.thermal3.enabled ? x[kTcan] : x[kTc]) - ambient_c(t)) / c.r_th_k_per_w;
    }
};

struct Sample {
    double t, v, i, soc, ocv, core, surface, ambient, flux, qgen, qout;
    int step;
};

double quantize(double x, int decimals) {
    const double scale = std::pow(10.0, decimals);
    return static_cast<double>(std::llround(x * scale)) / scale;  // k / 10^d: the double nearest the decimal
}

}  // namespace

Recording simulate(const CellSpec& cell, const Program& program, const InitialState& initial, bool bench_effects,
                   std::uint64_t noise_seed, bool noise, std::string name) {
    const double capacity_ah = cell.capacity_ah * (bench_effects ? cell.bench.capacity_scale : 1.0);
    Plant plant{cell, bench_effects, capacity_ah * 3600.0};

    State x{};
    x[kSoc] = initial.soc;
    x[kTc] = x[kTcan] = x[kTs] = plant.ambient_c(0.0);
    if (cell.hysteresis.enabled) {  // settled on the branch of the last current direction
        const double sgn = initial.charged_last ? 1.0 : -1.0;
        const double w = 1.0 + cell.hysteresis.low_soc_gain * std::exp(-initial.soc / 0.15);
        x[kHf] = sgn * cell.hysteresis.m_fast_v * w;
        x[kHs] = sgn * cell.hysteresis.m_slow_v * w;
    }
    Direction last_dir = initial.charged_last ? Direction::charge : Direction::discharge;

    Recording rec;
    rec.name = std::move(name);
    rec.initial_soc = initial.soc;
    rec.unix_start_s = 1767225600.0 + static_cast<double>(cell.seed % 1000) * 86400.0;
    std::vector<Sample> samples;
    std::vector<std::string> step_types;  // by step count - 1

    double t = 0.0;
    std::size_t index = 0;
    std::size_t tail = program.size();
    for (std::size_t k = 0; k < program.size(); ++k)
        if (program[k].tail) {
            tail = k;
            break;
        }

    while (index < program.size()) {
        const Step& step = program[index];
        const int count = static_cast<int>(rec.steps.size()) + 1;
        step_types.push_back(step.type);
        const Direction dir = step.mode == Mode::rest || step.current_a == 0.0
                                  ? last_dir
                                  : (step.current_a > 0.0 ? Direction::charge : Direction::discharge);
        const bool charging = dir == Direction::charge;
        const double dt_sample = step.fine_sampling ? cell.measurement.sample_s : cell.measurement.coarse_sample_s;
        const double t0 = t, t_limit = t0 + step.duration_s;
        const double ah_limit = step.ah_limit ? step.ah_limit(rec.steps) : kInf;
        const double soc0 = x[kSoc];
        Phase phase = step.mode == Mode::rest ? Phase::rest : Phase::cc;
        const double cv_v = step.voltage_limit_v;
        StepResult result{count, step.type, t0, t0, 0.0, "", false};

        auto current = [&](const State& s, Phase p) { return plant.current_a(s, p, step.current_a, cv_v, dir); };
        // Event functions: >= 0 when the condition is met.
        auto voltage_event = [&](const State& s, Phase p) {
            if (p != Phase::cc || std::isnan(cv_v)) return -1.0;
            const double v = plant.terminal_v(s, current(s, p), dir);
            return charging ? v - cv_v : cv_v - v;
        };
        auto taper_event = [&](const State& s, Phase p) {
            if (p != Phase::cv || step.cutoff_current_a <= 0.0) return -1.0;
            return step.cutoff_current_a - std::abs(current(s, p));
        };
        auto ah_event = [&](const State& s) { return std::abs(s[kSoc] - soc0) * capacity_ah - ah_limit; };

        std::size_t k_sample = 0;
        auto emit_until = [&](double t_stop, auto&& state_at, Phase p) {
            while (true) {
                const double ts = t0 + static_cast<double>(k_sample) * dt_sample;
                if (!(ts < t_stop)) break;
                State s = state_at(ts);
                const double i = current(s, p);
                samples.push_back({ts, plant.terminal_v(s, i, dir), i, s[kSoc], cell.ocv_v(s[kSoc], s[kTc]), s[kTc],
                                   plant.surface_c(s), plant.ambient_c(ts), plant.heat_out_w(s, ts) / cell.area_m2,
                                   s[kQgen], s[kQout], count});
                ++k_sample;
            }
        };

        // Immediate conditions at the step start.
        std::string reason;
        if (step.duration_s <= 0.0) reason = "time";
        if (reason.empty() && ah_event(x) >= 0.0) reason = "ah";
        if (reason.empty() && voltage_event(x, phase) >= 0.0) {
            if (step.mode == Mode::cccv) {
                phase = Phase::cv;
                result.reached_cv = true;
            } else {
                reason = "voltage";
            }
        }
        if (reason.empty() && taper_event(x, phase) >= 0.0) reason = "current";

        while (reason.empty()) {  // one ODE segment per phase
            const Phase p = phase;
            auto sys = [&](const State& s, State& ds, double tt) { plant.rhs(s, ds, tt, current(s, p), dir); };
            auto stepper = odeint::make_dense_output(1e-10, 1e-10, odeint::runge_kutta_dopri5<State>());
            stepper.initialize(x, t, 1e-3);
            bool switched = false;
            while (true) {
                const auto [ta, tb] = stepper.do_step(sys);
                auto state_at = [&](double tt) {
                    State s;
                    stepper.calc_state(tt, s);
                    return s;
                };
                // Earliest event in (ta, tb].
                double t_stop = kInf;
                std::string why;
                auto locate = [&](auto&& g, const char* name) {
                    if (g(stepper.current_state()) < 0.0) return;
                    double lo = ta, hi = tb;
                    for (int it = 0; it < 80 && hi - lo > 1e-9; ++it) {
                        const double mid = 0.5 * (lo + hi);
                        (g(state_at(mid)) >= 0.0 ? hi : lo) = mid;
                    }
                    if (hi < t_stop) {
                        t_stop = hi;
                        why = name;
                    }
                };
                if (tb >= t_limit) {
                    t_stop = t_limit;
                    why = "time";
                }
                locate([&](const State& s) { return voltage_event(s, p); }, "voltage");
                locate([&](const State& s) { return taper_event(s, p); }, "current");
                locate([&](const State& s) { return ah_event(s); }, "ah");
                if (why.empty()) {
                    emit_until(tb, state_at, p);
                    continue;
                }
                const bool ends_step = !(why == "voltage" && step.mode == Mode::cccv);
                emit_until(ends_step ? t_stop - 1e-3 : t_stop, state_at, p);
                x = state_at(t_stop);
                t = t_stop;
                if (ends_step) {
                    reason = why;
                } else {
                    phase = Phase::cv;
                    result.reached_cv = true;
                    switched = true;
                }
                break;
            }
            if (switched) continue;
        }
        result.end_s = t;
        result.ah = (x[kSoc] - soc0) * capacity_ah;
        result.end_reason = reason;
        rec.steps.push_back(result);
        if (step.mode != Mode::rest && step.current_a != 0.0) last_dir = dir;

        if (step.end_loop_on_cutoff && (reason == "voltage" || result.reached_cv) && index < tail)
            index = tail;
        else
            ++index;
    }

    // Measurement: noise, then quantization.
    Rng rng(noise_seed, 7);
    const Measurement& m = cell.measurement;
    const std::size_t n = samples.size();
    for (auto* v : {&rec.time_s, &rec.voltage_v, &rec.current_a, &rec.ambient_c, &rec.surface_c, &rec.heat_flux_w_per_m2,
                    &rec.true_voltage_v, &rec.true_current_a, &rec.true_soc, &rec.true_ocv_v, &rec.true_core_c,
                    &rec.true_surface_c, &rec.true_ambient_c, &rec.true_heat_flux_w_per_m2, &rec.true_heat_generated_j,
                    &rec.true_heat_out_j})
        v->reserve(n);
    rec.step_count.reserve(n);
    rec.step_type.reserve(n);
    const double gain = bench_effects ? cell.bench.heat_flux_gain : 1.0;
    const double offset = bench_effects ? cell.bench.heat_flux_offset_w_per_m2 : 0.0;
    for (const Sample& s : samples) {
        const double nv = noise ? rng.normal() : 0.0, ni = noise ? rng.normal() : 0.0, nt = noise ? rng.normal() : 0.0,
                     na = noise ? rng.normal() : 0.0, nq = noise ? rng.normal() : 0.0;
        const double ambient_reported = cell.reference_temperature_c;  // the chamber's set point / its own sensor
        rec.time_s.push_back(quantize(s.t, 3));
        if (noise) {
            rec.voltage_v.push_back(quantize(s.v + m.voltage_noise_v * nv, m.voltage_decimals));
            rec.current_a.push_back(s.i == 0.0 ? 0.0 : quantize(s.i + m.current_noise_a * ni, m.current_decimals));
            rec.surface_c.push_back(quantize(s.surface + m.temperature_noise_c * nt, m.temperature_decimals));
            rec.ambient_c.push_back(quantize(ambient_reported + m.temperature_noise_c * na, m.temperature_decimals));
            rec.heat_flux_w_per_m2.push_back(
                quantize(gain * s.flux + offset + m.heat_flux_noise_w_per_m2 * nq, m.heat_flux_decimals));
        } else {
            rec.voltage_v.push_back(s.v);
            rec.current_a.push_back(s.i);
            rec.surface_c.push_back(s.surface);
            rec.ambient_c.push_back(ambient_reported);
            rec.heat_flux_w_per_m2.push_back(gain * s.flux + offset);
        }
        rec.step_count.push_back(s.step);
        rec.step_type.push_back(step_types[static_cast<std::size_t>(s.step - 1)]);
        rec.true_voltage_v.push_back(s.v);
        rec.true_current_a.push_back(s.i);
        rec.true_soc.push_back(s.soc);
        rec.true_ocv_v.push_back(s.ocv);
        rec.true_core_c.push_back(s.core);
        rec.true_surface_c.push_back(s.surface);
        rec.true_ambient_c.push_back(s.ambient);
        rec.true_heat_flux_w_per_m2.push_back(s.flux);
        rec.true_heat_generated_j.push_back(s.qgen);
        rec.true_heat_out_j.push_back(s.qout);
    }
    return rec;
}

}  // namespace cellbench::plant
