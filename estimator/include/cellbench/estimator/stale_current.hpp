#pragma once
// Rows a cycler writes at the instant a current step begins, with the step's new voltage but the current of the
// step before (the current reading not yet updated). A published Digatron HPPC (the Battery Data Alliance's
// FZJ INR21700 reference file) starts every pulse so: a row 7 ms into the step reads 0 A while the voltage has
// already fallen by R0 * 5 A. Read as it stands, the pulse starts a row late: the rest before it ends in the
// pulse's ohmic drop, which no parameter explains, and the per-pulse-set fits lose the pulse's first edge (the
// synthetic HPPC of the unit test: no usable pulse set left). They are found by what they show, whatever the
// cycler: the row before is at rest and row k still reads its current (both within 1 % of the step), the next
// row's current steps (by at least 0.1 A), and the voltage of row k has already moved, in the direction the step
// drives it, by more than 5 mV and more than half of the move to the next row.
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

// The rows of `rec` that show a new voltage with the old current.
std::vector<std::size_t> stale_current_rows(const Recording& rec);

// The voltage shows that the step had begun: each such row takes the current of the row after it (under the
// sampling convention of electrical.hpp, the step's current then flowed over the interval before the row, as
// the drop shows). Returns how many rows.
std::size_t take_next_current_for_stale_rows(Recording& rec);

// take_next_current_for_stale_rows, said in plain words for a fit's warnings or a diagnosis' notes ("SOURCE: N rows
// ... the first at t = ..."); empty when the recording has no such row.
std::string correct_stale_current_rows(Recording& rec);

}  // namespace cellbench::estimator
