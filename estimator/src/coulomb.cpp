// Coulomb counting (coulomb.hpp).
#include "cellbench/estimator/coulomb.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>

namespace cellbench::estimator {

namespace {

bool finite_at(const std::vector<double>& t, const std::vector<double>& i, std::size_t k) {
    return std::isfinite(t[k]) && std::isfinite(i[k]);
}

// Two logging intervals that are the same (5 % and 20 ms: loggers' intervals jitter).
bool same_interval(double x, double h) { return std::isfinite(h) && h > 0 && std::abs(x - h) <= 0.05 * h + 0.02; }

enum class Vote { start, after, none };

// Whether a current step lies between rows k - 1 and k (element k; element 0 false): the current steps
// (is_current_step) between two finite rows that advance in time and, where the recording has a step column, the
// step changes there too. Within one of the logger's steps the current's changes are the step's own course: a CV
// taper logged every minute falls by more than 5 % between its rows, and it is a curve, not a staircase.
std::vector<char> current_steps(const std::vector<double>& t, const std::vector<double>& i,
                                const std::vector<double>* step_count) {
    const std::size_t n = std::min(t.size(), i.size());
    const bool steps_known = step_count && step_count->size() >= n;
    std::vector<char> step(n, 0);
    for (std::size_t k = 1; k < n; ++k) {
        if (!finite_at(t, i, k) || !finite_at(t, i, k - 1) || !(t[k] > t[k - 1]) || !is_current_step(i[k - 1], i[k]))
            continue;
        step[k] = !steps_known || !((*step_count)[k] == (*step_count)[k - 1]);
    }
    return step;
}

// What the step between rows k - 1 and k tells (k >= 1, both rows finite, a step between them): the interval's
// length against the old step's logging interval (rows k - 2, k - 1) and the new one's (rows k, k + 1).
Vote vote(const std::vector<double>& t, const std::vector<double>& i, const std::vector<char>& step, std::size_t k) {
    const std::size_t n = step.size();
    const double dt = t[k] - t[k - 1];
    const double h_old = k >= 2 && finite_at(t, i, k - 2) && !step[k - 1] ? t[k - 1] - t[k - 2] : NAN;
    const double h_new = k + 1 < n && finite_at(t, i, k + 1) && !step[k + 1] ? t[k + 1] - t[k] : NAN;
    const bool as_old = same_interval(dt, h_old), as_new = same_interval(dt, h_new);
    if (as_new && !as_old) return Vote::after;
    // The old step's interval, or cut short by the step (a limit reached between two of its rows).
    const bool cut_short = std::isfinite(h_old) && dt < h_old && !as_new;
    if ((as_old && !as_new) || cut_short) return Vote::start;
    return Vote::none;
}

// The vote of every row's interval (row k: the interval from row k - 1): none where no current step is in it.
std::vector<Vote> step_votes(const std::vector<double>& t, const std::vector<double>& i, const std::vector<char>& step) {
    std::vector<Vote> v(step.size(), Vote::none);
    for (std::size_t k = 1; k < step.size(); ++k)
        if (step[k]) v[k] = vote(t, i, step, k);
    return v;
}

StepLogging majority(const std::vector<Vote>& votes) {
    const auto start = std::count(votes.begin(), votes.end(), Vote::start);
    const auto after = std::count(votes.begin(), votes.end(), Vote::after);
    if (start > 2 * after) return StepLogging::at_step_start;
    if (after > 2 * start) return StepLogging::one_interval_after;
    return StepLogging::unknown;
}

IntervalCurrents interval_currents(const std::vector<double>& time_s, const std::vector<double>& current_a,
                                   const std::vector<double>* step_count) {
    const std::size_t n = std::min(time_s.size(), current_a.size());
    IntervalCurrents out;
    out.step = current_steps(time_s, current_a, step_count);
    const auto votes = step_votes(time_s, current_a, out.step);
    // Steps that do not tell follow the recording's majority; where nothing tells, the electrical model's own ZOH
    // convention (the new current over the interval before its row), as on a recording sampled at one rate.
    const Vote fallback = majority(votes) == StepLogging::at_step_start ? Vote::start : Vote::after;
    auto& i = out.mean_a;
    i.assign(current_a.begin(), current_a.begin() + static_cast<std::ptrdiff_t>(n));
    for (std::size_t k = 1; k < n; ++k) {
        if (!finite_at(time_s, current_a, k) || !finite_at(time_s, current_a, k - 1)) continue;
        const double a = current_a[k - 1], b = current_a[k];
        if (out.step[k])
            i[k] = (votes[k] == Vote::none ? fallback : votes[k]) == Vote::start ? a : b;
        else
            i[k] = 0.5 * (a + b);  // within a step: trapezoid
    }
    return out;
}

std::vector<double> charge_from(const std::vector<double>& time_s, const std::vector<double>& current_a,
                                const std::vector<double>& interval_a) {
    const std::size_t n = interval_a.size();
    std::vector<double> q(n, 0.0);
    for (std::size_t k = 1; k < n; ++k) {
        q[k] = q[k - 1];
        if (!finite_at(time_s, current_a, k) || !finite_at(time_s, current_a, k - 1)) continue;
        const double dt = time_s[k] - time_s[k - 1];
        if (!(dt > 0)) continue;
        q[k] += interval_a[k] * dt / 3600.0;
    }
    return q;
}

}  // namespace

bool is_current_step(double a, double b) { return is_current_step(a, b, 0.05); }

bool is_current_step(double a, double b, double floor_a) {
    return std::abs(b - a) > std::max(floor_a, 0.05 * std::max(std::abs(a), std::abs(b)));
}

StepLogging step_logging(const std::vector<double>& time_s, const std::vector<double>& current_a) {
    return majority(step_votes(time_s, current_a, current_steps(time_s, current_a, nullptr)));
}

IntervalCurrents interval_currents(const Recording& rec) {
    return interval_currents(rec.time_s, rec.current_a, rec.step_count.empty() ? nullptr : &rec.step_count);
}

std::vector<double> cumulative_charge_ah(const std::vector<double>& time_s, const std::vector<double>& current_a) {
    return charge_from(time_s, current_a, interval_currents(time_s, current_a, nullptr).mean_a);
}

std::vector<double> cumulative_charge_ah(const Recording& rec) {
    return charge_from(rec.time_s, rec.current_a, interval_currents(rec).mean_a);
}

}  // namespace cellbench::estimator
