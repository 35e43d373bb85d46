#include "cellbench/estimator/logger_timing.hpp"

#include <cmath>

#include "cellbench/estimator/coulomb.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {

// Calls f(k) at every row k whose current stepped from the row before and was held for a row either side: the
// current steps that show the logger rather than a transient.
template <class F>
void for_each_held_step(const Recording& rec, F&& f) {
    const auto& i = rec.current_a;
    for (std::size_t k = 2; k + 1 < rec.size(); ++k)
        if (is_current_step(i[k - 1], i[k]) && !is_current_step(i[k - 2], i[k - 1]) && !is_current_step(i[k], i[k + 1]))
            f(k);
}

}  // namespace

StepTiming step_timing(const Recording& rec) {
    constexpr double kLagCheckIntervalS = 0.25;
    StepTiming out;
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    for_each_held_step(rec, [&](std::size_t k) {
        if (rec.time_s[k] - rec.time_s[k - 1] > kLagCheckIntervalS ||
            rec.time_s[k + 1] - rec.time_s[k] > kLagCheckIntervalS)
            return;
        if (!std::isfinite(v[k - 1]) || !std::isfinite(v[k]) || !std::isfinite(v[k + 1])) return;
        const double di = i[k] - i[k - 1];
        ++out.steps;
        out.voltage_later += (v[k + 1] - v[k]) / di > (v[k] - v[k - 1]) / di;
    });
    return out;
}

std::string voltage_lag_text(const Recording& rec) {
    const auto t = step_timing(rec);
    if (!t.voltage_lags()) return {};
    return rec.source + printf_text(": its voltage lags its current by more than a sample (at %zu of its %zu current "
                                    "steps the voltage moves more across the second sample than across the first)",
                                    t.voltage_later, t.steps);
}

CurrentSign current_sign(const Recording& rec) {
    CurrentSign out;
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    for_each_held_step(rec, [&](std::size_t k) {
        const double dv = v[k] - v[k - 1], di = i[k] - i[k - 1];
        if (!std::isfinite(dv) || !std::isfinite(di) || dv == 0.0) return;
        ++out.steps;
        out.against += (dv > 0) != (di > 0);
    });
    return out;
}

std::string reversed_current_text(const Recording& rec) {
    const auto s = current_sign(rec);
    if (!s.reversed()) return {};
    return rec.source + printf_text(": its current counts discharging as positive (at %zu of its %zu current steps the "
                                    "voltage moves against the current); cellbench reads current positive when it "
                                    "charges the cell (BDF): negate the current column",
                                    s.against, s.steps);
}

}  // namespace cellbench::estimator
