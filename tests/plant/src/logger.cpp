// A cycler's record conditions applied to a recording the plant wrote densely (plant.hpp: log_on_change).
#include <cmath>
#include <cstddef>
#include <vector>

#include "cellbench/plant/plant.hpp"

namespace cellbench::plant {

namespace {

template <typename T>
void keep_rows(std::vector<T>& column, const std::vector<std::size_t>& rows) {
    if (column.empty()) return;
    std::vector<T> out;
    out.reserve(rows.size());
    for (std::size_t k : rows) out.push_back(column[k]);
    column = std::move(out);
}

}  // namespace

Recording log_on_change(const Recording& dense, const RecordConditions& c) {
    const std::size_t n = dense.size();
    std::vector<std::size_t> rows;
    double last_t = 0, last_v = 0, last_i = 0;
    for (std::size_t k = 0; k < n; ++k) {
        const bool first = k == 0 || dense.step_count[k] != dense.step_count[k - 1];
        const bool last = k + 1 == n || dense.step_count[k + 1] != dense.step_count[k];
        const double t = dense.time_s[k], v = dense.voltage_v[k], i = dense.current_a[k];
        if (first || last || rows.empty() || std::abs(v - last_v) >= c.dv_v || std::abs(i - last_i) >= c.di_a ||
            t - last_t >= c.dt_s) {
            rows.push_back(k);
            last_t = t, last_v = v, last_i = i;
        }
    }
    Recording out = dense;
    for (auto* col : {&out.time_s, &out.voltage_v, &out.current_a, &out.ambient_c, &out.surface_c,
                      &out.heat_flux_w_per_m2, &out.true_voltage_v, &out.true_current_a, &out.true_soc, &out.true_ocv_v,
                      &out.true_core_c, &out.true_surface_c, &out.true_ambient_c, &out.true_heat_flux_w_per_m2,
                      &out.true_heat_generated_j, &out.true_heat_out_j})
        keep_rows(*col, rows);
    keep_rows(out.step_count, rows);
    keep_rows(out.step_type, rows);
    return out;
}

}  // namespace cellbench::plant
