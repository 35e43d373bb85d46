// Traces of a diagnosis for plotting (diagnose.hpp: decimate_rows, diagnosis_traces, traces_to_json).
#include <algorithm>
#include <cmath>
#include <limits>

#include "cellbench/estimator/diagnose.hpp"

namespace cellbench::estimator {

std::vector<std::size_t> decimate_rows(const std::vector<double>& t, const std::vector<const std::vector<double>*>& series,
                                       std::size_t max_points) {
    std::vector<std::size_t> rows;
    if (t.empty()) return rows;
    const std::size_t per_bucket = 2 * std::max<std::size_t>(series.size(), 1);
    const std::size_t buckets = std::max<std::size_t>(1, max_points / per_bucket);
    const double t0 = t.front(), t1 = std::max(t.back(), t0 + 1e-9);
    const auto bucket_of = [&](double x) {
        const double f = (x - t0) / (t1 - t0) * static_cast<double>(buckets);
        if (!(f > 0)) return std::size_t{0};  // also NaN
        return std::min(buckets - 1, static_cast<std::size_t>(f));
    };
    constexpr auto none = std::numeric_limits<std::size_t>::max();
    std::vector<std::size_t> lo(buckets * series.size(), none), hi(buckets * series.size(), none);
    for (std::size_t s = 0; s < series.size(); ++s) {
        const auto& y = *series[s];
        const std::size_t n = std::min(t.size(), y.size());
        for (std::size_t k = 0; k < n; ++k) {
            if (!std::isfinite(y[k])) continue;
            const std::size_t b = bucket_of(t[k]) * series.size() + s;
            if (lo[b] == none || y[k] < y[lo[b]]) lo[b] = k;
            if (hi[b] == none || y[k] > y[hi[b]]) hi[b] = k;
        }
    }
    for (std::size_t b = 0; b < lo.size(); ++b) {
        if (lo[b] != none) rows.push_back(lo[b]);
        if (hi[b] != none) rows.push_back(hi[b]);
    }
    std::sort(rows.begin(), rows.end());
    rows.erase(std::unique(rows.begin(), rows.end()), rows.end());
    return rows;
}

DiagnosisTraces diagnosis_traces(const Diagnosis& d, const Recording& rec, std::size_t max_points) {
    DiagnosisTraces out;
    const std::size_t n = rec.size();
    out.rows = n;
    const bool improved = !d.accepted.empty() && d.improved_trace.voltage_v.size() == n;
    const bool surface = rec.has_surface() && rec.surface_c.size() == n;
    const auto at = [](const std::vector<double>& v, std::size_t k) {
        return k < v.size() ? v[k] : std::numeric_limits<double>::quiet_NaN();
    };
    std::vector<double> eb(n), ei;
    for (std::size_t k = 0; k < n; ++k) eb[k] = at(d.baseline_trace.voltage_v, k) - rec.voltage_v[k];
    if (improved) {
        ei.resize(n);
        for (std::size_t k = 0; k < n; ++k) ei[k] = at(d.improved_trace.voltage_v, k) - rec.voltage_v[k];
    }
    std::vector<const std::vector<double>*> guides = {&rec.voltage_v, &eb};
    if (improved) guides.push_back(&ei);
    if (surface) guides.push_back(&rec.surface_c);
    for (const std::size_t k : decimate_rows(rec.time_s, guides, max_points)) {
        out.time_s.push_back(rec.time_s[k]);
        out.voltage_measured_v.push_back(rec.voltage_v[k]);
        out.voltage_baseline_v.push_back(at(d.baseline_trace.voltage_v, k));
        out.voltage_error_baseline_v.push_back(eb[k]);
        if (improved) {
            out.voltage_improved_v.push_back(d.improved_trace.voltage_v[k]);
            out.voltage_error_improved_v.push_back(ei[k]);
        }
        if (surface) {
            out.surface_measured_c.push_back(rec.surface_c[k]);
            out.surface_baseline_c.push_back(at(d.baseline_trace.temperature_c, k));
            if (improved) out.surface_improved_c.push_back(at(d.improved_trace.temperature_c, k));
        }
    }
    return out;
}

nlohmann::json traces_to_json(const DiagnosisTraces& t) {
    // NaN as null explicitly (nlohmann would write null too, but a consumer of the object sees NaN before).
    const auto arr = [](const std::vector<double>& v) {
        nlohmann::json a = nlohmann::json::array();
        for (double x : v) a.push_back(std::isfinite(x) ? nlohmann::json(x) : nlohmann::json(nullptr));
        return a;
    };
    nlohmann::json j = {{"rows", t.rows}, {"points", t.time_s.size()}, {"time_s", arr(t.time_s)}};
    j["voltage_v"] = {{"measured", arr(t.voltage_measured_v)}, {"baseline", arr(t.voltage_baseline_v)}};
    j["voltage_error_v"] = {{"baseline", arr(t.voltage_error_baseline_v)}};
    if (!t.voltage_improved_v.empty()) {
        j["voltage_v"]["improved"] = arr(t.voltage_improved_v);
        j["voltage_error_v"]["improved"] = arr(t.voltage_error_improved_v);
    }
    if (!t.surface_measured_c.empty()) {
        j["surface_c"] = {{"measured", arr(t.surface_measured_c)}, {"baseline", arr(t.surface_baseline_c)}};
        if (!t.surface_improved_c.empty()) j["surface_c"]["improved"] = arr(t.surface_improved_c);
    }
    return j;
}

}  // namespace cellbench::estimator
