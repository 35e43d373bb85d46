// Clock offset between cycler and DAQ from the heat balance (see align.hpp).
#include "cellbench/estimator/align.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "cellbench/estimator/thermal_fit.hpp"

#include "median.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {
namespace {

bool finite(double v) { return std::isfinite(v); }


// Weights of the local-linear derivative seen as a smoother: the slope of a least-squares line over
// [t-h, t+h] equals the derivative smoothed with the parabolic kernel K(s) = 3/(4h) (1 - s^2/h^2). Applying K to
// every term of the DAQ heat and to the cycler side makes both sides see the same (symmetric) smoothing, so the
// smoothing cannot masquerade as lag or offset.
//
// Parabolic-kernel local mean of y on (possibly non-uniform) samples, window [t-h, t+h] (truncated at the ends).
std::vector<double> parabolic_smooth(const std::vector<double>& t, const std::vector<double>& y, double h) {
    const std::size_t n = t.size();
    std::vector<double> out(n, kNaN);
    if (n == 0) return out;
    const double t_ref = t.front();
    std::vector<long double> c0(n + 1, 0), c1(n + 1, 0), c2(n + 1, 0), cy(n + 1, 0), c1y(n + 1, 0), c2y(n + 1, 0);
    for (std::size_t k = 0; k < n; ++k) {
        const bool ok = finite(y[k]);
        const long double tt = t[k] - t_ref, yy = ok ? y[k] : 0.0;
        const long double w = ok ? 1.0L : 0.0L;
        c0[k + 1] = c0[k] + w;
        c1[k + 1] = c1[k] + w * tt;
        c2[k + 1] = c2[k] + w * tt * tt;
        cy[k + 1] = cy[k] + yy;
        c1y[k + 1] = c1y[k] + tt * yy;
        c2y[k + 1] = c2y[k] + tt * tt * yy;
    }
    std::size_t lo = 0, hi = 0;
    for (std::size_t k = 0; k < n; ++k) {
        while (lo < n && t[lo] < t[k] - h) ++lo;
        if (hi < lo) hi = lo;
        while (hi < n && t[hi] <= t[k] + h) ++hi;
        const long double c = t[k] - t_ref, hh = static_cast<long double>(h) * h;
        const long double N = c0[hi] - c0[lo], S1 = c1[hi] - c1[lo], S2 = c2[hi] - c2[lo];
        const long double Y = cy[hi] - cy[lo], Y1 = c1y[hi] - c1y[lo], Y2 = c2y[hi] - c2y[lo];
        // sum of w_i = h^2 - (t_i - c)^2 over the window, and of w_i * y_i
        const long double wsum = hh * N - (S2 - 2 * c * S1 + c * c * N);
        const long double wy = hh * Y - (Y2 - 2 * c * Y1 + c * c * Y);
        if (N >= 1 && wsum > 0) out[k] = static_cast<double>(wy / wsum);
        else if (N >= 1) out[k] = static_cast<double>(Y / N);
    }
    return out;
}

// The cycler side: I^2 passed through a first-order lag (time constant lag_s, 0 = none) with the model's hold
// convention (I[k] flows during (t[k-1], t[k]]; exact integral per interval), averaged over a fine uniform grid,
// then smoothed with the same parabolic kernel as the DAQ side. NaN where the kernel leaves the cycler record.
class CyclerHeat {
public:
    CyclerHeat(const std::vector<double>& t, const std::vector<double>& i, double lag_s, double h, double step_s)
        : t0_(t.front()), step_(step_s) {
        const std::size_t n = t.size();
        std::vector<double> x(n), y(n), cum(n);
        for (std::size_t k = 0; k < n; ++k) x[k] = finite(i[k]) ? i[k] * i[k] : 0.0;
        y[0] = x[0];  // the state before the record: as if the first current had held for long
        cum[0] = 0.0;
        auto partial = [&](std::size_t k, double s) {  // integral over the first s seconds of interval k
            if (!(s > 0)) return 0.0;
            if (lag_s <= 0) return x[k] * s;
            return x[k] * s + (y[k - 1] - x[k]) * lag_s * (1.0 - std::exp(-s / lag_s));
        };
        for (std::size_t k = 1; k < n; ++k) {
            const double dt = t[k] - t[k - 1];
            cum[k] = cum[k - 1] + partial(k, dt);
            y[k] = lag_s > 0 ? x[k] + (y[k - 1] - x[k]) * std::exp(-dt / lag_s) : x[k];
        }
        // Box averages on the fine grid [t0 + g*step, t0 + (g+1)*step], value placed at the box centre.
        const auto ng = static_cast<std::size_t>(std::floor((t.back() - t0_) / step_s));
        std::vector<double> box(ng);
        std::size_t hint = 1;
        auto cumulative = [&](double tq) {
            while (hint < n - 1 && t[hint] < tq) ++hint;
            const std::size_t k = hint;
            const double s = std::clamp(tq - t[k - 1], 0.0, t[k] - t[k - 1]);
            return cum[k - 1] + partial(k, s);
        };
        double prev = cumulative(t0_);
        for (std::size_t g = 0; g < ng; ++g) {
            const double next = cumulative(t0_ + static_cast<double>(g + 1) * step_s);
            box[g] = (next - prev) / step_s;
            prev = next;
        }
        // Parabolic kernel on the grid.
        const int half = static_cast<int>(std::floor(h / step_s));
        std::vector<double> kern;
        double ksum = 0;
        for (int j = -half; j <= half; ++j) {
            const double s = j * step_s;
            const double w = half > 0 ? 1.0 - (s * s) / (h * h) : 1.0;
            kern.push_back(std::max(w, 0.0));
            ksum += kern.back();
        }
        for (double& w : kern) w /= ksum;
        val_.assign(ng, kNaN);
        for (std::size_t g = static_cast<std::size_t>(half); g + static_cast<std::size_t>(half) < ng; ++g) {
            double acc = 0;
            for (int j = -half; j <= half; ++j) acc += kern[static_cast<std::size_t>(j + half)] * box[g + j];
            val_[g] = acc;
        }
    }

    // Linear interpolation between box centres; NaN outside the valid part.
    double at(double tq) const {
        const double u = (tq - t0_) / step_ - 0.5;
        if (!(u >= 0)) return kNaN;
        const auto g = static_cast<std::size_t>(u);
        if (g + 1 >= val_.size()) return kNaN;
        const double f = u - static_cast<double>(g);
        return val_[g] + f * (val_[g + 1] - val_[g]);  // NaN propagates at the edges
    }

private:
    double t0_, step_;
    std::vector<double> val_;
};

struct CorrSums {
    double n = 0, sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
    void add(double x, double y) {
        n += 1;
        sx += x, sy += y, sxx += x * x, syy += y * y, sxy += x * y;
    }
    double r() const {
        if (n < 3) return kNaN;
        const double vx = sxx - sx * sx / n, vy = syy - sy * sy / n, c = sxy - sx * sy / n;
        if (!(vx > 0) || !(vy > 0)) return kNaN;
        return c / std::sqrt(vx * vy);
    }
    double slope_y_on_x() const {
        const double vx = sxx - sx * sx / n, c = sxy - sx * sy / n;
        return vx > 0 ? c / vx : kNaN;
    }
};

struct Candidate {
    double offset_s = kNaN, r = -2.0, overlap_s = 0.0, slope = kNaN;
};

class Aligner {
public:
    Aligner(const std::vector<double>& tc, const std::vector<double>& ic, const std::vector<double>& td,
            std::vector<double> heat, double h, double bin_s, double min_overlap_s)
        : tc_(tc), ic_(ic), td_(td), heat_(std::move(heat)), h_(h), bin_s_(bin_s), min_overlap_s_(min_overlap_s) {
        // DAQ heat in bins of bin_s anchored at the first DAQ stamp.
        const std::size_t nb = static_cast<std::size_t>(std::floor((td.back() - td.front()) / bin_s)) + 1;
        std::vector<double> sum(nb, 0.0), cnt(nb, 0.0);
        for (std::size_t k = 0; k < td.size(); ++k) {
            if (!finite(heat_[k])) continue;
            const auto j = static_cast<std::size_t>((td[k] - td.front()) / bin_s);
            if (j < nb) sum[j] += heat_[k], cnt[j] += 1;
        }
        dbin_.assign(nb, kNaN);
        for (std::size_t j = 0; j < nb; ++j)
            if (cnt[j] > 0) dbin_[j] = sum[j] / cnt[j];
        std::vector<double> dts;
        for (std::size_t k = 1; k < td.size(); ++k) dts.push_back(td[k] - td[k - 1]);
        sample_s_ = std::max(upper_median(std::move(dts)), 1e-3);
    }

    CyclerHeat cycler(double lag_s) const { return CyclerHeat(tc_, ic_, lag_s, h_, std::min(0.1, sample_s_)); }

    // Coarse: offsets that are whole multiples of bin_s in [lo_s, hi_s], on bins; returns the best.
    Candidate coarse(const CyclerHeat& ch, double lo_s, double hi_s) const {
        const double td0 = td_.front();
        const long nb = static_cast<long>(dbin_.size());
        // Cycler value of "bin m" = the smoothed series at the centre of [td0 + m*bin, td0 + (m+1)*bin].
        const long m0 = static_cast<long>(std::floor((tc_.front() - td0) / bin_s_));
        const long m1 = static_cast<long>(std::ceil((tc_.back() - td0) / bin_s_));
        std::vector<double> cbin(static_cast<std::size_t>(std::max(0L, m1 - m0 + 1)));
        for (long m = m0; m <= m1; ++m)
            cbin[static_cast<std::size_t>(m - m0)] = ch.at(td0 + (static_cast<double>(m) + 0.5) * bin_s_);
        Candidate best;
        const long s_lo = static_cast<long>(std::ceil(lo_s / bin_s_ - 1e-9));
        const long s_hi = static_cast<long>(std::floor(hi_s / bin_s_ + 1e-9));
        for (long s = s_lo; s <= s_hi; ++s) {
            const long j_lo = std::max(0L, m0 - s), j_hi = std::min(nb - 1, m1 - s);
            CorrSums cs;
            for (long j = j_lo; j <= j_hi; ++j) {
                const double d = dbin_[static_cast<std::size_t>(j)];
                const double c = cbin[static_cast<std::size_t>(j + s - m0)];
                if (finite(d) && finite(c)) cs.add(c, d);
            }
            if (cs.n * bin_s_ < min_overlap_s_) continue;
            const double r = cs.r();
            if (finite(r) && r > best.r) best = {static_cast<double>(s) * bin_s_, r, cs.n * bin_s_, cs.slope_y_on_x()};
        }
        return best;
    }

    // Full resolution: every DAQ sample against the cycler series at the shifted time.
    Candidate at(const CyclerHeat& ch, double offset_s) const {
        CorrSums cs;
        for (std::size_t k = 0; k < td_.size(); ++k) {
            if (!finite(heat_[k])) continue;
            const double c = ch.at(td_[k] + offset_s);
            if (finite(c)) cs.add(c, heat_[k]);
        }
        Candidate c;
        c.offset_s = offset_s;
        c.overlap_s = cs.n * sample_s_;
        if (c.overlap_s < min_overlap_s_) return c;
        const double r = cs.r();
        c.r = finite(r) ? r : -2.0;
        c.slope = cs.slope_y_on_x();
        return c;
    }

    // Fine search around a centre: 0.1 s steps over +-span_s, then a parabola through the peak.
    Candidate refine(const CyclerHeat& ch, double centre_s, double span_s) const {
        const double step = 0.1;
        const int n = static_cast<int>(std::round(span_s / step));
        std::vector<Candidate> cs;
        for (int i = -n; i <= n; ++i) cs.push_back(at(ch, centre_s + step * i));
        std::size_t b = 0;
        for (std::size_t i = 1; i < cs.size(); ++i)
            if (cs[i].r > cs[b].r) b = i;
        Candidate best = cs[b];
        if (b > 0 && b + 1 < cs.size() && cs[b - 1].r > -2 && cs[b + 1].r > -2) {
            const double y0 = cs[b - 1].r, y1 = cs[b].r, y2 = cs[b + 1].r;
            const double den = y0 - 2 * y1 + y2;
            if (den < 0) {
                const double delta = std::clamp(0.5 * (y0 - y2) / den, -0.5, 0.5);
                const Candidate p = at(ch, best.offset_s + delta * step);
                if (p.r >= best.r) best = p;
            }
        }
        return best;
    }

private:
    const std::vector<double>& tc_;
    const std::vector<double>& ic_;
    const std::vector<double>& td_;
    std::vector<double> heat_;
    double h_, bin_s_, min_overlap_s_;
    std::vector<double> dbin_;
    double sample_s_ = 0.1;
};

}  // namespace

ClockAlignment estimate_clock_offset(const std::vector<double>& cycler_time_s, const std::vector<double>& current_a,
                                     const std::vector<double>& daq_time_s, const std::vector<double>& temperature_c,
                                     const std::vector<double>& heat_flux_w_per_m2, double c_th_j_per_k,
                                     double area_m2, double max_offset_s, const AlignOptions& options) {
    if (cycler_time_s.size() != current_a.size())
        throw InputError("clock alignment: cycler time and current differ in length");
    if (daq_time_s.size() != temperature_c.size() || daq_time_s.size() != heat_flux_w_per_m2.size())
        throw InputError("clock alignment: DAQ time, temperature and heat flux differ in length");
    if (cycler_time_s.size() < 10 || daq_time_s.size() < 10)
        throw InputError("clock alignment: fewer than 10 samples");
    if (!(c_th_j_per_k > 0) || !(area_m2 > 0) || !(max_offset_s > 0))
        throw InputError("clock alignment: C_th, area and max_offset_s must be > 0");
    for (std::size_t k = 1; k < cycler_time_s.size(); ++k)
        if (!(cycler_time_s[k] >= cycler_time_s[k - 1]))
            throw InputError("clock alignment: cycler time is not ascending at sample " + std::to_string(k));
    for (std::size_t k = 1; k < daq_time_s.size(); ++k)
        if (!(daq_time_s[k] > daq_time_s[k - 1]))
            throw InputError("clock alignment: DAQ time is not increasing at sample " + std::to_string(k));

    // DAQ side of the heat balance (thesis eq. 4.3): Q = C_th dT/dt + q'' A.
    // dT/dt by local linear regression = T' smoothed with the parabolic kernel; q'' gets the same kernel.
    const double h = 0.5 * options.derivative_window_s;
    const auto dtdt = smooth_derivative(daq_time_s, temperature_c, 0, daq_time_s.size(), options.derivative_window_s);
    const auto q_smooth = parabolic_smooth(daq_time_s, heat_flux_w_per_m2, h);
    std::vector<double> heat(daq_time_s.size(), kNaN);
    for (std::size_t k = 0; k < heat.size(); ++k)
        if (finite(dtdt[k]) && finite(q_smooth[k]) && finite(heat_flux_w_per_m2[k]))
            heat[k] = c_th_j_per_k * dtdt[k] + q_smooth[k] * area_m2;

    const double dur_c = cycler_time_s.back() - cycler_time_s.front();
    const double dur_d = daq_time_s.back() - daq_time_s.front();
    const double min_overlap = options.min_overlap_fraction * std::min(dur_c, dur_d);
    std::vector<double> dts;
    for (std::size_t k = 1; k < daq_time_s.size(); ++k) dts.push_back(daq_time_s[k] - daq_time_s[k - 1]);
    const double bin_s = std::max(1.0, upper_median(std::move(dts)));
    const Aligner al(cycler_time_s, current_a, daq_time_s, std::move(heat), h, bin_s, min_overlap);

    // 1) Coarse, full offset range, on a lag grid.
    std::vector<double> lag_grid;
    for (double l : {0.0, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0, 120.0})
        if (l <= options.max_lag_s + 1e-9) lag_grid.push_back(l);
    std::vector<Candidate> coarse;
    for (double l : lag_grid) coarse.push_back(al.coarse(al.cycler(l), -max_offset_s, max_offset_s));
    std::size_t gi = 0;
    for (std::size_t i = 1; i < coarse.size(); ++i)
        if (coarse[i].r > coarse[gi].r) gi = i;
    if (!finite(coarse[gi].offset_s))
        throw InputError("clock alignment: no offset within +-" + printf_text("%.0f", max_offset_s) +
                         " s gives an overlap of at least " + printf_text("%.0f", min_overlap) + " s");
    const double global_offset = coarse[gi].offset_s;

    // 2) Every lag in 1 s steps: coarse offsets near the ridge (+-15 s around the interpolated coarse optimum,
    //    which stays on the global peak's ridge), then 0.1 s refinement at full resolution.
    auto ridge_centre = [&](double lag) {
        std::size_t i = 0;
        while (i + 1 < lag_grid.size() && lag_grid[i + 1] < lag) ++i;
        if (i + 1 >= lag_grid.size()) return coarse[i].offset_s;
        const double f = (lag - lag_grid[i]) / (lag_grid[i + 1] - lag_grid[i]);
        double a = coarse[i].offset_s, b = coarse[i + 1].offset_s;
        // A grid lag whose own optimum jumped to another peak does not steer the ridge.
        if (!finite(a) || std::abs(a - global_offset) > 60.0 + lag_grid[i]) a = global_offset;
        if (!finite(b) || std::abs(b - global_offset) > 60.0 + lag_grid[i + 1]) b = global_offset;
        return a + f * (b - a);
    };
    struct LagResult {
        double lag;
        Candidate c;
    };
    std::vector<LagResult> scan;
    const double lag_max = lag_grid.back();
    for (double lag = 0.0; lag <= lag_max + 1e-9; lag += 1.0) {
        const double centre = ridge_centre(lag);
        const CyclerHeat ch = al.cycler(lag);
        const Candidate c0 = al.coarse(ch, std::max(-max_offset_s, centre - 15.0), std::min(max_offset_s, centre + 15.0));
        if (!finite(c0.offset_s)) continue;
        scan.push_back({lag, al.refine(ch, c0.offset_s, 1.5 * bin_s)});
    }
    if (scan.empty()) throw InputError("clock alignment: refinement found no overlap");
    std::size_t bi = 0;
    for (std::size_t i = 1; i < scan.size(); ++i)
        if (scan[i].c.r > scan[bi].c.r) bi = i;

    ClockAlignment out;
    out.offset_s = scan[bi].c.offset_s;
    out.correlation = scan[bi].c.r;
    out.lag_s = scan[bi].lag;
    out.overlap_s = scan[bi].c.overlap_s;
    out.joule_resistance_ohm = scan[bi].c.slope;
    for (const auto& s : scan)
        if (s.lag == 0.0) out.offset_no_lag_s = s.c.offset_s, out.correlation_no_lag = s.c.r;
    double lo = out.offset_s, hi = out.offset_s;
    for (const auto& s : scan)
        if (s.c.r >= out.correlation - options.ridge_tolerance) lo = std::min(lo, s.c.offset_s), hi = std::max(hi, s.c.offset_s);
    out.uncertainty_s = std::max(0.05, 0.5 * (hi - lo));
    out.at_search_limit = std::abs(std::abs(out.offset_s) - max_offset_s) < 2.0 * bin_s;
    out.start_mismatch_s = daq_time_s.front() + out.offset_s - cycler_time_s.front();
    out.end_mismatch_s = daq_time_s.back() + out.offset_s - cycler_time_s.back();

    out.note = "heat balance correlation r = " + printf_text("%.3f", out.correlation) + " at offset " +
               printf_text("%+.2f", out.offset_s) + " s with a " + printf_text("%.0f", out.lag_s) +
               " s first-order response lag (effective Joule resistance " +
               printf_text("%.1f", 1e3 * out.joule_resistance_ohm) + " mOhm); plain I^2 cross-correlation gives " +
               printf_text("%+.2f", out.offset_no_lag_s) + " s (r = " + printf_text("%.3f", out.correlation_no_lag) +
               "); offset and lag trade off: offsets within " + printf_text("%.1f", out.uncertainty_s) +
               " s fit as well; overlap " + printf_text("%.0f", out.overlap_s) + " s";
    if (out.correlation < 0.5)
        out.note += "; WEAK correlation: little current variation, or the two files are not of the same test";
    if (out.at_search_limit) out.note += "; best offset at the search limit: widen max_offset_s";
    return out;
}

void check_clock_alignment(const ClockAlignment& al, const std::string& what, const AlignOptions& options) {
    const std::string found = "best offset " + printf_text("%+.1f", al.offset_s) + " s, correlation r = " +
                              printf_text("%.3f", al.correlation) + ", offsets within " + printf_text("%.1f", al.uncertainty_s) +
                              " s fit as well; the DAQ record would start " + printf_text("%+.1f", al.start_mismatch_s) +
                              " s and end " + printf_text("%+.1f", al.end_mismatch_s) + " s from the cycler's";
    auto refuse = [&](const std::string& why) {
        throw InputError(what + ": clock alignment refused: " + why + " (" + found +
                         "); check that both files are complete exports of the same test");
    };
    if (!finite(al.offset_s) || !finite(al.correlation)) refuse("no alignment found");
    if (al.correlation < options.min_correlation)
        refuse("weak evidence: correlation below " + printf_text("%.2f", options.min_correlation));
    if (al.at_search_limit) refuse("the best offset is at the edge of the search range (widen --max-offset)");
    if (al.uncertainty_s > options.max_uncertainty_s)
        refuse("ambiguous: a ridge of equally good offsets wider than " + printf_text("%.0f", options.max_uncertainty_s) + " s");
    if (std::abs(al.start_mismatch_s) > options.max_end_mismatch_s &&
        std::abs(al.end_mismatch_s) > options.max_end_mismatch_s)
        refuse("neither end of the DAQ record lands within " + printf_text("%.0f", options.max_end_mismatch_s) +
               " s of the cycler's own first and last timestamps");
}

}  // namespace cellbench::estimator
