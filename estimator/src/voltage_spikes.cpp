#include "cellbench/estimator/voltage_spikes.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include "cellbench/estimator/current_glitches.hpp"
#include "cellbench/estimator/stale_current.hpp"
#include "artefact_runs.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {
constexpr double kMinSpikeV = 0.05;         // there and back within a few samples: no cell does 50 mV
constexpr double kNeighboursAgree = 0.25;   // of the spike: the rows either side tell the same voltage
constexpr double kSameCurrentA = 0.05;      // the current holds over the spike and the rows either side ...
constexpr double kSameCurrentShare = 0.02;  // ... or within 2 % of itself
constexpr std::size_t kMaxSpikeRows = 3;    // a glitch of up to three rows in a row (a logger's dropout)

// The spike of `length` rows starting at row k, between rows k - 1 and k + length: every row on the same side of
// both by more than kMinSpikeV, the two agreeing within kNeighboursAgree of the smallest departure, the current
// holding from the row before to the row after.
bool is_spike(const Recording& rec, std::size_t k, std::size_t length) {
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    const std::size_t a = k - 1, b = k + length;
    if (b >= rec.size()) return false;
    for (std::size_t r = a; r <= b; ++r)
        if (!std::isfinite(v[r]) || !std::isfinite(i[r])) return false;
    const double tol = std::max(kSameCurrentA, kSameCurrentShare * std::abs(i[k]));
    for (std::size_t r = a; r <= b; ++r)
        if (std::abs(i[r] - i[k]) > tol) return false;
    double smallest = INFINITY;
    for (std::size_t r = k; r < b; ++r) {
        const double up = v[r] - v[a], down = v[r] - v[b];
        if (up * down <= 0.0 || up * (v[k] - v[a]) <= 0.0) return false;  // each row beyond both, all on one side
        smallest = std::min({smallest, std::abs(up), std::abs(down)});
    }
    return smallest > kMinSpikeV && std::abs(v[b] - v[a]) < kNeighboursAgree * smallest;
}
}  // namespace

std::vector<std::size_t> voltage_spike_rows(const Recording& rec) {
    return artefact_run_rows(rec.size(), kMaxSpikeRows,
                             [&](std::size_t k, std::size_t length) { return is_spike(rec, k, length); });
}

std::string correct_voltage_spikes(Recording& rec) {
    const auto rows = voltage_spike_rows(rec);
    if (rows.empty()) return {};
    const double first_v = rec.voltage_v[rows.front()];
    // Each run of spike rows takes the line between the rows either side (not spike rows: voltage_spike_rows
    // lists whole runs, at least one row apart).
    bridge_artefact_runs(rec.time_s, rec.voltage_v, rows);
    const bool one = rows.size() == 1;
    return rec.source + ": " + std::to_string(rows.size()) +
           (one ? " row shows a voltage spike (at t = " : " rows show a voltage spike (the first at t = ") +
           printf_text("%.3f s: %.4f V", rec.time_s[rows.front()], first_v) +
           ") that leaves and returns within at most " + std::to_string(kMaxSpikeRows) +
           " samples while the current holds, which no cell does: " + (one ? "its" : "their") +
           " voltage is taken between the rows either side";
}

std::vector<std::string> correct_logging_artifacts(Recording& rec) {
    std::vector<std::string> notes;
    for (auto* correct : {&correct_stale_current_rows, &correct_current_glitches, &correct_voltage_spikes})
        if (auto note = correct(rec); !note.empty()) notes.push_back(std::move(note));
    return notes;
}

}  // namespace cellbench::estimator
