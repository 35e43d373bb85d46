#pragma once
// Checks that a recording read with its logging artefacts corrected fits as the clean one does (the row-rule
// tests of stale_current.hpp, voltage_spikes.hpp and current_glitches.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "unit/hppc_synthetic.hpp"

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

// The synthetic HPPC the row-rule tests corrupt: four levels, rows 1 s apart, 0.2 mV of voltage noise.
inline Recording synthetic_hppc_one_second() {
    SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    return synthesize(hppc_program(4), so);
}

// Every 300th row (5 minutes at 1 s) where the current holds from the row before to the row after, corrupted by
// corrupt(rec, k): those rows, in order.
template <typename Corrupt>
std::vector<std::size_t> corrupt_every_300th_held_row(Recording& rec, Corrupt&& corrupt) {
    std::vector<std::size_t> rows;
    for (std::size_t k = 300; k + 1 < rec.size(); k += 300) {
        if (!(rec.current_a[k - 1] == rec.current_a[k] && rec.current_a[k] == rec.current_a[k + 1])) continue;
        corrupt(rec, k);
        rows.push_back(k);
    }
    return rows;
}

// The fit of `corrupted` says `warning` and gives the fit of `clean`: the same pulse sets, the discharge R0 and R2
// within 0.1 %, the OCV within 1 mV.
inline void expect_fits_as_clean(const Recording& clean, const Recording& corrupted, const std::string& warning) {
    const auto options = characterization_options();
    const auto a = estimator::characterize({clean}, options);
    const auto b = estimator::characterize({corrupted}, options);
    EXPECT_TRUE(warns(b.warnings, warning));
    ASSERT_TRUE(a.global && b.global);
    EXPECT_EQ(b.pulse_fits.size(), a.pulse_fits.size());
    expect_discharge_column_near(a, b, &estimator::RcTable::r0_ohm, 1e-3);
    expect_discharge_column_near(a, b, &estimator::RcTable::r2_ohm, 1e-3);
    for (std::size_t k = 0; k < a.params.ocv_v.size(); ++k)
        EXPECT_NEAR(b.params.ocv_v[k], a.params.ocv_v[k], 1e-3) << "OCV row " << k;
}

}  // namespace cellbench::test
