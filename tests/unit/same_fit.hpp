#pragma once
// Checks that a recording read with its logging artefacts corrected fits as the clean one does (the row-rule
// tests of stale_current.hpp and voltage_spikes.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/estimator/fit.hpp"

namespace cellbench::test {

// Whether one of a fit's warnings contains `text`.
inline bool warns(const std::vector<std::string>& warnings, const std::string& text) {
    return std::any_of(warnings.begin(), warnings.end(),
                       [&](const std::string& w) { return w.find(text) != std::string::npos; });
}

// Every row of one discharge table of `b` within `relative` of `a`'s.
inline void expect_discharge_column_near(const estimator::Characterization& a, const estimator::Characterization& b,
                                         std::vector<double> estimator::RcTable::*column, double relative) {
    const auto& x = a.params.discharge.*column;
    const auto& y = b.params.discharge.*column;
    ASSERT_EQ(x.size(), y.size());
    for (std::size_t k = 0; k < x.size(); ++k)
        EXPECT_NEAR(y[k], x[k], relative * x[k]) << "row " << k << " (SOC " << a.params.soc[k] << ")";
}

}  // namespace cellbench::test
