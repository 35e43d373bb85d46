// Noise estimate and sparse regression of a residual (diagnose.hpp: estimate_noise, sparse_residual_model).
#include <algorithm>
#include <cmath>
#include <numeric>

#include <Eigen/Dense>

#include "cellbench/estimator/diagnose.hpp"

#include "median.hpp"

namespace cellbench::estimator {

namespace {

// Robust 1-sigma noise of a signal from the differences of consecutive rest rows: the differences remove slow
// relaxation, the median absolute deviation ignores the odd step; sigma_diff = sqrt(2) sigma. Where the scatter
// is below the quantization (all differences 0 or one LSB), the LSB/sqrt(12) floor is used.
std::optional<double> scatter(const std::vector<double>& x, const std::vector<char>& pair_ok, double scale) {
    if (x.empty()) return std::nullopt;
    // A slower instrument merged onto a faster time base repeats each value over several rows (sample and hold):
    // the typical run of equal values among the rows that change tells the hold length, and only rows that far
    // apart are compared. A quantized signal that does not move has no changing rows: the LSB floor applies.
    std::size_t hold = 1;
    {
        std::vector<std::size_t> runs;
        std::size_t run = 1;
        for (std::size_t k = 1; k < x.size(); ++k) {
            if (x[k] == x[k - 1]) {
                ++run;
            } else {
                if (run < 100) runs.push_back(run);
                run = 1;
            }
        }
        if (runs.size() > 20) {
            std::nth_element(runs.begin(), runs.begin() + static_cast<long>(runs.size() / 2), runs.end());
            hold = std::max<std::size_t>(1, runs[runs.size() / 2]);
        }
    }
    std::vector<double> d;
    double lsb = INFINITY;
    for (std::size_t k = hold; k < x.size() && k < pair_ok.size(); k += hold) {
        bool ok = true;
        for (std::size_t j = k - hold + 1; j <= k && ok; ++j) ok = pair_ok[j];
        if (!ok || !std::isfinite(x[k]) || !std::isfinite(x[k - hold])) continue;
        const double v = x[k] - x[k - hold];
        d.push_back(v);
        if (std::abs(v) > 0) lsb = std::min(lsb, std::abs(v));
    }
    if (d.size() < 20) return std::nullopt;
    const double m = upper_median(d);
    for (auto& v : d) v = std::abs(v - m);
    double sigma = 1.4826 * upper_median(d) / std::sqrt(2.0);
    if (std::isfinite(lsb)) sigma = std::max(sigma, lsb / std::sqrt(12.0));
    return sigma * scale;
}

double lowpass_step(double y, double x, double dt, double tau) { return y + (x - y) * (1.0 - std::exp(-dt / tau)); }

}  // namespace

NoiseEstimate estimate_noise(const Recording& rec, double capacity_ah) {
    NoiseEstimate ne;
    const std::size_t n = rec.size();
    std::vector<char> ok(n, 0);
    const double i_rest = std::max(0.01, 0.01 * capacity_ah);
    double t_step = rec.time_s.empty() ? 0.0 : rec.time_s[0];
    for (std::size_t k = 1; k < n; ++k) {
        if (std::abs(rec.current_a[k] - rec.current_a[k - 1]) > i_rest) t_step = rec.time_s[k];
        const bool rest = std::abs(rec.current_a[k]) < i_rest && std::abs(rec.current_a[k - 1]) < i_rest;
        const double dt = rec.time_s[k] - rec.time_s[k - 1];
        ok[k] = rest && dt > 0 && dt <= 5.0 && rec.time_s[k] - t_step > 10.0;
        ne.rest_pairs += ok[k];
    }
    ne.sigma.voltage_v = scatter(rec.voltage_v, ok, 1.0);
    if (rec.has_surface()) ne.sigma.temperature_c = scatter(rec.surface_c, ok, 1.0);
    // heat flux in W over the configured surface is scaled by the caller (area)
    if (rec.has_heat_flux()) ne.sigma.heat_flux_w = scatter(rec.heat_flux_w_per_m2, ok, 1.0);
    return ne;
}

ResidualModel sparse_residual_model(const Recording& rec, const SimulationTrace& tr, const ParameterSet& params,
                                    bool temperature) {
    ResidualModel out;
    out.quantity = temperature ? "temperature_c" : "voltage_v";
    const std::size_t n = std::min(rec.size(), tr.time_s.size());
    if (n < 50 || (temperature && !rec.has_surface())) return out;
    const double c1 = std::max(params.capacity_ah, 1e-3);
    // Library, in natural units (I in A, dT in K, SOC fraction).
    struct Col {
        std::string name, meaning;
        std::vector<double> v;
    };
    std::vector<Col> cols;
    auto add = [&](std::string name, std::string meaning) -> std::vector<double>& {
        cols.push_back({std::move(name), std::move(meaning), std::vector<double>(n)});
        return cols.back().v;
    };
    double t_first = kNaN;
    if (rec.has_surface())
        for (double v : rec.surface_c)
            if (std::isfinite(v)) {
                t_first = v;
                break;
            }
    std::vector<double> I(n), dT(n), soc(n);
    for (std::size_t k = 0; k < n; ++k) {
        I[k] = rec.current_a[k];
        const double ts = std::isfinite(tr.temperature_c[k]) ? tr.temperature_c[k] : kNaN;
        dT[k] = std::isfinite(ts) && std::isfinite(t_first) ? ts - t_first : 0.0;
        soc[k] = tr.soc[k];
    }
    {
        auto& c = add("I", "current (an ohmic term: a resistance off)");
        c = I;
    }
    {
        auto& c = add("|I|", "current magnitude (a direction-independent overpotential)");
        for (std::size_t k = 0; k < n; ++k) c[k] = std::abs(I[k]);
    }
    {
        auto& c = add("I*|I|", "current squared with its sign (overpotential not linear in current)");
        for (std::size_t k = 0; k < n; ++k) c[k] = I[k] * std::abs(I[k]) / c1;
    }
    for (double tau : {10.0, 100.0, 1000.0}) {
        auto& c = add("I_lp" + std::to_string(static_cast<int>(tau)) + "s",
                      "current low-passed at " + std::to_string(static_cast<int>(tau)) + " s (a polarization with this time constant)");
        double y = 0;
        for (std::size_t k = 0; k < n; ++k) {
            if (k > 0) y = lowpass_step(y, I[k], rec.time_s[k] - rec.time_s[k - 1], tau);
            c[k] = y;
        }
    }
    {
        auto& c = add("h_dir", "direction of the recent charge throughput (hysteresis-like, settles over 5 % of the capacity)");
        double h = 0;
        for (std::size_t k = 1; k < n; ++k) {
            const double dq = std::abs(I[k]) * (rec.time_s[k] - rec.time_s[k - 1]) / 3600.0 / c1;
            const double s = I[k] > 0.02 * c1 ? 1.0 : I[k] < -0.02 * c1 ? -1.0 : h;
            h += (s - h) * (1.0 - std::exp(-dq / 0.05));
            c[k] = h;
        }
    }
    {
        auto& c = add("dT", "temperature rise (a temperature dependence)");
        c = dT;
    }
    {
        auto& c = add("I*dT", "current times temperature rise (resistance changing with temperature)");
        for (std::size_t k = 0; k < n; ++k) c[k] = I[k] * dT[k];
    }
    {
        auto& c = add("SOC", "state of charge (OCV or capacity off)");
        c = soc;
    }
    {
        auto& c = add("I*SOC", "current times SOC (a resistance table off along SOC)");
        for (std::size_t k = 0; k < n; ++k) c[k] = I[k] * (soc[k] - 0.5);
    }
    {
        auto& c = add("t", "elapsed time in hours (a drift)");
        for (std::size_t k = 0; k < n; ++k) c[k] = (rec.time_s[k] - rec.time_s[0]) / 3600.0;
    }
    {
        // A voltage read a fraction of a sample after (or before) the current misses R0 times that fraction of
        // each change: the Panasonic 18650PF's drive-cycle logs, whose voltage moves 5 mOhm x dI over the sample
        // that shows a step and 16 mOhm x dI over the next (docs/model.md).
        auto& c = add("dI", "the current's change since the previous row (voltage and current read at different "
                            "instants, or one of them filtered: the logger's timing, not the cell)");
        for (std::size_t k = 1; k < n; ++k) c[k] = I[k] - I[k - 1];
    }
    {
        auto& c = add("I^2_lp100s", "I^2 low-passed at 100 s (heat: a thermal or heat-driven effect)");
        double y = 0;
        for (std::size_t k = 0; k < n; ++k) {
            if (k > 0) y = lowpass_step(y, I[k] * I[k], rec.time_s[k] - rec.time_s[k - 1], 100.0);
            c[k] = y;
        }
    }
    // Residual (simulated minus measured) on rows where it exists; weights = time.
    std::vector<std::size_t> rows;
    std::vector<double> r;
    for (std::size_t k = 0; k < n; ++k) {
        const double e = temperature ? tr.temperature_c[k] - rec.surface_c[k] : tr.voltage_v[k] - rec.voltage_v[k];
        if (std::isfinite(e)) rows.push_back(k), r.push_back(e);
    }
    if (rows.size() < 50) return out;
    const std::size_t m = rows.size(), p = cols.size();
    Eigen::MatrixXd X(m, p);
    Eigen::VectorXd y(m);
    std::vector<double> mean(p), sd(p);
    const double ry = std::accumulate(r.begin(), r.end(), 0.0) / static_cast<double>(m);
    for (std::size_t i = 0; i < m; ++i) y(static_cast<long>(i)) = r[i] - ry;
    const double sy = std::sqrt(y.squaredNorm() / static_cast<double>(m));
    if (!(sy > 0)) return out;
    for (std::size_t j = 0; j < p; ++j) {
        double s = 0, s2 = 0;
        for (std::size_t i = 0; i < m; ++i) s += cols[j].v[rows[i]];
        mean[j] = s / static_cast<double>(m);
        for (std::size_t i = 0; i < m; ++i) s2 += std::pow(cols[j].v[rows[i]] - mean[j], 2);
        sd[j] = std::sqrt(s2 / static_cast<double>(m));
        for (std::size_t i = 0; i < m; ++i)
            X(static_cast<long>(i), static_cast<long>(j)) = sd[j] > 0 ? (cols[j].v[rows[i]] - mean[j]) / sd[j] : 0.0;
    }
    // Correlations.
    for (std::size_t j = 0; j < p; ++j) {
        if (!(sd[j] > 0)) continue;
        const double c = X.col(static_cast<long>(j)).dot(y) / static_cast<double>(m) / sy;
        out.correlations.emplace_back(cols[j].name, c);
    }
    std::sort(out.correlations.begin(), out.correlations.end(),
              [](const auto& a, const auto& b) { return std::abs(a.second) > std::abs(b.second); });
    if (out.correlations.size() > 4) out.correlations.resize(4);
    // Forward selection on the standardised columns (ridge 1e-6 for near-collinear ones): each step adds the term
    // that lowers the squared residual most, refitting all kept terms, up to 5 terms and while a term removes at
    // least 1 % of the residual's variance; then a kept term must move the residual by at least 10 % of its spread
    // per sigma. Thresholding the full least-squares fit first (before session 44) let a drive profile's
    // collinear low-passed currents take the five places with their inflated coefficients: on the Panasonic US06
    // log the current's row-to-row change (correlation 0.67 with the residual) was never kept.
    std::vector<char> active(p, 0);
    const double threshold = 0.1 * sy;
    Eigen::VectorXd beta = Eigen::VectorXd::Zero(static_cast<long>(p));
    const Eigen::MatrixXd G = X.transpose() * X / static_cast<double>(m);
    const Eigen::VectorXd b = X.transpose() * y / static_cast<double>(m);
    // The least-squares coefficients of the columns idx alone (ridge 1e-6 on the diagonal).
    auto solve_on = [&](const std::vector<long>& idx) -> Eigen::VectorXd {
        Eigen::MatrixXd g = G(idx, idx);
        g.diagonal().array() += 1e-6;
        return g.ldlt().solve(Eigen::VectorXd(b(idx)));
    };
    // Mean squared residual of the fit on idx, from the Gram matrix: y'y/m - 2 b'x + x'Gx.
    const double yy = y.squaredNorm() / static_cast<double>(m);
    auto mse_on = [&](const std::vector<long>& idx) {
        if (idx.empty()) return yy;
        const Eigen::VectorXd x = solve_on(idx);
        return yy - 2.0 * b(idx).dot(x) + x.dot(G(idx, idx) * x);
    };
    std::vector<long> kept;
    double mse = yy;
    while (kept.size() < 5) {
        long best = -1;
        double best_mse = mse;
        for (std::size_t j = 0; j < p; ++j) {
            if (!(sd[j] > 0) || std::find(kept.begin(), kept.end(), static_cast<long>(j)) != kept.end()) continue;
            auto idx = kept;
            idx.push_back(static_cast<long>(j));
            const double e = mse_on(idx);
            if (e < best_mse) best_mse = e, best = static_cast<long>(j);
        }
        if (best < 0 || mse - best_mse < 0.01 * yy) break;
        kept.push_back(best);
        mse = best_mse;
    }
    for (bool dropped = true; dropped && !kept.empty();) {
        dropped = false;
        const Eigen::VectorXd sol = solve_on(kept);
        long smallest = -1;
        for (std::size_t a = 0; a < kept.size(); ++a)
            if (std::abs(sol(static_cast<long>(a))) < threshold &&
                (smallest < 0 || std::abs(sol(static_cast<long>(a))) < std::abs(sol(smallest))))
                smallest = static_cast<long>(a);
        if (smallest >= 0) kept.erase(kept.begin() + smallest), dropped = true;
    }
    if (!kept.empty()) {
        const Eigen::VectorXd sol = solve_on(kept);
        for (std::size_t a = 0; a < kept.size(); ++a) {
            beta(kept[a]) = sol(static_cast<long>(a));
            active[static_cast<std::size_t>(kept[a])] = 1;
        }
    }
    const Eigen::VectorXd res = y - X * beta;
    out.explained = std::max(0.0, 1.0 - res.squaredNorm() / y.squaredNorm());
    // Share of a kept term: the variance the model explains less when it is refitted without that term (columns
    // of a drive profile are correlated, so beta^2 alone would overstate it).
    auto sse_without = [&](long drop) {
        std::vector<long> idx;
        for (std::size_t j = 0; j < p; ++j)
            if (active[j] && static_cast<long>(j) != drop) idx.push_back(static_cast<long>(j));
        if (idx.empty()) return y.squaredNorm();
        const Eigen::VectorXd sol = solve_on(idx);
        Eigen::VectorXd fit = Eigen::VectorXd::Zero(static_cast<long>(m));
        for (std::size_t a = 0; a < idx.size(); ++a) fit += sol(static_cast<long>(a)) * X.col(idx[a]);
        return (y - fit).squaredNorm();
    };
    const double sse_full = res.squaredNorm();
    for (std::size_t j = 0; j < p; ++j) {
        const double bj = beta(static_cast<long>(j));
        if (bj == 0.0) continue;
        const double share = std::max(0.0, (sse_without(static_cast<long>(j)) - sse_full) / y.squaredNorm());
        out.terms.push_back({cols[j].name, cols[j].meaning, bj / sd[j], share});
    }
    std::sort(out.terms.begin(), out.terms.end(), [](const auto& a, const auto& b) { return a.share > b.share; });
    return out;
}

}  // namespace cellbench::estimator
