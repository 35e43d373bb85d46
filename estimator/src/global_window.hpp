#pragma once
// The global fit's window model (internal to the estimator): the knot grid, a window's ticks, one window's
// simulation for doubles and Jets (simulate_window), and the window cost whose Jacobian the fit uses
// (window_jacobian, global_window_jacobian.cpp). global_fit.cpp builds the windows and the problem around them.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <memory>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/electrical.hpp"
#include "cellbench/estimator/plausibility.hpp"

#include "median.hpp"

namespace ceres {
class CostFunction;
}

namespace cellbench::estimator::global_window {

constexpr double kGasConstantJPerMolK = 8.314462618;
constexpr int kKnotSize = 10;        // 5 log-parameters per direction (the OCV has its own finer grid)
constexpr double kEaScale = 1e4;

// Physical plausibility (plausibility.hpp): outside these a value is flagged; the search range is twice as wide.
constexpr double kRMinOhm = kPlausibleRMinOhm, kRMaxOhm = kPlausibleRMaxOhm;
constexpr double kTau1MinS = kPlausibleTau1MinS, kTau1MaxS = kPlausibleTau1MaxS;
constexpr double kTau2MinS = kPlausibleTau2MinS, kTau2MaxS = kPlausibleTau2MaxS;
// The slow pair's search range: from a resistance that changes nothing (its lower bound means "no slow pair") and
// from five minutes (slower than the pulses' pairs, which a long rest's relaxation follows) to three hours, and
// never beyond the longest rest (Grid::slow_tau_max_s): a relaxation slower than every rest is a drift within
// them, which the OCV and the capacity explain as well.
constexpr double kSlowRMinOhm = 1e-6;
constexpr double kSlowTauMinS = 300.0, kSlowTauMaxS = 10800.0;

inline double scalar(double x) { return x; }
template <typename J>
double scalar(const J& x) { return x.a; }

// asinh(x)/x for x >= 0 (ceres' Jet has no asinh), 1 at x = 0.
template <typename T>
T asinh_ratio(const T& x) {
    using std::log;
    using std::sqrt;
    if (scalar(x) < 1e-4) return T(1.0) - x * x / 6.0;
    return log(x + sqrt(x * x + 1.0)) / x;
}

// Writes one direction's five knot variables (log R0, log R1, log tau1, log R2, log(tau2/tau1 - 1): tau2 > tau1
// by construction) from a start in SI units: resistances clamped to their plausible range, tau1 to 0.2-20 s and
// tau2 to at least three tau1 (a start the search can move both ways from).
inline void encode_start(double* x, double r0_ohm, double r1_ohm, double tau1_s, double r2_ohm, double tau2_s) {
    const double t1 = std::clamp(tau1_s, 0.2, 20.0), t2 = std::clamp(tau2_s, 3 * t1, 2000.0);
    x[0] = std::log(std::clamp(r0_ohm, kRMinOhm, kRMaxOhm));
    x[1] = std::log(std::clamp(r1_ohm, kRMinOhm, kRMaxOhm));
    x[2] = std::log(t1);
    x[3] = std::log(std::clamp(r2_ohm, kRMinOhm, kRMaxOhm));
    x[4] = std::log(t2 / t1 - 1.0);
}

// One tick of a window: the merged rows (t0, t1] with the mean current held, and the voltage measured at t1.
struct Tick {
    double dt_s = 0, current_a = 0;     // mean of the currents its rows report
    double current_before_a = 0;        // a step tick: the current the row before it reports
    bool step = false;                  // one sample interval across which the current steps
    double soc_start = 0, soc_end = 0;  // Coulomb-counted (before a window's fitted offset)
    double temperature_c = 0;
    double voltage_v = kNaN;            // NaN: no residual
    bool fitted = true;                 // its voltage is a residual (false: thinned out, see make_ticks' caller)
    [[nodiscard]] bool has_residual() const { return fitted && std::isfinite(voltage_v); }
};

struct WindowData {
    std::vector<Tick> ticks;
    int knot_lo = 0, knot_hi = 0;  // table indices the window touches
    int ocv_lo = 0, ocv_hi = 0;    // OCV-grid indices the window touches
    bool fit_offset = false;
    bool low_rate = false;  // mean |I| of its current below C/5
    // Only a slow discharge (below C/5, typically an OCV test from another day) gets its own charge scale: at
    // higher rates what looks like less capacity is polarization, which the model must explain itself.
    [[nodiscard]] bool capacity_scale_free() const { return fit_offset && low_rate; }
    std::size_t residuals = 0;       // one per tick with a measured voltage: (V_model - V) / sigma_v
    std::size_t step_residuals = 0;  // one per current step between two measured voltages (see simulate_window)
    // Whether tick k is such a step: the current steps across it, it is fitted, and both its voltage and the one
    // before are measured.
    [[nodiscard]] bool has_step_residual(std::size_t k) const {
        return k > 0 && k < ticks.size() && ticks[k].step && ticks[k].has_residual() &&
               std::isfinite(ticks[k - 1].voltage_v);
    }
    double step_sigma_v = 1e-3;      // the measurement noise of a voltage difference across one sample interval
};

// The knot grid and the model options shared by every cost function. Knots at any increasing SOC (the test's
// levels need not be evenly spaced: 5 % steps at the ends, 10 % in the middle); the OCV grid divides every knot
// interval into m equal parts.
struct Grid {
    std::vector<double> knot;  // knot SOCs, increasing
    int n = 0;                 // knots
    int m = 1;                 // OCV knots per knot interval
    double ref_ds = 0.1;       // the typical knot spacing: the unit of the smoothness penalties
    double t_ref_k = 298.15;
    double i_ref_a = 1.0;
    bool temperature = false, current = false;
    bool slow = false;  // a third, SOC-independent pair (extra_rc) for the relaxation the long rests show
    double slow_tau_max_s = kSlowTauMaxS;  // its time constant's upper bound: the longest rest
    double sigma_v = 1e-3;
    void set_knots(std::vector<double> k) {
        knot = std::move(k);
        n = static_cast<int>(knot.size());
        std::vector<double> gaps;
        for (int j = 1; j < n; ++j) gaps.push_back(knot[j] - knot[j - 1]);
        ref_ds = upper_median(std::move(gaps));
    }
    [[nodiscard]] double soc(int j) const { return knot[j]; }
    [[nodiscard]] double width(int k) const { return k + 1 < n ? knot[k + 1] - knot[k] : ref_ds; }
    // The knot interval [k, k + 1] holding s (clamped to the table: k in [0, n - 2]).
    [[nodiscard]] int interval(double s) const {
        const auto it = std::upper_bound(knot.begin(), knot.end(), s);
        return std::clamp(static_cast<int>(it - knot.begin()) - 1, 0, n - 2);
    }
    // The first knot at or above s (n - 1 beyond the table).
    [[nodiscard]] int knot_at_or_above(double s) const {
        const auto it = std::lower_bound(knot.begin(), knot.end(), s - 1e-12);
        return std::min(static_cast<int>(it - knot.begin()), n - 1);
    }
    // OCV knots below the first knot: a stretch the data reach below the lowest level that is too short for a knot
    // of the tables (a discharge to the cut-off), where no pulse identifies the pairs (held at the first knot's
    // values, as outside the table) but the OCV bends hardest (see fit_global).
    int ocv_prefix = 0;
    double ocv_prefix_soc = 0.0;
    [[nodiscard]] int ocv_n() const { return ocv_prefix + (n - 1) * m + 1; }
    [[nodiscard]] double ocv_soc(int j) const {
        if (j < ocv_prefix) return ocv_prefix_soc;
        j -= ocv_prefix;
        const int k = std::min(j / m, n - 2);
        return knot[k] + (knot[k + 1] - knot[k]) * static_cast<double>(j - k * m) / m;
    }
    // OCV knot j sits on a knot of the tables (else between two, or below the first).
    [[nodiscard]] bool ocv_on_knot(int j) const { return j >= ocv_prefix && (j - ocv_prefix) % m == 0; }
    // The knot interval [k, k + 1] and the weight within it where OCV knot j lies (k = 0, weight 0 below the table).
    [[nodiscard]] std::pair<int, double> ocv_knot_position(int j) const {
        if (j < ocv_prefix) return {0, 0.0};
        j -= ocv_prefix;
        const int k = std::min(j / m, n - 1);
        return {k, static_cast<double>(j - k * m) / m};
    }
    [[nodiscard]] double ocv_width(int j) const { return j + 1 < ocv_n() ? ocv_soc(j + 1) - ocv_soc(j) : ref_ds / m; }
    // The OCV interval [j, j + 1] holding s (clamped: j in [0, ocv_n() - 2]).
    [[nodiscard]] int ocv_interval(double s) const {
        if (ocv_prefix > 0 && s < knot[0]) return 0;
        const int k = interval(s);
        const int r = std::clamp(static_cast<int>(std::floor((s - knot[k]) / width(k) * m)), 0, m - 1);
        return std::clamp(ocv_prefix + k * m + r, 0, ocv_n() - 2);
    }
    [[nodiscard]] int ocv_at_or_above(double s) const {
        int j = ocv_interval(s);
        while (j < ocv_n() - 1 && ocv_soc(j) < s - 1e-12) ++j;
        return j;
    }
    [[nodiscard]] int ocv_nearest(double s) const {
        const int j = ocv_interval(s);
        return std::abs(s - ocv_soc(j)) <= std::abs(ocv_soc(j + 1) - s) ? j : j + 1;
    }
};

template <typename T>
struct KnotValues {
    T r0d, r1d, c1d, r2d, c2d, r0c, r1c, c1c, r2c, c2c;
};

template <typename T>
KnotValues<T> knot_values(const T* p) {
    using std::exp;
    const T t1d = exp(p[2]), t2d = t1d * (1.0 + exp(p[4]));
    const T t1c = exp(p[7]), t2c = t1c * (1.0 + exp(p[9]));
    const T r1d = exp(p[1]), r2d = exp(p[3]), r1c = exp(p[6]), r2c = exp(p[8]);
    return {exp(p[0]), r1d, t1d / r1d, r2d, t2d / r2d, exp(p[5]), r1c, t1c / r1c, r2c, t2c / r2c};
}

// One exact ZOH step of an RC pair over a span that may itself be a parameter.
template <typename T>
T rc_step(const T& v, const T& r_ohm, const T& tau_s, const T& current_a, const T& dt_s) {
    using std::exp;
    const T decay = exp(-dt_s / tau_s);
    return decay * v + r_ohm * (T(1.0) - decay) * current_a;
}

// What a plain (double) pass of a window records at the start of every tick, so that a derivative pass can start
// there and read the same intervals (WindowJacobian): the RC voltages, the residual counters, and the knot and OCV
// intervals the tick reads.
struct PassTrace {
    std::vector<std::array<double, 5>> state;  // v1d, v2d, v1c, v2c, v3
    std::vector<std::size_t> r, rs;             // tick and step residual counters
    std::vector<int> knot, ocv;                 // the knot interval [knot, knot + 1] and the OCV interval read
};

// Simulates one window; writes (V_model - V_measured) / sigma for every tick with a measured voltage.
// knots[j] for j in [knot_lo, knot_hi] (absolute table indices), ocv[j] the OCV knots [ocv_lo, ocv_hi],
// global = {Ea/1e4, log I0}, slow = {log R3, log tau3} (used when g.slow). With `trace`, records every tick's
// start (the plain pass of WindowJacobian).
template <typename T>
void simulate_window(const Grid& g, const WindowData& w, const KnotValues<T>* kv, T const* const* ocv_knots,
                     const T* ea_scaled, const T* log_i0, const T* step_lag, const T* slow, const T* offset,
                     T* residuals, double* model_v = nullptr, PassTrace* trace = nullptr) {
    using std::exp;
    const int lo = w.knot_lo, hi = w.knot_hi;
    // Linear interpolation inside [lo, hi] with hold outside (R, C) or linear extrapolation (OCV) at the
    // table's ends, as ParameterSet does (the window's knot range covers its SOC unless it is a table end).
    auto locate = [&](const T& soc, int& i, T& w_) {
        const int k = std::clamp(g.interval(scalar(soc)), lo, std::max(lo, hi - 1));
        i = k;
        w_ = (soc - g.soc(k)) / g.width(k);
    };
    const T ea = *ea_scaled * kEaScale;
    const T i0 = exp(*log_i0);
    const T ref_ratio = asinh_ratio(T(g.i_ref_a) / (2.0 * i0));
    const T lag = *step_lag;
    T v1d(0.0), v2d(0.0), v1c(0.0), v2c(0.0), v3(0.0);
    const T r3 = g.slow ? exp(slow[0]) : T(0.0), tau3 = g.slow ? exp(slow[1]) : T(1.0);
    std::size_t r = 0;
    // offset = {initial-SOC correction, log of the window's capacity scale}: SOC = s0 + off + g (s - s0)
    const T off = offset ? offset[0] : T(0.0);
    const T gain = offset ? exp(offset[1]) : T(1.0);
    const double s_first = w.ticks.empty() ? 0.0 : w.ticks.front().soc_start;
    T v_prev(0.0);
    std::size_t rs = w.residuals;  // the step residuals follow the tick residuals
    if (trace) {
        const std::size_t n = w.ticks.size();
        trace->state.resize(n), trace->r.resize(n), trace->rs.resize(n), trace->knot.resize(n), trace->ocv.resize(n);
    }
    for (std::size_t k = 0; k < w.ticks.size(); ++k) {
        if (trace) {
            trace->state[k] = {scalar(v1d), scalar(v2d), scalar(v1c), scalar(v2c), scalar(v3)};
            trace->r[k] = r, trace->rs[k] = rs;
        }
        const Tick& tk = w.ticks[k];
        const double i = tk.current_a;
        T soc0 = s_first + off + gain * (tk.soc_start - s_first), soc1 = s_first + off + gain * (tk.soc_end - s_first);
        // R and C at the tick's mid-SOC: the midpoint rule over the tick's span (at its start, a 30 s tick
        // of a 1C discharge, 0.8 % of SOC, read the tables a whole tick early where they bend towards empty: the
        // independent plant's R0 up to 4 % high at 10 % SOC).
        const T socm = 0.5 * (soc0 + soc1);
        int idx;
        T wt;
        locate(socm, idx, wt);
        if (trace) trace->knot[k] = idx;
        // A weight on the tick's knot interval, held at its ends (R, C and R0 are held outside the table).
        auto hold = [&](T x) {
            if (scalar(x) < 0) x = T(0.0);
            if (scalar(x) > 1) x = T(1.0);
            if (lo == hi) x = T(0.0);
            return x;
        };
        const T wr = hold(wt);
        const auto& a = kv[idx - lo];
        const auto& b = kv[std::min(idx + 1, hi) - lo];
        auto lerp = [&](const T& x, const T& y) { return x + wr * (y - x); };
        T f_t(1.0);  // the current factor is applied per sub-step in advance()
        if (g.temperature) f_t = exp(ea / kGasConstantJPerMolK * (1.0 / (tk.temperature_c + kZeroCelsiusK) - 1.0 / g.t_ref_k));
        // R0 where the tick's voltage is read, at its end (on the same knot interval).
        const T w0 = hold((soc1 - g.soc(idx)) / g.width(idx));
        const T r0d = (a.r0d + w0 * (b.r0d - a.r0d)) * f_t, r0c = (a.r0c + w0 * (b.r0c - a.r0c)) * f_t;
        // The RC pairs over a span dt with current ic held (R and C at this tick's SOC and temperature).
        auto advance = [&](double ic_a, const T& dt) {
            T fi(1.0);
            if (g.current) fi = asinh_ratio(T(std::abs(ic_a)) / (2.0 * i0)) / ref_ratio;
            const T fr = f_t * fi;  // C held: tau scales with R
            const T r1d = lerp(a.r1d, b.r1d) * fr, r2d = lerp(a.r2d, b.r2d) * fr;
            const T r1c = lerp(a.r1c, b.r1c) * fr, r2c = lerp(a.r2c, b.r2c) * fr;
            const T t1d = r1d * lerp(a.c1d, b.c1d), t2d = r2d * lerp(a.c2d, b.c2d);
            const T t1c = r1c * lerp(a.c1c, b.c1c), t2c = r2c * lerp(a.c2c, b.c2c);
            const T id(discharge_part(ic_a)), icc(charge_part(ic_a));
            v1d = rc_step(v1d, r1d, t1d, id, dt);
            v2d = rc_step(v2d, r2d, t2d, id, dt);
            v1c = rc_step(v1c, r1c, t1c, icc, dt);
            v2c = rc_step(v2c, r2c, t2c, icc, dt);
            // The slow pair as CellModel applies extra_rc: the whole current, R and tau scaled by temperature only.
            if (g.slow) v3 = rc_step(v3, r3 * f_t, tau3 * f_t, T(ic_a), dt);
        };
        if (tk.step) {
            // The step happened `lag` of the interval before the row that shows it (see make_ticks).
            advance(tk.current_before_a, (1.0 - lag) * tk.dt_s);
            advance(i, lag * tk.dt_s);
        } else if (tk.dt_s > 0) {
            advance(i, T(tk.dt_s));
        }
        // OCV on its own grid, linear with linear extrapolation past the window's first and last OCV knots.
        const int olo = w.ocv_lo, ohi = w.ocv_hi;
        const int jo = std::clamp(g.ocv_interval(scalar(soc1)), olo, std::max(olo, ohi - 1));
        if (trace) trace->ocv[k] = jo;
        T wo = (soc1 - g.ocv_soc(jo)) / g.ocv_width(jo);
        if (olo == ohi) wo = T(0.0);
        const T& oa = *ocv_knots[jo - olo];
        const T ocv = oa + wo * (*ocv_knots[std::min(jo + 1, ohi) - olo] - oa);
        const T v = ocv + (i < 0 ? r0d * i : r0c * i) + v1d + v2d + v1c + v2c + v3;
        if (model_v) model_v[k] = scalar(v);
        if (tk.has_residual()) residuals[r++] = (v - tk.voltage_v) / g.sigma_v;
        // The voltage's jump across a current step, over one sample interval: R0 times the step plus the pairs'
        // movement in that interval. It is measured to the logger's noise, while the tick residuals above also
        // carry the model's structural error (slow diffusion, heating, hysteresis), which is smooth in time and
        // large on long discharges. Weighted by its own noise, the jump keeps R0 what the steps say (thesis
        // eq. 3.2 less the pairs' movement), instead of a compromise R0 that absorbs the slow errors of other windows.
        if (w.has_step_residual(k))
            residuals[rs++] = ((v - v_prev) - (tk.voltage_v - w.ticks[k - 1].voltage_v)) / w.step_sigma_v;
        v_prev = v;
    }
}

struct WindowCost {
    const Grid* grid;
    const WindowData* w;
    template <typename T>
    bool operator()(T const* const* p, T* residuals) const {
        const int nk = w->knot_hi - w->knot_lo + 1, no = w->ocv_hi - w->ocv_lo + 1;
        std::vector<KnotValues<T>> kv;
        kv.reserve(nk);
        for (int j = 0; j < nk; ++j) kv.push_back(knot_values(p[j]));
        const int g = nk + no;
        simulate_window(*grid, *w, kv.data(), p + nk, p[g], p[g + 1], p[g + 2], p[g + 3],
                        w->fit_offset ? p[g + 4] : nullptr, residuals);
        return true;
    }
};

// The cost of window w: its residuals (simulate_window) and their Jacobian by forward sensitivity (see
// global_window_jacobian.cpp). Both pointers must outlive it.
std::unique_ptr<ceres::CostFunction> window_jacobian(const Grid* grid, const WindowData* w);

}  // namespace cellbench::estimator::global_window
