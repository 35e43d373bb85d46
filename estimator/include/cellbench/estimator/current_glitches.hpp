#pragma once
// Current glitches: a logged current that leaves and returns within one to three samples while the voltage does
// not follow (a misread current channel, a logger's dropout to 0 A in a pulse). A cell cannot do that: a current
// change of dI moves its voltage at once by R0 * dI (R0 is instantaneous), so a current that really flowed shows
// in the voltage of the same row. One such row (-18 A for 0.1 s in a rest of the P45B HPPC) moved the fitted
// discharge R0 by up to 74 %, C1 by 96 %: the model drops the voltage by R0 * 18 A there and back, which the data
// do not show, and the fit bends the tables around it.
//
// Found by what it shows: the rows either side of the run agree on the current (within 0.05 A or 2 %), every row
// of the run departs from it by more than 0.2 A and 10 % of it, and no row's voltage leaves the line between the
// rows either side by a quarter of what the recording's own ohmic resistance (the median voltage step over its
// held current steps) gives that departure. Without three such steps to measure that resistance by, nothing is
// called a glitch. Four or more rows are left alone.
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

// The recording's ohmic resistance as its own current steps show it: the median |dV / dI| over the rows where the
// current steps by at least 0.5 A from a held current and holds at the next row. NaN with fewer than three.
double apparent_step_resistance_ohm(const Recording& rec);

std::vector<std::size_t> current_glitch_rows(const Recording& rec);

// Each run of glitch rows takes the current interpolated in time between the rows either side; in plain words for
// a fit's warnings or a diagnosis' notes ("SOURCE: N rows ... the first at t = ..."); empty when there is none.
std::string correct_current_glitches(Recording& rec);

}  // namespace cellbench::estimator
