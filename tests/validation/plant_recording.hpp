#pragma once
// The validation tests' one bridge between the independent plant (which shares no type with the project) and
// the estimator: a plant recording as the Recording the fitter and diagnose read, column by column.
#include <string>

#include "cellbench/core/recording.hpp"
#include "cellbench/plant/plant.hpp"

namespace cellbench::test {

inline Recording to_recording(const plant::Recording& p, const std::string& name) {
    Recording r;
    r.source = name;
    r.time_s = p.time_s;
    r.voltage_v = p.voltage_v;
    r.current_a = p.current_a;
    r.ambient_c = p.ambient_c;
    r.surface_c = p.surface_c;
    r.heat_flux_w_per_m2 = p.heat_flux_w_per_m2;
    r.step_type = p.step_type;
    r.step_count.assign(p.step_count.begin(), p.step_count.end());
    return r;
}

}  // namespace cellbench::test
