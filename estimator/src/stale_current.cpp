#include "cellbench/estimator/stale_current.hpp"

#include <cmath>
#include <vector>

#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {
constexpr double kMinStepA = 0.1;       // a current step
constexpr double kSameCurrent = 0.01;   // of the step: the current has not moved
constexpr double kMinMoveV = 5e-3;      // well above any cycler's voltage noise and quantization
constexpr double kShareOfMove = 0.5;    // of the move to the next row
}  // namespace

std::vector<std::size_t> stale_current_rows(const Recording& rec) {
    std::vector<std::size_t> rows;
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    for (std::size_t k = 1; k + 1 < rec.size(); ++k) {
        if (!(std::isfinite(i[k - 1]) && std::isfinite(i[k]) && std::isfinite(i[k + 1]) && std::isfinite(v[k - 1]) &&
              std::isfinite(v[k]) && std::isfinite(v[k + 1])))
            continue;
        const double step_a = i[k + 1] - i[k - 1];
        if (std::abs(step_a) < kMinStepA || std::abs(i[k] - i[k - 1]) > kSameCurrent * std::abs(step_a)) continue;
        // From a rest: the step's first record. (A stale reading inside a CC-CV switch is left alone: it is one
        // row where the current tapers, and the fit of the P45B HPPC moves when it is dropped.)
        if (std::abs(i[k - 1]) > kSameCurrent * std::abs(step_a)) continue;
        const double move_v = v[k] - v[k - 1];
        const double full_move_v = v[k + 1] - v[k - 1];
        // A current step moves the voltage its own way (up when the current rises): a positive resistance.
        if (move_v * step_a <= 0.0 || std::abs(move_v) <= kMinMoveV) continue;
        if (std::abs(move_v) > kShareOfMove * std::abs(full_move_v)) rows.push_back(k);
    }
    return rows;
}

namespace {
void take_next_current(Recording& rec, const std::vector<std::size_t>& rows) {
    for (const std::size_t k : rows) rec.current_a[k] = rec.current_a[k + 1];
}
}  // namespace

std::size_t take_next_current_for_stale_rows(Recording& rec) {
    const auto rows = stale_current_rows(rec);
    take_next_current(rec, rows);
    return rows.size();
}

std::string correct_stale_current_rows(Recording& rec) {
    const auto rows = stale_current_rows(rec);
    if (rows.empty()) return {};
    take_next_current(rec, rows);
    const bool one = rows.size() == 1;
    return rec.source + ": " + std::to_string(rows.size()) +
           (one ? " row at a current step shows the step's new voltage with the current before it (at t = "
                : " rows at current steps show the step's new voltage with the current before it (the first at t = ") +
           printf_text("%.3f", rec.time_s[rows.front()]) + " s): " + (one ? "its" : "their") +
           " current is taken from the next row";
}

}  // namespace cellbench::estimator
