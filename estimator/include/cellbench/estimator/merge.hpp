#pragma once
// Putting recordings of one test onto one clock: the cycler's own export and an already merged BDF file
// (same instrument, different time origin and resolution) are aligned by their current steps; DAQ channels
// are resampled onto the cycler's time base.
#include <string>
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

// Linear interpolation of (time_s, y) at query times; NaN outside [time_s.front(), time_s.back()].
std::vector<double> resample_linear(const std::vector<double>& time_s, const std::vector<double>& y,
                                    const std::vector<double>& query_time_s);

}  // namespace cellbench::estimator
