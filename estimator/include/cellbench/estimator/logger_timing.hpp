#pragma once
// What a recording's current steps say about its logger rather than the cell: whether its voltage lags its current
// by more than a sample (timing), and whether its current counts charging as positive (the sign convention).
#include <cstddef>
#include <string>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

// At a recording's clean current steps (held for a sample before and after, sampled at most 0.25 s apart, where an
// RC pair's growth over one sample is a small part of the ohmic jump for any time constant from a second up): how
// many there are, and at how many the voltage moves more across the second sample than across the first. A cycler
// or DAQ that samples voltage and current together shows the ohmic jump at once (the P45B and Panasonic HPPCs: 0-1 %
// of their steps); the Panasonic's drive-cycle logs show 5 mOhm in the first 0.1 s and 16 mOhm in the next (89-98 %
// of their steps).
struct StepTiming {
    std::size_t steps = 0, voltage_later = 0;
    // At least five such steps, and the voltage late at most of them.
    [[nodiscard]] bool voltage_lags() const { return steps >= 5 && 2 * voltage_later > steps; }
};
StepTiming step_timing(const Recording& rec);

// "SOURCE: its voltage lags its current by more than a sample (at N of its M current steps ...)", or empty when it
// does not lag; callers add what it means for them.
std::string voltage_lag_text(const Recording& rec);

// At a recording's current steps (held for a sample before and after; any sampling interval): the voltage moves
// with the current, by R0 and the pairs' growth, all positive, whatever the logger's timing. Where it moves against
// the current at nearly every step, the current counts discharging as positive (some cyclers' exports), and every
// SOC, resistance and heat computed from it has the wrong sign.
struct CurrentSign {
    std::size_t steps = 0, against = 0;  // steps where voltage and current moved at all; of them, in opposite senses
    [[nodiscard]] bool reversed() const { return steps >= 5 && against * 10 >= steps * 9; }
};
CurrentSign current_sign(const Recording& rec);

// "SOURCE: its current counts discharging as positive (...)" when current_sign says it is reversed, else empty.
std::string reversed_current_text(const Recording& rec);

}  // namespace cellbench::estimator
