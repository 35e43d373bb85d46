// The global fit's window cost: residuals and Jacobian of one window (global_window.hpp).
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <limits>
#include <memory>
#include <stdexcept>
#include <vector>

#include <ceres/ceres.h>

#include "global_window.hpp"

namespace cellbench::estimator::global_window {

namespace {

// A derivative pass over part of a window. Values that first enter at tick `begin` have no effect before it, so
// the pass starts there from the plain pass's state (derivatives zero); after `direct_last`, the last tick they
// enter directly, they act only through the RC voltages, and the pass stops once those have forgotten them
// (every derivative below kForgottenV). On exit `r` and `rs` are the counters where it stopped.
struct PassRange {
    std::size_t begin = 0, direct_last = 0;
    std::array<double, 5> state{};  // the RC voltages at begin (the previous voltage's derivative starts at zero)
    std::size_t r = 0, rs = 0;
};

// Below this (V per unit of a fitted variable) a derivative passed on through the RC voltages is taken as zero:
// 1e-10 of a residual in units of a 1 mV noise, against entries of order 1 to 1e3.
constexpr double kForgottenV = 1e-13;

// The direct dependence of one of a tick's quantities on the variables of a derivative pass: a short list of
// (lane, partial derivative), duplicates allowed. A tick's quantities each depend directly on a few variables (the
// two knots it interpolates between, the SOC offset, Ea, I0); only the RC voltages carry every lane (dense).
struct Grad {
    // The longest list is a second pair's tau = R C: R from two knots' log R2 and the interpolation weight's four
    // (SOC offset and capacity scale, through the tick's start and end SOC), times the temperature and current
    // factors (2), plus C2 from two knots' three variables each and the weight's four: 18 entries. A longer one is a
    // programming error (logic_error).
    static constexpr int kMax = 24;
    int n = 0;
    std::array<int, kMax> lane{};
    std::array<double, kMax> d{};
    void add(int l, double c) {
        if (l < 0) return;
        if (n == kMax) throw std::logic_error("global fit: a tick's quantity depends on more variables than expected");
        lane[n] = l, d[n] = c, ++n;
    }
    void add(const Grad& o, double s) {
        if (s != 0.0)
            for (int k = 0; k < o.n; ++k) add(o.lane[k], o.d[k] * s);
    }
    template <std::size_t L>
    void scatter(std::array<double, L>& dense, double s) const {
        for (int k = 0; k < n; ++k) dense[lane[k]] += d[k] * s;
    }
};

// x + w (y - x) and its gradient, for values x, y of two knots (gx, gy) and a weight w (gw).
double lerp_grad(double x, double y, const Grad& gx, const Grad& gy, double w, const Grad& gw, Grad& out) {
    out.n = 0;
    out.add(gx, 1.0 - w);
    out.add(gy, w);
    out.add(gw, y - x);
    return x + w * (y - x);
}

// d asinh_ratio(x) / dx (asinh_ratio's two branches).
double asinh_ratio_slope(double x) {
    if (x < 1e-4) return -x / 3.0;
    return (1.0 / std::sqrt(x * x + 1.0) - asinh_ratio(x)) / x;
}

// A window's residuals and their Jacobian, the same as DynamicAutoDiffCostFunction<WindowCost, 12> gives (the
// reference, Builder::reference_cost; GlobalFitOptions::check_jacobian compares them) for a fraction of the work.
// Ceres' dynamic autodiff simulates the whole window once per 12 variables, with every variable's derivative
// carried through every operation of every tick. But a knot's values enter only where the SOC is within one knot
// interval of it, an OCV knot only there, and a slow discharge over the whole SOC range touches every knot (the
// independent plant's C/20 discharge: 13 passes over 2500 ticks, 60 % of the fit). Here a plain pass records each
// tick's state and the intervals it reads; the variables are then grouped, kLanes to a derivative pass, in the order
// they first enter (a knot's two directions apart: a direction enters with its first current), and each pass runs
// from the first tick any of its variables enters to where the RC voltages have forgotten the last (PassRange).
// Before that tick the derivatives are zero exactly; after it they are below kForgottenV. A pass is forward
// sensitivity by hand: only the RC voltages carry a derivative for every lane; a tick's other quantities depend
// directly on a few variables each (Grad), so a tick costs a few multiplications per lane instead of one per lane
// for every operation (with ceres::Jet<double, 12> passes the whole P45B fit took twice the CPU; docs/model.md).
class WindowJacobian final : public ceres::CostFunction {
public:
    // Variables per derivative pass: the P45B fit measured at 12 to 96, flat from 48 (docs/model.md).
    static constexpr int kLanes = 48;
    WindowJacobian(const Grid* grid, const WindowData* w) : grid_(grid), w_(w) {
        auto& sizes = *mutable_parameter_block_sizes();
        for (int j = w->knot_lo; j <= w->knot_hi; ++j) sizes.push_back(kKnotSize);
        for (int j = w->ocv_lo; j <= w->ocv_hi; ++j) sizes.push_back(1);
        for (int size : {1, 1, 1, 2}) sizes.push_back(size);  // Ea, log I0, step lag, slow pair
        if (w->fit_offset) sizes.push_back(2);
        set_num_residuals(static_cast<int>(w->residuals + w->step_residuals));
    }

    bool Evaluate(double const* const* p, double* residuals, double** jacobians) const override {
        const WindowData& w = *w_;
        const int nk = w.knot_hi - w.knot_lo + 1, g = nk + w.ocv_hi - w.ocv_lo + 1;
        std::vector<KnotValues<double>> kv;
        kv.reserve(nk);
        for (int j = 0; j < nk; ++j) kv.push_back(knot_values(p[j]));
        PassTrace trace;
        simulate_window(*grid_, w, kv.data(), p + nk, p[g], p[g + 1], p[g + 2], p[g + 3],
                        w.fit_offset ? p[g + 4] : nullptr, residuals, nullptr, jacobians ? &trace : nullptr);
        if (jacobians) derivative_passes(p, kv, jacobians, trace);
        return true;
    }

private:
    using Dense = std::array<double, kLanes>;
    // The lane of the pass each variable has (-1: not in this pass).
    struct Lanes {
        std::vector<std::array<int, kKnotSize>> knot;  // per knot of the window
        std::vector<int> ocv;                          // per OCV knot of the window
        int ea = -1, i0 = -1, lag = -1;
        std::array<int, 2> slow{-1, -1}, offset{-1, -1};
        int count = 0;                       // lanes in use
        std::array<double*, kLanes> column;  // where each lane's derivatives go: column[l][row * stride[l]]
        std::array<int, kLanes> stride;
    };
    // Per knot of the window and direction: the gradients of R0, R1, C1, R2, C2 in the pass's lanes.
    using KnotGrads = std::array<std::array<Grad, 5>, 2>;

    static KnotGrads knot_grads(const double* p, const KnotValues<double>& kv, const std::array<int, kKnotSize>& lane) {
        KnotGrads out;
        for (int d = 0; d < 2; ++d) {
            const int* l = lane.data() + 5 * d;
            const double r0 = d ? kv.r0c : kv.r0d, r1 = d ? kv.r1c : kv.r1d, c1 = d ? kv.c1c : kv.c1d;
            const double r2 = d ? kv.r2c : kv.r2d, c2 = d ? kv.c2c : kv.c2d, e4 = std::exp(p[5 * d + 4]);
            auto& gd = out[d];
            gd[0].add(l[0], r0);                          // R0 = exp(p0)
            gd[1].add(l[1], r1);                          // R1 = exp(p1)
            gd[2].add(l[1], -c1), gd[2].add(l[2], c1);    // C1 = exp(p2) / R1
            gd[3].add(l[3], r2);                          // R2 = exp(p3)
            gd[4].add(l[2], c2), gd[4].add(l[3], -c2);    // C2 = exp(p2) (1 + exp(p4)) / R2
            gd[4].add(l[4], c2 * e4 / (1.0 + e4));
        }
        return out;
    }

    // One exact ZOH step of an RC pair and its gradient: v' = decay v + R (1 - decay) I, decay = exp(-dt / tau),
    // with R, tau depending directly on the variables in gr, gtau and dt on the step lag (ddt_dlag).
    static void rc_step_grad(double& v, Dense& dv, int lanes, double r, const Grad& gr, double tau, const Grad& gtau,
                             double current_a, double dt_s, int lag_lane, double ddt_dlag) {
        const double decay = std::exp(-dt_s / tau);
        const double m = (v - r * current_a) * decay;  // d v' / d (-dt / tau)
        for (int l = 0; l < lanes; ++l) dv[l] *= decay;
        gtau.scatter(dv, m * dt_s / (tau * tau));
        gr.scatter(dv, current_a * (1.0 - decay));
        if (lag_lane >= 0) dv[lag_lane] -= m / tau * ddt_dlag;
        v = decay * v + r * (1.0 - decay) * current_a;
    }

    // One derivative pass over range: the model as simulate_window<double> computes it, on the knot and OCV
    // intervals its plain pass read (trace), and every residual's derivative by each lane, written to the Jacobian
    // (Lanes::column). On exit range.r and range.rs are the counters where it stopped.
    void sensitivity_pass(double const* const* p, const std::vector<KnotValues<double>>& kv, const Lanes& ln,
                          const std::vector<KnotGrads>& kg, const PassTrace& trace, PassRange& range) const {
        const Grid& g = *grid_;
        const WindowData& w = *w_;
        const int lo = w.knot_lo, hi = w.knot_hi, olo = w.ocv_lo, ohi = w.ocv_hi;
        const int nk = hi - lo + 1, gb = nk + ohi - olo + 1;
        const double ea_scaled = p[gb][0], i0 = std::exp(p[gb + 1][0]), lag = p[gb + 2][0];
        const double off = w.fit_offset ? p[gb + 4][0] : 0.0, gain = w.fit_offset ? std::exp(p[gb + 4][1]) : 1.0;
        const double x_ref = g.i_ref_a / (2.0 * i0);
        const double ref_ratio = asinh_ratio(x_ref), ref_slope = asinh_ratio_slope(x_ref);
        const double r3 = g.slow ? std::exp(p[gb + 3][0]) : 0.0, tau3 = g.slow ? std::exp(p[gb + 3][1]) : 1.0;
        const double s_first = w.ticks.empty() ? 0.0 : w.ticks.front().soc_start;
        std::array<double, 5> v = range.state;  // v1d, v2d, v1c, v2c, v3 (the model voltage itself is not needed)
        std::array<Dense, 5> dv{};
        Dense dv_prev{}, dvm{};
        std::size_t r = range.r, rs = range.rs;
        Grad dsoc0, dsoc1, dwr, dw0, dwo, dft, dfi, dfr, gR, gC, gr, gtau, gocv, gr0;
        const int nl = ln.count;
        auto forgotten_all = [&] {
            for (int l = 0; l < nl; ++l)
                if (std::abs(dv[0][l]) >= kForgottenV || std::abs(dv[1][l]) >= kForgottenV || std::abs(dv[2][l]) >= kForgottenV ||
                    std::abs(dv[3][l]) >= kForgottenV || std::abs(dv[4][l]) >= kForgottenV || std::abs(dv_prev[l]) >= kForgottenV)
                    return false;
            return true;
        };
        for (std::size_t k = range.begin; k < w.ticks.size(); ++k) {
            if (k > range.direct_last && forgotten_all()) break;
            const Tick& tk = w.ticks[k];
            const double i = tk.current_a;
            const double u0 = tk.soc_start - s_first, u1 = tk.soc_end - s_first;
            const double soc0 = s_first + off + gain * u0, soc1 = s_first + off + gain * u1;
            dsoc0.n = 0, dsoc0.add(ln.offset[0], 1.0), dsoc0.add(ln.offset[1], gain * u0);
            dsoc1.n = 0, dsoc1.add(ln.offset[0], 1.0), dsoc1.add(ln.offset[1], gain * u1);
            // R and C: linear between the tick's two knots at its mid-SOC, held outside the table.
            const int idx = trace.knot[k];
            // A weight on the tick's knot interval and its gradient, held at the interval's ends.
            auto hold = [&](double x, Grad& dx) {
                if (x < 0) x = 0.0, dx.n = 0;
                if (x > 1) x = 1.0, dx.n = 0;
                if (lo == hi) x = 0.0, dx.n = 0;
                return x;
            };
            dwr.n = 0, dwr.add(dsoc0, 0.5 / g.width(idx)), dwr.add(dsoc1, 0.5 / g.width(idx));
            const double wr = hold((0.5 * (soc0 + soc1) - g.soc(idx)) / g.width(idx), dwr);
            const int ia = idx - lo, ib = std::min(idx + 1, hi) - lo;
            const auto &a = kv[ia], &b = kv[ib];
            double f_t = 1.0;
            dft.n = 0;
            if (g.temperature) {
                const double c = kEaScale / kGasConstantJPerMolK * (1.0 / (tk.temperature_c + kZeroCelsiusK) - 1.0 / g.t_ref_k);
                f_t = std::exp(ea_scaled * c);
                dft.add(ln.ea, f_t * c);
            }
            // R0 where the tick's voltage is read, at its end (on the same knot interval).
            dw0.n = 0, dw0.add(dsoc1, 1.0 / g.width(idx));
            const double w0 = hold((soc1 - g.soc(idx)) / g.width(idx), dw0);
            const int dir0 = i < 0 ? 0 : 1;
            const double r0_knots = lerp_grad(dir0 ? a.r0c : a.r0d, dir0 ? b.r0c : b.r0d, kg[ia][dir0][0], kg[ib][dir0][0],
                                              w0, dw0, gR);
            gr0.n = 0, gr0.add(gR, f_t), gr0.add(dft, r0_knots);
            auto advance = [&](double ic_a, double dt_s, double ddt_dlag) {
                double fi = 1.0;
                dfi.n = 0;
                if (g.current) {
                    const double x = std::abs(ic_a) / (2.0 * i0), h = asinh_ratio(x);
                    fi = h / ref_ratio;
                    // x and x_ref both scale as 1 / I0: d x / d log I0 = -x.
                    dfi.add(ln.i0, (-x * asinh_ratio_slope(x) * ref_ratio + x_ref * h * ref_slope) / (ref_ratio * ref_ratio));
                }
                const double fr = f_t * fi;  // C held: tau scales with R
                dfr.n = 0, dfr.add(dft, fi), dfr.add(dfi, f_t);
                auto pair = [&](int s, int d, int qr, int qc, double ra, double rb, double ca, double cb, double cur) {
                    const double rk = lerp_grad(ra, rb, kg[ia][d][qr], kg[ib][d][qr], wr, dwr, gR);
                    const double ck = lerp_grad(ca, cb, kg[ia][d][qc], kg[ib][d][qc], wr, dwr, gC);
                    const double rr = rk * fr, tau = rr * ck;
                    gr.n = 0, gr.add(gR, fr), gr.add(dfr, rk);
                    gtau.n = 0, gtau.add(gr, ck), gtau.add(gC, rr);
                    rc_step_grad(v[s], dv[s], nl, rr, gr, tau, gtau, cur, dt_s, ln.lag, ddt_dlag);
                };
                const double id = discharge_part(ic_a), icc = charge_part(ic_a);
                pair(0, 0, 1, 2, a.r1d, b.r1d, a.c1d, b.c1d, id);
                pair(1, 0, 3, 4, a.r2d, b.r2d, a.c2d, b.c2d, id);
                pair(2, 1, 1, 2, a.r1c, b.r1c, a.c1c, b.c1c, icc);
                pair(3, 1, 3, 4, a.r2c, b.r2c, a.c2c, b.c2c, icc);
                if (g.slow) {  // the whole current, R and tau scaled by temperature only
                    gr.n = 0, gr.add(ln.slow[0], r3 * f_t), gr.add(dft, r3);
                    gtau.n = 0, gtau.add(ln.slow[1], tau3 * f_t), gtau.add(dft, tau3);
                    rc_step_grad(v[4], dv[4], nl, r3 * f_t, gr, tau3 * f_t, gtau, ic_a, dt_s, ln.lag, ddt_dlag);
                }
            };
            if (tk.step) {
                advance(tk.current_before_a, (1.0 - lag) * tk.dt_s, -tk.dt_s);
                advance(i, lag * tk.dt_s, tk.dt_s);
            } else if (tk.dt_s > 0) {
                advance(i, tk.dt_s, 0.0);
            }
            // OCV on its own grid, linear with linear extrapolation past the window's first and last OCV knots.
            const int jo = trace.ocv[k];
            double wo = (soc1 - g.ocv_soc(jo)) / g.ocv_width(jo);
            dwo.n = 0, dwo.add(dsoc1, 1.0 / g.ocv_width(jo));
            if (olo == ohi) wo = 0.0, dwo.n = 0;
            const int ja = jo - olo, jb = std::min(jo + 1, ohi) - olo;
            const double oa = p[nk + ja][0], ob = p[nk + jb][0];
            gocv.n = 0, gocv.add(ln.ocv[ja], 1.0 - wo), gocv.add(ln.ocv[jb], wo), gocv.add(dwo, ob - oa);
            for (int l = 0; l < nl; ++l) dvm[l] = dv[0][l] + dv[1][l] + dv[2][l] + dv[3][l] + dv[4][l];
            gocv.scatter(dvm, 1.0);
            gr0.scatter(dvm, i);
            if (tk.has_residual()) {
                for (int l = 0; l < nl; ++l) ln.column[l][r * ln.stride[l]] = dvm[l] / g.sigma_v;
                ++r;
            }
            if (w.has_step_residual(k)) {
                for (int l = 0; l < nl; ++l) ln.column[l][rs * ln.stride[l]] = (dvm[l] - dv_prev[l]) / w.step_sigma_v;
                ++rs;
            }
            dv_prev = dvm;
        }
        range.r = r, range.rs = rs;
    }

    void derivative_passes(double const* const* p, const std::vector<KnotValues<double>>& kv, double** jacobians,
                           const PassTrace& trace) const {
        const WindowData& w = *w_;
        const auto& sizes = parameter_block_sizes();
        const int nk = w.knot_hi - w.knot_lo + 1, no = w.ocv_hi - w.ocv_lo + 1, g = nk + no;
        const int nb = static_cast<int>(sizes.size());
        const std::size_t n = static_cast<std::size_t>(num_residuals()), nt = w.ticks.size();
        for (int b = 0; b < nb; ++b)
            if (jacobians[b]) std::fill(jacobians[b], jacobians[b] + n * sizes[b], 0.0);
        // The variables in units: each knot's two directions (5 each: log R0, log R1, log tau1, log R2, the tau2
        // ratio), each OCV knot, and Ea, I0, the step lag, the slow pair and the SOC offset as whole blocks. The
        // ticks at which a unit enters directly: a knot's direction where a tick interpolates from that knot and
        // either a current of that direction flows in it (ZOH: its pairs are driven; R0 multiplies the current) or
        // that direction's pairs hold a voltage (their decay depends on tau); before its first such tick the
        // direction's pairs are exactly zero and R0 multiplies nothing. An OCV knot where a tick interpolates from
        // it; the whole blocks everywhere.
        constexpr std::size_t kNone = std::numeric_limits<std::size_t>::max();
        struct Unit {
            int block = 0, q0 = 0, size = 0;
            std::size_t first = kNone, last = 0;
        };
        // Units 2j and 2j + 1: knot j's discharge and charge halves; then one unit per other block, in block order.
        std::vector<Unit> units;
        for (int b = 0; b < nk; ++b) units.push_back({b, 0, 5}), units.push_back({b, 5, 5});
        for (int b = nk; b < nb; ++b) units.push_back({b, 0, sizes[b]});
        auto unit_of_block = [&](int b) { return 2 * nk + (b - nk); };  // b >= nk
        auto enters = [&](int u, std::size_t k) {
            if (units[u].first == kNone) units[u].first = k;
            units[u].last = k;
        };
        for (std::size_t k = 0; k < nt; ++k) {
            const Tick& tk = w.ticks[k];
            const auto& st = trace.state[k];
            const bool discharge = tk.current_a < 0 || (tk.step && tk.current_before_a < 0) || st[0] != 0 || st[1] != 0;
            const bool charge = tk.current_a > 0 || (tk.step && tk.current_before_a > 0) || st[2] != 0 || st[3] != 0;
            const int ki = trace.knot[k] - w.knot_lo, oi = trace.ocv[k] - w.ocv_lo;
            for (int kb : {ki, std::min(ki + 1, nk - 1)}) {
                if (discharge) enters(2 * kb, k);
                if (charge) enters(2 * kb + 1, k);
            }
            enters(unit_of_block(nk + oi), k), enters(unit_of_block(nk + std::min(oi + 1, no - 1)), k);
        }
        for (int b = g; b < nb; ++b)
            if (nt > 0) units[unit_of_block(b)].first = 0, units[unit_of_block(b)].last = nt - 1;
        std::vector<int> order;
        for (int u = 0; u < static_cast<int>(units.size()); ++u)
            if (jacobians[units[u].block] && units[u].first != kNone) order.push_back(u);
        std::stable_sort(order.begin(), order.end(), [&](int a, int c) {
            return units[a].first != units[c].first ? units[a].first < units[c].first : units[a].last < units[c].last;
        });
        // Derivative passes of up to kLanes variables, whole units, in that order.
        std::vector<KnotGrads> kg(nk);
        Lanes ln;
        std::size_t next = 0;
        while (next < order.size()) {
            std::vector<int> chunk;
            int lanes = 0;
            while (next < order.size() && lanes + units[order[next]].size <= kLanes)
                lanes += units[order[next]].size, chunk.push_back(order[next++]);
            ln = Lanes{};
            ln.knot.assign(nk, {});
            for (auto& l : ln.knot) l.fill(-1);
            ln.ocv.assign(no, -1);
            PassRange range;
            range.begin = kNone, range.direct_last = 0;
            int lane = 0;
            for (int u : chunk) {
                const Unit& un = units[u];
                for (int q = un.q0; q < un.q0 + un.size; ++q, ++lane) {
                    const int b = un.block;
                    if (b < nk) ln.knot[b][q] = lane;
                    else if (b < g) ln.ocv[b - nk] = lane;
                    else if (b == g) ln.ea = lane;
                    else if (b == g + 1) ln.i0 = lane;
                    else if (b == g + 2) ln.lag = lane;
                    else if (b == g + 3) ln.slow[q] = lane;
                    else ln.offset[q] = lane;
                    ln.column[lane] = jacobians[b] + q, ln.stride[lane] = sizes[b];
                }
                range.begin = std::min(range.begin, un.first);
                range.direct_last = std::max(range.direct_last, un.last);
            }
            for (int j = 0; j < nk; ++j) kg[j] = knot_grads(p[j], kv[j], ln.knot[j]);
            range.state = trace.state[range.begin];
            range.r = trace.r[range.begin], range.rs = trace.rs[range.begin];
            ln.count = lane;
            sensitivity_pass(p, kv, ln, kg, trace, range);
        }
    }

    const Grid* grid_;
    const WindowData* w_;
};

}  // namespace

std::unique_ptr<ceres::CostFunction> window_jacobian(const Grid* grid, const WindowData* w) {
    return std::make_unique<WindowJacobian>(grid, w);
}

}  // namespace cellbench::estimator::global_window
