#include "cellbench/estimator/merge.hpp"
#include "median.hpp"
#include "printf_text.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

namespace cellbench::estimator {

namespace {

// Times at which the current changes by more than min_step_a between consecutive samples.
std::vector<double> current_edges(const Recording& r, double min_step_a) {
    std::vector<double> edges;
    for (std::size_t k = 1; k < r.size(); ++k)
        if (std::abs(r.current_a[k] - r.current_a[k - 1]) > min_step_a) {
            if (edges.empty() || r.time_s[k] - edges.back() > 2.0) edges.push_back(r.time_s[k]);
        }
    return edges;
}

// Current of recording r at time t under its hold convention (the value recorded at the first sample at or
// after t was flowing during the interval before it).
double current_at(const Recording& r, double t) {
    auto it = std::lower_bound(r.time_s.begin(), r.time_s.end(), t);
    if (it == r.time_s.end()) return kNaN;
    return r.current_a[static_cast<std::size_t>(it - r.time_s.begin())];
}

}  // namespace

std::vector<double> resample_linear(const std::vector<double>& t, const std::vector<double>& y,
                                    const std::vector<double>& q) {
    std::vector<double> out(q.size(), kNaN);
    if (t.size() < 2) return out;
    std::size_t j = 0;
    for (std::size_t k = 0; k < q.size(); ++k) {
        const double x = q[k];
        if (x < t.front() || x > t.back()) continue;
        if (j > 0 && t[j] > x) j = 0;  // queries are normally sorted; restart otherwise
        while (j + 2 < t.size() && t[j + 1] < x) ++j;
        const double w = (x - t[j]) / (t[j + 1] - t[j]);
        out[k] = y[j] + w * (y[j + 1] - y[j]);
    }
    return out;
}

CurrentAlignment align_by_current(const Recording& a, const Recording& b, double max_offset_s) {
    const auto ea = current_edges(a, 1.0), eb = current_edges(b, 1.0);
    if (ea.empty() || eb.empty())
        throw InputError(b.source + ": no current steps to align with " + a.source);
    // Vote for offsets that map an edge of b onto an edge of a (1 s bins), then score each candidate by how
    // many of b's edges it matches within 1.5 s.
    std::map<long long, int> votes;
    for (double tb : eb)
        for (double ta : ea)
            if (!(std::abs(ta - tb) > max_offset_s)) ++votes[std::llround(ta - tb)];
    CurrentAlignment best;
    best.edges_b = eb.size();
    for (const auto& [offset, n] : votes) {
        if (n * 2 < static_cast<int>(best.matched_edges)) continue;
        std::size_t matched = 0;
        for (double tb : eb) {
            auto it = std::lower_bound(ea.begin(), ea.end(), tb + offset - 1.5);
            if (it != ea.end() && *it <= tb + offset + 1.5) ++matched;
        }
        if (matched > best.matched_edges) {
            best.matched_edges = matched;
            best.offset_s = static_cast<double>(offset);
        }
    }
    if (best.matched_edges * 2 < eb.size())
        throw InputError(b.source + ": cannot align with " + a.source + ": only " +
                         std::to_string(best.matched_edges) + " of " + std::to_string(eb.size()) +
                         " current steps match at any offset within " + printf_text("%g", max_offset_s) + " s");
    // Refine: least squares on the current near the edges of b, offsets within +-1.5 s in 0.05 s steps.
    double best_cost = INFINITY;
    const double coarse = best.offset_s;
    for (double d = -1.5; d <= 1.5 + 1e-9; d += 0.05) {
        double cost = 0;
        std::size_t n = 0;
        for (double tb : eb)
            for (double u = -5.0; u <= 5.0; u += 0.1) {
                const double ia = current_at(a, tb + u + coarse + d), ib = current_at(b, tb + u);
                if (std::isfinite(ia) && std::isfinite(ib)) {
                    cost += (ia - ib) * (ia - ib);
                    ++n;
                }
            }
        if (n > 0 && cost / n < best_cost) {
            best_cost = cost / n;
            best.offset_s = coarse + d;
        }
    }
    best.current_rms_a = std::sqrt(best_cost);
    return best;
}

Recording splice_recordings(const Recording& a, const Recording& b, double offset_s) {
    Recording out;
    out.source = a.source + " + " + b.source;
    // b's times on a's clock, rounded to the microsecond: the sum t + offset carries the last-digit error of
    // both terms (0.1 + 19674.1 is not 19674.2), and a value that differs from what a BDF writer round-trips
    // would put this splice and `import`'s written file into different resampling bins.
    auto shifted = [&](double t) { return std::round((t + offset_s) * 1e6) / 1e6; };
    const double b_start = shifted(b.time_s.front()), b_end = shifted(b.time_s.back());
    std::size_t na = 0;
    while (na < a.size() && a.time_s[na] < b_start) ++na;
    // a's rows after b ends are kept: the cycler's export often runs on past the finer file (a last rest).
    std::size_t tail = a.size();
    while (tail > na && a.time_s[tail - 1] > b_end) --tail;
    const std::size_t nt = a.size() - tail, n = na + b.size() + nt;

    auto take = [&](const std::vector<double>& va, const std::vector<double>& vb, std::vector<double>& dst) {
        if (va.empty() && vb.empty()) return;
        dst.assign(n, kNaN);
        for (std::size_t k = 0; k < na && !va.empty(); ++k) dst[k] = va[k];
        for (std::size_t k = 0; k < b.size() && !vb.empty(); ++k) dst[na + k] = vb[k];
        for (std::size_t k = 0; k < nt && !va.empty(); ++k) dst[na + b.size() + k] = va[tail + k];
    };
    out.time_s.resize(n);
    for (std::size_t k = 0; k < na; ++k) out.time_s[k] = a.time_s[k];
    for (std::size_t k = 0; k < b.size(); ++k) out.time_s[na + k] = shifted(b.time_s[k]);
    for (std::size_t k = 0; k < nt; ++k) out.time_s[na + b.size() + k] = a.time_s[tail + k];
    take(a.voltage_v, b.voltage_v, out.voltage_v);
    take(a.current_a, b.current_a, out.current_a);
    take(a.unix_time_s, b.unix_time_s, out.unix_time_s);
    take(a.ambient_c, b.ambient_c, out.ambient_c);
    take(a.surface_c, b.surface_c, out.surface_c);
    take(a.t1_c, b.t1_c, out.t1_c);
    take(a.t2_c, b.t2_c, out.t2_c);
    take(a.heat_flux_w_per_m2, b.heat_flux_w_per_m2, out.heat_flux_w_per_m2);
    if (!a.step_type.empty() || !b.step_type.empty()) {
        out.step_type.assign(n, std::string{});
        for (std::size_t k = 0; k < na && !a.step_type.empty(); ++k) out.step_type[k] = a.step_type[k];
        for (std::size_t k = 0; k < b.size() && !b.step_type.empty(); ++k) out.step_type[na + k] = b.step_type[k];
        for (std::size_t k = 0; k < nt && !a.step_type.empty(); ++k) out.step_type[na + b.size() + k] = a.step_type[tail + k];
    }
    // Step numbering continues from a's steps so that steps stay distinct across the splice.
    if (!a.step_count.empty()) {
        out.step_count.assign(n, kNaN);
        double last = 0;
        for (std::size_t k = 0; k < na; ++k) last = out.step_count[k] = a.step_count[k];
        // b's steps are the continuation of a's: derive them from b's own step changes.
        double step = last;
        for (std::size_t k = 0; k < b.size(); ++k) {
            const bool changed = k == 0 || (!b.step_type.empty() && b.step_type[k] != b.step_type[k - 1]) ||
                                 (!b.step_count.empty() && b.step_count[k] != b.step_count[k - 1]);
            if (changed && !(k == 0 && na > 0 && !a.step_type.empty() && !b.step_type.empty() &&
                             a.step_type[na - 1] == b.step_type[0]))
                step += 1;
            out.step_count[na + k] = step;
        }
        // a's tail continues from b's last step, by a's own step changes (the first tail row continues b's last
        // step when a numbers it the same as a's row at b's end).
        for (std::size_t k = 0; k < nt; ++k) {
            const std::size_t j = tail + k;
            if (j > 0 && a.step_count[j] != a.step_count[j - 1]) step += 1;
            out.step_count[na + b.size() + k] = step;
        }
    }
    return out;
}

double median_interval_s(const Recording& rec) {
    std::vector<double> dt;
    for (std::size_t k = 1; k < rec.size(); k += std::max<std::size_t>(1, rec.size() / 5000))
        dt.push_back(rec.time_s[k] - rec.time_s[k - 1]);
    return upper_median(std::move(dt));
}

std::optional<double> continuation_offset_s(const Recording& a, const Recording& b, double lowest_voltage_v) {
    if (a.size() < 2 || b.size() < 2) return std::nullopt;
    const double va = a.voltage_v.back(), vb = b.voltage_v.front();
    const double ia = a.current_a.back(), ib = b.current_a.front();
    if (!std::isfinite(va) || !std::isfinite(vb) || !std::isfinite(ia) || !std::isfinite(ib)) return std::nullopt;
    // The cheap test first: the junction's voltages (10 mV is the wider of the two tolerances below).
    if (std::abs(vb - va) > 0.010) return std::nullopt;
    // The same current on both sides of the junction: a rest, or a step that runs on into the next file.
    double peak_a = 0;
    for (double i : a.current_a)
        if (std::isfinite(i)) peak_a = std::max(peak_a, std::abs(i));
    if (std::abs(ib - ia) > std::max(0.02, 0.01 * peak_a)) return std::nullopt;
    const bool unix_times = Recording::has_values(a.unix_time_s) && Recording::has_values(b.unix_time_s) &&
                            std::isfinite(a.unix_time_s.back()) && std::isfinite(b.unix_time_s.front());
    if (unix_times) {
        const double gap_s = b.unix_time_s.front() - a.unix_time_s.back();
        if (!(gap_s > 0 && gap_s <= 3600.0) || std::abs(vb - va) > 0.010) return std::nullopt;
        return a.time_s.back() + gap_s - b.time_s.front();
    }
    // Without a common clock: the same voltage, and a part that did not run the cell empty.
    if (std::abs(vb - va) > 0.005) return std::nullopt;
    double lowest_a = std::numeric_limits<double>::infinity();
    for (double v : a.voltage_v)
        if (std::isfinite(v)) lowest_a = std::min(lowest_a, v);
    if (lowest_a < lowest_voltage_v + 0.05) return std::nullopt;
    return a.time_s.back() + median_interval_s(a) - b.time_s.front();
}

std::vector<Recording> join_continued_recordings(std::vector<Recording> recs, std::vector<std::string>& notes) {
    double lowest = std::numeric_limits<double>::infinity();
    for (const auto& r : recs)
        for (double v : r.voltage_v)
            if (std::isfinite(v)) lowest = std::min(lowest, v);
    merge_pairwise(recs, [&](const Recording& a, const Recording& b) -> std::optional<Recording> {
        const auto offset = continuation_offset_s(a, b, lowest);
        if (!offset) return std::nullopt;
        notes.push_back(b.source + " continues " + a.source +
                        printf_text(" (its first row, %.4f V at %.3g A, follows the other's last, %.4f V at %.3g A, "
                                    "%.3g s later): joined as one test",
                                    b.voltage_v.front(), b.current_a.front(), a.voltage_v.back(), a.current_a.back(),
                                    *offset + b.time_s.front() - a.time_s.back()));
        Recording whole = splice_recordings(a, b, *offset);
        // The step that runs across the junction is one step (splice_recordings starts a new one there).
        const std::size_t junction = a.size();
        if (!whole.step_count.empty() && junction < whole.size() &&
            whole.step_count[junction] == whole.step_count[junction - 1] + 1)
            for (std::size_t k = junction; k < whole.size(); ++k) whole.step_count[k] -= 1;
        return whole;
    });
    return recs;
}

}  // namespace cellbench::estimator
