#pragma once
// Coulomb counting: the one convention every count of a recording's charge in the estimator follows (the SOC of
// the characterization's rows, the capacity a test measures, a phase's charge, the global fit's SOC).
//
// Rows are samples. Within a step the current is integrated by the trapezoid rule (a CV taper is a curve). Across
// a current step the question is when, between the two rows, the step happened, and loggers differ:
//  - a cycler that writes a step's first row the moment the step begins (Neware, the validation plant): the old
//    current flowed until the row that shows the new one. The interval before that row is then the old step's own
//    logging interval, or shorter where the step cut it short (a step ended by a voltage or Ah limit);
//  - a logger that writes a step's end as a row of the old step and the new step's first row one of its logging
//    intervals later (the Panasonic 18650PF's Digatron: "the first row of each discharge is logged about 60 s
//    after it starts"): the new current flowed over the whole interval, whose length is the new step's interval.
// Each step whose intervals tell the two apart votes; a recording comes from one logger, so the steps they leave
// ambiguous (both steps logged at the same rate) follow the recording's majority (twice the other's votes), and
// the electrical model's ZOH convention (the new current over the interval before its row) where none is clear.
// Where the recording has a step column, a current step is one only where that column changes as well: within one
// of the logger's steps the current's changes are the step's own course (a CV taper logged every minute by a
// cycler's voltage-change rule falls by more than 5 % between its rows; counted as steps, the CCCV charge of the
// validation plant's HPPC logged that way came out 13 mAh short, 0.5 % of the cell).
// Counting every interval at its closing row's current alone (that ZOH convention) adds the step times the interval
// before it at every step of a cycler's recording, which does not cancel where rests are logged at another rate
// than pulses: on the independent validation plant's HPPCs (60: three layouts, seeds 1-20) the SOC drifted by up
// to 0.64 % of the capacity over the test (3-8 mV of OCV at the low levels), by at most 0.03 % with this rule; on
// the Panasonic HPPC this rule gives the source's own Ah counter (2.833 Ah), where holding the old current would
// give 3.62 Ah.
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

// Whether the current steps between two rows' currents a and b (A): they differ by more than 50 mA and 5 % of the
// larger. The one test of a step for Coulomb counting and for the global fit's ticks.
bool is_current_step(double a, double b);
// The same with another floor than 50 mA (a recording whose current noise is larger: a large cell's channel).
bool is_current_step(double a, double b, double floor_a);

// How a recording's logger placed its rows at current steps (see above), from the steps that tell.
enum class StepLogging { at_step_start, one_interval_after, unknown };
StepLogging step_logging(const std::vector<double>& time_s, const std::vector<double>& current_a);

// How the current flowed over the interval before every row under this convention. `mean_a`: the mean current (A)
// (row 0: its own current): within a step the trapezoid of its two rows, across a step the old or the new current as
// the step's vote says; a row with a non-finite time or current (or its predecessor's) keeps its own current.
// Whatever integrates over a recording's intervals reads it: the charge count below and the model simulated on the
// recording (simulate.hpp), so that both see one current. `step`: whether a current step lies between rows k - 1
// and k (element k; element 0 false): is_current_step between two finite rows that advance in time and, where the
// recording has a step column, that column changes there too. Elsewhere the current moved within one step, along a
// curve its rows sample.
struct IntervalCurrents {
    std::vector<double> mean_a;
    std::vector<char> step;
};
IntervalCurrents interval_currents(const Recording& rec);  // with its step column, where it has one

// Charge throughput (Ah, + = charged) at every row from the first (0 there): interval_currents' mean over each
// interval.
// Rows with a non-finite time or current, and intervals that do not advance, add nothing.
std::vector<double> cumulative_charge_ah(const std::vector<double>& time_s, const std::vector<double>& current_a);
std::vector<double> cumulative_charge_ah(const Recording& rec);  // with its step column, where it has one

}  // namespace cellbench::estimator
