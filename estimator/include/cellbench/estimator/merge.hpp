#pragma once
// Putting recordings of one test onto one clock: the cycler's own export and an already merged BDF file
// (same instrument, different time origin and resolution) are aligned by their current steps; DAQ channels
// are resampled onto the cycler's time base.
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

struct CurrentAlignment {
    double offset_s = 0.0;          // time_in_a = time_in_b + offset_s
    std::size_t matched_edges = 0;  // current steps of b that land on a step of a
    std::size_t edges_b = 0;
    double current_rms_a = 0.0;     // RMS current mismatch over the overlap after alignment
};

// Aligns recording b to recording a by matching their current steps (changes larger than step_a), then
// refines to 0.1 s by least squares on the current over the overlap. Throws InputError if no consistent
// offset exists.
CurrentAlignment align_by_current(const Recording& a, const Recording& b, double max_offset_s);

// Cycler rows of a before b starts, then b's rows on a's clock (b shifted by offset_s, to the microsecond),
// then a's rows after b ends. Channels present in either are kept; rows without a value hold NaN.
Recording splice_recordings(const Recording& a, const Recording& b, double offset_s);

// The median interval between a recording's rows (from at most about 5000 of them).
double median_interval_s(const Recording& rec);

// Merges recordings pairwise until no pair merges: merge(a, b) returns the one recording that stands for both, or
// nothing; it takes a's place, b is dropped, and the search starts again from the first pair. The loop of
// merge_overlapping (fit.cpp: a finer recording spliced into a coarser one of the same test) and of
// join_continued_recordings.
template <class Merge>
void merge_pairwise(std::vector<Recording>& recs, Merge&& merge) {
    for (bool merged = true; merged;) {
        merged = false;
        for (std::size_t i = 0; i < recs.size() && !merged; ++i)
            for (std::size_t j = 0; j < recs.size() && !merged; ++j) {
                if (i == j) continue;
                if (std::optional<Recording> both = merge(recs[i], recs[j])) {
                    recs[i] = std::move(*both);
                    recs.erase(recs.begin() + static_cast<std::ptrdiff_t>(j));
                    merged = true;
                }
            }
    }
}

// Files that continue one another (a cycler's export split into parts, a test logged day by day): b continues a
// when b starts where a ends. With Unix time in both, b starts after a ends, within an hour, and its first voltage
// is within 10 mV of a's last; without it, the current is the same at the junction, the voltages agree within
// 5 mV, and a does not end on the lowest voltage any of the recordings reaches (a part that ran the cell empty
// ends the test). Returns the offset that puts b's clock on a's (b's first row one sample interval, or the Unix
// gap, after a's last), or nothing.
std::optional<double> continuation_offset_s(const Recording& a, const Recording& b, double lowest_voltage_v);

// Joins the recordings that continue one another into one recording each (splice_recordings of the parts in
// order), so that a test split into files is one test: its SOC counted through from the full charge at its
// start, its capacity from that charge to the cut-off. Each join is described in notes.
std::vector<Recording> join_continued_recordings(std::vector<Recording> recs, std::vector<std::string>& notes);

// Linear interpolation of (time_s, y) at query times; NaN outside [time_s.front(), time_s.back()].
std::vector<double> resample_linear(const std::vector<double>& time_s, const std::vector<double>& y,
                                    const std::vector<double>& query_time_s);

}  // namespace cellbench::estimator
