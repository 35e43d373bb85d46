#pragma once
// Internal to the estimator: what the row rules for logging artefacts of one to a few rows share (voltage spikes,
// voltage_spikes.hpp; current glitches, current_glitches.hpp): finding their runs and bridging them.

#include <cstddef>
#include <vector>

namespace cellbench::estimator {

// The rows of every run a rule finds, left to right: at each row k the shortest run length of 1..max_rows that
// is_run(k, length) accepts (the run's rows k .. k + length - 1, bracketed by rows k - 1 and k + length). The row
// after a run is its bracket, not the start of another, so runs are at least one row apart.
template <typename IsRun>
std::vector<std::size_t> artefact_run_rows(std::size_t n_rows, std::size_t max_rows, IsRun&& is_run) {
    std::vector<std::size_t> rows;
    for (std::size_t k = 1; k + 1 < n_rows; ++k)
        for (std::size_t length = 1; length <= max_rows; ++length)
            if (is_run(k, length)) {
                for (std::size_t r = k; r < k + length; ++r) rows.push_back(r);
                k += length;
                break;
            }
    return rows;
}

// Where row k lies between the bracket rows a and b: its share of their time apart (of their row count where
// the time does not advance).
inline double bracket_weight(const std::vector<double>& time_s, std::size_t k, std::size_t a, std::size_t b) {
    const double t0 = time_s[a], t1 = time_s[b];
    return t1 > t0 ? (time_s[k] - t0) / (t1 - t0) : static_cast<double>(k - a) / static_cast<double>(b - a);
}

// Each run of `rows` (as artefact_run_rows lists them) takes the straight line in time between the values of
// `column` at the rows either side of it.
inline void bridge_artefact_runs(const std::vector<double>& time_s, std::vector<double>& column,
                                 const std::vector<std::size_t>& rows) {
    for (std::size_t n = 0; n < rows.size();) {
        std::size_t m = n + 1;
        while (m < rows.size() && rows[m] == rows[m - 1] + 1) ++m;
        const std::size_t a = rows[n] - 1, b = rows[m - 1] + 1;
        for (std::size_t q = n; q < m; ++q)
            column[rows[q]] = column[a] + bracket_weight(time_s, rows[q], a, b) * (column[b] - column[a]);
        n = m;
    }
}

}  // namespace cellbench::estimator
