#pragma once
// Internal to the estimator: the median the fits use for robust scales and typical spacings.

#include <algorithm>
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

}  // namespace cellbench::estimator
