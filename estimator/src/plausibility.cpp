#include "cellbench/estimator/plausibility.hpp"

#include <cmath>

namespace cellbench::estimator {

RcValues rc_sigma(const Rc2Params<double>& v, const Rc2Params<double>& s) {
    RcValues out;
    out.r0_ohm = s.r0_ohm;
    out.r1_ohm = s.r1_ohm;
    out.r2_ohm = s.r2_ohm;
    // C = tau / R: relative variances add.
    auto c_sigma = [](double tau, double r, double s_tau, double s_r) {
        if (!(r > 0.0 && tau > 0.0) || !std::isfinite(s_tau) || !std::isfinite(s_r)) return kNaN;
        return tau / r * std::hypot(s_tau / tau, s_r / r);
    };
    out.c1_f = c_sigma(v.tau1_s, v.r1_ohm, s.tau1_s, s.r1_ohm);
    out.c2_f = c_sigma(v.tau2_s, v.r2_ohm, s.tau2_s, s.r2_ohm);
    return out;
}

std::vector<std::pair<std::string, std::vector<std::string>>> rc_flags(const RcValues& v, const RcValues& s,
                                                                        bool tau_at_bound) {
    auto r_ok = [](double r) { return std::isfinite(r) && r >= kPlausibleRMinOhm && r <= kPlausibleRMaxOhm; };
    auto in = [](double x, double lo, double hi) { return std::isfinite(x) && x >= lo && x <= hi; };
    const double tau1 = v.r1_ohm * v.c1_f, tau2 = v.r2_ohm * v.c2_f;
    const bool tau1_ok = in(tau1, kPlausibleTau1MinS, kPlausibleTau1MaxS);
    const bool tau2_ok = in(tau2, kPlausibleTau2MinS, kPlausibleTau2MaxS);
    const struct {
        const char* name;
        double value, sigma;
        bool plausible, pair;
    } q[5] = {{"r0_ohm", v.r0_ohm, s.r0_ohm, r_ok(v.r0_ohm), false},
              {"r1_ohm", v.r1_ohm, s.r1_ohm, r_ok(v.r1_ohm), true},
              {"c1_f", v.c1_f, s.c1_f, tau1_ok && v.c1_f > 0.0, true},
              {"r2_ohm", v.r2_ohm, s.r2_ohm, r_ok(v.r2_ohm), true},
              {"c2_f", v.c2_f, s.c2_f, tau2_ok && v.c2_f > 0.0, true}};
    std::vector<std::pair<std::string, std::vector<std::string>>> out;
    for (const auto& x : q) {
        // A quantity nobody fitted (the whole direction NaN) is absent, not implausible.
        if (std::isnan(x.value) && std::isnan(v.r0_ohm) && std::isnan(v.r1_ohm)) continue;
        std::vector<std::string> f;
        if (!x.plausible) f.emplace_back("implausible");
        if (std::isfinite(x.sigma) && std::isfinite(x.value) && x.sigma > std::abs(x.value)) f.emplace_back("uncertain");
        // A value without an uncertainty (the thesis' per-segment fits give none; a joint fit whose covariance
        // is rank deficient) is not shown as fine either.
        if (std::isfinite(x.value) && !std::isfinite(x.sigma)) f.emplace_back("no_uncertainty");
        if (tau_at_bound && x.pair) f.emplace_back("at_bound");
        if (!f.empty()) out.emplace_back(x.name, std::move(f));
    }
    return out;
}

}  // namespace cellbench::estimator
