#include "cellbench/estimator/simulate.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/estimator/segment.hpp"
#include "golden.hpp"
#include "median.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {

double first_finite(const std::vector<double>& v) {
    for (double x : v)
        if (std::isfinite(x)) return x;
    return kNaN;
}

// A recording with no ambient column that starts with a rest during which the surface temperature moves by more
// than 0.5 K started out of equilibrium (a cell still cooling after its charge, as the Panasonic 18650PF's 0 degC
// drive cycles do, from 18 degC in a 0 degC chamber): its first reading is not the ambient. The lumped model's
// decay in a rest, T(t) = T_amb + (T_0 - T_amb) exp(-t / tau), tau = R_th C_th, fitted to that rest (linear least
// squares in T_amb and T_0) gives the ambient, when the rest lasts at least half of tau (else nullopt).
std::optional<double> ambient_from_first_rest(const Recording& rec, double tau_s) {
    if (!rec.has_surface() || !(tau_s > 0)) return std::nullopt;
    constexpr double kRestA = 0.01;
    std::vector<std::pair<double, double>> pts;  // (exp(-t/tau), T)
    double t_lo = kNaN, t_hi = kNaN, temp_lo = 1e300, temp_hi = -1e300;
    for (std::size_t k = 0; k < rec.size() && std::abs(rec.current_a[k]) < kRestA; ++k) {
        const double temp = rec.surface_c[k];
        if (!std::isfinite(temp) || !std::isfinite(rec.time_s[k])) continue;
        if (!std::isfinite(t_lo)) t_lo = rec.time_s[k];
        t_hi = rec.time_s[k];
        pts.emplace_back(std::exp(-(rec.time_s[k] - t_lo) / tau_s), temp);
        temp_lo = std::min(temp_lo, temp), temp_hi = std::max(temp_hi, temp);
    }
    if (pts.size() < 10 || !(t_hi - t_lo >= 0.5 * tau_s) || !(temp_hi - temp_lo > 0.5)) return std::nullopt;
    double se = 0, see = 0, st = 0, set = 0;
    for (const auto& [e, temp] : pts) se += e, see += e * e, st += temp, set += e * temp;
    const double n = static_cast<double>(pts.size()), det = n * see - se * se;
    if (!(std::abs(det) > 1e-12)) return std::nullopt;
    const double amb = (see * st - se * set) / det;  // the intercept: the temperature the rest decays to
    return std::isfinite(amb) ? std::optional<double>(amb) : std::nullopt;
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

std::string start_outside_ocv_range(const ParameterSet& params, const Recording& rec) {
    if (rec.size() == 0 || params.ocv_v.empty()) return {};
    const double v0 = rec.voltage_v[0], i0 = std::isfinite(rec.current_a[0]) ? rec.current_a[0] : 0.0;
    if (!std::isfinite(v0)) return {};
    const auto [lo, hi] = std::minmax_element(params.ocv_v.begin(), params.ocv_v.end());
    double r_max = 0;
    for (const auto* t : {&params.discharge, &params.charge})
        for (std::size_t k = 0; k < t->r0_ohm.size(); ++k)
            r_max = std::max(r_max, t->r0_ohm[k] + (k < t->r1_ohm.size() ? t->r1_ohm[k] : 0.0) +
                                        (k < t->r2_ohm.size() ? t->r2_ohm[k] : 0.0));
    const double margin_v = 0.1 + std::abs(i0) * r_max;
    if (v0 >= *lo - margin_v && v0 <= *hi + margin_v) return {};
    return rec.source + ": it starts at " + printf_text("%.3f V (%.3f A)", v0, i0) +
           ", outside the parameter set's OCV range " + printf_text("%.3f-%.3f V", *lo, *hi) +
           ": no SOC of that cell explains it, so the simulation starts at SOC " + (v0 < *lo ? "0" : "1") +
           ". Is the parameter set this cell's?";
}

std::string temperature_outside_characterization(const ParameterSet& params, const Recording& rec) {
    if (params.extensions.resistance_temperature) return {};
    const bool surface = rec.has_surface();
    const double cell_c = surface             ? finite_upper_median(rec.surface_c)
                          : rec.has_ambient() ? finite_upper_median(rec.ambient_c)
                                              : kNaN;
    if (!std::isfinite(cell_c) ||
        std::abs(cell_c - params.reference_temperature_c) <= kTemperatureOutsideCharacterizationK)
        return {};
    return rec.source + ": its cell is at " + printf_text("%.1f", cell_c) + " degC (median " +
           (surface ? "surface" : "ambient") + " temperature), " +
           printf_text("%.1f", std::abs(cell_c - params.reference_temperature_c)) + " K " +
           (cell_c < params.reference_temperature_c ? "below" : "above") +
           " the parameter set's characterization (" + printf_text("%.1f", params.reference_temperature_c) +
           " degC), and the set holds no temperature dependence of its resistances (resistance_temperature): the "
           "model runs on the resistances of " + printf_text("%.1f", params.reference_temperature_c) +
           " degC. Fit a characterization made at this temperature, or let `cellbench diagnose` identify the "
           "dependence";
}

std::string soc_outside_range(const ParameterSet& params, const SimulationTrace& trace, const std::string& source) {
    if (trace.soc.empty()) return {};
    const auto [lo, hi] = std::minmax_element(trace.soc.begin(), trace.soc.end());
    const bool below = *lo < -kSocOutsideRangeMargin;
    if (!below && !(*hi > 1.0 + kSocOutsideRangeMargin)) return {};
    const auto at = below ? lo : hi;
    const auto k = static_cast<std::size_t>(at - trace.soc.begin());
    const double t_s = k < trace.time_s.size() ? trace.time_s[k] : kNaN;
    return source + ": the simulated SOC leaves 0-100 % (it reaches " + printf_text("%.1f", 100.0 * *at) +
           " % at t = " + printf_text("%.1f", t_s) + " s): from its start at SOC " +
           printf_text("%.1f", 100.0 * trace.initial_soc) + " % the recording " + (below ? "draws" : "charges") +
           " more than the parameter set's capacity (" + printf_text("%.3f", params.capacity_ah) +
           " Ah) holds. Beyond its tables the model extrapolates, so the error there says little about the model. "
           "Is the parameter set this cell's, its capacity right, and the recording's start SOC?";
}

namespace {
// Unknown history: a cell above half charge at the start was most likely last charged (a test starts after a full
// CCCV charge), one below, last discharged.
double initial_hysteresis_v(const ParameterSet& p, double soc) {
    const auto& h = p.extensions.ocv_hysteresis;
    return h ? (soc > 0.5 ? 1.0 : -1.0) * h->magnitude_v : 0.0;
}
}  // namespace

double soc_from_first_row(const ParameterSet& p, const Recording& rec) {
    if (rec.size() == 0) return 1.0;
    // The state the recording implies: a rested cell's voltage is its OCV plus the hysteresis it holds; under
    // current, remove R0*I.
    const double soc_guess = p.soc_from_ocv(rec.voltage_v[0]);
    const double ohmic = ohmic_drop_v(p.rc_at(soc_guess, -1), p.rc_at(soc_guess, +1), rec.current_a[0]);
    return p.soc_from_ocv(rec.voltage_v[0] - ohmic - initial_hysteresis_v(p, soc_guess));
}

std::optional<FullChargeStart> initial_soc_from_full_charge(const ParameterSet& params, const Recording& rec) {
    if (rec.size() < 2 || !(params.capacity_ah > 0)) return std::nullopt;
    const RecordingSegments seg = segment_recording(rec);
    std::size_t first_activity = rec.size();  // the first pulse or discharge
    for (const auto& ph : seg.phases)
        if (ph.is_pulse() || ph.direction < 0) {
            first_activity = ph.begin;
            break;
        }
    for (const auto& ph : seg.phases) {
        if (ph.begin >= first_activity) break;
        if (ph.direction <= 0 || !ph.cv_tail || ph.kind != PhaseKind::Charge || ph.end > first_activity) continue;
        const std::size_t last = ph.end - 1;
        if (!(rec.voltage_v[last] >= params.ocv_at(1.0)) || last >= seg.charge_ah.size()) continue;
        const double soc = 1.0 - (seg.charge_ah[last] - seg.charge_ah[0]) / params.capacity_ah;
        if (!std::isfinite(soc) || soc < -0.02 || soc > 1.0) return std::nullopt;  // NaN: a current cell missing
        const double first_row_soc = std::clamp(soc_from_first_row(params, rec), 0.0, 1.0);
        if (std::abs(soc - first_row_soc) <= kFullChargeContradictsFirstRowSoc) return std::nullopt;
        return FullChargeStart{std::max(soc, 0.0), rec.time_s[last], first_row_soc};
    }
    return std::nullopt;
}

SimulationTrace simulate(const CellModel& model, const Recording& rec, const SimulationOptions& options) {
    const auto& p = model.params();
    const std::size_t n = rec.size();
    SimulationTrace tr;
    if (n == 0) return tr;

    // Ambient (constant unless measured per row): given, else measured, else where a first rest's cooling settles
    // (ambient_from_first_rest), else the first surface reading (cell at equilibrium), else the reference.
    const double first_surface = rec.has_surface() ? first_finite(rec.surface_c) : kNaN;
    double ambient_const = p.reference_temperature_c;
    if (options.ambient_c)
        ambient_const = *options.ambient_c;
    else if (rec.has_ambient())
        ambient_const = first_finite(rec.ambient_c);
    else if (const auto a = ambient_from_first_rest(rec, p.thermal.r_th_k_per_w * p.thermal.c_th_j_per_k))
        ambient_const = *a;
    else if (std::isfinite(first_surface))
        ambient_const = first_surface;
    auto ambient_at = [&](std::size_t k) {
        if (!options.ambient_c && rec.has_ambient() && std::isfinite(rec.ambient_c[k])) return rec.ambient_c[k];
        return ambient_const;
    };

    CellState s;
    s.temperature_c = options.initial_temperature_c.value_or(std::isfinite(first_surface) ? first_surface
                                                                                          : ambient_at(0));
    s.soc = std::clamp((options.initial_soc ? *options.initial_soc : soc_from_first_row(p, rec)) + options.initial_soc_offset,
                       0.0, 1.0);
    s.hysteresis_v = initial_hysteresis_v(p, s.soc);
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
    // The current over each interval as the Coulomb count has it (coulomb.hpp): across a step the old current until
    // a cycler's row at the step's start (each row's voltage reads its own current's R0 drop), within a step the
    // straight line between its two rows. A long interval is followed in held sub-intervals: where that line moves by
    // a current step (a CV taper logged once a minute), at least kRampSubsteps, as the fast pair follows the current
    // and the slow one and the SOC its mean; and wherever the SOC moves by more than kSubstepSoc, enough that the
    // tables are read along the way (rows 40 s apart at 1C: 2.4 mV off the same model at 10 ms).
    constexpr int kRampSubsteps = 8, kMaxSubsteps = 64;
    constexpr double kSubstepSoc = 0.002;
    const double substeps_per_a_s = model.capacity_ah() > 0 ? 1.0 / (3600.0 * model.capacity_ah() * kSubstepSoc) : 0.0;
    const IntervalCurrents intervals = interval_currents(rec);
    const double* interval_current = intervals.mean_a.data();
    const char* step_row = intervals.step.data();
    for (std::size_t k = 0; k < n; ++k) {
        const double dt = k == 0 ? 0.0 : time[k] - time[k - 1];
        const double amb = ambient && std::isfinite(ambient[k]) ? ambient[k] : ambient_const;
        int substeps = 1;
        bool ramp = false;
        if (k > 0 && dt > 0) {
            ramp = !step_row[k] && is_current_step(current[k - 1], current[k]);
            const double moves = std::abs(interval_current[k]) * dt * substeps_per_a_s;
            if (moves > 1.0) substeps = static_cast<int>(std::min<double>(std::ceil(moves), kMaxSubsteps));
            if (ramp) substeps = std::max(substeps, kRampSubsteps);
        }
        CellOutputs o;
        if (substeps == 1) {
            o = stepper.step(s, interval_current[k], amb, dt, current[k]);
        } else {
            const double a = ramp ? current[k - 1] : interval_current[k], b = ramp ? current[k] : interval_current[k];
            double irreversible_w = 0, reversible_w = 0;  // the interval's mean heat, as one step reports it
            for (int j = 0; j < substeps; ++j) {
                o = stepper.step(s, a + (b - a) * (j + 0.5) / substeps, amb, dt / substeps, current[k]);
                irreversible_w += o.heat_irreversible_w / substeps, reversible_w += o.heat_reversible_w / substeps;
            }
            o.heat_irreversible_w = irreversible_w, o.heat_reversible_w = reversible_w;
        }
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

std::optional<FittedStart> fit_initial_soc_under_load(const CellModel& model, const Recording& rec,
                                                      const SimulationOptions& options) {
    if (options.initial_soc || rec.size() < 3) return std::nullopt;
    const double i0 = rec.current_a[0];
    if (!std::isfinite(i0) || !(std::abs(i0) > std::max(0.05, model.capacity_ah() / 100.0))) return std::nullopt;
    const double t0 = rec.time_s.front(), duration_s = rec.time_s.back() - t0;
    const double window_s = std::clamp(0.1 * duration_s, 120.0, 900.0);
    std::size_t n = 1;
    while (n < rec.size() && rec.time_s[n] <= t0 + window_s) ++n;
    const Recording stretch = rec.slice(0, n);
    FittedStart out;
    out.window_s = rec.time_s[n - 1] - t0;
    out.guess_soc = simulate(model, rec.slice(0, 2), options).initial_soc;
    auto rms_at = [&](double soc) {
        SimulationOptions o = options;
        o.initial_soc = soc;
        const auto m = compare(model.params(), stretch, simulate(model, stretch, o));
        return m.voltage_v.rms && std::isfinite(*m.voltage_v.rms) ? *m.voltage_v.rms : 1e300;
    };
    const double lo = std::max(0.0, out.guess_soc - 0.25), hi = std::min(1.0, out.guess_soc + 0.25);
    double best = out.guess_soc, best_rms = rms_at(best);
    out.guess_rms_v = best_rms;
    for (double s = lo; s <= hi + 1e-12; s += 0.01)
        if (const double r = rms_at(s); r < best_rms) best = s, best_rms = r;
    // Golden section within a grid step either side, to 1e-5 of SOC.
    const double a = std::max(lo, best - 0.01), b = std::min(hi, best + 0.01);
    const double mid = golden_section(rms_at, a, b, golden_section_steps(b - a, 1e-5)), mid_rms = rms_at(mid);
    out.soc = mid_rms < best_rms ? mid : best;
    out.rms_v = std::min(mid_rms, best_rms);
    // The first row's SOC stands unless the stretch contradicts it: the model at least twice as close from another,
    // and off by more than a cycler's voltage accuracy (2 mV) from the first row's.
    constexpr double kAccuracyV = 0.002;
    if (!(out.rms_v <= 0.5 * out.guess_rms_v && out.guess_rms_v > kAccuracyV)) return std::nullopt;
    return out;
}

SimulationMetrics compare(const ParameterSet& params, const Recording& rec, const SimulationTrace& tr,
                          const std::vector<bool>* mask) {
    SimulationMetrics m;
    const std::size_t n = std::min(rec.size(), tr.time_s.size());
    m.samples = 0;
    const auto w = time_weights(rec.time_s);
    // Rows where the recording has no value are left out; a row where it has one and the model none (a model
    // that diverged: an overflow, a parameter no cell has) makes the error infinite, never "not measured" nor
    // the RMS of the rows that stayed finite.
    auto stats = [&](const std::vector<double>& simulated, const std::vector<double>& measured, double scale) {
        ErrorStats e;
        if (measured.empty()) return e;
        double sum_w = 0, sum_e2 = 0, max_abs = 0;
        bool diverged = false;
        for (std::size_t k = 0; k < n; ++k) {
            if (mask && !(*mask)[k]) continue;
            const double y = measured[k] * scale;
            if (!std::isfinite(y)) continue;
            const double err = simulated[k] - y;
            if (!std::isfinite(err)) {
                diverged = true;
                continue;
            }
            sum_w += w[k];
            sum_e2 += w[k] * err * err;
            max_abs = std::max(max_abs, std::abs(err));
        }
        if (diverged) {
            e.rms = e.max_abs = std::numeric_limits<double>::infinity();
        } else if (sum_w > 0) {
            e.rms = std::sqrt(sum_e2 / sum_w);
            e.max_abs = max_abs;
        }
        return e;
    };
    for (std::size_t k = 0; k < n; ++k)
        if (!mask || (*mask)[k]) ++m.samples;
    m.voltage_v = stats(tr.voltage_v, rec.voltage_v, 1.0);
    if (rec.has_surface()) m.temperature_c = stats(tr.temperature_c, rec.surface_c, 1.0);
    if (rec.has_heat_flux()) m.heat_flux_w = stats(tr.heat_flow_out_w, rec.heat_flux_w_per_m2, params.thermal.area_m2);
    return m;
}

ErrorBands error_bands(const ParameterSet& params, const Recording& rec, const SimulationTrace& tr) {
    ErrorBands out;
    const std::size_t n = std::min({rec.size(), tr.time_s.size(), tr.voltage_v.size(), tr.soc.size()});
    const auto w = time_weights(rec.time_s);
    double total_w = 0.0;
    for (std::size_t k = 0; k < n; ++k)
        if (std::isfinite(tr.voltage_v[k] - rec.voltage_v[k])) total_w += w[k];
    if (!(total_w > 0.0)) return out;
    auto band = [&](std::string name, auto&& in_band) -> std::optional<ErrorBand> {
        double sw = 0, se = 0, se2 = 0;
        for (std::size_t k = 0; k < n; ++k) {
            const double e = tr.voltage_v[k] - rec.voltage_v[k];
            if (!std::isfinite(e) || !in_band(k)) continue;
            sw += w[k], se += w[k] * e, se2 += w[k] * e * e;
        }
        if (!(sw > 0.0)) return std::nullopt;
        return ErrorBand{std::move(name), sw / total_w, std::sqrt(se2 / sw), se / sw};
    };
    for (int b = 0; b < 10; ++b) {
        const double lo = 0.1 * b, hi = 0.1 * (b + 1);
        auto e = band("SOC " + std::to_string(10 * b) + "-" + std::to_string(10 * (b + 1)) + " %", [&](std::size_t k) {
            const double s = tr.soc[k];
            return s >= lo && (s < hi || (b == 9 && s <= 1.0 + 1e-9));
        });
        if (e) out.by_soc.push_back(*e);
    }
    const double cap = params.capacity_ah > 0 ? params.capacity_ah : 1.0;
    auto c_rate = [&](std::size_t k) { return std::isfinite(rec.current_a[k]) ? rec.current_a[k] / cap : 0.0; };
    if (auto e = band("rest", [&](std::size_t k) { return !(std::abs(rec.current_a[k]) >= 0.05); })) out.by_current.push_back(*e);
    struct Range { const char* name; double lo, hi; int sign; };
    static constexpr Range kRanges[] = {{"discharge 0-1C", 0, 1, -1}, {"discharge 1-2C", 1, 2, -1},
                                        {"discharge 2-4C", 2, 4, -1}, {"discharge above 4C", 4, 1e9, -1},
                                        {"charge 0-1C", 0, 1, +1},    {"charge 1-2C", 1, 2, +1},
                                        {"charge above 2C", 2, 1e9, +1}};
    for (const auto& r : kRanges) {
        auto e = band(r.name, [&](std::size_t k) {
            if (!(std::abs(rec.current_a[k]) >= 0.05) || r.sign * rec.current_a[k] <= 0) return false;
            const double c = std::abs(c_rate(k));
            return c >= r.lo && c < r.hi;
        });
        if (e) out.by_current.push_back(*e);
    }
    return out;
}

}  // namespace cellbench::estimator
