#pragma once
// Clock offset between a cycler recording (current) and a DAQ recording (surface temperature, heat flux) of
// the same test, from the physics that links them: the heat the cell generates.
//
// The cycler knows the current, so the generated heat is ~ a*I^2 (Joule; the reversible part, linear in I, is
// smaller and changes sign with SOC). The DAQ sees the same heat as C_th*dT/dt + q''*A (thesis eq. 4.3).
// The offset maximises the Pearson correlation of the two over their overlap:
//     cycler_time = daq_time + offset_s.
// The heat reaches the surface sensor with a lag (radial conduction, sensor contact, and the polarisation
// heat that builds up with the RC time constants), which a plain cross-correlation would book as clock
// offset. The cycler side is therefore passed through a first-order lag L_tau[I^2] whose time constant is fitted
// together with the offset (coarse grid on 1 s bins over +-max_offset_s and a lag grid, then refinement at
// 0.1 s and 1 s of lag, then a parabola through the peak). Offset and lag trade off along a shallow ridge;
// `uncertainty_s` is the half-width of the offsets on that ridge whose correlation is within 0.005 of the
// best, and the lag-free result is reported as well.
// dT/dt comes from a local linear regression over derivative_window_s, which is T' smoothed with the parabolic
// kernel K(s) = 3/(4h)(1 - s^2/h^2), h = window/2; q'' and the cycler side get the same kernel, so both sides
// carry identical symmetric smoothing and it cannot pass for lag or offset.
//
// Only DAQ samples whose shifted time falls inside the cycler's record are compared, so a DAQ that keeps
// recording the cool-down after the cycler stopped (or starts before it) does not bias the result; at least
// min_overlap_fraction of the shorter record must overlap.
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

struct AlignOptions {
    double derivative_window_s = 10.0;     // window of dT/dt (and of the matching smoothing on both sides)
    double max_lag_s = 60.0;               // largest response lag tried
    double min_overlap_fraction = 0.5;     // of the shorter recording's duration
    double ridge_tolerance = 0.005;        // correlation drop that defines uncertainty_s
    // check_clock_alignment: evidence below this correlation is refused...
    double min_correlation = 0.5;
    // ...and so is an offset that puts both the DAQ's first and its last sample further than this from the
    // cycler's own first and last timestamps (the bench starts and stops both instruments together; a cut or
    // foreign DAQ file lands its best match anywhere).
    double max_end_mismatch_s = 300.0;
    double max_uncertainty_s = 30.0;       // ...and a ridge of equally good offsets wider than this
};

struct ClockAlignment {
    double offset_s = kNaN;          // cycler_time = daq_time + offset_s
    double correlation = kNaN;       // Pearson r of lagged I^2 and DAQ heat at offset_s (quality, 1 = perfect)
    double lag_s = kNaN;             // fitted response lag (first-order time constant)
    double uncertainty_s = kNaN;     // see header comment
    double offset_no_lag_s = kNaN;   // plain cross-correlation of I^2 and DAQ heat (lag 0)
    double correlation_no_lag = kNaN;
    double overlap_s = 0.0;          // compared duration at offset_s
    double joule_resistance_ohm = kNaN;  // slope of DAQ heat against lagged I^2 (an effective resistance)
    bool at_search_limit = false;    // best offset within 2 s of +-max_offset_s: widen the search
    // Where the shifted DAQ record starts and ends relative to the cycler's record (+ = later), s.
    double start_mismatch_s = kNaN;
    double end_mismatch_s = kNaN;
    std::string note;
};

// Throws InputError on size mismatches, fewer than 10 samples, non-positive c_th/area/max_offset, or when no
// offset within +-max_offset_s gives the required overlap.
ClockAlignment estimate_clock_offset(const std::vector<double>& cycler_time_s, const std::vector<double>& current_a,
                                     const std::vector<double>& daq_time_s, const std::vector<double>& temperature_c,
                                     const std::vector<double>& heat_flux_w_per_m2, double c_th_j_per_k,
                                     double area_m2, double max_offset_s, const AlignOptions& options = {});

}  // namespace cellbench::estimator

namespace cellbench::estimator {

// Refuses (InputError with the numbers) an alignment whose evidence is weak (correlation below
// options.min_correlation, best offset at the search limit, an uncertainty ridge wider than max_uncertainty_s)
// or that lands the DAQ record far from the cycler's (both ends further than max_end_mismatch_s). `what` names
// the DAQ file for the message.
void check_clock_alignment(const ClockAlignment& al, const std::string& what, const AlignOptions& options = {});

}  // namespace cellbench::estimator
