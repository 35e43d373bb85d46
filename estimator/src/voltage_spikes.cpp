#include "cellbench/estimator/voltage_spikes.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include "cellbench/estimator/stale_current.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {
constexpr double kMinSpikeV = 0.05;         // there and back within one sample: no cell does 50 mV
constexpr double kNeighboursAgree = 0.25;   // of the spike: the rows either side tell the same voltage
constexpr double kSameCurrentA = 0.05;      // the current holds over the three rows ...
constexpr double kSameCurrentShare = 0.02;  // ... or within 2 % of itself
}  // namespace

std::vector<std::size_t> voltage_spike_rows(const Recording& rec) {
    std::vector<std::size_t> rows;
    const auto& i = rec.current_a;
    const auto& v = rec.voltage_v;
    for (std::size_t k = 1; k + 1 < rec.size(); ++k) {
        if (!(std::isfinite(v[k - 1]) && std::isfinite(v[k]) && std::isfinite(v[k + 1]) && std::isfinite(i[k - 1]) &&
              std::isfinite(i[k]) && std::isfinite(i[k + 1])))
            continue;
        const double up = v[k] - v[k - 1], down = v[k] - v[k + 1];
        if (up * down <= 0.0) continue;
        const double spike = std::min(std::abs(up), std::abs(down));
        if (spike <= kMinSpikeV || std::abs(v[k + 1] - v[k - 1]) >= kNeighboursAgree * spike) continue;
        const double tol = std::max(kSameCurrentA, kSameCurrentShare * std::abs(i[k]));
        if (std::abs(i[k] - i[k - 1]) > tol || std::abs(i[k + 1] - i[k]) > tol) continue;
        rows.push_back(k);
    }
    return rows;
}

std::string correct_voltage_spikes(Recording& rec) {
    const auto rows = voltage_spike_rows(rec);
    if (rows.empty()) return {};
    const double first_v = rec.voltage_v[rows.front()];
    for (const std::size_t k : rows) {
        const double t0 = rec.time_s[k - 1], t1 = rec.time_s[k + 1];
        const double w = t1 > t0 ? (rec.time_s[k] - t0) / (t1 - t0) : 0.5;
        rec.voltage_v[k] = rec.voltage_v[k - 1] + w * (rec.voltage_v[k + 1] - rec.voltage_v[k - 1]);
    }
    const bool one = rows.size() == 1;
    return rec.source + ": " + std::to_string(rows.size()) +
           (one ? " row shows a voltage spike (at t = " : " rows show a voltage spike (the first at t = ") +
           printf_text("%.3f s: %.4f V", rec.time_s[rows.front()], first_v) +
           ") that leaves and returns within one sample while the current holds, which no cell does: " +
           (one ? "its" : "their") + " voltage is taken between the rows either side";
}

std::vector<std::string> correct_logging_artifacts(Recording& rec) {
    std::vector<std::string> notes;
    for (auto* correct : {&correct_stale_current_rows, &correct_voltage_spikes})
        if (auto note = correct(rec); !note.empty()) notes.push_back(std::move(note));
    return notes;
}

}  // namespace cellbench::estimator
