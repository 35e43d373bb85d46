#include "cellbench/estimator/pulse_fit.hpp"
#include "printf_text.hpp"
#include "solve.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>
#include <utility>
#include <vector>
#include <string>

#include <Eigen/Dense>
#include <ceres/ceres.h>

namespace cellbench::estimator {

const char* to_string(PulseSetFit::Method method) {
    return method == PulseSetFit::Method::Joint ? "joint" : "thesis";
}

RcValues to_rc_values(const Rc2Params<double>& p) {
    RcValues v;
    v.r0_ohm = p.r0_ohm;
    v.r1_ohm = p.r1_ohm;
    v.r2_ohm = p.r2_ohm;
    v.c1_f = p.r1_ohm > 0.0 ? p.tau1_s / p.r1_ohm : kNaN;
    v.c2_f = p.r2_ohm > 0.0 ? p.tau2_s / p.r2_ohm : kNaN;
    return v;
}

namespace {


double finite_mean(std::initializer_list<double> xs) {
    double s = 0.0;
    int n = 0;
    for (double x : xs)
        if (std::isfinite(x)) { s += x; ++n; }
    return n ? s / n : kNaN;
}

// The rows of one pulse set in a form the fits share: row 0 is A (the last row of the long rest).
struct Window {
    std::size_t first = 0;          // recording row of window row 0
    std::vector<double> t, i, v;    // time, current (non-finite -> 0), voltage (may be NaN)
    std::vector<double> q_ah;       // charge throughput since row 0 (+ = charge), sampling convention
    std::vector<int> dir;           // sign of the current: -1 discharge (R0_dis), +1 charge (R0_chg), 0 none
    std::vector<double> ocv;        // ocv_v + docv_dah * q_ah
    std::size_t n() const { return t.size(); }
    // Whether any row charges the cell: without one (a discharge-only pulse set) the charge direction's
    // parameters are not identifiable and are held (and reported NaN).
    bool has_charge() const { return std::any_of(dir.begin(), dir.end(), [](int d) { return d > 0; }); }
};

Window make_window(const Recording& rec, std::size_t first, std::size_t end, double ocv_v, double docv) {
    Window w;
    w.first = first;
    const std::size_t n = end - first;
    w.t.assign(rec.time_s.begin() + first, rec.time_s.begin() + end);
    w.v.assign(rec.voltage_v.begin() + first, rec.voltage_v.begin() + end);
    w.i.resize(n);
    w.q_ah.resize(n);
    w.dir.resize(n);
    w.ocv.resize(n);
    double q = 0.0;
    for (std::size_t k = 0; k < n; ++k) {
        const double c = rec.current_a[first + k];
        w.i[k] = std::isfinite(c) ? c : 0.0;
        if (k > 0) q += w.i[k] * (w.t[k] - w.t[k - 1]) / 3600.0;
        w.q_ah[k] = q;
        w.dir[k] = w.i[k] < 0 ? -1 : (w.i[k] > 0 ? +1 : 0);
        w.ocv[k] = ocv_v + docv * q;
    }
    return w;
}

// The pulse set's rows at full resolution, then rows [pulse_end, ext_end) merged where the current holds: full
// resolution for 10 s after each current step, 1 s steps up to 120 s, 10 s after that. The merged row's
// current is the mean over its interval. OCV linear in throughput from ocv_v to ocv_end_v.
Window make_extended_window(const Recording& rec, std::size_t first, std::size_t pulse_end, std::size_t ext_end,
                            double ocv_v, double ocv_end_v) {
    Window w = make_window(rec, first, pulse_end, ocv_v, 0.0);
    double q = w.q_ah.back();
    double charge_since = 0.0, t_last = w.t.back(), t_edge = w.t.back();
    for (std::size_t k = pulse_end; k < ext_end; ++k) {
        const double c = std::isfinite(rec.current_a[k]) ? rec.current_a[k] : 0.0;
        const double dt = rec.time_s[k] - rec.time_s[k - 1];
        charge_since += c * dt;
        const double prev = std::isfinite(rec.current_a[k - 1]) ? rec.current_a[k - 1] : 0.0;
        if (std::abs(c - prev) > 0.2) t_edge = rec.time_s[k - 1];
        const double age = rec.time_s[k] - t_edge;
        const double step = age < 10.0 ? 0.0 : age < 120.0 ? 1.0 : 10.0;
        const bool next_is_edge = k + 1 < ext_end && std::isfinite(rec.current_a[k + 1]) &&
                                  std::abs(rec.current_a[k + 1] - c) > 0.2;
        if (rec.time_s[k] - t_last + 1e-9 < step && !next_is_edge && k + 1 != ext_end) continue;
        const double span = rec.time_s[k] - t_last;
        const double i = span > 0 ? charge_since / span : c;
        q += charge_since / 3600.0;
        w.t.push_back(rec.time_s[k]);
        w.v.push_back(rec.voltage_v[k]);
        w.i.push_back(i);
        w.q_ah.push_back(q);
        w.dir.push_back(i < 0 ? -1 : (i > 0 ? +1 : 0));
        w.ocv.push_back(0.0);
        charge_since = 0.0;
        t_last = rec.time_s[k];
    }
    const double q_total = w.q_ah.back();
    for (std::size_t k = 0; k < w.n(); ++k)
        w.ocv[k] = q_total != 0.0 ? ocv_v + (ocv_end_v - ocv_v) * w.q_ah[k] / q_total : ocv_v;
    return w;
}

// RMS of (ocv + offset + simulated overpotential - measured) over the window, with simulate_overpotential.
double simulated_rms(const Window& w, const Rc2Params<double>& dis, const Rc2Params<double>& chg, double offset_v) {
    for (double x : {dis.r0_ohm, dis.r1_ohm, dis.tau1_s, dis.r2_ohm, dis.tau2_s, chg.r0_ohm, chg.r1_ohm,
                     chg.tau1_s, chg.r2_ohm, chg.tau2_s})
        if (!std::isfinite(x)) return kNaN;
    std::vector<double> eta(w.n());
    simulate_overpotential<double>(w.t.data(), w.i.data(), w.n(), dis, chg, RcVoltages<double>{}, eta.data());
    double s = 0.0;
    std::size_t m = 0;
    for (std::size_t k = 0; k < w.n(); ++k) {
        if (!std::isfinite(w.v[k])) continue;
        const double e = w.ocv[k] + offset_v + eta[k] - w.v[k];
        s += e * e;
        ++m;
    }
    return m ? std::sqrt(s / static_cast<double>(m)) : kNaN;
}

// ------------------------------------------------------------------------------------------------------------
// Method 1: the thesis' per-segment exponential fits.

enum class ExpForm {
    Pulse,        // eq. 3.6:  y = -a(1 - e^{-t/tau1}) - b(1 - e^{-t/tau2}) + c
    NegDecay,     // eq. 3.10: y = -a e^{-t/tau1} - b e^{-t/tau2} + c
    ChargePulse,  // eq. 3.14: y = a(1 - e^{-t/tau1}) - V1 e^{-t/tau1} + b(1 - e^{-t/tau2}) - V2 e^{-t/tau2} + c
    PosDecay,     // eq. 3.18: y = a e^{-t/tau1} + b e^{-t/tau2} + c
};

struct ExpResidual {
    const double* x;
    const double* y;
    std::size_t n;
    ExpForm form;
    double v1, v2;  // ChargePulse only: residual polarizations passed as problem constants (Script 3.5)

    template <typename T>
    bool operator()(const T* const p, T* r) const {
        using std::exp;
        const T& a = p[0];
        const T& tau1 = p[1];
        const T& b = p[2];
        const T& tau2 = p[3];
        const T& c = p[4];
        for (std::size_t k = 0; k < n; ++k) {
            const T e1 = exp(-T(x[k]) / tau1);
            const T e2 = exp(-T(x[k]) / tau2);
            T m = c;
            switch (form) {
                case ExpForm::Pulse: m = -a * (T(1.0) - e1) - b * (T(1.0) - e2) + c; break;
                case ExpForm::NegDecay: m = -a * e1 - b * e2 + c; break;
                case ExpForm::ChargePulse:
                    m = a * (T(1.0) - e1) - T(v1) * e1 + b * (T(1.0) - e2) - T(v2) * e2 + c;
                    break;
                case ExpForm::PosDecay: m = a * e1 + b * e2 + c; break;
            }
            r[k] = m - T(y[k]);
        }
        return true;
    }
};

// Scripts 3.3-3.6: [a, tau1, b, tau2, c], Lower = [1e-5, 0.05, 1e-5, 5, -1], Upper = [1, 5, 1, 200, 1],
// StartPoint = [0.05, 0.5, 0.05, 30, 0].
constexpr std::array<double, 5> kExpLower{1e-5, 0.05, 1e-5, 5.0, -1.0};
constexpr std::array<double, 5> kExpUpper{1.0, 5.0, 1.0, 200.0, 1.0};
constexpr std::array<double, 5> kExpStart{0.05, 0.5, 0.05, 30.0, 0.0};

// Fits one segment; x relative time, y the transformed voltage. Rows with a non-finite y are skipped.
ExpSegmentFit fit_exp_segment(std::vector<double> x, std::vector<double> y, ExpForm form, double v1, double v2,
                              int max_iterations) {
    ExpSegmentFit f;
    {
        std::size_t m = 0;
        for (std::size_t k = 0; k < y.size(); ++k)
            if (std::isfinite(y[k]) && std::isfinite(x[k])) { x[m] = x[k]; y[m] = y[k]; ++m; }
        x.resize(m);
        y.resize(m);
    }
    if (x.size() < 6) return f;
    std::array<double, 5> p = kExpStart;
    ceres::Problem problem;
    auto* cost = new ceres::AutoDiffCostFunction<ExpResidual, ceres::DYNAMIC, 5>(
        new ExpResidual{x.data(), y.data(), x.size(), form, v1, v2}, static_cast<int>(x.size()));
    problem.AddResidualBlock(cost, nullptr, p.data());
    for (int j = 0; j < 5; ++j) {
        problem.SetParameterLowerBound(p.data(), j, kExpLower[j]);
        problem.SetParameterUpperBound(p.data(), j, kExpUpper[j]);
    }
    ceres::Solver::Options opt;
    opt.linear_solver_type = ceres::DENSE_QR;
    opt.max_num_iterations = max_iterations;
    opt.function_tolerance = 1e-12;
    opt.gradient_tolerance = 1e-14;
    opt.parameter_tolerance = 1e-10;
    opt.logging_type = ceres::SILENT;
    opt.minimizer_progress_to_stdout = false;
    ceres::Solver::Summary sum;
    solve_from_finite_start(opt, &problem, &sum);
    f.converged = sum.termination_type == ceres::CONVERGENCE;
    f.a_v = p[0];
    f.tau1_s = p[1];
    f.b_v = p[2];
    f.tau2_s = p[3];
    f.c_v = p[4];
    f.rms_v = std::sqrt(2.0 * sum.final_cost / static_cast<double>(x.size()));
    for (int j = 0; j < 4; ++j) {
        const double tol = 1e-6 * (kExpUpper[j] - kExpLower[j]);
        if (p[j] <= kExpLower[j] + tol || p[j] >= kExpUpper[j] - tol) f.at_bound = true;
    }
    return f;
}

void set_rc(ExpSegmentFit& f, double r1, double r2) {
    f.r1_ohm = r1;
    f.r2_ohm = r2;
    f.c1_f = r1 > 0.0 ? f.tau1_s / r1 : kNaN;
    f.c2_f = r2 > 0.0 ? f.tau2_s / r2 : kNaN;
}

void thesis_fits(const Recording& rec, const PulseSet& ps, const Window& w, std::size_t end,
                 const PulseFitOptions& o, PulseSetFit& out) {
    const auto& t = rec.time_s;
    const auto& v = rec.voltage_v;
    const auto& cur = rec.current_a;
    SegmentFits& s = out.thesis;
    const std::size_t pb = ps.pulse_begin, de = ps.discharge_end, cb = ps.charge_begin, ce = ps.charge_end;
    auto ocv_at = [&](std::size_t row) { return w.ocv[row - w.first]; };  // "InstantOCV" of Scripts 3.4-3.6
    const double id = std::abs(cur[pb]);  // |I_d| = |Current(ends(rest)+1)|
    const double ic = std::abs(cur[cb]);  // |I_c| = |Current(ends(rest 2)+1)|
    s.current_discharge_a = id;
    s.current_charge_a = ic;

    auto rows = [&](std::size_t b, std::size_t e, double t0, double y0) {
        std::pair<std::vector<double>, std::vector<double>> xy;
        for (std::size_t k = b; k < e; ++k) {
            xy.first.push_back(t[k] - t0);
            xy.second.push_back(v[k] - y0);
        }
        return xy;
    };

    // Discharge pulse B..C (Script 3.3): y = V - V_B, which removes OCV and the R0 drop; eqs. 3.6-3.7.
    {
        auto [x, y] = rows(pb, de, t[pb], v[pb]);
        s.discharge = fit_exp_segment(x, y, ExpForm::Pulse, 0, 0, o.max_iterations);
        s.discharge.begin = pb;
        s.discharge.end = de;
        set_rc(s.discharge, s.discharge.a_v / id, s.discharge.b_v / id);
    }
    const double td = t[de - 1] - t[pb];  // T_d: relative time of the last discharge row
    // Discharge relaxation D..E (Script 3.4): y = V - OCV; eqs. 3.8-3.11.
    {
        auto [x, y] = rows(de, cb, t[de], ocv_at(de));
        s.discharge_relaxation = fit_exp_segment(x, y, ExpForm::NegDecay, 0, 0, o.max_iterations);
        auto& f = s.discharge_relaxation;
        f.begin = de;
        f.end = cb;
        set_rc(f, f.a_v / (id * (1.0 - std::exp(-td / s.discharge.tau1_s))),
               f.b_v / (id * (1.0 - std::exp(-td / s.discharge.tau2_s))));
    }
    // Charge pulse F..G (Script 3.5): V1(0), V2(0) from eq. 3.13, y = V - OCV - R0_C * I_c; eqs. 3.12-3.15.
    const double tdr = t[cb - 1] - t[de];
    s.v1_residual_v = s.discharge_relaxation.a_v * std::exp(-tdr / s.discharge_relaxation.tau1_s);
    s.v2_residual_v = s.discharge_relaxation.b_v * std::exp(-tdr / s.discharge_relaxation.tau2_s);
    {
        auto [x, y] = rows(cb, ce, t[cb], ocv_at(cb) + out.r0.ef_ohm * ic);
        s.charge = fit_exp_segment(x, y, ExpForm::ChargePulse, s.v1_residual_v, s.v2_residual_v,
                                   o.max_iterations);
        s.charge.begin = cb;
        s.charge.end = ce;
        set_rc(s.charge, s.charge.a_v / ic, s.charge.b_v / ic);
    }
    // Charge relaxation H..I (Script 3.6): y = V - OCV; eqs. 3.16-3.19 with V_c(0) * e^{-T_c/tau_c}.
    const double tc = t[ce - 1] - t[cb];
    {
        auto [x, y] = rows(ce, end, t[ce], ocv_at(ce));
        s.charge_relaxation = fit_exp_segment(x, y, ExpForm::PosDecay, 0, 0, o.max_iterations);
        auto& f = s.charge_relaxation;
        f.begin = ce;
        f.end = end;
        const double e1 = std::exp(-tc / s.charge.tau1_s), e2 = std::exp(-tc / s.charge.tau2_s);
        set_rc(f, (f.a_v + s.v1_residual_v * e1) / (ic * (1.0 - e1)),
               (f.b_v + s.v2_residual_v * e2) / (ic * (1.0 - e2)));
    }

    // Direction averages (Table 3.2 "DA" / "CA"): mean of the two segments' R and C; tau = R_avg * C_avg.
    auto average = [](double r0, const ExpSegmentFit& a, const ExpSegmentFit& b) {
        Rc2Params<double> p{};
        p.r0_ohm = r0;
        p.r1_ohm = finite_mean({a.r1_ohm, b.r1_ohm});
        p.r2_ohm = finite_mean({a.r2_ohm, b.r2_ohm});
        p.tau1_s = p.r1_ohm * finite_mean({a.c1_f, b.c1_f});
        p.tau2_s = p.r2_ohm * finite_mean({a.c2_f, b.c2_f});
        return p;
    };
    out.thesis_discharge = average(out.r0.discharge_ohm, s.discharge, s.discharge_relaxation);
    out.thesis_charge = average(out.r0.charge_ohm, s.charge, s.charge_relaxation);

    const std::pair<const char*, const ExpSegmentFit*> segs[] = {
        {"discharge pulse", &s.discharge},
        {"discharge relaxation", &s.discharge_relaxation},
        {"charge pulse", &s.charge},
        {"charge relaxation", &s.charge_relaxation}};
    for (const auto& [name, f] : segs) {
        if (!std::isfinite(f->a_v)) {
            out.warnings.push_back(std::string("thesis method: the ") + name + " segment has too few rows to fit");
        } else if (f->at_bound) {
            out.warnings.push_back(std::string("thesis method: the ") + name +
                                   " fit ended on a bound of Scripts 3.3-3.6" +
                                   printf_text(" (a = %.4g V, tau1 = %.3g s, ", f->a_v, f->tau1_s) +
                                   printf_text("b = %.4g V, tau2 = %.3g s)", f->b_v, f->tau2_s));
        }
        if (std::isfinite(f->r1_ohm) && (!(f->r1_ohm > 0.0) || !(f->r2_ohm > 0.0)))
            out.warnings.push_back(std::string("thesis method: the ") + name +
                                   " segment gives a non-positive R1 or R2");
    }
}

// ------------------------------------------------------------------------------------------------------------
// Method 2: joint fit of the whole pulse set with the exact ZOH model.
//
// Parameter vector (11): [R0d, R1d, tau1d, R2d, tau2d, R0c, R1c, tau1c, R2c, tau2c, c].
constexpr int kNumJoint = 11;
constexpr int kC = 10;
inline int base_of(int dir) { return dir > 0 ? 5 : 0; }

// Residuals c + eta_k - (V_k - OCV_k) with an analytic Jacobian (forward sensitivities of the same ZOH
// recursion as simulate_overpotential: v <- a v + R (1 - a) I, a = exp(-dt/tau)).
class JointCost final : public ceres::CostFunction {
public:
    JointCost(const Window& w, std::vector<std::size_t> rows) : w_(w), rows_(std::move(rows)) {
        set_num_residuals(static_cast<int>(rows_.size()));
        mutable_parameter_block_sizes()->push_back(kNumJoint);
    }

    bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
        const double* p = parameters[0];
        double* jac = jacobians ? jacobians[0] : nullptr;
        // RC voltages v[direction][pair] (direction 0 = discharge, driven by I-; 1 = charge, by I+) and their
        // sensitivities with respect to that pair's own [R, tau].
        double v[2][2] = {{0, 0}, {0, 0}};
        double dv[2][2][2] = {};
        std::size_t r = 0;
        const std::size_t n = w_.n();
        for (std::size_t k = 0; k < n; ++k) {
            const double i = w_.i[k];
            if (k > 0) {
                const double dt = w_.t[k] - w_.t[k - 1];
                for (int d = 0; d < 2; ++d) {
                    const double u = d == 0 ? discharge_part(i) : charge_part(i);
                    for (int pair = 0; pair < 2; ++pair) {
                        const double rr = p[5 * d + 1 + 2 * pair];
                        const double tau = p[5 * d + 2 + 2 * pair];
                        const double a = std::exp(-dt / tau);
                        if (jac) {
                            const double da = a * dt / (tau * tau);
                            dv[d][pair][1] = a * dv[d][pair][1] + da * (v[d][pair] - rr * u);
                            dv[d][pair][0] = a * dv[d][pair][0] + (1.0 - a) * u;
                        }
                        v[d][pair] = a * v[d][pair] + rr * (1.0 - a) * u;
                    }
                }
            }
            if (r < rows_.size() && rows_[r] == k) {
                const int b = base_of(w_.dir[k]);
                residuals[r] = p[kC] + (w_.dir[k] != 0 ? p[b] * i : 0.0) + v[0][0] + v[0][1] + v[1][0] + v[1][1] -
                               (w_.v[k] - w_.ocv[k]);
                if (jac) {
                    double* row = jac + r * kNumJoint;
                    std::fill(row, row + kNumJoint, 0.0);
                    if (w_.dir[k] != 0) row[b] = i;
                    for (int d = 0; d < 2; ++d)
                        for (int pair = 0; pair < 2; ++pair) {
                            row[5 * d + 1 + 2 * pair] = dv[d][pair][0];
                            row[5 * d + 2 + 2 * pair] = dv[d][pair][1];
                        }
                    row[kC] = 1.0;
                }
                ++r;
            }
        }
        return true;
    }

private:
    const Window& w_;
    std::vector<std::size_t> rows_;
};

// exp(-dt/tau) for the searches, recomputed only when tau changes or dt changes by more than 1e-9 s (the
// sampling interval is nearly constant). The final refinement (JointCost) does not use it.
struct DecayCache {
    double dt = -1.0, tau = -1.0, a = 1.0;
    double operator()(double dt_s, double tau_s) {
        if (std::abs(dt_s - dt) > 1e-9 || tau_s != tau) {
            dt = dt_s;
            tau = tau_s;
            a = std::exp(-dt_s / tau_s);
        }
        return a;
    }
};

// Unit-resistance responses of one RC pair of each direction, on the fitted rows: x_d (multiplied by R_dis)
// and x_c (by R_chg); v = R_dis * x_d + R_chg * x_c solves the model's recursion.
// With `deriv`, also their derivatives with respect to tau_dis and tau_chg (forward sensitivities).
struct PairColumns {
    std::vector<double> xd, xc, dxd_dtd, dxd_dtc, dxc_dtd, dxc_dtc;
};

void pair_columns(const Window& w, const std::vector<std::size_t>& rows, double tau_dis, double tau_chg,
                  bool deriv, PairColumns& out) {
    const std::size_t m = rows.size();
    out.xd.resize(m);
    out.xc.resize(m);
    if (deriv) {
        out.dxd_dtd.resize(m);
        out.dxd_dtc.resize(m);
        out.dxc_dtd.resize(m);
        out.dxc_dtc.resize(m);
    }
    // x_d responds to the discharge part of the current with tau_dis only, x_c to the charge part with tau_chg
    // only (electrical.hpp), so the cross sensitivities are zero.
    DecayCache cache_d, cache_c;
    double xd = 0, xc = 0, xd_td = 0, xc_tc = 0;
    std::size_t r = 0;
    for (std::size_t k = 0; k < w.n() && r < m; ++k) {
        if (k > 0) {
            const double dt = w.t[k] - w.t[k - 1];
            const double ad = cache_d(dt, tau_dis), ac = cache_c(dt, tau_chg);
            const double id = discharge_part(w.i[k]), ic = charge_part(w.i[k]);
            if (deriv) {
                xd_td = ad * xd_td + ad * dt / (tau_dis * tau_dis) * (xd - id);
                xc_tc = ac * xc_tc + ac * dt / (tau_chg * tau_chg) * (xc - ic);
            }
            xd = ad * xd + (1.0 - ad) * id;
            xc = ac * xc + (1.0 - ac) * ic;
        }
        if (rows[r] == k) {
            out.xd[r] = xd;
            out.xc[r] = xc;
            if (deriv) {
                out.dxd_dtd[r] = xd_td;
                out.dxd_dtc[r] = 0.0;
                out.dxc_dtd[r] = 0.0;
                out.dxc_dtc[r] = xc_tc;
            }
            ++r;
        }
    }
}

using Vec7 = Eigen::Matrix<double, 7, 1>;
using Mat7 = Eigen::Matrix<double, 7, 7>;
using Row7 = std::array<double, 7>;

// Linear parameters theta = [c, R0d, R0c, R1d, R1c, R2d, R2c] for fixed time constants: the design matrix
// rows are (1, I*[dis], I*[chg], pair 1 x_d, x_c, pair 2 x_d, x_c). Thin matrices: plain row loops.
struct LinearModel {
    std::vector<Row7> phi;
    Mat7 gram;
    Vec7 rhs, scale, theta;
    Eigen::LDLT<Mat7> ldlt;

    void build(const Window& w, const std::vector<std::size_t>& rows, const PairColumns& p1, const PairColumns& p2) {
        const std::size_t m = rows.size();
        phi.resize(m);
        for (std::size_t r = 0; r < m; ++r) {
            const std::size_t k = rows[r];
            const double i = w.i[k];
            phi[r] = {1.0, w.dir[k] < 0 ? i : 0.0, w.dir[k] > 0 ? i : 0.0, p1.xd[r], p1.xc[r], p2.xd[r], p2.xc[r]};
        }
    }
    // Solves the normal equations (equilibrated); false if singular.
    bool solve(const std::vector<double>& y) {
        double g[7][7] = {};
        double h[7] = {};
        for (std::size_t r = 0; r < phi.size(); ++r) {
            const Row7& f = phi[r];
            for (int a = 0; a < 7; ++a) {
                h[a] += f[a] * y[r];
                for (int b = a; b < 7; ++b) g[a][b] += f[a] * f[b];
            }
        }
        for (int a = 0; a < 7; ++a) {
            rhs(a) = h[a];
            for (int b = a; b < 7; ++b) gram(a, b) = gram(b, a) = g[a][b];
        }
        for (int j = 0; j < 7; ++j) scale(j) = gram(j, j) > 0.0 ? 1.0 / std::sqrt(gram(j, j)) : 1.0;
        ldlt.compute(scale.asDiagonal() * gram * scale.asDiagonal());
        if (ldlt.info() != Eigen::Success) return false;
        theta = apply_inverse(rhs);
        return theta.allFinite();
    }
    // (Phi'Phi)^-1 v
    Vec7 apply_inverse(const Vec7& v) const { return scale.asDiagonal() * ldlt.solve(scale.asDiagonal() * v); }
    double predict(std::size_t r) const {
        double s = 0.0;
        for (int a = 0; a < 7; ++a) s += phi[r][a] * theta(a);
        return s;
    }
};

// Variable projection over the four time constants (parameterized by their logarithms): residual
// Phi(tau) theta*(tau) - y with theta* the linear least-squares solution; Kaufman's Jacobian
// J_j = P_perp (dPhi/dtau_j) theta*.
class VarProCost final : public ceres::CostFunction {
public:
    VarProCost(const Window& w, const std::vector<std::size_t>& rows, const std::vector<double>& y)
        : w_(w), rows_(rows), y_(y) {
        set_num_residuals(static_cast<int>(rows.size()));
        mutable_parameter_block_sizes()->push_back(4);
    }

    // Linear solution at the given time constants [tau1d, tau2d, tau1c, tau2c]; cost = 0.5 * sum r^2.
    bool linear(const std::array<double, 4>& tau, Vec7& theta, double& cost) const {
        pair_columns(w_, rows_, tau[0], tau[2], false, p1_);
        pair_columns(w_, rows_, tau[1], tau[3], false, p2_);
        lin_.build(w_, rows_, p1_, p2_);
        if (!lin_.solve(y_)) return false;
        theta = lin_.theta;
        cost = 0.0;
        for (std::size_t r = 0; r < rows_.size(); ++r) cost += 0.5 * std::pow(lin_.predict(r) - y_[r], 2);
        return true;
    }

    bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
        const double* u = parameters[0];
        const std::array<double, 4> tau{std::exp(u[0]), std::exp(u[1]), std::exp(u[2]), std::exp(u[3])};
        const bool deriv = jacobians && jacobians[0];
        pair_columns(w_, rows_, tau[0], tau[2], deriv, p1_);
        pair_columns(w_, rows_, tau[1], tau[3], deriv, p2_);
        lin_.build(w_, rows_, p1_, p2_);
        if (!lin_.solve(y_)) return false;
        const std::size_t m = rows_.size();
        for (std::size_t r = 0; r < m; ++r) residuals[r] = lin_.predict(r) - y_[r];
        if (!deriv) return true;
        // v_j = dPhi/dtau_j * theta for j = tau1d, tau2d, tau1c, tau2c (into the Jacobian buffer), and Phi'v.
        const Vec7& th = lin_.theta;
        double* jac = jacobians[0];
        double pv[4][7] = {};
        for (std::size_t r = 0; r < m; ++r) {
            double* v = jac + 4 * r;
            v[0] = th(3) * p1_.dxd_dtd[r] + th(4) * p1_.dxc_dtd[r];
            v[1] = th(5) * p2_.dxd_dtd[r] + th(6) * p2_.dxc_dtd[r];
            v[2] = th(3) * p1_.dxd_dtc[r] + th(4) * p1_.dxc_dtc[r];
            v[3] = th(5) * p2_.dxd_dtc[r] + th(6) * p2_.dxc_dtc[r];
            const Row7& f = lin_.phi[r];
            for (int j = 0; j < 4; ++j)
                for (int a = 0; a < 7; ++a) pv[j][a] += f[a] * v[j];
        }
        double coef[4][7];
        for (int j = 0; j < 4; ++j) {
            const Vec7 c = lin_.apply_inverse(Eigen::Map<const Vec7>(pv[j]));
            for (int a = 0; a < 7; ++a) coef[j][a] = c(a);
        }
        // Project out the span of Phi, then the chain rule for log tau.
        for (std::size_t r = 0; r < m; ++r) {
            double* v = jac + 4 * r;
            const Row7& f = lin_.phi[r];
            for (int j = 0; j < 4; ++j) {
                double s = v[j];
                for (int a = 0; a < 7; ++a) s -= f[a] * coef[j][a];
                v[j] = s * tau[static_cast<std::size_t>(j)];
            }
        }
        return true;
    }

private:
    const Window& w_;
    const std::vector<std::size_t>& rows_;
    const std::vector<double>& y_;
    mutable PairColumns p1_, p2_;
    mutable LinearModel lin_;
};

struct Candidate {
    std::array<double, 4> tau{};  // tau1d, tau2d, tau1c, tau2c
    Vec7 theta = Vec7::Zero();    // c, R0d, R0c, R1d, R1c, R2d, R2c
    double cost = std::numeric_limits<double>::infinity();  // 0.5 * sum r^2
    bool feasible = false;        // all resistances >= 0
};

bool better(const Candidate& a, const Candidate& b) {
    if (a.feasible != b.feasible) return a.feasible;
    return a.cost < b.cost;
}

std::vector<double> log_grid(double lo, double hi, std::size_t n) {
    std::vector<double> g(std::max<std::size_t>(n, 2));
    for (std::size_t j = 0; j < g.size(); ++j)
        g[j] = lo * std::pow(hi / lo, static_cast<double>(j) / static_cast<double>(g.size() - 1));
    return g;
}


// Variable projection over a (tau1, tau2) grid of one direction (dir), the other direction's taus fixed.
// The Gram matrix is assembled from precomputed blocks, so each grid point costs a 7x7 solve. Every
// evaluated point is appended to `all`.
Candidate grid_search(const Window& w, const std::vector<std::size_t>& rows, const std::vector<double>& y,
                      const std::array<double, 4>& fixed, int dir, const std::vector<double>& g1,
                      const std::vector<double>& g2, std::vector<Candidate>& all) {
    const std::size_t m = rows.size();
    // Fixed columns 1, I*[dis], I*[chg]: their Gram block and right-hand side.
    std::vector<std::array<double, 3>> F(m);
    Eigen::Matrix3d FtF = Eigen::Matrix3d::Zero();
    Eigen::Vector3d FtY = Eigen::Vector3d::Zero();
    double YtY = 0.0;
    for (std::size_t r = 0; r < m; ++r) {
        const std::size_t k = rows[r];
        F[r] = {1.0, w.dir[k] < 0 ? w.i[k] : 0.0, w.dir[k] > 0 ? w.i[k] : 0.0};
        for (int a = 0; a < 3; ++a) {
            FtY(a) += F[r][a] * y[r];
            for (int b = 0; b < 3; ++b) FtF(a, b) += F[r][a] * F[r][b];
        }
        YtY += y[r] * y[r];
    }
    struct Cols {
        std::vector<double> xd, xc;
        Eigen::Matrix<double, 3, 2> ftp = Eigen::Matrix<double, 3, 2>::Zero();
        Eigen::Matrix2d ptp = Eigen::Matrix2d::Zero();
        Eigen::Vector2d pty = Eigen::Vector2d::Zero();
    };
    auto columns = [&](const std::vector<double>& grid, bool pair1) {
        std::vector<Cols> out(grid.size());
        PairColumns pc;
        for (std::size_t j = 0; j < grid.size(); ++j) {
            const double td = dir < 0 ? grid[j] : fixed[pair1 ? 0 : 1];
            const double tc = dir > 0 ? grid[j] : fixed[pair1 ? 2 : 3];
            pair_columns(w, rows, td, tc, false, pc);
            Cols& c = out[j];
            c.xd = pc.xd;
            c.xc = pc.xc;
            for (std::size_t r = 0; r < m; ++r) {
                const double p[2] = {pc.xd[r], pc.xc[r]};
                for (int b = 0; b < 2; ++b) {
                    for (int a = 0; a < 3; ++a) c.ftp(a, b) += F[r][a] * p[b];
                    for (int a = 0; a < 2; ++a) c.ptp(a, b) += p[a] * p[b];
                    c.pty(b) += p[b] * y[r];
                }
            }
        }
        return out;
    };
    const auto P1 = columns(g1, true);
    const auto P2 = columns(g2, false);

    Candidate best;
    for (std::size_t a = 0; a < g1.size(); ++a) {
        for (std::size_t b = 0; b < g2.size(); ++b) {
            if (g2[b] < 1.5 * g1[a]) continue;
            Eigen::Matrix2d cross = Eigen::Matrix2d::Zero();
            for (std::size_t r = 0; r < m; ++r) {
                cross(0, 0) += P1[a].xd[r] * P2[b].xd[r];
                cross(0, 1) += P1[a].xd[r] * P2[b].xc[r];
                cross(1, 0) += P1[a].xc[r] * P2[b].xd[r];
                cross(1, 1) += P1[a].xc[r] * P2[b].xc[r];
            }
            Mat7 G;
            Vec7 h;
            G.block<3, 3>(0, 0) = FtF;
            G.block<3, 2>(0, 3) = P1[a].ftp;
            G.block<3, 2>(0, 5) = P2[b].ftp;
            G.block<2, 2>(3, 3) = P1[a].ptp;
            G.block<2, 2>(5, 5) = P2[b].ptp;
            G.block<2, 2>(3, 5) = cross;
            G.block<2, 3>(3, 0) = P1[a].ftp.transpose();
            G.block<2, 3>(5, 0) = P2[b].ftp.transpose();
            G.block<2, 2>(5, 3) = cross.transpose();
            h.segment<3>(0) = FtY;
            h.segment<2>(3) = P1[a].pty;
            h.segment<2>(5) = P2[b].pty;
            Vec7 s;
            for (int j = 0; j < 7; ++j) s(j) = G(j, j) > 0.0 ? 1.0 / std::sqrt(G(j, j)) : 1.0;
            const Mat7 Gs = s.asDiagonal() * G * s.asDiagonal();
            Candidate c;
            c.theta = s.asDiagonal() * Gs.ldlt().solve(s.asDiagonal() * h);
            if (!c.theta.allFinite()) continue;
            c.cost = 0.5 * std::max(0.0, YtY - 2.0 * c.theta.dot(h) + c.theta.dot(G * c.theta));
            c.tau = fixed;
            if (dir < 0) {
                c.tau[0] = g1[a];
                c.tau[1] = g2[b];
            } else {
                c.tau[2] = g1[a];
                c.tau[3] = g2[b];
            }
            c.feasible = (c.theta.segment<6>(1).array() >= 0.0).all();
            all.push_back(c);
            if (better(c, best)) best = c;
        }
    }
    return best;
}

ceres::Solver::Options solver_options(int max_iterations, double function_tolerance = 1e-12) {
    ceres::Solver::Options opt;
    opt.linear_solver_type = ceres::DENSE_QR;
    opt.max_num_iterations = max_iterations;
    opt.function_tolerance = function_tolerance;
    opt.gradient_tolerance = 1e-14;
    opt.parameter_tolerance = 1e-10;
    opt.logging_type = ceres::SILENT;
    opt.minimizer_progress_to_stdout = false;
    opt.num_threads = 1;
    return opt;
}

// Bounds of one direction's (tau1, tau2); split_at keeps tau1 <= split <= tau2.
struct TauBounds {
    double lo1, hi1, lo2, hi2;
    explicit TauBounds(const PulseFitOptions& o)
        : lo1(o.tau1_min_s), hi1(o.tau1_max_s), lo2(o.tau2_min_s), hi2(o.tau2_max_s) {}
    TauBounds split_at(double split) const {
        TauBounds b = *this;
        b.hi1 = std::clamp(split, lo1, hi1);
        b.lo2 = std::clamp(split, lo2, hi2);
        return b;
    }
};

bool ordered(const std::array<double, 4>& tau) { return tau[0] < tau[1] && tau[2] < tau[3]; }

// Refines the four time constants by variable projection from a start (with the linear parameters solved
// at every step).
Candidate varpro_refine(const Window& w, const std::vector<std::size_t>& rows, const std::vector<double>& y,
                        const Candidate& start, const TauBounds& bd, const TauBounds& bc, int max_iterations) {
    auto* cost = new VarProCost(w, rows, y);
    std::array<double, 4> u{};
    const std::array<double, 4> lo{bd.lo1, bd.lo2, bc.lo1, bc.lo2}, hi{bd.hi1, bd.hi2, bc.hi1, bc.hi2};
    for (std::size_t j = 0; j < 4; ++j) u[j] = std::log(std::clamp(start.tau[j], lo[j], hi[j]));
    ceres::Problem problem;
    problem.AddResidualBlock(cost, nullptr, u.data());
    if (!w.has_charge()) problem.SetManifold(u.data(), new ceres::SubsetManifold(4, {2, 3}));
    for (int j = 0; j < 4; ++j) {
        problem.SetParameterLowerBound(u.data(), j, std::log(lo[static_cast<std::size_t>(j)]));
        problem.SetParameterUpperBound(u.data(), j, std::log(hi[static_cast<std::size_t>(j)]));
    }
    ceres::Solver::Summary sum;
    solve_from_finite_start(solver_options(max_iterations, 1e-9), &problem, &sum);
    Candidate c;
    for (std::size_t j = 0; j < 4; ++j) c.tau[j] = std::exp(u[j]);
    if (!cost->linear(c.tau, c.theta, c.cost)) return start;
    c.feasible = (c.theta.segment<6>(1).array() >= 0.0).all();
    return c;
}

struct JointResult {
    std::array<double, kNumJoint> p{};
    std::array<double, kNumJoint> sigma{};
    double cost = std::numeric_limits<double>::infinity();
    bool converged = false;
    bool sigma_ok = false;
};

// Final refinement of all 11 parameters with the exact model (JointCost) under the bounds, then covariance.
JointResult polish(const Window& w, const std::vector<std::size_t>& rows, const Candidate& start,
                   const TauBounds& bd, const TauBounds& bc, const PulseFitOptions& o, const R0Steps& r0) {
    JointResult res;
    auto& p = res.p;
    const auto& th = start.theta;  // c, R0d, R0c, R1d, R1c, R2d, R2c
    p = {std::max(0.0, th(1)), std::max(0.0, th(3)), start.tau[0], std::max(0.0, th(5)), start.tau[1],
         std::max(0.0, th(2)), std::max(0.0, th(4)), start.tau[2], std::max(0.0, th(6)), start.tau[3], th(0)};
    std::vector<int> held;
    const bool charge = w.has_charge();
    if (o.r0_from_steps && std::isfinite(r0.discharge_ohm) && (std::isfinite(r0.charge_ohm) || !charge)) {
        p[0] = r0.discharge_ohm;
        held.push_back(0);
        if (charge) {
            p[5] = r0.charge_ohm;
            held.push_back(5);
        }
    }
    if (!charge)  // no charge rows: the charge direction's parameters do nothing, hold them
        for (int j = 5; j < 10; ++j) held.push_back(j);
    ceres::Problem problem;
    problem.AddResidualBlock(new JointCost(w, rows), nullptr, p.data());
    if (!held.empty()) problem.SetManifold(p.data(), new ceres::SubsetManifold(kNumJoint, held));
    for (int b : {0, 5}) {
        const TauBounds& tb = b == 0 ? bd : bc;
        for (int j : {0, 1, 3}) problem.SetParameterLowerBound(p.data(), b + j, 0.0);
        p[b + 2] = std::clamp(p[b + 2], tb.lo1, tb.hi1);
        p[b + 4] = std::clamp(p[b + 4], tb.lo2, tb.hi2);
        problem.SetParameterLowerBound(p.data(), b + 2, tb.lo1);
        problem.SetParameterUpperBound(p.data(), b + 2, tb.hi1);
        problem.SetParameterLowerBound(p.data(), b + 4, tb.lo2);
        problem.SetParameterUpperBound(p.data(), b + 4, tb.hi2);
    }
    ceres::Solver::Summary sum;
    solve_from_finite_start(solver_options(o.max_iterations), &problem, &sum);
    res.cost = sum.final_cost;
    res.converged = sum.termination_type == ceres::CONVERGENCE;

    res.sigma.fill(kNaN);
    if (!o.compute_covariance || rows.size() <= kNumJoint) return res;
    // The covariance (J'J)^-1 in the tangent space (held parameters have no column), computed with the columns
    // scaled to unit norm: J'J's conditioning in raw units is that of ohms against seconds, not of what the pulse
    // set identifies. A 40 Ah cell (resistances a tenth of a 21700's at ten times the current) spread its raw
    // eigenvalues by 1e14-1e17, which the rank check and ceres::Covariance's SVD read as rank deficient (no sd at
    // all for the first pulse set of a run), while the scaled ones spread by 1e3. Rank deficient only where the
    // scaled matrix is.
    ceres::CRSMatrix crs;
    double cost = 0.0;
    problem.Evaluate(ceres::Problem::EvaluateOptions(), &cost, nullptr, nullptr, &crs);
    Eigen::MatrixXd jtj = Eigen::MatrixXd::Zero(crs.num_cols, crs.num_cols);
    for (int r = 0; r < crs.num_rows; ++r) {
        for (int a = crs.rows[r]; a < crs.rows[r + 1]; ++a)
            for (int b = crs.rows[r]; b < crs.rows[r + 1]; ++b)
                jtj(crs.cols[a], crs.cols[b]) += crs.values[a] * crs.values[b];
    }
    if (crs.num_cols == 0) return res;
    const Eigen::VectorXd scale = jtj.diagonal().cwiseSqrt();
    if (!(scale.minCoeff() > 0.0) || !scale.allFinite()) return res;  // a parameter the residuals do not see
    const Eigen::MatrixXd jn = scale.cwiseInverse().asDiagonal() * jtj * scale.cwiseInverse().asDiagonal();
    const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(jn);
    if (eig.info() != Eigen::Success) return res;
    const Eigen::VectorXd& ev = eig.eigenvalues();  // ascending
    if (!(ev(ev.size() - 1) > 0.0) || !(ev(0) > 1e-12 * ev(ev.size() - 1))) return res;
    const Eigen::MatrixXd cov_n = eig.eigenvectors() * ev.cwiseInverse().asDiagonal() * eig.eigenvectors().transpose();
    // (J'J)^-1 scaled by the residual variance.
    const double s2 = 2.0 * sum.final_cost / static_cast<double>(rows.size() - static_cast<std::size_t>(crs.num_cols));
    int col = 0;
    for (int j = 0; j < kNumJoint; ++j) {
        if (std::find(held.begin(), held.end(), j) != held.end()) continue;  // SubsetManifold: tangent in order
        const double var = cov_n(col, col) / (scale(col) * scale(col)) * s2;
        res.sigma[static_cast<std::size_t>(j)] = var >= 0.0 ? std::sqrt(var) : kNaN;
        ++col;
    }
    res.sigma_ok = true;
    return res;
}

Rc2Params<double> unpack(const std::array<double, kNumJoint>& p, int b) {
    return {p[b], p[b + 1], p[b + 2], p[b + 3], p[b + 4]};
}

// Total RC-pair voltage at every window row for the joint parameters p (the JointCost recursion).
std::vector<double> rc_voltage(const Window& w, const std::array<double, kNumJoint>& p) {
    std::vector<double> s(w.n(), 0.0);
    double v[2][2] = {{0, 0}, {0, 0}};
    for (std::size_t k = 1; k < w.n(); ++k) {
        const double dt = w.t[k] - w.t[k - 1];
        for (int d = 0; d < 2; ++d) {
            const double u = d == 0 ? discharge_part(w.i[k]) : charge_part(w.i[k]);
            for (int pair = 0; pair < 2; ++pair) {
                const double a = std::exp(-dt / p[5 * d + 2 + 2 * pair]);
                v[d][pair] = a * v[d][pair] + p[5 * d + 1 + 2 * pair] * (1.0 - a) * u;
            }
        }
        s[k] = v[0][0] + v[0][1] + v[1][0] + v[1][1];
    }
    return s;
}

// Eq. 3.2 at the four steps with the fitted pairs' movement between the rows either side taken out:
// R0 = (dV - dV_rc - dOCV) / dI. Window row of recording row r: r - w.first.
void sampling_corrected_r0(const Window& w, const std::array<double, kNumJoint>& p, const PulseSet& ps, R0Steps& r0) {
    const auto s = rc_voltage(w, p);
    auto at = [&](std::size_t rec_row) {
        const std::size_t k = rec_row - w.first;
        if (k < 1 || k >= w.n()) return kNaN;
        const double di = w.i[k] - w.i[k - 1];
        if (!(std::abs(di) > 0.0)) return kNaN;
        return ((w.v[k] - w.v[k - 1]) - (s[k] - s[k - 1]) - (w.ocv[k] - w.ocv[k - 1])) / di;
    };
    // A step only where a rest is on its other side (PulseSet::rest_*), not into another current.
    r0.discharge_corrected_ohm = finite_mean({ps.rest_before_discharge ? at(ps.discharge_begin) : kNaN,
                                              ps.rest_after_discharge ? at(ps.discharge_end) : kNaN});
    if (!ps.has_charge_pulse()) return;
    r0.charge_corrected_ohm = finite_mean({ps.rest_before_charge ? at(ps.charge_begin) : kNaN,
                                           ps.rest_after_charge ? at(ps.charge_end) : kNaN});
}

Candidate candidate_of(const JointResult& r) {
    Candidate c;
    const auto& p = r.p;
    c.theta << p[kC], p[0], p[5], p[1], p[6], p[3], p[8];
    c.tau = {p[2], p[4], p[7], p[9]};
    c.cost = r.cost;
    c.feasible = true;
    return c;
}

// The rows of w with a voltage and a time, and the overpotential V - OCV at each (what the joint model fits).
void overpotential_rows(const Window& w, std::vector<std::size_t>& rows, std::vector<double>& y) {
    for (std::size_t k = 0; k < w.n(); ++k) {
        if (!std::isfinite(w.v[k]) || !std::isfinite(w.t[k])) continue;
        rows.push_back(k);
        y.push_back(w.v[k] - w.ocv[k]);
    }
}

void joint_fit(const Window& w, const PulseFitOptions& o, PulseSetFit& out) {
    std::vector<std::size_t> rows;
    std::vector<double> y;
    overpotential_rows(w, rows, y);
    if (rows.size() < 4 * kNumJoint) {
        out.warnings.push_back("joint method: too few valid rows to fit");
        return;
    }
    const auto g1 = log_grid(o.tau1_min_s, o.tau1_max_s, o.tau1_grid);
    const auto g2 = log_grid(o.tau2_min_s, o.tau2_max_s, o.tau2_grid);

    // 1. Coordinate-wise variable projection on the grid: discharge taus, then charge taus, twice (the
    //    discharge taus alone without charge rows).
    const bool charge = w.has_charge();
    std::array<double, 4> tau{2.0, 30.0, 2.0, 30.0};
    std::vector<Candidate> all;
    for (int sweep = 0; sweep < 2; ++sweep) {
        for (int dir : {-1, +1}) {
            if (dir > 0 && !charge) continue;
            if (sweep == 1 && dir < 0) all.clear();
            const Candidate c = grid_search(w, rows, y, tau, dir, g1, g2, all);
            if (std::isfinite(c.cost)) tau = c.tau;
        }
    }
    std::sort(all.begin(), all.end(), better);
    std::vector<Candidate> starts;
    for (const Candidate& c : all) {
        if (starts.size() >= std::max<std::size_t>(1, o.refine_starts)) break;
        const bool distinct = std::all_of(starts.begin(), starts.end(), [&](const Candidate& s) {
            for (std::size_t j = 0; j < 4; ++j)
                if (std::abs(std::log(c.tau[j] / s.tau[j])) > std::log(1.3)) return true;
            return false;
        });
        if (distinct) starts.push_back(c);
    }
    if (starts.empty()) {
        out.warnings.push_back("joint method: the time-constant search found no usable start");
        return;
    }

    // 2. Variable-projection refinement of the time constants from each start. tau1 < tau2 is kept by
    //    re-running with the pairs split at the start's geometric mean when the free run crosses them.
    Candidate best;
    const TauBounds box(o);
    TauBounds best_bd = box, best_bc = box;
    for (const Candidate& s : starts) {
        TauBounds bd = box, bc = box;
        Candidate c = varpro_refine(w, rows, y, s, bd, bc, o.max_iterations);
        if (!ordered(c.tau)) {
            if (!(c.tau[0] < c.tau[1])) bd = box.split_at(std::sqrt(s.tau[0] * s.tau[1]));
            if (!(c.tau[2] < c.tau[3])) bc = box.split_at(std::sqrt(s.tau[2] * s.tau[3]));
            c = varpro_refine(w, rows, y, s, bd, bc, o.max_iterations);
        }
        if (!ordered(c.tau)) continue;
        if (better(c, best)) {
            best = c;
            best_bd = bd;
            best_bc = bc;
        }
    }
    if (!std::isfinite(best.cost)) best = starts.front();

    // 3. All 11 parameters with the exact model, resistances bounded at zero; if the pairs cross, again with
    //    them split at the geometric mean of the variable-projection result.
    JointResult r = polish(w, rows, best, best_bd, best_bc, o, out.r0);
    if (!(r.p[2] < r.p[4]) || !(r.p[7] < r.p[9])) {
        if (!(r.p[2] < r.p[4])) best_bd = box.split_at(std::sqrt(best.tau[0] * best.tau[1]));
        if (!(r.p[7] < r.p[9])) best_bc = box.split_at(std::sqrt(best.tau[2] * best.tau[3]));
        r = polish(w, rows, best, best_bd, best_bc, o, out.r0);
    }
    // 4. R0 held at the sampling-corrected steps: correct with the fitted pairs, refine the pairs, repeat (the
    //    correction is ~1 % of R0 and moves the pairs little, so this settles in two or three rounds).
    if (o.r0_from_steps && o.r0_step_sampling_correction && std::isfinite(out.r0.discharge_ohm) &&
        (std::isfinite(out.r0.charge_ohm) || !charge)) {
        R0Steps held = out.r0;
        auto good = [](double x) { return std::isfinite(x) && x > 0.0; };
        for (int round = 0; round < 4; ++round) {
            sampling_corrected_r0(w, r.p, out.pulse_set, held);
            if (!good(held.discharge_corrected_ohm) || (charge && !good(held.charge_corrected_ohm))) break;
            double change = std::abs(held.discharge_corrected_ohm - r.p[0]) / r.p[0];
            if (charge) change = std::max(change, std::abs(held.charge_corrected_ohm - r.p[5]) / r.p[5]);
            if (change < 1e-5) break;
            held.discharge_ohm = held.discharge_corrected_ohm;
            if (charge) held.charge_ohm = held.charge_corrected_ohm;
            const JointResult next = polish(w, rows, candidate_of(r), best_bd, best_bc, o, held);
            if (!(next.p[2] < next.p[4]) || !(next.p[7] < next.p[9])) break;
            r = next;
            out.r0.discharge_corrected_ohm = r.p[0];
            if (charge) out.r0.charge_corrected_ohm = r.p[5];
        }
    }

    out.joint_discharge = unpack(r.p, 0);
    out.joint_charge = charge ? unpack(r.p, 5) : kNaNRc2;
    out.joint_ocv_offset_v = r.p[kC];
    out.joint_converged = r.converged;
    if (r.sigma_ok) {
        out.joint_discharge_sigma = unpack(r.sigma, 0);
        out.joint_charge_sigma = charge ? unpack(r.sigma, 5) : kNaNRc2;
        out.joint_ocv_offset_sigma_v = r.sigma[kC];
    } else if (o.compute_covariance) {
        out.warnings.push_back("joint method: covariance not computable (the Jacobian is rank deficient: a "
                               "parameter is not identifiable from this pulse set)");
    }
    out.joint_fit_rms_v = std::sqrt(2.0 * r.cost / static_cast<double>(rows.size()));
    if (!r.converged) out.warnings.push_back("joint method: Ceres did not report convergence");

    auto check = [&](const Rc2Params<double>& p, const char* name) {
        auto near = [](double x, double b) { return std::abs(x - b) <= 1e-6 * b; };
        if (near(p.tau1_s, o.tau1_min_s) || near(p.tau1_s, o.tau1_max_s) || near(p.tau2_s, o.tau2_min_s) ||
            near(p.tau2_s, o.tau2_max_s))
            out.warnings.push_back(std::string("joint method: a ") + name +
                                   printf_text(" time constant is on its bound (tau1 = %.3g s, tau2 = %.3g s)",
                                       p.tau1_s, p.tau2_s));
        if (!(p.r1_ohm > 0.0) || !(p.r2_ohm > 0.0) || !(p.r0_ohm > 0.0))
            out.warnings.push_back(std::string("joint method: a ") + name + " resistance is zero (on its bound)");
    };
    check(out.joint_discharge, "discharge");
    if (charge) check(out.joint_charge, "charge");
}

// The joint method's cost (0.5 * sum of squared residuals) over a window after its time-constant search and
// variable-projection refinement (steps 1 and 2 of joint_fit, without the final refinement): what the OCV slope
// search below compares. Infinity when nothing is usable.
double joint_search_cost(const Window& w, const PulseFitOptions& o) {
    std::vector<std::size_t> rows;
    std::vector<double> y;
    overpotential_rows(w, rows, y);
    if (rows.size() < 4 * kNumJoint) return std::numeric_limits<double>::infinity();
    const auto g1 = log_grid(o.tau1_min_s, o.tau1_max_s, o.tau1_grid);
    const auto g2 = log_grid(o.tau2_min_s, o.tau2_max_s, o.tau2_grid);
    std::array<double, 4> tau{2.0, 30.0, 2.0, 30.0};
    std::vector<Candidate> all;
    Candidate best;
    const bool charge = w.has_charge();
    for (int sweep = 0; sweep < 2; ++sweep)
        for (int dir : {-1, +1}) {
            if (dir > 0 && !charge) continue;
            const Candidate c = grid_search(w, rows, y, tau, dir, g1, g2, all);
            if (std::isfinite(c.cost)) tau = c.tau;
            if (better(c, best)) best = c;
        }
    if (!std::isfinite(best.cost)) return best.cost;
    const TauBounds box(o);
    TauBounds bd = box, bc = box;
    Candidate c = varpro_refine(w, rows, y, best, bd, bc, o.max_iterations);
    if (!ordered(c.tau)) {
        if (!(c.tau[0] < c.tau[1])) bd = box.split_at(std::sqrt(best.tau[0] * best.tau[1]));
        if (!(c.tau[2] < c.tau[3])) bc = box.split_at(std::sqrt(best.tau[2] * best.tau[3]));
        c = varpro_refine(w, rows, y, best, bd, bc, o.max_iterations);
    }
    if (!ordered(c.tau)) return best.cost;
    return better(c, best) ? c.cost : best.cost;
}

// The OCV slope (V/Ah) of a pulse set whose caller does not know it (PulseFitOptions::docv_dah_v_per_ah = 0):
// the slope whose window the joint model fits best, by golden-section search between 0 and the largest slope
// the discharge pulse allows (its whole voltage fall after the ohmic step taken as OCV). Over a 30 s pulse the
// OCV's fall and the slow pair's rise look alike; the rests tell them apart (the pairs relax, the OCV stays),
// and without the slope the pairs absorb the fall (R2 and C2 of the discharge ~50 % high on the thesis cell).
double estimate_ocv_slope(const Recording& rec, const PulseSet& ps, std::size_t first, std::size_t end,
                          double ocv_v, double r0_discharge_ohm, const PulseFitOptions& o) {
    const Window w0 = make_window(rec, first, end, ocv_v, 0.0);
    const std::size_t de = ps.discharge_end - first;  // window row just after the discharge pulse
    if (de >= w0.n() || !(w0.q_ah[de - 1] < 0.0)) return 0.0;
    const double fall_v = ocv_v - w0.v[de - 1] + r0_discharge_ohm * w0.i[de - 1];  // V_A - V_C - R0 |I|
    const double s_max = std::isfinite(fall_v) && fall_v > 0.0 ? fall_v / -w0.q_ah[de - 1] : 0.0;
    if (!(s_max > 0.0)) return 0.0;
    PulseFitOptions fast = o;
    fast.max_iterations = std::min(o.max_iterations, 30);
    auto cost = [&](double slope) {
        Window w = w0;
        for (std::size_t k = 0; k < w.n(); ++k) w.ocv[k] = ocv_v + slope * w.q_ah[k];
        return joint_search_cost(w, fast);
    };
    const double g = 0.5 * (std::sqrt(5.0) - 1.0);
    double a = 0.0, b = s_max;
    double x1 = b - g * (b - a), x2 = a + g * (b - a);
    double f1 = cost(x1), f2 = cost(x2);
    for (int it = 0; it < 14; ++it) {
        if (f1 <= f2) {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = cost(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = cost(x2);
        }
    }
    const double slope = f1 <= f2 ? x1 : x2;
    const double best = std::min(f1, f2);
    // The bracket's end at 0 is never evaluated by the search: a flat OCV is taken when it fits as well.
    if (!std::isfinite(best) || !(best < cost(0.0))) return 0.0;
    return slope;
}

}  // namespace

PulseSetFit fit_pulse_set(const Recording& rec, const PulseSet& ps, const PulseFitOptions& options) {
    PulseFitOptions o = options;  // the OCV slope may be estimated below
    PulseSetFit out;
    out.pulse_set = ps;
    out.ocv_v = ps.ocv_v;
    const std::size_t n = rec.size();
    const bool sizes_ok = rec.voltage_v.size() == n && rec.current_a.size() == n;
    // Row order: A < first pulse <= each pulse < its end <= the set's end; the thesis form has the charge pulse
    // after the discharge pulse and rows after G (its relaxation).
    const bool charge_pulse = ps.has_charge_pulse();
    auto inside = [&](std::size_t b, std::size_t e) { return ps.pulse_begin <= b && b < e && e <= ps.end; };
    const bool rows_ok = ps.pulse_begin >= 1 && ps.end <= n && inside(ps.discharge_begin, ps.discharge_end) &&
                         (!charge_pulse || inside(ps.charge_begin, ps.charge_end)) &&
                         ps.discharge_end <= ps.pulses_end && ps.pulses_end <= ps.end &&
                         (ps.form != PulseSetForm::Thesis ||
                          (ps.discharge_end < ps.charge_begin && ps.charge_end < ps.end));
    if (!sizes_ok || !rows_ok) {
        out.warnings.push_back("pulse set row indices do not fit this recording: nothing fitted");
        return out;
    }
    if (!std::isfinite(out.ocv_v)) out.ocv_v = rec.voltage_v[ps.pulse_begin - 1];

    // Rows used: A .. end of the last relaxation, cut after max_relaxation_s.
    const std::size_t first = ps.pulse_begin - 1;
    const std::size_t last_pulse_end = ps.pulses_end;
    std::size_t end = ps.end;
    {
        const double t_g = rec.time_s[last_pulse_end - 1];
        std::size_t k = last_pulse_end;
        while (k < ps.end && rec.time_s[k] - t_g <= o.max_relaxation_s) ++k;
        end = std::max(k, std::min(ps.end, last_pulse_end + 2));
    }
    out.begin = first;
    out.end = end;

    // R0, thesis eq. 3.2 / Script 3.2: the rows on either side of each current step.
    {
        const auto& v = rec.voltage_v;
        const auto& c = rec.current_a;
        const std::size_t pb = ps.discharge_begin, de = ps.discharge_end, cb = ps.charge_begin, ce = ps.charge_end;
        // Each step only where a rest is on its other side (PulseSet::rest_*): a step into the SOC step's current,
        // or from one pulse straight into the other, moves both directions' R0.
        if (ps.rest_before_discharge) out.r0.ab_ohm = (v[pb - 1] - v[pb]) / std::abs(c[pb]);
        if (ps.rest_after_discharge && de < ps.end) out.r0.cd_ohm = (v[de] - v[de - 1]) / std::abs(c[de - 1]);
        if (charge_pulse) {
            if (ps.rest_before_charge) out.r0.ef_ohm = (v[cb] - v[cb - 1]) / std::abs(c[cb]);
            if (ps.rest_after_charge && ce < ps.end) out.r0.gh_ohm = (v[ce - 1] - v[ce]) / std::abs(c[ce - 1]);
        }
        out.r0.discharge_ohm = finite_mean({out.r0.ab_ohm, out.r0.cd_ohm});
        out.r0.charge_ohm = finite_mean({out.r0.ef_ohm, out.r0.gh_ohm});
    }

    // The OCV slope: the caller's, else (an online fit of the first pulse set) estimated from the pulse set.
    const bool extended_requested = o.extended_end > ps.end;
    if (o.docv_dah_v_per_ah == 0.0 && o.estimate_unknown_ocv_slope && o.joint_method && !extended_requested) {
        o.docv_dah_v_per_ah = estimate_ocv_slope(rec, ps, first, end, out.ocv_v, out.r0.discharge_ohm, o);
        if (o.docv_dah_v_per_ah > 0.0)
            out.warnings.push_back(printf_text("OCV slope unknown (docv_dah_v_per_ah = 0): estimated from the pulse set itself, %.4f V/Ah",
                                       o.docv_dah_v_per_ah));
    }
    const Window w = make_window(rec, first, end, out.ocv_v, o.docv_dah_v_per_ah);

    // Temperature: mean surface temperature, else ambient.
    for (const auto* ch : {&rec.surface_c, &rec.ambient_c}) {
        if (ch->size() != n) continue;
        double s = 0.0;
        std::size_t m = 0;
        for (std::size_t k = first; k < end; ++k)
            if (std::isfinite((*ch)[k])) { s += (*ch)[k]; ++m; }
        if (m) {
            out.temperature_c = s / static_cast<double>(m);
            break;
        }
    }

    if (ps.charge_cv)
        out.warnings.push_back(
            printf_text("the charge pulse hit the upper voltage limit and turned CV (current fell from %.2f A to %.2f A): "
                "its charge parameters (and R0 GH) are not those of a constant-current pulse",
                std::abs(rec.current_a[ps.charge_begin]), std::abs(rec.current_a[ps.charge_end - 1])));
    if (ps.discharge_cv)
        out.warnings.push_back(
            printf_text("the discharge pulse hit the lower voltage limit and turned CV (current fell from %.2f A to "
                "%.2f A): its discharge parameters are not those of a constant-current pulse",
                std::abs(rec.current_a[ps.discharge_begin]), std::abs(rec.current_a[ps.discharge_end - 1])));
    if (o.docv_dah_v_per_ah == 0.0)
        out.warnings.push_back("OCV slope unknown (docv_dah_v_per_ah = 0): the OCV is held at V_A during the "
                               "pulse set");
    if (ps.charge_relaxation_s > 0.0 && ps.charge_relaxation_s < 30.0)
        out.warnings.push_back(printf_text("the charge relaxation lasts only %.1f s", ps.charge_relaxation_s));

    if (o.thesis_method && ps.form == PulseSetForm::Thesis) thesis_fits(rec, ps, w, end, o, out);
    else if (o.thesis_method)
        out.warnings.push_back(std::string("pulse set of the ") + to_string(ps.form) +
                               " form: the thesis' per-segment fits need its four segments (discharge pulse, rest, "
                               "charge pulse, rest); the joint fit alone");
    if (!charge_pulse)
        out.warnings.push_back("no charge pulse in this pulse set: charge parameters not identified (null)");
    const bool extended = o.extended_end > ps.end && o.extended_end <= n && std::isfinite(o.extended_end_ocv_v);
    const Window wx = extended ? make_extended_window(rec, first, ps.end, o.extended_end, out.ocv_v,
                                                      o.extended_end_ocv_v)
                               : Window{};
    const Window& wj = extended ? wx : w;
    if (extended) out.end = o.extended_end;
    if (o.joint_method) joint_fit(wj, o, out);

    // Without charge rows the charge parameters do nothing: the discharge ones stand in for them in the RMS.
    const bool window_charges = wj.has_charge();
    out.thesis_rms_v = simulated_rms(wj, out.thesis_discharge, window_charges ? out.thesis_charge : out.thesis_discharge, 0.0);
    out.joint_rms_v = simulated_rms(wj, out.joint_discharge, window_charges ? out.joint_charge : out.joint_discharge, 0.0);

    // Choice: the better predictor among the results with usable parameters (see the header).
    auto usable = [](const Rc2Params<double>& p) {
        for (double x : {p.r0_ohm, p.r1_ohm, p.tau1_s, p.r2_ohm, p.tau2_s})
            if (!std::isfinite(x) || !(x > 0.0)) return false;
        return true;
    };
    const auto& th = out.thesis;
    out.thesis_at_bound = !usable(out.thesis_discharge) || (window_charges && !usable(out.thesis_charge)) || th.discharge.at_bound ||
                          th.discharge_relaxation.at_bound || th.charge.at_bound || th.charge_relaxation.at_bound;
    auto on_box = [&](const Rc2Params<double>& p) {
        auto near = [](double x, double b) { return std::abs(x - b) <= 1e-6 * b; };
        return near(p.tau1_s, o.tau1_min_s) || near(p.tau1_s, o.tau1_max_s) || near(p.tau2_s, o.tau2_min_s) ||
               near(p.tau2_s, o.tau2_max_s);
    };
    out.joint_at_bound = !usable(out.joint_discharge) || on_box(out.joint_discharge) ||
                         (window_charges && (!usable(out.joint_charge) || on_box(out.joint_charge)));
    const bool thesis_ok = std::isfinite(out.thesis_rms_v), joint_ok = std::isfinite(out.joint_rms_v);
    const bool joint_better = joint_ok && !(out.thesis_rms_v < out.joint_rms_v);
    if (thesis_ok && joint_ok && out.thesis_at_bound != out.joint_at_bound) {
        out.chosen = out.joint_at_bound ? PulseSetFit::Method::Thesis : PulseSetFit::Method::Joint;
        const bool against_rms = (out.chosen == PulseSetFit::Method::Joint) != joint_better;
        if (against_rms)
            out.warnings.push_back(std::string("chose the ") + to_string(out.chosen) +
                                   " result although the other predicts the pulse set better" +
                                   printf_text(" (%.2f mV vs %.2f mV RMS): the other's parameters are on a bound or not "
                                       "positive",
                                       1e3 * std::min(out.joint_rms_v, out.thesis_rms_v),
                                       1e3 * std::max(out.joint_rms_v, out.thesis_rms_v)));
    } else {
        out.chosen = joint_better || !thesis_ok ? PulseSetFit::Method::Joint : PulseSetFit::Method::Thesis;
    }
    return out;
}

}  // namespace cellbench::estimator
