#include "cellbench/estimator/simulate.hpp"

#include <algorithm>
#include <cmath>

namespace cellbench::estimator {

namespace {

double first_finite(const std::vector<double>& v) {
    for (double x : v)
        if (std::isfinite(x)) return x;
    return kNaN;
}

}  // namespace

std::vector<double> time_weights(const std::vector<double>& t) {
    const std::size_t n = t.size();
    std::vector<double> w(n, 0.0);
    if (n == 1) w[0] = 1.0;
    for (std::size_t k = 0; k + 1 < n; ++k) {
        const double half = 0.5 * (t[k + 1] - t[k]);
        w[k] += half;
        w[k + 1] += half;
    }
    return w;
}

SimulationTrace simulate(const CellModel& model, const Recording& rec, const SimulationOptions& options) {
    const auto& p = model.params();
    const std::size_t n = rec.size();
    SimulationTrace tr;
    if (n == 0) return tr;

    // Ambient: measured when present, else given, else the first surface reading (cell at equilibrium).
    const double first_surface = rec.has_surface() ? first_finite(rec.surface_c) : kNaN;
    double ambient_const = options.ambient_c.value_or(std::isfinite(first_surface) ? first_surface
                                                                                    : p.reference_temperature_c);
    if (!options.ambient_c && rec.has_ambient()) ambient_const = first_finite(rec.ambient_c);
    auto ambient_at = [&](std::size_t k) {
        if (!options.ambient_c && rec.has_ambient() && std::isfinite(rec.ambient_c[k])) return rec.ambient_c[k];
        return ambient_const;
    };

    CellState s;
    s.temperature_c = options.initial_temperature_c.value_or(std::isfinite(first_surface) ? first_surface
                                                                                          : ambient_at(0));
    // Unknown history: a cell above half charge at the start was most likely last charged (a test starts after a
    // full CCCV charge), one below, last discharged.
    auto initial_hysteresis_v = [&](double soc) {
        const auto& h = p.extensions.ocv_hysteresis;
        return h ? (soc > 0.5 ? 1.0 : -1.0) * h->magnitude_v : 0.0;
    };
    if (options.initial_soc) {
        s.soc = *options.initial_soc;
    } else {
        // The state the recording implies: a rested cell's voltage is its OCV plus the hysteresis it holds; under
        // current, remove R0*I.
        const double soc_guess = p.soc_from_ocv(rec.voltage_v[0]);
        const double ohmic = ohmic_drop_v(p.rc_at(soc_guess, -1), p.rc_at(soc_guess, +1), rec.current_a[0]);
        s.soc = p.soc_from_ocv(rec.voltage_v[0] - ohmic - initial_hysteresis_v(soc_guess));
    }
    s.hysteresis_v = initial_hysteresis_v(s.soc);
    tr.initial_soc = s.soc;
    tr.ambient_c = ambient_const;

    for (auto* v : {&tr.time_s, &tr.voltage_v, &tr.ocv_v, &tr.soc, &tr.temperature_c, &tr.heat_flow_out_w,
                    &tr.heat_generated_w})
        v->reserve(n);
    // The fast path of CellModel::step (same results; model.hpp): this loop runs millions of times in diagnose.
    CellStepper stepper(model);
    const bool measured_ambient = !options.ambient_c && rec.has_ambient();
    const double* time = rec.time_s.data();
    const double* current = rec.current_a.data();
    const double* ambient = measured_ambient ? rec.ambient_c.data() : nullptr;
    for (std::size_t k = 0; k < n; ++k) {
        const double dt = k == 0 ? 0.0 : time[k] - time[k - 1];
        const double amb = ambient && std::isfinite(ambient[k]) ? ambient[k] : ambient_const;
        const CellOutputs o = stepper.step(s, current[k], amb, dt);
        tr.time_s.push_back(time[k]);
        tr.voltage_v.push_back(o.voltage_v);
        tr.ocv_v.push_back(o.ocv_v);
        tr.soc.push_back(s.soc);
        tr.temperature_c.push_back(s.temperature_c);
        tr.heat_flow_out_w.push_back(o.sensor_heat_flow_w);
        tr.heat_generated_w.push_back(o.heat_irreversible_w + o.heat_reversible_w);
    }
    return tr;
}

SimulationMetrics compare(const ParameterSet& params, const Recording& rec, const SimulationTrace& tr,
                          const std::vector<bool>* mask) {
    SimulationMetrics m;
    const std::size_t n = std::min(rec.size(), tr.time_s.size());
    m.samples = 0;
    const auto w = time_weights(rec.time_s);
    auto stats = [&](auto&& error_at, bool measured) {
        ErrorStats e;
        if (!measured) return e;
        double sum_w = 0, sum_e2 = 0, max_abs = 0;
        for (std::size_t k = 0; k < n; ++k) {
            if (mask && !(*mask)[k]) continue;
            const double err = error_at(k);
            if (!std::isfinite(err)) continue;
            sum_w += w[k];
            sum_e2 += w[k] * err * err;
            max_abs = std::max(max_abs, std::abs(err));
        }
        if (sum_w > 0) {
            e.rms = std::sqrt(sum_e2 / sum_w);
            e.max_abs = max_abs;
        }
        return e;
    };
    for (std::size_t k = 0; k < n; ++k)
        if (!mask || (*mask)[k]) ++m.samples;
    m.voltage_v = stats([&](std::size_t k) { return tr.voltage_v[k] - rec.voltage_v[k]; }, true);
    m.temperature_c = stats([&](std::size_t k) { return tr.temperature_c[k] - rec.surface_c[k]; }, rec.has_surface());
    m.heat_flux_w = stats(
        [&](std::size_t k) { return tr.heat_flow_out_w[k] - rec.heat_flux_w_per_m2[k] * params.thermal.area_m2; },
        rec.has_heat_flux());
    return m;
}

}  // namespace cellbench::estimator
