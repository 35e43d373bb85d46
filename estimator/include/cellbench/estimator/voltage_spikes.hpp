#pragma once
// Single-row voltage spikes: a logged voltage that leaves and returns within one sample while the current holds
// (an instrument's glitch; the Battery Data Alliance keeps a BioLogic export with such "physically implausible
// voltage outlier spikes" as an example). A cell cannot do that: at a constant current its voltage moves by the
// RC pairs' and the OCV's slow drift, well under a millivolt per sample, and a step of the current is excluded by
// the current test. One such row (0.5 V in a 3.5 V rest of the P45B HPPC) moved the fitted tables by up to 7 % in
// R0 and a factor 84 in C2. Found by what it shows: the row's voltage differs from both neighbours by more than
// 50 mV in the same direction, the neighbours agree with each other within a quarter of that, and the current of
// the three rows is the same (within 0.05 A or 2 %).
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

std::vector<std::size_t> voltage_spike_rows(const Recording& rec);

// Each spike row takes the voltage interpolated in time between its neighbours; in plain words for a fit's
// warnings or a diagnosis' notes ("SOURCE: N rows ... the first at t = ..."); empty when there is none.
std::string correct_voltage_spikes(Recording& rec);

// The recording as the estimator reads it: stale step rows (stale_current.hpp) and voltage spikes corrected, one
// note per kind found. fit, simulate and diagnose all read their recordings through this.
std::vector<std::string> correct_logging_artifacts(Recording& rec);

}  // namespace cellbench::estimator
