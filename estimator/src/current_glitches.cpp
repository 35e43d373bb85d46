#include "cellbench/estimator/current_glitches.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include "artefact_runs.hpp"
#include "median.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {
constexpr double kSameCurrentA = 0.05;      // the rows either side of a run agree on the current ...
constexpr double kSameCurrentShare = 0.02;  // ... or within 2 % of it
constexpr double kMinGlitchA = 0.2;         // a row of the run departs by more than this ...
constexpr double kMinGlitchShare = 0.1;     // ... and by more than 10 % of the current either side
constexpr double kVoltageShare = 0.25;      // of the voltage the recording's own R0 gives that departure
constexpr double kMinStepA = 0.5;           // a current step the apparent resistance is measured on
constexpr std::size_t kMaxGlitchRows = 3;

bool same_current(double x, double y) { return std::abs(x - y) <= std::max(kSameCurrentA, kSameCurrentShare * std::abs(y)); }

// The glitch of `length` rows starting at row k, between rows k - 1 and k + length.
bool is_glitch(const Recording& rec, std::size_t k, std::size_t length, double r_ohm) {
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    const std::size_t a = k - 1, b = k + length;
    if (b >= rec.size()) return false;
    for (std::size_t r = a; r <= b; ++r)
        if (!std::isfinite(v[r]) || !std::isfinite(i[r]) || !std::isfinite(rec.time_s[r])) return false;
    if (!same_current(i[b], i[a])) return false;
    for (std::size_t r = k; r < b; ++r) {
        const double di = std::abs(i[r] - i[a]);
        if (!(di > std::max(kMinGlitchA, kMinGlitchShare * std::abs(i[a])))) return false;
        const double line_v = v[a] + bracket_weight(rec.time_s, r, a, b) * (v[b] - v[a]);
        if (!(std::abs(v[r] - line_v) < kVoltageShare * r_ohm * di)) return false;
    }
    return true;
}
}  // namespace

double apparent_step_resistance_ohm(const Recording& rec) {
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    std::vector<double> r;
    for (std::size_t k = 2; k + 1 < rec.size(); ++k) {
        const double di = i[k] - i[k - 1];
        if (!(std::abs(di) >= kMinStepA) || !same_current(i[k - 1], i[k - 2]) || !same_current(i[k + 1], i[k])) continue;
        const double dv = v[k] - v[k - 1];
        if (std::isfinite(dv)) r.push_back(std::abs(dv / di));
    }
    return r.size() >= 3 ? upper_median(std::move(r)) : NAN;
}

std::vector<std::size_t> current_glitch_rows(const Recording& rec) {
    const double r_ohm = apparent_step_resistance_ohm(rec);
    if (!(r_ohm > 0)) return {};
    return artefact_run_rows(rec.size(), kMaxGlitchRows,
                             [&](std::size_t k, std::size_t length) { return is_glitch(rec, k, length, r_ohm); });
}

std::string correct_current_glitches(Recording& rec) {
    const auto rows = current_glitch_rows(rec);
    if (rows.empty()) return {};
    const double first_a = rec.current_a[rows.front()];
    bridge_artefact_runs(rec.time_s, rec.current_a, rows);
    const bool one = rows.size() == 1;
    return rec.source + ": " + std::to_string(rows.size()) +
           (one ? " row shows a current glitch (at t = " : " rows show a current glitch (the first at t = ") +
           printf_text("%.3f s: %.3f A", rec.time_s[rows.front()], first_a) + ") that leaves and returns within at most " +
           std::to_string(kMaxGlitchRows) + " samples while the voltage does not follow, which no cell does: " +
           (one ? "its" : "their") + " current is taken between the rows either side";
}

}  // namespace cellbench::estimator
