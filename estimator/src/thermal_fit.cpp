// Thermal parameter fits (thesis chapter 4): derivative, C_th from rests (eq. 4.7-4.8), R_th two ways (eq. 4.9
// and the cooling time constant), entropic heat coefficient (eq. 4.4-4.6), charge throughput and capacity.
#include "cellbench/estimator/thermal_fit.hpp"
#include "median.hpp"
#include "printf_text.hpp"
#include "solve.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <numeric>
#include <string>
#include <utility>

#include <Eigen/Dense>
#include <ceres/ceres.h>

namespace cellbench::estimator {
namespace {

bool finite(double v) { return std::isfinite(v); }


void require_thermal_channels(const Recording& rec, const char* who) {
    if (!rec.has_surface())
        throw InputError(rec.source + ": " + who + " needs the surface temperature column (Surface Temperature / degC)");
    if (!rec.has_heat_flux())
        throw InputError(rec.source + ": " + who + " needs the heat flux column (Heat Flux Density / W/m^2)");
}

RowRange clamp_range(const Recording& rec, RowRange r) {
    r.end = std::min(r.end, rec.size());
    r.begin = std::min(r.begin, r.end);
    return r;
}

double median_of(std::vector<double> v) {
    if (v.empty()) return kNaN;
    const std::size_t mid = v.size() / 2;
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(mid), v.end());
    double m = v[mid];
    if (v.size() % 2 == 0) {
        const double lo = *std::max_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(mid));
        m = 0.5 * (m + lo);
    }
    return m;
}

// Median of |v| * 1.4826 (robust sigma of residuals about zero).
double mad_sigma_about_zero(const std::vector<double>& v) {
    std::vector<double> a;
    a.reserve(v.size());
    for (double x : v) a.push_back(std::abs(x));
    return 1.4826 * median_of(std::move(a));
}

// Weighted median of values with non-negative weights (lower weighted median).
double weighted_median(std::vector<std::pair<double, double>> value_weight) {
    if (value_weight.empty()) return kNaN;
    std::sort(value_weight.begin(), value_weight.end());
    double total = 0;
    for (const auto& vw : value_weight) total += vw.second;
    if (!(total > 0)) return kNaN;
    double acc = 0;
    for (const auto& vw : value_weight) {
        acc += vw.second;
        if (acc >= 0.5 * total) return vw.first;
    }
    return value_weight.back().first;
}

// Lag-1 autocorrelation of a residual series made of clusters (no pair across clusters), clamped to [0, 0.999].
double lag1_autocorrelation(const std::vector<double>& r, const std::vector<std::size_t>& cluster) {
    double num = 0, den = 0;
    for (std::size_t i = 0; i < r.size(); ++i) {
        den += r[i] * r[i];
        if (i > 0 && cluster[i] == cluster[i - 1]) num += r[i] * r[i - 1];
    }
    if (!(den > 0)) return 0.0;
    return std::clamp(num / den, 0.0, 0.999);
}

// Effective number of independent samples of an AR(1) residual series.
double effective_n(double n, double rho) { return std::max(1.0, n * (1.0 - rho) / (1.0 + rho)); }

// Linear interpolation with linear extrapolation from the end segments (x ascending, size >= 2).
double interp_linear_extrap(const std::vector<double>& x, const std::vector<double>& y, double xq) {
    const std::size_t n = x.size();
    std::size_t i;
    if (xq <= x.front()) i = 0;
    else if (xq >= x.back()) i = n - 2;
    else i = static_cast<std::size_t>(std::upper_bound(x.begin(), x.end(), xq) - x.begin()) - 1;
    i = std::min(i, n - 2);
    const double f = (xq - x[i]) / (x[i + 1] - x[i]);
    return y[i] + f * (y[i + 1] - y[i]);
}

bool strictly_ascending(const std::vector<double>& v) {
    for (std::size_t i = 1; i < v.size(); ++i)
        if (!(v[i] > v[i - 1])) return false;
    return std::all_of(v.begin(), v.end(), finite);
}

// Through-origin regression y = b*x with weights w, plus cluster-robust and autocorrelation-corrected errors.
struct OriginRegression {
    double slope = kNaN, se = kNaN, r_squared = kNaN;
    std::size_t kept = 0, rejected = 0, clusters = 0;
};

// x_noise_var (optional, per point): variance of the noise in x. Noise in the regressor biases a least-squares
// slope towards zero by sum(x_true^2) / sum(x^2); the denominator sum(w x^2) is corrected by sum(w var) (method of
// moments for errors in variables), the correction capped at half the raw sum.
OriginRegression robust_origin_regression(const std::vector<double>& x, const std::vector<double>& y,
                                          const std::vector<std::size_t>& cluster,
                                          const std::vector<double>& x_noise_var = {}) {
    OriginRegression out;
    const std::size_t n = x.size();
    auto xvar = [&](std::size_t i) { return i < x_noise_var.size() && finite(x_noise_var[i]) ? x_noise_var[i] : 0.0; };
    if (n < 3) return out;
    // Start: weighted median of the point slopes y/x, weights x^2 (robust, through the origin).
    std::vector<std::pair<double, double>> sw;
    sw.reserve(n);
    for (std::size_t i = 0; i < n; ++i)
        if (x[i] != 0.0) sw.emplace_back(y[i] / x[i], x[i] * x[i]);
    double b = weighted_median(std::move(sw));
    if (!finite(b)) return out;
    std::vector<double> w(n, 1.0), r(n);
    double ymax = 0;
    for (double v : y) ymax = std::max(ymax, std::abs(v));
    // Tukey biweight IRLS (tuning constant 4.685: 95 % efficiency for Gaussian noise).
    for (int it = 0; it < 100; ++it) {
        for (std::size_t i = 0; i < n; ++i) r[i] = y[i] - b * x[i];
        const double sigma = std::max(mad_sigma_about_zero(r), 1e-12 * std::max(ymax, 1e-300));
        double sxy = 0, sxx = 0, svv = 0;
        for (std::size_t i = 0; i < n; ++i) {
            const double u = r[i] / (4.685 * sigma);
            w[i] = std::abs(u) < 1.0 ? (1 - u * u) * (1 - u * u) : 0.0;
            sxy += w[i] * x[i] * y[i];
            sxx += w[i] * x[i] * x[i];
            svv += w[i] * xvar(i);
        }
        if (!(sxx > 0)) return out;
        const double nb = sxy / (sxx - std::min(svv, 0.5 * sxx));
        const bool done = std::abs(nb - b) <= 1e-10 * std::abs(b);
        b = nb;
        if (done) break;
    }
    out.slope = b;
    // Fit quality and errors over the kept points.
    double sxx = 0, svv_kept = 0, ysum = 0, sse = 0, wsse = 0;
    std::size_t kept = 0;
    for (std::size_t i = 0; i < n; ++i) {
        r[i] = y[i] - b * x[i];
        if (w[i] <= 0) continue;
        ++kept;
        ysum += y[i];
        sse += r[i] * r[i];
        wsse += w[i] * r[i] * r[i];
        sxx += w[i] * x[i] * x[i];
        svv_kept += w[i] * xvar(i);
    }
    sxx -= std::min(svv_kept, 0.5 * sxx);
    out.kept = kept;
    out.rejected = n - kept;
    if (kept < 3 || !(sxx > 0)) return out;
    const double ymean = ysum / static_cast<double>(kept);
    double sst = 0;
    for (std::size_t i = 0; i < n; ++i)
        if (w[i] > 0) sst += (y[i] - ymean) * (y[i] - ymean);
    out.r_squared = sst > 0 ? 1.0 - sse / sst : kNaN;

    // (1) OLS error with an effective sample count from the residuals' lag-1 autocorrelation.
    std::vector<double> rk;
    std::vector<std::size_t> ck;
    for (std::size_t i = 0; i < n; ++i)
        if (w[i] > 0) rk.push_back(r[i]), ck.push_back(cluster[i]);
    const double rho = lag1_autocorrelation(rk, ck);
    const double nk = static_cast<double>(kept);
    const double s2 = wsse / std::max(1.0, nk - 1.0);
    const double se_ar1 = std::sqrt(s2 / sxx * nk / effective_n(nk, rho));
    // (2) cluster-robust sandwich (clusters = rests), when there are enough clusters.
    std::vector<double> score;
    std::vector<std::size_t> ids;
    for (std::size_t i = 0; i < n; ++i) {
        if (w[i] <= 0) continue;
        auto pos = std::find(ids.begin(), ids.end(), cluster[i]);
        if (pos == ids.end()) ids.push_back(cluster[i]), score.push_back(0.0), pos = ids.end() - 1;
        score[static_cast<std::size_t>(pos - ids.begin())] += w[i] * x[i] * r[i];
    }
    out.clusters = ids.size();
    double se = se_ar1;
    if (ids.size() >= 3) {
        double s = 0;
        for (double v : score) s += v * v;
        const double g = static_cast<double>(ids.size());
        const double se_cluster = std::sqrt(s * g / (g - 1.0)) / sxx;
        se = std::max(se, se_cluster);
    }
    out.se = se;
    return out;
}

// Fixed-effects regression Q = g * (T - T_amb,k) with one T_amb per cluster (or a known T_amb per row).
struct FluxRegression {
    double g = kNaN, se_g = kNaN, r_squared = kNaN;
    std::size_t n = 0;
};

// First-order cooling T = T_inf + dT * exp(-(t - t0)/tau), parameters (T_inf, dT, log tau).
struct CoolingResidual {
    CoolingResidual(double t_rel, double temp) : t_rel_(t_rel), temp_(temp) {}
    template <typename T>
    bool operator()(const T* const p, T* residual) const {
        residual[0] = p[0] + p[1] * exp(-T(t_rel_) / exp(p[2])) - T(temp_);
        return true;
    }
    double t_rel_, temp_;
};

RestCoolingFit fit_rest_cooling(const Recording& rec, RowRange range, const ThermalResistanceOptions& opt) {
    RestCoolingFit out;
    out.range = range;
    const auto& t = rec.time_s;
    const auto& temp = rec.surface_c;
    std::vector<double> ts, ys;
    for (std::size_t k = range.begin; k < range.end; ++k) {
        if (t[k] - t[range.begin] < opt.skip_s || !finite(temp[k])) continue;
        ts.push_back(t[k]);
        ys.push_back(temp[k]);
    }
    if (ts.size() < 20 || ts.back() - ts.front() < 60.0) {
        out.reason = "shorter than skip + 60 s";
        return out;
    }
    // At most ~600 points (one every ~5 s of a 1 h rest): the time constant is hundreds of seconds, so denser
    // rows add nothing but cost (each row is one Ceres residual block).
    const std::size_t stride = std::max<std::size_t>(1, ts.size() / 600);
    std::vector<double> tr, yr;
    for (std::size_t i = 0; i < ts.size(); i += stride) tr.push_back(ts[i] - ts.front()), yr.push_back(ys[i]);
    const double duration = tr.back();

    // Start values: asymptote from the last 5 %, excess at t0, 1/e time.
    const std::size_t tail = std::max<std::size_t>(1, yr.size() / 20);
    double t_inf0 = 0;
    for (std::size_t i = yr.size() - tail; i < yr.size(); ++i) t_inf0 += yr[i];
    t_inf0 /= static_cast<double>(tail);
    const std::size_t head = std::max<std::size_t>(1, std::min<std::size_t>(yr.size() / 50, 50));
    double y00 = 0;
    for (std::size_t i = 0; i < head; ++i) y00 += yr[i];
    y00 /= static_cast<double>(head);
    const double dt0 = y00 - t_inf0;
    double tau0 = duration / 3.0;
    for (std::size_t i = 0; i < yr.size(); ++i)
        if (std::abs(yr[i] - t_inf0) <= std::abs(dt0) * std::exp(-1.0)) {
            tau0 = std::max(tr[i], 5.0);
            break;
        }
    if (std::abs(dt0) < opt.min_delta_t_k) {
        out.delta_t_k = dt0;
        out.t_inf_c = t_inf0;
        out.reason = "excess temperature " + printf_text("%.3f", dt0) + " K below " + printf_text("%.3f", opt.min_delta_t_k) + " K";
        return out;
    }

    std::array<double, 3> p{t_inf0, dt0, std::log(tau0)};
    // The problem owns the loss (default Problem::Options) and deletes it once, however many blocks share it.
    auto solve = [&](ceres::LossFunction* loss) {
        ceres::Problem problem;
        for (std::size_t i = 0; i < tr.size(); ++i)
            problem.AddResidualBlock(
                new ceres::AutoDiffCostFunction<CoolingResidual, 1, 3>(new CoolingResidual(tr[i], yr[i])), loss,
                p.data());
        problem.SetParameterLowerBound(p.data(), 2, std::log(1.0));
        problem.SetParameterUpperBound(p.data(), 2, std::log(100.0 * std::max(duration, 1.0)));
        ceres::Solver::Options so;
        so.linear_solver_type = ceres::DENSE_QR;
        so.max_num_iterations = 200;
        so.function_tolerance = 1e-12;
        so.parameter_tolerance = 1e-12;
        so.logging_type = ceres::SILENT;
        ceres::Solver::Summary sum;
        solve_from_finite_start(so, &problem, &sum);
        return sum.IsSolutionUsable();
    };
    std::vector<double> res(tr.size());
    auto residuals = [&] {
        for (std::size_t i = 0; i < tr.size(); ++i) res[i] = p[0] + p[1] * std::exp(-tr[i] / std::exp(p[2])) - yr[i];
    };
    // Plain least squares, then a Cauchy loss at 3 robust sigmas of its residuals: rows that do not cool
    // (heat of the next step smeared in, chamber disturbance) stop pulling tau.
    if (!solve(nullptr)) {
        out.reason = "cooling fit failed";
        return out;
    }
    residuals();
    const double sigma0 = std::max(mad_sigma_about_zero(res), 1e-6);
    if (!solve(new ceres::CauchyLoss(3.0 * sigma0))) {
        out.reason = "robust cooling fit failed";
        return out;
    }
    residuals();
    const double tau = std::exp(p[2]);
    out.tau_s = tau;
    out.t_inf_c = p[0];
    out.delta_t_k = p[1];

    // Standard error of tau: Gauss-Newton covariance over the inlier rows (|r| < 3 sigma), residual variance,
    // inflated for the residuals' autocorrelation (ambient ripple is slow, rows are not independent).
    const double sigma = std::max(mad_sigma_about_zero(res), 1e-9);
    Eigen::Matrix3d jtj = Eigen::Matrix3d::Zero();
    double sse = 0;
    std::vector<double> rin;
    std::vector<std::size_t> cl;
    for (std::size_t i = 0; i < tr.size(); ++i) {
        if (std::abs(res[i]) > 3.0 * sigma) continue;
        const double e = std::exp(-tr[i] / tau);
        const Eigen::Vector3d j(1.0, e, p[1] * e * tr[i] / (tau * tau));
        jtj += j * j.transpose();
        sse += res[i] * res[i];
        rin.push_back(res[i]);
        cl.push_back(0);
    }
    double ms = 0;
    for (double v : res) ms += v * v;
    out.rms_c = std::sqrt(ms / static_cast<double>(res.size()));
    const double nin = static_cast<double>(rin.size());
    if (nin < 10 || std::abs(jtj.determinant()) < 1e-300) {
        out.reason = "too few inlier rows";
        return out;
    }
    const double s2 = sse / (nin - 3.0);
    const double rho = lag1_autocorrelation(rin, cl);
    const Eigen::Matrix3d cov = jtj.inverse() * s2 * (nin / effective_n(nin, rho));
    out.tau_se_s = std::sqrt(std::max(0.0, cov(2, 2)));

    if (std::abs(out.delta_t_k) < opt.min_delta_t_k) {
        out.reason = "fitted excess temperature " + printf_text("%.3f", out.delta_t_k) + " K below " +
                     printf_text("%.3f", opt.min_delta_t_k) + " K";
        return out;
    }
    if (tau < 5.0 || tau > 20.0 * std::max(duration, 1.0)) {
        out.reason = "time constant " + printf_text("%.0f", tau) + " s outside [5 s, 20 x rest]";
        return out;
    }
    if (!(out.tau_se_s < 0.5 * tau)) {
        out.reason = "time constant undetermined (se > 50 %)";
        return out;
    }
    out.used = true;
    return out;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------------
std::vector<double> smooth_derivative(const std::vector<double>& time_s, const std::vector<double>& y,
                                      std::size_t begin, std::size_t end, double window_s) {
    end = std::min({end, time_s.size(), y.size()});
    begin = std::min(begin, end);
    const std::size_t n = end - begin;
    std::vector<double> out(n, kNaN);
    if (n == 0) return out;
    // Prefix sums over finite samples, relative to the first time stamp and first finite value, in long double:
    // windows are small against the range, so differences of large sums must keep their digits.
    double y_ref = 0;
    for (std::size_t k = begin; k < end; ++k)
        if (finite(y[k])) {
            y_ref = y[k];
            break;
        }
    const double t_ref = time_s[begin];
    std::vector<long double> c0(n + 1, 0), ct(n + 1, 0), ctt(n + 1, 0), cy(n + 1, 0), cty(n + 1, 0);
    for (std::size_t i = 0; i < n; ++i) {
        const std::size_t k = begin + i;
        const bool ok = finite(y[k]) && finite(time_s[k]);
        const long double tt = ok ? static_cast<long double>(time_s[k] - t_ref) : 0.0L;
        const long double yy = ok ? static_cast<long double>(y[k] - y_ref) : 0.0L;
        c0[i + 1] = c0[i] + (ok ? 1 : 0);
        ct[i + 1] = ct[i] + tt;
        ctt[i + 1] = ctt[i] + tt * tt;
        cy[i + 1] = cy[i] + yy;
        cty[i + 1] = cty[i] + tt * yy;
    }
    const double h = 0.5 * std::max(window_s, 0.0);
    std::size_t lo = 0, hi = 0;  // window rows [lo, hi) relative to begin
    for (std::size_t i = 0; i < n; ++i) {
        const double tc = time_s[begin + i];
        while (lo < n && time_s[begin + lo] < tc - h) ++lo;
        if (hi < lo) hi = lo;
        while (hi < n && time_s[begin + hi] <= tc + h) ++hi;
        const long double N = c0[hi] - c0[lo];
        if (N < 3) continue;
        const long double St = ct[hi] - ct[lo], Stt = ctt[hi] - ctt[lo];
        const long double Sy = cy[hi] - cy[lo], Sty = cty[hi] - cty[lo];
        const long double den = N * Stt - St * St;
        if (!(den > 1e-12L * N * N)) continue;
        out[i] = static_cast<double>((N * Sty - St * Sy) / den);
    }
    return out;
}

// ---------------------------------------------------------------------------------------------------------------
namespace {

// Value at row c of the least-squares line through the rows of [lo, hi) within +-half of t[c], and its variance
// (from the line's own residuals).
struct LineValue {
    double value = kNaN, var = kNaN;
};
LineValue local_line_value(const std::vector<double>& t, const std::vector<double>& y, std::size_t lo, std::size_t hi,
                           std::size_t c, double half) {
    LineValue out;
    std::size_t a = c, b = c + 1;
    while (a > lo && t[a - 1] >= t[c] - half) --a;
    while (b < hi && t[b] <= t[c] + half) ++b;
    double n = 0, st = 0, stt = 0, sy = 0, sty = 0;
    const double y_ref = finite(y[c]) ? y[c] : 0.0;
    for (std::size_t k = a; k < b; ++k) {
        if (!finite(y[k])) continue;
        const double tt = t[k] - t[c], yy = y[k] - y_ref;
        n += 1, st += tt, stt += tt * tt, sy += yy, sty += tt * yy;
    }
    if (n < 5) return out;
    const double den = n * stt - st * st;
    if (!(den > 0)) return out;
    const double slope = (n * sty - st * sy) / den, icpt = (sy - slope * st) / n;
    double sse = 0;
    for (std::size_t k = a; k < b; ++k)
        if (finite(y[k])) {
            const double e = y[k] - y_ref - icpt - slope * (t[k] - t[c]);
            sse += e * e;
        }
    const double s2 = sse / (n - 2.0), tbar = st / n, sxx = stt - n * tbar * tbar;
    out.value = y_ref + icpt;
    out.var = s2 * (1.0 / n + tbar * tbar / sxx);
    return out;
}

// Value at row c of the least-squares parabola through the rows of [lo, hi) within +-half of t[c], and its
// variance: for rests logged sparsely (a row a minute), whose windows must span a good part of the cooling's time
// constant to hold five rows; a line through a curve that long reads its centre high by about (half/tau)^2/6 of the
// excess temperature (2 % at a minute's rows), a parabola centred on the row by the curve's fourth-order term only.
LineValue local_parabola_value(const std::vector<double>& t, const std::vector<double>& y, std::size_t lo,
                               std::size_t hi, std::size_t c, double half) {
    LineValue out;
    std::size_t a = c, b = c + 1;
    while (a > lo && t[a - 1] >= t[c] - half) --a;
    while (b < hi && t[b] <= t[c] + half) ++b;
    Eigen::Matrix3d xtx = Eigen::Matrix3d::Zero();
    Eigen::Vector3d xty = Eigen::Vector3d::Zero();
    const double y_ref = finite(y[c]) ? y[c] : 0.0;
    double n = 0;
    for (std::size_t k = a; k < b; ++k) {
        if (!finite(y[k])) continue;
        const double u = (t[k] - t[c]) / half;
        const Eigen::Vector3d x(1.0, u, u * u);
        xtx += x * x.transpose();
        xty += x * (y[k] - y_ref);
        n += 1;
    }
    if (n < 5) return out;
    const Eigen::LDLT<Eigen::Matrix3d> ldlt(xtx);
    if (ldlt.info() != Eigen::Success || !(ldlt.rcond() > 1e-10)) return out;
    const Eigen::Vector3d beta = ldlt.solve(xty);
    double sse = 0;
    for (std::size_t k = a; k < b; ++k)
        if (finite(y[k])) {
            const double u = (t[k] - t[c]) / half;
            const double e = y[k] - y_ref - (beta[0] + beta[1] * u + beta[2] * u * u);
            sse += e * e;
        }
    const Eigen::Matrix3d inv = ldlt.solve(Eigen::Matrix3d::Identity());
    out.value = y_ref + beta[0];
    out.var = sse / (n - 3.0) * inv(0, 0);
    return out;
}

// The median interval between the rows of [lo, hi) (NaN with fewer than two).
double median_interval_s(const std::vector<double>& t, std::size_t lo, std::size_t hi) {
    std::vector<double> d;
    for (std::size_t k = lo + 1; k < hi; ++k)
        if (t[k] > t[k - 1]) d.push_back(t[k] - t[k - 1]);
    return upper_median(std::move(d));
}

}  // namespace

ThermalCapacityFit fit_thermal_capacity(const std::vector<ThermalRests>& sets, double area_m2, double skip_s,
                                        double window_s) {
    if (!(area_m2 > 0)) throw InputError("thermal capacity fit: area_m2 must be > 0");
    ThermalCapacityFit out;
    out.skip_s = skip_s;
    out.window_s = window_s;
    const double half_dense = 0.25 * window_s;  // end values: lines over window_s / 2, centred
    const double chunk_dense_s = std::max(skip_s, 2.0 * window_s);
    std::size_t sparse_rests = 0;

    // Energy balance per chunk of a rest (eq. 4.7 integrated): C_th * (T(a) - T(b)) = integral_a^b Q_out dt.
    std::vector<double> xs, ys, vx;
    std::vector<std::size_t> cl, rows;
    std::size_t cluster = 0;
    for (const auto& set : sets) {
        const Recording& rec = *set.recording;
        require_thermal_channels(rec, "thermal capacity fit");
        const auto& t = rec.time_s;
        const auto& temp = rec.surface_c;
        const auto& q = rec.heat_flux_w_per_m2;
        for (const RowRange& r0 : set.rests) {
            const RowRange range = clamp_range(rec, r0);
            double sxy = 0, sxx = 0;
            std::size_t chunks = 0;
            // A rest logged sparsely (a cycler's "every 60 s"): end windows that hold five rows and parabolas through
            // them, on the dense chunks (chunks twice the windows apart, or the rows themselves as end values, did
            // worse on the plant logged that way: seeds 1-5 within -1.4..+15 % and 0.6..+3.1 % with one seed lost,
            // against -1.1..+2.0 % and one seed at +30 % +- 28 %).
            const double h_rows = median_interval_s(t, range.begin, range.end);
            const bool sparse = std::isfinite(h_rows) && 2.5 * h_rows > half_dense;
            const double half = sparse ? 2.5 * h_rows : half_dense;
            sparse_rests += sparse;
            auto end_value = [&](std::size_t k) {
                return sparse ? local_parabola_value(t, temp, range.begin, range.end, k, half)
                              : local_line_value(t, temp, range.begin, range.end, k, half);
            };
            if (range.size() >= 10) {
                const double t0 = t[range.begin], t1 = t[range.end - 1];
                // Chunk boundaries: from skip_s into the rest every chunk_s, the last one where its end window
                // still lies inside the rest (a shorter tail of at least half a chunk makes one more chunk).
                std::vector<std::size_t> bounds;
                double next = t0 + std::max(skip_s, half);
                std::size_t last_ok = range.begin;
                for (std::size_t k = range.begin; k < range.end; ++k)
                    if (t[k] + half <= t1) last_ok = k;
                for (std::size_t k = range.begin; k <= last_ok; ++k)
                    if (t[k] >= next) {
                        bounds.push_back(k);
                        next = t[k] + chunk_dense_s;
                    }
                if (!bounds.empty() && last_ok > bounds.back() && t[last_ok] - t[bounds.back()] >= 0.5 * chunk_dense_s)
                    bounds.push_back(last_ok);
                std::vector<LineValue> tv;
                for (std::size_t k : bounds) tv.push_back(end_value(k));
                for (std::size_t c = 0; c + 1 < bounds.size(); ++c) {
                    if (!finite(tv[c].value) || !finite(tv[c + 1].value)) continue;
                    double e = 0, covered = 0, prev_t = kNaN, prev_q = kNaN;
                    for (std::size_t k = bounds[c]; k <= bounds[c + 1]; ++k) {
                        if (!finite(q[k])) continue;
                        if (finite(prev_t)) e += 0.5 * (q[k] + prev_q) * (t[k] - prev_t), covered += t[k] - prev_t;
                        prev_t = t[k], prev_q = q[k];
                    }
                    const double span = t[bounds[c + 1]] - t[bounds[c]];
                    if (!(span > 0) || covered < 0.9 * span) continue;  // heat flux missing over the chunk
                    xs.push_back(tv[c].value - tv[c + 1].value);
                    ys.push_back(e * area_m2);
                    vx.push_back(tv[c].var + tv[c + 1].var);
                    cl.push_back(cluster);
                    rows.push_back(bounds[c + 1] - bounds[c]);
                    sxy += xs.back() * ys.back();
                    sxx += xs.back() * xs.back() - vx.back();
                    ++chunks;
                }
            }
            out.per_rest_c_th_j_per_k.push_back(chunks && sxx > 0 ? sxy / sxx : kNaN);
            if (chunks) ++out.rests_used;
            ++cluster;
        }
    }
    std::size_t total_rows = 0;
    for (std::size_t n : rows) total_rows += n;
    out.points = total_rows;
    if (xs.size() < 3) {
        out.note = "no usable rest rows (rests shorter than skip " + printf_text("%.0f", skip_s) + " s + a chunk of " +
                   printf_text("%.0f", chunk_dense_s) + " s, or no thermal data in them)";
        return out;
    }
    const auto reg = robust_origin_regression(xs, ys, cl, vx);
    out.c_th_j_per_k = reg.slope;
    out.c_th_se_j_per_k = reg.se;
    out.r_squared = reg.r_squared;
    // Rows of the chunks the robust weights dropped.
    {
        std::vector<double> res(xs.size());
        for (std::size_t i = 0; i < xs.size(); ++i) res[i] = ys[i] - reg.slope * xs[i];
        const double sigma = std::max(mad_sigma_about_zero(res), 1e-300);
        for (std::size_t i = 0; i < xs.size(); ++i)
            if (std::abs(res[i]) >= 4.685 * sigma) out.points_rejected += rows[i];
    }
    if (!finite(out.c_th_j_per_k) || !(out.c_th_j_per_k > 0)) {
        out.note = "energy balance of the rests gave no positive C_th: the rests do not cool measurably";
        out.c_th_j_per_k = kNaN;
        return out;
    }
    out.note = "C_th " + printf_text("%.2f", out.c_th_j_per_k) + " +- " + printf_text("%.2f", out.c_th_se_j_per_k) +
               " J/K from the energy balance of " + std::to_string(out.rests_used) + " rest(s) in " +
               std::to_string(xs.size()) + " chunks of " + printf_text("%.0f", chunk_dense_s) + " s" +
               (sparse_rests ? " (" + std::to_string(sparse_rests) + " rest(s) logged sparsely: end values from parabolas)" : std::string()) +
               ", " + std::to_string(out.points) +
               " rows (skip " + printf_text("%.0f", skip_s) + " s), R^2 " + printf_text("%.4f", out.r_squared) +
               "; robust weights dropped " +
               printf_text("%.1f", 100.0 * static_cast<double>(out.points_rejected) / static_cast<double>(std::max<std::size_t>(out.points, 1))) +
               " % of the rows";
    if (finite(out.r_squared) && out.r_squared < 0.9)
        out.note += "; low R^2: the rests hold little cooling (small excess temperature) or the data are noisy";
    return out;
}

ThermalCapacityFit fit_thermal_capacity(const Recording& rec, const std::vector<RowRange>& rests, double area_m2,
                                        double skip_s, double window_s) {
    require_thermal_channels(rec, "thermal capacity fit");
    if (!(area_m2 > 0)) throw InputError(rec.source + ": thermal capacity fit: area_m2 must be > 0");
    return fit_thermal_capacity(std::vector<ThermalRests>{{&rec, rests}}, area_m2, skip_s, window_s);
}

// ---------------------------------------------------------------------------------------------------------------
ThermalResistanceFit fit_thermal_resistance(const Recording& rec, const std::vector<RowRange>& ranges, double area_m2,
                                            double c_th_j_per_k, const ThermalResistanceOptions& opt) {
    require_thermal_channels(rec, "thermal resistance fit");
    if (!(area_m2 > 0)) throw InputError(rec.source + ": thermal resistance fit: area_m2 must be > 0");
    if (!(c_th_j_per_k > 0)) throw InputError(rec.source + ": thermal resistance fit: C_th must be > 0");
    ThermalResistanceFit out;
    const auto& T = rec.surface_c;
    const auto& q = rec.heat_flux_w_per_m2;
    std::vector<std::string> notes;

    // (a) Q_out = (T - T_amb) / R_th  (eq. 1.37 / 4.9: R_th = 1/(h*A)), regression of Q_out on the temperature.
    const bool amb_column = rec.has_ambient();
    const bool amb_given = !amb_column && finite(opt.ambient_c);
    out.ambient_source = amb_column ? "ambient column" : amb_given ? "given" : "intercept per range";
    {
        std::vector<double> xs, ys;  // x: T - T_amb (known) or T - mean_k(T) (fixed effects); y likewise for Q
        std::vector<std::size_t> cl;
        std::vector<std::pair<double, double>> means;  // per range: mean T, mean Q (fixed effects)
        for (std::size_t r = 0; r < ranges.size(); ++r) {
            const RowRange range = clamp_range(rec, ranges[r]);
            std::vector<double> tx, qy;
            for (std::size_t k = range.begin; k < range.end; ++k) {
                const double amb = amb_column ? rec.ambient_c[k] : amb_given ? opt.ambient_c : 0.0;
                if (!finite(T[k]) || !finite(q[k]) || !finite(amb)) continue;
                tx.push_back(T[k] - amb);
                qy.push_back(q[k] * area_m2);
            }
            double mt = kNaN, mq = kNaN;
            if (!tx.empty()) {
                mt = std::accumulate(tx.begin(), tx.end(), 0.0) / static_cast<double>(tx.size());
                mq = std::accumulate(qy.begin(), qy.end(), 0.0) / static_cast<double>(qy.size());
            }
            means.emplace_back(mt, mq);
            for (std::size_t i = 0; i < tx.size(); ++i) {
                xs.push_back(amb_column || amb_given ? tx[i] : tx[i] - mt);
                ys.push_back(amb_column || amb_given ? qy[i] : qy[i] - mq);
                cl.push_back(r);
            }
        }
        out.flux_points = xs.size();
        if (xs.size() >= 3) {
            // Plain least squares (the heat flux is the noisy variable); errors as for C_th.
            double sxy = 0, sxx = 0;
            for (std::size_t i = 0; i < xs.size(); ++i) sxy += xs[i] * ys[i], sxx += xs[i] * xs[i];
            const double g = sxx > 0 ? sxy / sxx : kNaN;  // = h*A = 1/R_th
            if (finite(g) && g > 0) {
                std::vector<double> res(xs.size());
                double sse = 0, sst = 0, ym = 0;
                for (double v : ys) ym += v;
                ym /= static_cast<double>(ys.size());
                for (std::size_t i = 0; i < xs.size(); ++i) {
                    res[i] = ys[i] - g * xs[i];
                    sse += res[i] * res[i];
                    sst += (ys[i] - ym) * (ys[i] - ym);
                }
                const double n = static_cast<double>(xs.size());
                const double rho = lag1_autocorrelation(res, cl);
                double se_g = std::sqrt(sse / std::max(1.0, n - 1.0) / sxx * n / effective_n(n, rho));
                std::vector<double> score;
                std::vector<std::size_t> ids;
                for (std::size_t i = 0; i < xs.size(); ++i) {
                    auto pos = std::find(ids.begin(), ids.end(), cl[i]);
                    if (pos == ids.end()) ids.push_back(cl[i]), score.push_back(0.0), pos = ids.end() - 1;
                    score[static_cast<std::size_t>(pos - ids.begin())] += xs[i] * res[i];
                }
                if (ids.size() >= 3) {
                    double s = 0;
                    for (double v : score) s += v * v;
                    const double gg = static_cast<double>(ids.size());
                    se_g = std::max(se_g, std::sqrt(s * gg / (gg - 1.0)) / sxx);
                }
                out.r_th_flux_k_per_w = 1.0 / g;
                out.r_th_flux_se_k_per_w = se_g / (g * g);
                out.flux_r_squared = sst > 0 ? 1.0 - sse / sst : kNaN;
                for (const auto& [mt, mq] : means) {
                    if (amb_column) out.ambient_per_range_c.push_back(kNaN);
                    else if (amb_given) out.ambient_per_range_c.push_back(opt.ambient_c);
                    else out.ambient_per_range_c.push_back(finite(mt) ? mt - mq / g : kNaN);
                }
            } else {
                notes.push_back("(a) heat flow does not rise with temperature in these ranges: no R_th from the flux");
            }
        } else {
            notes.push_back("(a) no rows with temperature and heat flux");
        }
        if (!amb_column && !amb_given && ranges.size() == 1)
            notes.push_back("(a) ambient estimated as the intercept of a single range: prefer a measured or given "
                            "ambient (h grows with the temperature excess, which biases the intercept)");
    }

    // (b) cooling time constant of rests: tau = R_th * C_th (first-order model).
    {
        std::vector<std::pair<double, double>> tw;  // tau, weight 1/se^2
        for (const RowRange& r0 : ranges) {
            const RowRange range = clamp_range(rec, r0);
            bool rest = range.size() > 0;
            for (std::size_t k = range.begin; k < range.end && rest; ++k)
                if (finite(rec.current_a[k]) && std::abs(rec.current_a[k]) > opt.rest_current_a) rest = false;
            if (!rest) continue;
            RestCoolingFit f = fit_rest_cooling(rec, range, opt);
            if (f.used) tw.emplace_back(f.tau_s, 1.0 / (f.tau_se_s * f.tau_se_s));
            out.rests.push_back(std::move(f));
        }
        out.rests_used = tw.size();
        if (!tw.empty()) {
            double sw = 0, sw2 = 0, swt = 0;
            for (const auto& [tau, w] : tw) sw += w, sw2 += w * w, swt += w * tau;
            const double mean = swt / sw;
            double se = std::sqrt(1.0 / sw);  // formal
            if (tw.size() >= 2) {
                double s = 0;
                for (const auto& [tau, w] : tw) s += w * (tau - mean) * (tau - mean);
                const double neff = sw * sw / sw2;
                if (neff > 1.0) se = std::max(se, std::sqrt(s / sw / (neff - 1.0)));
            }
            // The weighted median resists a rest whose excess temperature does not decay as one exponential;
            // its error is ~1.25 x that of the mean.
            out.tau_s = tw.size() >= 3 ? weighted_median(tw) : mean;
            out.tau_se_s = tw.size() >= 3 ? 1.2533 * se : se;
            out.r_th_tau_k_per_w = out.tau_s / c_th_j_per_k;
            const double rel = std::hypot(out.tau_se_s / out.tau_s, opt.c_th_se_j_per_k / c_th_j_per_k);
            out.r_th_tau_se_k_per_w = out.r_th_tau_k_per_w * rel;
        } else if (!out.rests.empty()) {
            notes.push_back("(b) no rest cools measurably (excess temperature >= " + printf_text("%.2f", opt.min_delta_t_k) +
                            " K after the skip)");
        } else {
            notes.push_back("(b) no rest among the ranges: the cooling time constant needs a rest");
        }
    }

    if (finite(out.r_th_flux_k_per_w) && finite(out.r_th_tau_k_per_w)) {
        const double a = out.r_th_flux_k_per_w, b = out.r_th_tau_k_per_w;
        out.relative_difference = (a - b) / (0.5 * (a + b));
        out.disagree = std::abs(out.relative_difference) > opt.disagree_fraction;
        std::string s = "R_th from heat flow " + printf_text("%.2f", a) + " K/W vs from cooling time constant " +
                        printf_text("%.2f", b) + " K/W (tau " + printf_text("%.0f", out.tau_s) + " s / C_th " +
                        printf_text("%.1f", c_th_j_per_k) + " J/K): " + printf_text("%+.1f", 100 * out.relative_difference) + " %";
        if (out.disagree)
            s += " - they DISAGREE by more than " + printf_text("%.0f", 100 * opt.disagree_fraction) +
                 " %. Likely causes: the sensor sees the flux of one patch of the can, not the terminals and "
                 "cables (flux-based R_th too high) or a sensor gain error; core hotter than the surface "
                 "(two-node cooling: tau/C_th too high); C_th error; ambient drift during the rests";
        else
            s += ", consistent";
        notes.insert(notes.begin(), s);
    }
    for (std::size_t i = 0; i < notes.size(); ++i) out.note += (i ? "; " : "") + notes[i];
    return out;
}

// ---------------------------------------------------------------------------------------------------------------
EntropicFit fit_entropic_coefficient(const Recording& rec, RowRange cc_discharge, const std::vector<double>& soc_of_row,
                                     const std::vector<double>& ocv_soc, const std::vector<double>& ocv_v,
                                     double c_th_j_per_k, double area_m2, const std::vector<double>& soc_grid,
                                     const EntropicOptions& opt) {
    require_thermal_channels(rec, "entropic coefficient fit");
    if (soc_of_row.size() != rec.size())
        throw InputError(rec.source + ": entropic coefficient fit: soc_of_row has " + std::to_string(soc_of_row.size()) +
                         " values, the recording " + std::to_string(rec.size()) + " rows");
    if (ocv_soc.size() != ocv_v.size() || ocv_soc.size() < 2 || !strictly_ascending(ocv_soc))
        throw InputError(rec.source + ": entropic coefficient fit: OCV table needs >= 2 ascending SOC points, one "
                                      "voltage each");
    if (soc_grid.empty() || !strictly_ascending(soc_grid))
        throw InputError(rec.source + ": entropic coefficient fit: SOC grid must be non-empty and ascending");
    if (!(c_th_j_per_k > 0) || !(area_m2 > 0))
        throw InputError(rec.source + ": entropic coefficient fit: C_th and area must be > 0");

    EntropicFit out;
    const std::size_t m = soc_grid.size();
    out.soc = soc_grid;
    out.ehc_v_per_k.assign(m, kNaN);
    out.spread_v_per_k.assign(m, kNaN);
    out.samples.assign(m, 0);
    out.has_data.assign(m, false);
    out.extrapolated_ocv.assign(m, false);
    for (std::size_t j = 0; j < m; ++j)
        out.extrapolated_ocv[j] = soc_grid[j] < ocv_soc.front() - 1e-9 || soc_grid[j] > ocv_soc.back() + 1e-9;

    // Bin edges: midpoints between grid points; the end bins reach half a spacing beyond the end points.
    std::vector<double> lo(m), hi(m);
    for (std::size_t j = 0; j < m; ++j) {
        const double left = j > 0 ? 0.5 * (soc_grid[j - 1] + soc_grid[j]) : kNaN;
        const double right = j + 1 < m ? 0.5 * (soc_grid[j] + soc_grid[j + 1]) : kNaN;
        lo[j] = j > 0 ? left : (m > 1 ? soc_grid[0] - (right - soc_grid[0]) : -1e300);
        hi[j] = j + 1 < m ? right : (m > 1 ? soc_grid[j] + (soc_grid[j] - left) : 1e300);
    }

    const RowRange range = clamp_range(rec, cc_discharge);
    std::vector<std::vector<double>> bins(m);
    std::vector<double> shares;
    double sum_abs_i = 0;
    if (range.size() >= 3) {
        const auto& t = rec.time_s;
        // A discharge logged sparsely (a cycler's 5 mV or 60 s): the derivative's window holds at least four rows.
        const double h_rows = median_interval_s(t, range.begin, range.end);
        const double window_s = std::isfinite(h_rows) ? std::max(opt.window_s, 4.0 * h_rows) : opt.window_s;
        const auto d = smooth_derivative(t, rec.surface_c, range.begin, range.end, window_s);
        const double t0 = t[range.begin];
        for (std::size_t k = range.begin; k < range.end; ++k) {
            const double i_a = rec.current_a[k], v = rec.voltage_v[k], temp = rec.surface_c[k];
            const double q = rec.heat_flux_w_per_m2[k], soc = soc_of_row[k], dtdt = d[k - range.begin];
            if (t[k] - t0 < opt.skip_s) continue;
            if (!finite(i_a) || std::abs(i_a) < opt.min_current_a) continue;
            if (!finite(v) || !finite(temp) || !finite(q) || !finite(soc) || !finite(dtdt)) continue;
            const double q_total = c_th_j_per_k * dtdt + q * area_m2;                 // eq. 4.3
            const double q_irr = i_a * (v - interp_linear_extrap(ocv_soc, ocv_v, soc));  // eq. 4.5
            const double q_rev = q_total - q_irr;                                         // eq. 4.4
            const double ehc = q_rev / (i_a * (temp + kZeroCelsiusK));                    // eq. 4.6
            // No bound per row: at a low rate (C/20) the per-row value is noisy (the smoothed dT/dt alone gives
            // about 1 mV/K of scatter), and cutting rows at +-max_abs_v_per_k around zero cut more of the tail on
            // the side of the true value than of the other, pulling every bin's median towards zero (independent
            // plant seed 11: 0.15 mV/K read as 0.04). The median needs no such cut; the bound applies to the bins.
            if (!finite(ehc)) {
                ++out.rows_rejected;
                continue;
            }
            std::size_t j = static_cast<std::size_t>(std::upper_bound(lo.begin(), lo.end(), soc) - lo.begin());
            if (j == 0) {
                ++out.rows_rejected;  // below the lowest bin
                continue;
            }
            --j;
            if (!(soc < hi[j])) {
                ++out.rows_rejected;  // above the highest bin
                continue;
            }
            bins[j].push_back(ehc);
            ++out.rows_used;
            sum_abs_i += std::abs(i_a);
            const double denom = std::abs(q_irr) + std::abs(q_rev);
            if (denom > 0) shares.push_back(q_irr / denom);
        }
    }
    if (out.rows_used > 0) out.mean_abs_current_a = sum_abs_i / static_cast<double>(out.rows_used);
    out.joule_share = median_of(shares);

    std::vector<std::string> empty_bins, extrap_bins, clipped_bins;
    for (std::size_t j = 0; j < m; ++j) {
        out.samples[j] = bins[j].size();
        if (bins[j].size() < opt.min_samples || bins[j].empty()) {
            empty_bins.push_back(printf_text("%.2f", soc_grid[j]));
            continue;
        }
        const double med = median_of(bins[j]);
        std::vector<double> dev;
        dev.reserve(bins[j].size());
        for (double v : bins[j]) dev.push_back(v - med);
        out.ehc_v_per_k[j] = std::clamp(med, -opt.max_abs_v_per_k, opt.max_abs_v_per_k);
        if (std::abs(med) > opt.max_abs_v_per_k) clipped_bins.push_back(printf_text("%.2f", soc_grid[j]));
        out.spread_v_per_k[j] = mad_sigma_about_zero(dev);
        out.has_data[j] = true;
        if (out.extrapolated_ocv[j]) extrap_bins.push_back(printf_text("%.2f", soc_grid[j]));
    }

    std::vector<std::string> notes;
    if (out.rows_used == 0) notes.push_back("no usable rows in the discharge range");
    if (finite(out.joule_share) && out.joule_share > 0.6)
        notes.push_back("Joule heat dominates (median " + printf_text("%.0f", 100 * out.joule_share) + " % of |Q_irr|+|Q_rev| at " +
                        printf_text("%.1f", out.mean_abs_current_a) +
                        " A): dU/dT is a small difference of large terms, sensitive to OCV (10 mV -> ~0.03 mV/K at "
                        "4C), C_th and the heat flux sensor gain; estimate kept robust (bound +-" +
                        printf_text("%.1f", 1e3 * opt.max_abs_v_per_k) +
                        " mV/K per SOC bin, medians of the rows). Prefer a C/2 or slower discharge (thesis 4.1.2)");
    // "<what> at SOC a b c<why>", when any bin is so.
    auto bins_note = [&](const std::vector<std::string>& bins_of, const std::string& what, const std::string& why) {
        if (bins_of.empty()) return;
        std::string s = what + " at SOC";
        for (const auto& b : bins_of) s += " " + b;
        notes.push_back(s + why);
    };
    bins_note(empty_bins, "no data", "");
    bins_note(extrap_bins, "OCV extrapolated outside the table", " (Joule heat and dU/dT unreliable there)");
    bins_note(clipped_bins, "held at the bound +-" + printf_text("%.1f", 1e3 * opt.max_abs_v_per_k) + " mV/K",
              " (implausible beyond it)");
    if (out.rows_rejected > 0)
        notes.push_back(std::to_string(out.rows_rejected) + " rows outside the SOC grid or not finite discarded");
    for (std::size_t i = 0; i < notes.size(); ++i) out.note += (i ? "; " : "") + notes[i];
    return out;
}

// ---------------------------------------------------------------------------------------------------------------
double charge_throughput_ah(const Recording& rec, RowRange range, CurrentIntegration method) {
    range = clamp_range(rec, range);
    const auto& t = rec.time_s;
    const auto& i = rec.current_a;
    double as = 0;
    if (method == CurrentIntegration::Hold) {
        for (std::size_t k = std::max<std::size_t>(range.begin, 1); k < range.end; ++k)
            if (finite(i[k])) as += i[k] * (t[k] - t[k - 1]);
    } else {
        for (std::size_t k = range.begin + 1; k < range.end; ++k)
            if (finite(i[k]) && finite(i[k - 1])) as += 0.5 * (i[k] + i[k - 1]) * (t[k] - t[k - 1]);
    }
    return as / 3600.0;
}

double pilot_discharge_capacity_ah(const Recording& rec, RowRange pilot, CurrentIntegration method) {
    const double ah = charge_throughput_ah(rec, pilot, method);
    if (!(ah < 0))
        throw InputError(rec.source + ": pilot discharge rows [" + std::to_string(pilot.begin) + ", " +
                         std::to_string(pilot.end) + ") discharge no charge");
    return -ah;
}

}  // namespace cellbench::estimator
