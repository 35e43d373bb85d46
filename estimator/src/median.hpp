#pragma once
// Internal to the estimator: the median the fits use for robust scales and typical spacings.

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

#include "cellbench/core/recording.hpp"  // kNaN

namespace cellbench::estimator {

// The middle element after a partial sort (of an even count, the upper of the two middle ones); NaN when empty.
inline double upper_median(std::vector<double> v) {
    if (v.empty()) return kNaN;
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
    return v[v.size() / 2];
}

// upper_median of the finite values of v (a recording's column with empty cells); NaN when none is finite.
inline double finite_upper_median(const std::vector<double>& v) {
    std::vector<double> finite;
    finite.reserve(v.size());
    for (const double x : v)
        if (std::isfinite(x)) finite.push_back(x);
    return upper_median(std::move(finite));
}

}  // namespace cellbench::estimator
