#pragma once
// Voltage spikes: a logged voltage that leaves and returns within one to three samples while the current holds
// (an instrument's glitch or a logger's dropout; the Battery Data Alliance keeps a BioLogic export with such
// "physically implausible voltage outlier spikes" as an example). A cell cannot do that: at a constant current
// its voltage moves by the RC pairs' and the OCV's slow drift, well under a millivolt per sample, and a step of
// the current is excluded by the current test. One such row (0.5 V in a 3.5 V rest of the P45B HPPC) moved the
// fitted tables by up to 7 % in R0 and a factor 84 in C2. Found by what it shows: each row of the run differs
// from both rows either side of the run by more than 50 mV, all in one direction, those two rows agree with each
// other within a quarter of the smallest such difference, and the current holds from the row before the run to
// the row after (within 0.05 A or 2 %). Four or more rows are left alone.
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

std::vector<std::size_t> voltage_spike_rows(const Recording& rec);

// Each run of spike rows takes the voltage interpolated in time between the rows either side; in plain words for a fit's
// warnings or a diagnosis' notes ("SOURCE: N rows ... the first at t = ..."); empty when there is none.
std::string correct_voltage_spikes(Recording& rec);

// The recording as the estimator reads it: stale step rows (stale_current.hpp), current glitches
// (current_glitches.hpp) and voltage spikes corrected, in that order, one note per kind found. fit, simulate and
// diagnose all read their recordings through this.
std::vector<std::string> correct_logging_artifacts(Recording& rec);

}  // namespace cellbench::estimator
