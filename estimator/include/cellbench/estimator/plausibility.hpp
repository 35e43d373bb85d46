#pragma once
// Physical plausibility of fitted 2RC values: one owner of the bounds and of the flag words ("implausible",
// "uncertain", "at_bound") for every place that reports a fitted value (the global fit's tables, the online
// per-pulse-set fits in GET /runs/{id}/fits, the dashboard). Any Li-ion cell from a coin cell to a large
// pouch lies inside these bounds; outside them a value is flagged, never shown as fine.
#include <string>
#include <utility>
#include <vector>

#include "cellbench/estimator/pulse_fit.hpp"

namespace cellbench::estimator {

inline constexpr double kPlausibleRMinOhm = 2e-5, kPlausibleRMaxOhm = 1.0;
inline constexpr double kPlausibleTau1MinS = 0.05, kPlausibleTau1MaxS = 60.0;
inline constexpr double kPlausibleTau2MinS = 1.0, kPlausibleTau2MaxS = 5000.0;

// 1-sigma uncertainties of R0, R1, C1, R2, C2 from those of R0, R1, tau1, R2, tau2 (C = tau / R, first-order
// propagation without the R-tau covariance, which the callers do not keep). NaN where a sigma is unknown.
RcValues rc_sigma(const Rc2Params<double>& value, const Rc2Params<double>& sigma);

// The flags of each of R0, R1, C1, R2, C2 (keyed by their parameter-set names, r0_ohm ... c2_f; only values
// with at least one flag are listed): "implausible" when the value or its time constant is outside the bounds
// above (or not finite), "uncertain" when its sigma exceeds the value, "at_bound" on the pair's R and C when
// the fit ended with a time constant on a bound of its search range.
std::vector<std::pair<std::string, std::vector<std::string>>> rc_flags(const RcValues& value, const RcValues& sigma,
                                                                        bool tau_at_bound = false);

}  // namespace cellbench::estimator
