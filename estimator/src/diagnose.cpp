#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/logger_timing.hpp"
#include "cellbench/estimator/voltage_spikes.hpp"
#include "printf_text.hpp"
#include "solve.hpp"

#include <algorithm>
#include <atomic>
#include <mutex>
#include <thread>
#include <cmath>
#include <map>
#include <numeric>

#include <ceres/ceres.h>

namespace cellbench::estimator {

namespace {

// ------------------------------------------------------------------------------------------------ catalogue

struct ParamSpec {
    const char* name;
    double lo, hi;
    bool log;  // searched in log space
    // The bounds mark the largest size this correction plausibly has: a fit on them means the candidate is
    // compensating something else, and it is flagged "implausible" (ranked after every plausible finding).
    bool bound_is_limit = false;
};

struct EffectSpec {
    std::string id;
    std::vector<ParamSpec> params;
    std::vector<std::vector<double>> starts;  // natural units
    void (*apply)(ParameterSet&, const std::vector<double>&);
    const char* kind = "physics_missing";     // or "parameters_wrong": the base set re-identified in part
    // The parameter set already holds it (then it is not proposed as missing); none for a re-identification of the
    // base set, which is always proposed.
    bool (*present)(const ParameterSet&) = nullptr;
    // The recording's initial SOC moved by this much (a state of the recording, not of the parameter set).
    double (*start_soc_offset)(const std::vector<double>&) = nullptr;
    // A state of the diagnosed recording (its start, its chamber's drift), not of the cell or the bench: it does not
    // carry over to another recording (DiagnoseOptions::confirm).
    bool recording_state = false;
    // A recording state held in the parameter set: how it leaves it (carried_over).
    void (*remove)(ParameterSet&) = nullptr;
};

// The band corrections' shape (ocv_band, resistance_band): 1 at SOC `centre`, falling linearly to 0 at
// `half_width` either side, 0 beyond.
double triangle(double soc, double centre, double half_width) {
    return std::max(0.0, 1.0 - std::abs(soc - centre) / half_width);
}

const std::vector<EffectSpec>& specs() {
    static const std::vector<EffectSpec> s = {
        {"entropic_heat",
         {{"ehc_v_per_k", -1e-3, 1e-3, false, true}, {"ehc_slope_v_per_k", -2e-3, 2e-3, false}},
         {{0.0, 0.0}, {2e-4, 0.0}, {-2e-4, 0.0}},
         [](ParameterSet& p, const std::vector<double>& x) { p.extensions.entropic_heat = EntropicHeatExt{x[0], x[1]}; },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.entropic_heat.has_value(); }},
        {"thermal_second_order",
         // The characterization fitted one lump to a cell that is not one: its C_th and R_th absorbed part of the
         // second node, so they are re-identified together with it (c_th_scale, r_th_scale).
         {{"core_fraction", 0.05, 0.95, false}, {"r_core_surface_k_per_w", 0.05, 20.0, true},
          {"c_th_scale", 0.5, 2.0, true}, {"r_th_scale", 0.5, 2.0, true}},
         {{0.7, 1.0, 1.0, 1.0}, {0.5, 0.3, 1.0, 1.0}, {0.85, 3.0, 1.0, 1.0}},
         [](ParameterSet& p, const std::vector<double>& x) {
             p.extensions.thermal_second_order = ThermalSecondOrderExt{x[0], x[1]};
             p.thermal.c_th_j_per_k *= x[2];
             p.thermal.r_th_k_per_w *= x[3];
         },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.thermal_second_order.has_value(); }},
        {"resistance_temperature",
         {{"activation_energy_j_per_mol", -2e4, 1.2e5, false}},
         {{3e4}, {6e4}},
         [](ParameterSet& p, const std::vector<double>& x) {
             p.extensions.resistance_temperature = ResistanceTemperatureExt{x[0]};
         },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.resistance_temperature.has_value(); }},
        {"resistance_current",
         {{"exchange_current_a", 0.3, 300.0, true}},
         {{2.0}, {10.0}, {50.0}},
         [](ParameterSet& p, const std::vector<double>& x) {
             // Tables are identified with 1C pulses (thesis Table 2.12): the factor is 1 at 1C.
             p.extensions.resistance_current = ResistanceCurrentExt{x[0], p.capacity_ah};
         },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.resistance_current.has_value(); }},
        {"ocv_hysteresis",
         // The characterization measured its OCV on one branch (rests after discharge steps, or after charge
         // steps), which the parameter set holds as if it were the centre: the hysteresis is fitted together with
         // where the centre lies relative to the table (branch_offset_v; about +magnitude for a discharge branch).
         // A branch change that needs more than a third of the capacity to settle (rate below 3 per capacity) is
         // a drift along the drive, which an OCV or capacity error explains as well, not a hysteresis: implausible.
         {{"magnitude_v", 0.0, 0.08, false, true}, {"rate_per_capacity", 3.0, 300.0, true, true}, {"branch_offset_v", -0.08, 0.08, false, true}},
         {{0.01, 20.0, 0.0}, {0.01, 20.0, 0.01}, {0.02, 100.0, 0.02}},
         [](ParameterSet& p, const std::vector<double>& x) {
             p.extensions.ocv_hysteresis = OcvHysteresisExt{x[0], x[1]};
             for (auto& v : p.ocv_v) v += x[2];
         },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.ocv_hysteresis.has_value(); }},
        {"extra_rc",
         // A characterization with two RC pairs puts part of a slower process into its second pair (a larger R2
         // and a longer tau2 than the cell's): that pair is re-identified together with the new one
         // (the absorbed process only makes them larger, hence the scales' upper bound near 1).
         {{"r_ohm", 1e-5, 0.05, true, true}, {"tau_s", 60.0, 5000.0, true}, {"r2_scale", 0.2, 1.2, true},
          {"tau2_scale", 0.2, 1.2, true}},
         {{2e-3, 800.0, 1.0, 1.0}, {5e-3, 1500.0, 0.7, 0.7}, {2e-3, 3000.0, 0.5, 0.5}},
         [](ParameterSet& p, const std::vector<double>& x) {
             p.extensions.extra_rc = ExtraRcExt{x[0], x[1]};
             for (RcTable* t : {&p.discharge, &p.charge})
                 for (std::size_t k = 0; k < t->r2_ohm.size() && k < t->c2_f.size(); ++k) {
                     t->r2_ohm[k] *= x[2];
                     t->c2_f[k] *= x[3] / x[2];  // tau2 = R2*C2 scales by tau2_scale
                 }
         },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.extra_rc.has_value(); }},
        {"capacity_error",
         {{"capacity_scale", 0.6, 1.4, false, true}},
         {{0.95}, {1.05}},
         [](ParameterSet& p, const std::vector<double>& x) { p.extensions.capacity_error = CapacityErrorExt{x[0]}; },
         "parameters_wrong",
         [](const ParameterSet& p) { return p.extensions.capacity_error.has_value(); }},
        {"thermal_parameters",
         // wide: a characterization without a long cooling can miss C_th by an order of magnitude
         {{"c_th_scale", 0.02, 200.0, true, true}, {"r_th_scale", 0.1, 10.0, true, true}},
         {{1.0, 1.0}, {0.3, 1.0}, {3.0, 1.0}, {20.0, 1.0}},
         [](ParameterSet& p, const std::vector<double>& x) {
             // the lumped thermal parameters re-identified on this recording
             p.thermal.c_th_j_per_k *= x[0];
             p.thermal.r_th_k_per_w *= x[1];
         },
         "parameters_wrong"},
        {"ocv_band",
         {{"offset_v", -0.1, 0.1, false, true}, {"center_soc", 0.0, 1.0, false}, {"half_width_soc", 0.1, 0.35, false}},
         {{-0.01, 0.0, 0.12}, {0.01, 0.0, 0.12}, {-0.01, 0.2, 0.15}, {0.01, 0.2, 0.15}, {-0.01, 0.95, 0.12}, {0.01, 0.95, 0.12}},
         [](ParameterSet& p, const std::vector<double>& x) {
             // the OCV table re-identified in one SOC band: a triangular correction of peak x0 at x1, half width x2
             for (std::size_t k = 0; k < p.ocv_v.size() && k < p.soc.size(); ++k)
                 p.ocv_v[k] += x[0] * triangle(p.soc[k], x[1], x[2]);
         },
         "parameters_wrong"},
        {"resistance_band",
         // The resistance tables re-identified in one SOC band: R0, R1, R2 scaled by a triangular factor of peak x0
         // at x1, half width x2, the time constants kept (C1, C2 by its inverse). Where a characterization fits a
         // SOC range poorly (towards empty, where the resistances rise steeply between two pulse levels) its
         // tables there are the least trustworthy; a band twice or half as resistive is compensating something else.
         {{"scale", 0.5, 2.0, true, true}, {"center_soc", 0.0, 1.0, false}, {"half_width_soc", 0.1, 0.35, false}},
         {{1.2, 0.05, 0.12}, {0.85, 0.05, 0.12}, {1.2, 0.5, 0.25}, {0.85, 0.5, 0.25}, {1.2, 0.95, 0.12}, {0.85, 0.95, 0.12}},
         [](ParameterSet& p, const std::vector<double>& x) {
             for (RcTable* t : {&p.discharge, &p.charge})
                 for (std::size_t k = 0; k < p.soc.size() && k < t->r0_ohm.size(); ++k) {
                     const double f = 1.0 + (x[0] - 1.0) * triangle(p.soc[k], x[1], x[2]);
                     t->r0_ohm[k] *= f, t->r1_ohm[k] *= f, t->r2_ohm[k] *= f, t->c1_f[k] /= f, t->c2_f[k] /= f;
                 }
         },
         "parameters_wrong"},
        {"initial_soc",
         // The recording did not start at the SOC its first voltage implies: the cell sat on another hysteresis
         // branch than the table's, or had not rested. Everything after the start then runs at the wrong SOC,
         // which a capacity or OCV correction would otherwise absorb.
         {{"soc_offset", -0.15, 0.15, false, true}},
         {{0.0}, {-0.02}, {0.02}},
         [](ParameterSet&, const std::vector<double>&) {},
         "parameters_wrong",
         nullptr,
         [](const std::vector<double>& x) { return x[0]; },
         true},
        {"ocv_offset",
         // a plain offset: a slope along SOC is what a capacity error looks like on a drive that discharges
         // steadily (the two cannot be told apart there), and a local error is ocv_band's
         {{"offset_v", -0.06, 0.06, false, true}},
         {{0.0}, {0.005}, {-0.005}},
         [](ParameterSet& p, const std::vector<double>& x) {
             for (std::size_t k = 0; k < p.ocv_v.size() && k < p.soc.size(); ++k) p.ocv_v[k] += x[0];
         },
         "parameters_wrong"},
        {"series_resistance_offset",
         {{"r_ohm", -5e-3, 0.03, false, true}},
         {{1e-3}, {-1e-3}},
         [](ParameterSet& p, const std::vector<double>& x) {
             p.extensions.series_resistance_offset = SeriesResistanceOffsetExt{x[0]};
         },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.series_resistance_offset.has_value(); }},
        {"heat_flux_sensor_gain",
         {{"gain", 0.4, 2.5, true, true}},
         {{0.9}, {1.1}},
         [](ParameterSet& p, const std::vector<double>& x) { p.extensions.heat_flux_sensor_gain = HeatFluxSensorGainExt{x[0]}; },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.heat_flux_sensor_gain.has_value(); }},
        {"ambient_drift",
         {{"offset_c", -5.0, 5.0, false, true}, {"rate_c_per_h", -10.0, 10.0, false, true}},
         {{0.0, 0.0}, {0.5, 1.0}, {-0.5, -1.0}},
         [](ParameterSet& p, const std::vector<double>& x) { p.extensions.ambient_drift = AmbientDriftExt{x[0], x[1]}; },
         "physics_missing",
         [](const ParameterSet& p) { return p.extensions.ambient_drift.has_value(); },
         nullptr,
         true,
         [](ParameterSet& p) { p.extensions.ambient_drift.reset(); }},
    };
    return s;
}

bool already_present(const EffectSpec& spec, const ParameterSet& p) { return spec.present && spec.present(p); }

bool has_entropic_table(const ParameterSet& p) {
    return std::any_of(p.thermal.ehc_v_per_k.begin(), p.thermal.ehc_v_per_k.end(), [](double v) { return v != 0.0; });
}

double to_u(const ParamSpec& s, double x) { return s.log ? std::log(x) : x; }
double from_u(const ParamSpec& s, double u) { return s.log ? std::exp(u) : u; }

// ------------------------------------------------------------------------------------------------ objective

// Divisors of each quantity's mean squared error in an objective.
struct Scale {
    double v, t, q;
};

// The data a search needs: the merged recording, which rows train, the baseline's mean squared errors.
struct Problem {
    const Recording* rec = nullptr;  // merged copy
    double start_soc_offset = 0.0;   // the accepted initial_soc correction (the current base's start)
    double ms_v = kNaN, ms_t = kNaN, ms_q = kNaN;  // baseline mean squared errors (normalisation)
    // The instruments' accuracy (DiagnoseOptions' floors), squared.
    double floor2_v = 0, floor2_t = 0, floor2_q = 0;
    double area_m2 = 0.0;
    // The cell's other recordings (DiagnoseOptions::confirm), merged like rec: a candidate that is a property of
    // the cell or the bench is fitted to them as well, so what they measure constrains it (an OCV branch another
    // drive pins down); the evidence stays the diagnosed recording's held-out blocks. Each quantity of each is
    // scaled by its mean squared error under the parameter set (at least the accuracy's square): every recording's
    // relative improvement counts alike, and one the model misses by far for other reasons (a 4C discharge's 40 mV
    // near empty) does not pull the candidate its own way.
    struct Confirm {
        const Recording* rec = nullptr;
        Scale scale{};
    };
    std::vector<Confirm> confirm;
};

struct Errors {
    std::vector<double> v, t, q;  // per row, NaN where not measured
};

// The recording's initial-SOC correction with candidate x on top of the current base.
double start_offset(const Problem& pb, const EffectSpec& spec, const std::vector<double>& x) {
    return pb.start_soc_offset + (spec.start_soc_offset ? spec.start_soc_offset(x) : 0.0);
}

// The model of p on rec, started start_soc_offset away from the SOC the first voltage implies.
SimulationTrace simulate_from(const ParameterSet& p, const Recording& rec, double start_soc_offset) {
    SimulationOptions so;
    so.initial_soc_offset = start_soc_offset;
    return simulate(CellModel(p), rec, so);
}

// Mean of the squares of the finite values (NaN when there are none).
double mean_square(const std::vector<double>& v) {
    double s = 0;
    std::size_t n = 0;
    for (double x : v)
        if (std::isfinite(x)) s += x * x, ++n;
    return n ? s / static_cast<double>(n) : kNaN;
}

// Variance of the finite values about their mean (NaN when there are none).
double variance_about_mean(const std::vector<double>& v) {
    double s = 0, s2 = 0;
    std::size_t n = 0;
    for (double x : v)
        if (std::isfinite(x)) s += x, s2 += x * x, ++n;
    if (!n) return kNaN;
    const double m = s / static_cast<double>(n);
    return std::max(0.0, s2 / static_cast<double>(n) - m * m);
}

Errors errors_of(const ParameterSet& p, const Recording& rec, double start_soc_offset = 0.0) {
    const auto tr = simulate_from(p, rec, start_soc_offset);
    Errors e;
    const std::size_t n = rec.size();
    e.v.resize(n);
    e.t.assign(n, kNaN);
    e.q.assign(n, kNaN);
    const bool surface = rec.has_surface(), heat_flux = rec.has_heat_flux();
    for (std::size_t k = 0; k < n; ++k) {
        e.v[k] = tr.voltage_v[k] - rec.voltage_v[k];
        if (surface) e.t[k] = tr.temperature_c[k] - rec.surface_c[k];
        if (heat_flux) e.q[k] = tr.heat_flow_out_w[k] - rec.heat_flux_w_per_m2[k] * p.thermal.area_m2;
    }
    return e;
}

// Which quantities an objective sums. The searches use all; the evidence (held-out scores, BIC) only those whose
// error under the current base exceeds the instrument's accuracy (evidence_quantities).
struct Quantities {
    bool v = true, t = true, q = true;
    // Each quantity's mean squared error over the square of its instrument's accuracy (DiagnoseOptions' floors)
    // instead of over the current base's: what the searches minimise (weighted least squares, the accuracy as
    // the weight). Over the base's own error, a quantity the base misses by far counted no more than one it
    // already meets within its accuracy: a hysteresis that removed 4 mV of a 21 mV voltage error lost to the
    // 0.1 degC it added to a temperature error inside its 0.3 degC accuracy.
    bool by_accuracy = false;
};
// What the searches minimise: every quantity, each against its instrument's accuracy.
constexpr Quantities kSearch{true, true, true, true};

// What each quantity's mean squared error is divided by: the current base's mean squared error (the evidence) or
// the instrument's accuracy squared (use.by_accuracy: the searches).
Scale scale_of(const Problem& pb, Quantities use) {
    return use.by_accuracy ? Scale{pb.floor2_v, pb.floor2_t, pb.floor2_q} : Scale{pb.ms_v, pb.ms_t, pb.ms_q};
}

// Sum over the quantities in use of mean squared error / ms, over the masked rows (nullptr: every row).
double scaled_objective(const Errors& e, const std::vector<char>* mask, Scale ms, Quantities use) {
    double sv = 0, st = 0, sq = 0;
    std::size_t nv = 0, nt = 0, nq = 0;
    for (std::size_t k = 0; k < e.v.size(); ++k) {
        if (mask && !(*mask)[k]) continue;
        if (std::isfinite(e.v[k])) sv += e.v[k] * e.v[k], ++nv;
        if (std::isfinite(e.t[k])) st += e.t[k] * e.t[k], ++nt;
        if (std::isfinite(e.q[k])) sq += e.q[k] * e.q[k], ++nq;
    }
    double j = 0;
    if (use.v && nv && ms.v > 0) j += sv / nv / ms.v;
    if (use.t && nt && ms.t > 0) j += st / nt / ms.t;
    if (use.q && nq && ms.q > 0) j += sq / nq / ms.q;
    return j;
}

// Sum over quantities of mean squared error / scale_of(use), over the masked rows.
double objective(const Problem& pb, const Errors& e, const std::vector<char>& mask, Quantities use) {
    return scaled_objective(e, &mask, scale_of(pb, use), use);
}

// The parameter set as it carries over to another recording of the cell: without the diagnosed recording's own
// states (EffectSpec::recording_state: those the parameter set holds leave it; initial_soc never enters it).
ParameterSet carried_over(ParameterSet p) {
    for (const EffectSpec& s : specs())
        if (s.recording_state && s.remove) s.remove(p);
    return p;
}

// Whether the search of spec also fits the confirm recordings (a state of the diagnosed recording does not carry).
bool fits_confirm(const Problem& pb, const EffectSpec& spec) { return !pb.confirm.empty() && !spec.recording_state; }

// The confirm recordings' part of the search objective (each quantity over its scale in Problem::Confirm).
double confirm_objective(const Problem& pb, const ParameterSet& p) {
    const ParameterSet carried = carried_over(p);
    double j = 0;
    for (const auto& c : pb.confirm) j += scaled_objective(errors_of(carried, *c.rec), nullptr, c.scale, kSearch);
    return j;
}

class EffectCost {
public:
    EffectCost(const Problem& pb, const ParameterSet& base, const EffectSpec& spec, const std::vector<char>& mask)
        : pb_(pb), base_(base), spec_(spec), mask_(mask) {
        for (std::size_t k = 0; k < mask.size(); ++k)
            if (mask[k]) rows_.push_back(k);
        nv_ = nt_ = nq_ = 0;
        for (std::size_t k : rows_) {
            nv_ += 1;
            nt_ += pb.rec->has_surface() && std::isfinite(pb.rec->surface_c[k]);
            nq_ += pb.rec->has_heat_flux() && std::isfinite(pb.rec->heat_flux_w_per_m2[k]);
        }
    }
    int residuals() const {
        std::size_t n = rows_.size();
        if (fits_confirm(pb_, spec_))
            for (const auto& c : pb_.confirm) n += c.rec->size();
        return static_cast<int>(3 * n);
    }

    bool operator()(double const* const* u, double* r) const {
        ParameterSet p = base_;
        std::vector<double> x(spec_.params.size());
        for (std::size_t j = 0; j < x.size(); ++j) x[j] = from_u(spec_.params[j], u[0][j]);
        spec_.apply(p, x);
        Errors e;
        try {
            e = errors_of(p, *pb_.rec, start_offset(pb_, spec_, x));
        } catch (const std::exception&) {
            return false;
        }
        // the weights of objective(..., kSearch)
        auto put = [](const Errors& err, const std::vector<std::size_t>* rows, std::size_t n, std::size_t nt,
                      std::size_t nq, Scale ms, double* out) {
            const double wv = n && ms.v > 0 ? 1.0 / std::sqrt(n * ms.v) : 0.0;
            const double wt = nt && ms.t > 0 ? 1.0 / std::sqrt(nt * ms.t) : 0.0;
            const double wq = nq && ms.q > 0 ? 1.0 / std::sqrt(nq * ms.q) : 0.0;
            for (std::size_t i = 0; i < n; ++i) {
                const std::size_t k = rows ? (*rows)[i] : i;
                out[3 * i] = std::isfinite(err.v[k]) ? wv * err.v[k] : 0.0;
                out[3 * i + 1] = std::isfinite(err.t[k]) ? wt * err.t[k] : 0.0;
                out[3 * i + 2] = std::isfinite(err.q[k]) ? wq * err.q[k] : 0.0;
                if (!std::isfinite(out[3 * i] + out[3 * i + 1] + out[3 * i + 2])) return false;
            }
            return true;
        };
        if (!put(e, &rows_, rows_.size(), nt_, nq_, scale_of(pb_, kSearch), r)) return false;
        if (!fits_confirm(pb_, spec_)) return true;
        r += 3 * rows_.size();
        const ParameterSet carried = carried_over(p);
        for (const auto& c : pb_.confirm) {
            Errors ec;
            try {
                ec = errors_of(carried, *c.rec);
            } catch (const std::exception&) {
                return false;
            }
            const std::size_t n = c.rec->size();
            std::size_t nt = 0, nq = 0;
            for (std::size_t k = 0; k < n; ++k) nt += std::isfinite(ec.t[k]), nq += std::isfinite(ec.q[k]);
            if (!put(ec, nullptr, n, nt, nq, c.scale, r)) return false;
            r += 3 * n;
        }
        return true;
    }

private:
    const Problem& pb_;
    const ParameterSet& base_;
    const EffectSpec& spec_;
    const std::vector<char>& mask_;
    std::vector<std::size_t> rows_;
    std::size_t nv_, nt_, nq_;
};

struct Fit {
    std::vector<double> x;  // natural units
    double j = INFINITY;    // objective on the fitted rows
};

// The objective at x without a search (one simulation).
double objective_at(const Problem& pb, const ParameterSet& base, const EffectSpec& spec, const std::vector<char>& mask,
                    const std::vector<double>& x, Quantities use = kSearch) {
    ParameterSet p = base;
    spec.apply(p, x);
    try {
        return objective(pb, errors_of(p, *pb.rec, start_offset(pb, spec, x)), mask, use) +
               (fits_confirm(pb, spec) && use.by_accuracy ? confirm_objective(pb, p) : 0.0);
    } catch (const std::exception&) {
        return INFINITY;
    }
}

// Searches from the `keep` most promising starts (ranked by their objective: one simulation each instead of a
// search each), keeping the best result.
Fit fit_effect(const Problem& pb, const ParameterSet& base, const EffectSpec& spec, const std::vector<char>& mask,
               std::vector<std::vector<double>> starts, int max_iterations, std::size_t keep = 2) {
    if (starts.size() > keep) {
        std::vector<std::pair<double, std::size_t>> ranked;
        for (std::size_t k = 0; k < starts.size(); ++k) ranked.emplace_back(objective_at(pb, base, spec, mask, starts[k]), k);
        std::stable_sort(ranked.begin(), ranked.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
        std::vector<std::vector<double>> kept;
        for (std::size_t k = 0; k < keep; ++k) kept.push_back(starts[ranked[k].second]);
        starts = std::move(kept);
    }
    Fit best;
    for (const auto& start : starts) {
        std::vector<double> u(spec.params.size());
        for (std::size_t j = 0; j < u.size(); ++j) u[j] = to_u(spec.params[j], start[j]);
        auto* functor = new EffectCost(pb, base, spec, mask);
        auto* cost = new ceres::DynamicNumericDiffCostFunction<EffectCost, ceres::FORWARD>(functor);
        cost->AddParameterBlock(static_cast<int>(u.size()));
        cost->SetNumResiduals(functor->residuals());
        ceres::Problem problem;
        problem.AddResidualBlock(cost, nullptr, u.data());
        for (std::size_t j = 0; j < u.size(); ++j) {
            problem.SetParameterLowerBound(u.data(), static_cast<int>(j), to_u(spec.params[j], spec.params[j].lo));
            problem.SetParameterUpperBound(u.data(), static_cast<int>(j), to_u(spec.params[j], spec.params[j].hi));
        }
        ceres::Solver::Options so;
        so.linear_solver_type = ceres::DENSE_QR;
        so.max_num_iterations = max_iterations;
        so.function_tolerance = 1e-6;
        so.parameter_tolerance = 1e-6;
        so.logging_type = ceres::SILENT;
        ceres::Solver::Summary sum;
        solve_from_finite_start(so, &problem, &sum);
        if (!sum.IsSolutionUsable()) continue;
        Fit f;
        for (std::size_t j = 0; j < u.size(); ++j) f.x.push_back(from_u(spec.params[j], u[j]));
        f.j = objective_at(pb, base, spec, mask, f.x);
        if (f.j < best.j) best = f;
    }
    return best;
}

// ------------------------------------------------------------------------------------------------ metrics

QuantityRms rms_of(const ParameterSet& p, const Recording& rec, SimulationTrace* trace_out = nullptr,
                   double start_soc_offset = 0.0) {
    auto tr = simulate_from(p, rec, start_soc_offset);
    const auto m = compare(p, rec, tr);
    if (trace_out) *trace_out = std::move(tr);
    return {m.voltage_v.rms, m.temperature_c.rms, m.heat_flux_w.rms};
}

nlohmann::json rms_json(const QuantityRms& q) {
    auto n = [](const std::optional<double>& x) -> nlohmann::json { return x ? nlohmann::json(*x) : nlohmann::json(nullptr); };
    return {{"voltage_rms_v", n(q.voltage_v)}, {"temperature_rms_c", n(q.temperature_c)}, {"heat_flux_rms_w", n(q.heat_flux_w)}};
}

// The quantities a confirmation found worse (or better), with their RMS before -> after.
std::string changes_in_words(const Confirmation& c, bool worse) {
    std::string out;
    auto one = [&](const char* name, const char* words, const std::optional<double>& b, const std::optional<double>& a,
                   double scale, const char* fmt, const char* unit) {
        const auto& list = worse ? c.worse : c.better;
        if (!b || !a || std::find(list.begin(), list.end(), name) == list.end()) return;
        out += (out.empty() ? "" : ", ") + std::string(words) + " " + printf_text(fmt, *b * scale) + " -> " +
               printf_text(fmt, *a * scale) + " " + unit;
    };
    one("voltage", "voltage", c.before.voltage_v, c.after.voltage_v, 1e3, "%.2f", "mV");
    one("temperature", "temperature", c.before.temperature_c, c.after.temperature_c, 1.0, "%.3f", "degC");
    one("heat_flux", "heat flux", c.before.heat_flux_w, c.after.heat_flux_w, 1.0, "%.3f", "W");
    return out;
}

std::string pct(double x) {
    char b[32];
    std::snprintf(b, sizeof b, "%.0f %%", 100.0 * x);
    return b;
}

double reduction(const std::optional<double>& before, const std::optional<double>& after) {
    if (!before || !after || !(*before > 0)) return 0.0;
    return 1.0 - (*after * *after) / (*before * *before);
}

// Plain-words account of a finding, with its parameters and what it fixed.
std::string explain(const std::string& id, const std::vector<double>& x, const QuantityRms& before,
                    const QuantityRms& after, double score, const ParameterSet& base) {
    const double dv = reduction(before.voltage_v, after.voltage_v), dt = reduction(before.temperature_c, after.temperature_c),
                 dq = reduction(before.heat_flux_w, after.heat_flux_w);
    std::string what;
    if (id == "entropic_heat")
        what = (has_entropic_table(base) ? "the entropic coefficient table is off (parameters wrong, corrected on this "
                                           "recording): dU/dT "
                                         : "reversible (entropic) heat I*T*dU/dT was missing: dU/dT ") +
               printf_text("%+.3f", x[0] * 1e3) + " mV/K at 50 % SOC (" + printf_text("%+.3f", x[1] * 1e3) + " mV/K per unit SOC)" +
               (has_entropic_table(base) ? " added to the table" : "");
    else if (id == "thermal_second_order")
        what = "the cell is not one lump: a core node holding " + pct(x[0]) + " of the heat capacity behind " +
               printf_text("%.2f", x[1]) + " K/W lags the surface the sensors see (with it, C_th " +
               printf_text("%.1f", x[2] * base.thermal.c_th_j_per_k) + " J/K and R_th " +
               printf_text("%.2f", x[3] * base.thermal.r_th_k_per_w) + " K/W)";
    else if (id == "resistance_temperature") {
        const double f10 = std::exp(x[0] / 8.314462618 *
                                    (1.0 / (base.reference_temperature_c + 283.15) - 1.0 / (base.reference_temperature_c + 273.15)));
        what = "resistances depend on cell temperature: they fall " + pct(1.0 - f10) + " per 10 K (Ea = " +
               printf_text("%.0f", x[0] / 1e3) + " kJ/mol), coupling the heat back into the voltage";
    } else if (id == "resistance_current") {
        const double x4 = 4.0 * base.capacity_ah / (2 * x[0]), x1 = base.capacity_ah / (2 * x[0]);
        what = "polarization is not linear in current (Butler-Volmer): at 4C the RC resistances are " +
               pct(std::asinh(x4) / x4 / (std::asinh(x1) / x1)) + " of their 1C value (I0 = " + printf_text("%.1f", x[0]) + " A)";
    } else if (id == "ocv_hysteresis") {
        what = "the OCV depends on the direction of the last current: +-" + printf_text("%.1f", x[0] * 1e3) +
               " mV, settling over " + printf_text("%.2g %%", 100.0 / x[1]) + " of the capacity";
        if (std::abs(x[2]) > 0.25 * x[0])
            what += "; the parameter set's OCV lies " + printf_text("%.1f", std::abs(x[2]) * 1e3) + " mV " +
                    (x[2] > 0 ? "below" : "above") + " the centre between the branches (measured on the " +
                    (x[2] > 0 ? "discharge" : "charge") + " branch)";
    }
    else if (id == "extra_rc")
        what = "a slow diffusion time constant beyond the two RC pairs: " + printf_text("%.2f", x[0] * 1e3) + " mOhm with tau " +
               printf_text("%.0f", x[1]) + " s (with it, the second pair's R2 x" + printf_text("%.2f", x[2]) + " and tau2 x" +
               printf_text("%.2f", x[3]) + ")";
    else if (id == "thermal_parameters")
        what = "the lumped thermal parameters are off (parameters wrong, re-identified on this recording): C_th " +
               printf_text("%.1f", x[0] * base.thermal.c_th_j_per_k) + " J/K instead of " + printf_text("%.1f", base.thermal.c_th_j_per_k) +
               ", R_th " + printf_text("%.2f", x[1] * base.thermal.r_th_k_per_w) + " K/W instead of " +
               printf_text("%.2f", base.thermal.r_th_k_per_w);
    else if (id == "ocv_band")
        what = "the OCV table is off in one SOC band (parameters wrong, re-identified on this recording): " +
               printf_text("%+.1f", x[0] * 1e3) + " mV at SOC " + pct(x[1]) + ", fading to 0 at SOC " +
               pct(std::max(0.0, x[1] - x[2])) + " and " + pct(std::min(1.0, x[1] + x[2]));
    else if (id == "resistance_band")
        what = "the resistance tables are off in one SOC band (parameters wrong, re-identified on this recording): R0, "
               "R1 and R2 x" + printf_text("%.2f", x[0]) + " at SOC " + pct(x[1]) + ", fading to x1 at SOC " +
               pct(std::max(0.0, x[1] - x[2])) + " and " + pct(std::min(1.0, x[1] + x[2])) + " (time constants kept)";
    else if (id == "initial_soc")
        what = "the recording starts at a SOC " + printf_text("%+.1f", x[0] * 100.0) +
               " % of the capacity from the one its first voltage implies (its history: the cell sat on another "
               "hysteresis branch than the OCV table's, or had not rested; a state of this recording, not written "
               "to the improved parameter set)";
    else if (id == "ocv_offset") {
        what = "the OCV table is off by " + printf_text("%+.1f", x[0] * 1e3) +
               " mV over the whole SOC range (parameters wrong, re-identified on this recording)";
    } else if (id == "capacity_error")
        what = "the usable capacity is " + pct(x[0]) + " of the parameter set's (" + printf_text("%.3f", x[0] * base.capacity_ah) +
               " Ah instead of " + printf_text("%.3f", base.capacity_ah) + " Ah): the SOC drifts";
    else if (id == "series_resistance_offset")
        what = x[0] >= 0 ? "extra series resistance of " + printf_text("%.2f", x[0] * 1e3) +
                               " mOhm (harness, contacts) that was not there in characterization"
                         : "series resistance " + printf_text("%.2f", -x[0] * 1e3) +
                               " mOhm lower than the parameter set's (its R0 is too high for this cell or set-up)";
    else if (id == "heat_flux_sensor_gain")
        what = "the heat flux sensor reads " + pct(x[0]) + " of the heat leaving the cell (sensitivity or coverage)";
    else if (id == "ambient_drift")
        what = "the ambient was not constant: offset " + printf_text("%+.2f", x[0]) + " K and drift " + printf_text("%+.2f", x[1]) + " K/h";
    std::string fixed;
    auto add = [&](const char* name, double r) {
        if (r > 0.02) fixed += (fixed.empty() ? "" : ", ") + std::string(name) + " " + pct(r);
    };
    add("voltage", dv);
    add("temperature", dt);
    add("heat flux", dq);
    return what + ". On blocks of the recording it was not fitted to, it removes " + pct(score) +
           " of the remaining error" + (fixed.empty() ? "" : "; over the whole recording it explains " + fixed +
                                                                  " of the squared error");
}

}  // namespace

const std::vector<std::string>& effect_catalogue() {
    static const std::vector<std::string> ids = [] {
        std::vector<std::string> v;
        for (const auto& s : specs()) v.push_back(s.id);
        return v;
    }();
    return ids;
}

Recording merge_intervals(const Recording& rec, double step_s) {
    Recording out;
    out.source = rec.source;
    if (rec.empty()) return out;
    auto copy_row = [&](std::size_t k, double current) {
        out.time_s.push_back(rec.time_s[k]);
        out.voltage_v.push_back(rec.voltage_v[k]);
        out.current_a.push_back(current);
        auto opt = [&](const std::vector<double>& src, std::vector<double>& dst) {
            if (!src.empty()) dst.push_back(src[k]);
        };
        opt(rec.ambient_c, out.ambient_c);
        opt(rec.surface_c, out.surface_c);
        opt(rec.t1_c, out.t1_c);
        opt(rec.t2_c, out.t2_c);
        opt(rec.heat_flux_w_per_m2, out.heat_flux_w_per_m2);
    };
    copy_row(0, rec.current_a[0]);
    // An interval never spans a change of the set current: a row's voltage is the instantaneous one at its end,
    // so an interval averaging two currents would pair that voltage with a current the cell never carried
    // (on a 0.1 s drive profile merged to 1 s: 21 mV RMS of error the model cannot remove, against 6.6 mV
    // on the rows themselves). A change is a step between rows larger than 0.5 % of the largest current
    // (far above a cycler's current noise).
    double i_max = 0;
    for (double i : rec.current_a) i_max = std::max(i_max, std::abs(i));
    const double step_a = std::max(0.005 * i_max, 1e-3);
    double charge = 0, span = 0;
    for (std::size_t k = 1; k < rec.size(); ++k) {
        if (span > 0 && std::abs(rec.current_a[k] - rec.current_a[k - 1]) > step_a) {
            copy_row(k - 1, charge / span);
            charge = span = 0;
        }
        const double dt = rec.time_s[k] - rec.time_s[k - 1];
        charge += rec.current_a[k] * dt;
        span += dt;
        if (span + 1e-9 < step_s && k + 1 < rec.size()) continue;
        copy_row(k, charge / span);
        charge = span = 0;
    }
    return out;
}

std::vector<ConditionError> locate_errors(const ParameterSet& params, const Recording& rec, const SimulationTrace& tr) {
    const std::size_t n = std::min(rec.size(), tr.time_s.size());
    const auto w = time_weights(rec.time_s);
    const double c1 = params.capacity_ah;  // 1C in A
    // Per-row condition labels.
    std::vector<std::string> dir(n), crate(n), socb(n), rise(n), since(n), thr(n);
    double t_last_step = rec.time_s.empty() ? 0.0 : rec.time_s[0], ah = 0;
    double t0 = kNaN;  // the first surface reading (the first rows may have empty DAQ cells)
    if (rec.has_surface())
        for (double v : rec.surface_c)
            if (std::isfinite(v)) {
                t0 = v;
                break;
            }
    const double total_ah = [&] {
        double a = 0;
        for (std::size_t k = 1; k < n; ++k) a += std::abs(rec.current_a[k]) * (rec.time_s[k] - rec.time_s[k - 1]) / 3600.0;
        return a;
    }();
    for (std::size_t k = 0; k < n; ++k) {
        const double i = rec.current_a[k];
        if (k > 0) {
            if (std::abs(i - rec.current_a[k - 1]) > std::max(0.1, 0.05 * c1)) t_last_step = rec.time_s[k - 1];
            ah += std::abs(i) * (rec.time_s[k] - rec.time_s[k - 1]) / 3600.0;
        }
        const double c = std::abs(i) / c1;
        dir[k] = std::abs(i) < 0.02 * c1 ? "rest" : i < 0 ? "discharge" : "charge";
        crate[k] = dir[k] == "rest" ? "rest" : c < 0.5 ? "below C/2" : c < 1.5 ? "C/2-1.5C" : c < 2.5 ? "1.5C-2.5C" : c < 3.5 ? "2.5C-3.5C" : "above 3.5C";
        const double s = tr.soc[k];
        socb[k] = s < 0.1 ? "SOC 0-10 %" : s < 0.3 ? "SOC 10-30 %" : s < 0.7 ? "SOC 30-70 %" : s < 0.9 ? "SOC 70-90 %" : "SOC 90-100 %";
        if (std::isfinite(t0) && std::isfinite(rec.surface_c[k])) {
            const double r = rec.surface_c[k] - t0;
            rise[k] = r < 1 ? "temperature rise below 1 K" : r < 3 ? "temperature rise 1-3 K" : r < 6 ? "temperature rise 3-6 K" : "temperature rise above 6 K";
        } else {
            rise[k] = "temperature not measured";
        }
        const double age = rec.time_s[k] - t_last_step;
        since[k] = age < 1 ? "within 1 s of a current step" : age < 10 ? "1-10 s after a step" : age < 100 ? "10-100 s after a step" : "over 100 s after a step";
        const double f = total_ah > 0 ? ah / total_ah : 0;
        thr[k] = f < 0.25 ? "first quarter of the throughput" : f < 0.5 ? "second quarter of the throughput" : f < 0.75 ? "third quarter of the throughput" : "last quarter of the throughput";
    }
    double total_w = 0, total_e2 = 0;
    for (std::size_t k = 0; k < n; ++k) {
        const double e = tr.voltage_v[k] - rec.voltage_v[k];
        total_w += w[k];
        total_e2 += w[k] * e * e;
    }
    std::vector<ConditionError> out;
    auto group = [&](const std::string& dimension, auto label_of) {
        struct Acc { double w = 0, e2 = 0, e = 0, tw = 0, te2 = 0, te = 0; };
        std::map<std::string, Acc> acc;
        for (std::size_t k = 0; k < n; ++k) {
            auto& a = acc[label_of(k)];
            const double e = tr.voltage_v[k] - rec.voltage_v[k];
            a.w += w[k];
            a.e2 += w[k] * e * e;
            a.e += w[k] * e;
            if (rec.has_surface() && std::isfinite(rec.surface_c[k])) {
                const double et = tr.temperature_c[k] - rec.surface_c[k];
                a.tw += w[k];
                a.te2 += w[k] * et * et;
                a.te += w[k] * et;
            }
        }
        for (const auto& [label, a] : acc) {
            if (a.w <= 0) continue;
            ConditionError c;
            c.dimension = dimension;
            c.condition = label;
            c.time_share = total_w > 0 ? a.w / total_w : 0;
            c.share_of_voltage_error = total_e2 > 0 ? a.e2 / total_e2 : 0;
            c.voltage_rms_v = std::sqrt(a.e2 / a.w);
            c.voltage_bias_v = a.e / a.w;
            if (a.tw > 0) {
                c.temperature_rms_c = std::sqrt(a.te2 / a.tw);
                c.temperature_bias_c = a.te / a.tw;
            }
            out.push_back(c);
        }
    };
    group("direction", [&](std::size_t k) { return dir[k]; });
    group("c_rate", [&](std::size_t k) { return crate[k]; });
    group("soc", [&](std::size_t k) { return socb[k]; });
    group("temperature_rise", [&](std::size_t k) { return rise[k]; });
    group("since_step", [&](std::size_t k) { return since[k]; });
    group("throughput", [&](std::size_t k) { return thr[k]; });
    group("combined", [&](std::size_t k) {
        return dir[k] == "rest" ? "rest, " + socb[k] : dir[k] + " " + crate[k] + ", " + socb[k];
    });
    return out;
}

void confirmation_verdict(Confirmation& c, double voltage_floor_v, double temperature_floor_c, double heat_flux_floor_w) {
    constexpr double kRelative = 0.05;     // of the RMS before
    constexpr double kFloorShare = 0.1;    // of the instrument's accuracy
    c.better.clear();
    c.worse.clear();
    auto judge = [&](const char* name, const std::optional<double>& b, const std::optional<double>& a, double floor) {
        if (!b || !a || !std::isfinite(*b) || !std::isfinite(*a)) return;
        const double margin = std::max(kRelative * *b, kFloorShare * floor);
        if (*a > floor && *a > *b + margin) c.worse.emplace_back(name);
        if (*b > floor && *a < *b - margin) c.better.emplace_back(name);
    };
    judge("voltage", c.before.voltage_v, c.after.voltage_v, voltage_floor_v);
    judge("temperature", c.before.temperature_c, c.after.temperature_c, temperature_floor_c);
    judge("heat_flux", c.before.heat_flux_w, c.after.heat_flux_w, heat_flux_floor_w);
    c.verdict = !c.worse.empty() ? "contradicts" : (!c.better.empty() ? "confirms" : "neutral");
}

std::size_t accepted_in_round(const std::vector<Finding>& round) {
    // A finding whose correction sits on its plausible limit ranks after every plausible one.
    auto stronger = [&](std::size_t a, std::size_t b) {
        const auto &fa = round[a], &fb = round[b];
        if (fa.implausible != fb.implausible) return !fa.implausible;
        return fa.score > fb.score;
    };
    std::size_t best = round.size();
    for (std::size_t k = 0; k < round.size(); ++k)
        if (round[k].significant && (best == round.size() || stronger(k, best))) best = k;
    // Occam: when re-identifying part of the base parameter set explains nearly as much (>= 80 % of the best
    // score) as adding physics, the one BIC prefers goes first and the other is tested again on top of it.
    // BIC charges each parameter, so the base correction (fewer parameters) wins unless the physics fits the
    // whole recording better by more than its extra parameters cost: a wrong C_th otherwise passes for a
    // second thermal node (which re-identifies C_th and R_th as well: four parameters against two).
    if (best < round.size() && round[best].kind == "physics_missing") {
        std::size_t alt = round.size();
        for (std::size_t k = 0; k < round.size(); ++k)
            if (round[k].significant && round[k].kind == "parameters_wrong" && !round[k].implausible &&
                round[k].score >= 0.8 * round[best].score &&
                (alt == round.size() || round[k].score > round[alt].score))
                alt = k;
        if (alt < round.size() && round[alt].delta_bic <= round[best].delta_bic) best = alt;
    }
    return best;
}

namespace {
Diagnosis diagnose_as_given(const ParameterSet& params, const Recording& rec_full, const DiagnoseOptions& options);
}  // namespace

// The recordings as the fit reads them (correct_logging_artifacts: stale step rows, voltage spikes), else each
// such row would pass for a miss of the model. A recording with nothing to correct is used as given.
Diagnosis diagnose(const ParameterSet& params, const Recording& rec, const DiagnoseOptions& options) {
    for (const Recording* r : options.confirm)
        if (r)
            if (auto reversed = reversed_current_text(*r); !reversed.empty()) throw InputError(reversed);
    if (auto reversed = reversed_current_text(rec); !reversed.empty()) throw InputError(reversed);
    std::vector<std::string> notes;
    auto corrected = [&](const Recording& r) -> std::optional<Recording> {
        Recording c = r;
        auto found = correct_logging_artifacts(c);
        if (found.empty()) return std::nullopt;
        for (auto& note : found) notes.push_back(std::move(note));
        return c;
    };
    const auto main = corrected(rec);
    std::vector<std::optional<Recording>> confirm;
    confirm.reserve(options.confirm.size());  // opts.confirm points into it
    DiagnoseOptions opts = options;
    for (std::size_t k = 0; k < options.confirm.size(); ++k) {
        confirm.push_back(options.confirm[k] ? corrected(*options.confirm[k]) : std::nullopt);
        if (confirm.back()) opts.confirm[k] = &*confirm.back();
    }
    if (auto note = start_outside_ocv_range(params, rec); !note.empty()) notes.push_back(std::move(note));
    if (auto note = temperature_outside_characterization(params, rec); !note.empty()) notes.push_back(std::move(note));
    if (auto lag = voltage_lag_text(rec); !lag.empty())
        notes.push_back(lag + ": at every current step part of the error is the logger's timing, not the cell's");
    // The same heat flux accuracy per m^2 is more W over a larger cell: on a 60 Ah pouch (0.039 m^2) a clean drive's
    // heat flux error of 0.10 W, inside the sensor's accuracy there, read as evidence against the 0.05 W of a
    // 21700, and an extra_rc was declared significant on the independent plant's control (seed 3 scaled).
    if (opts.scale_heat_flux_floor_with_area && params.thermal.area_m2 > kHeatFluxFloorAreaM2)
        opts.heat_flux_floor_w *= params.thermal.area_m2 / kHeatFluxFloorAreaM2;
    Diagnosis d = diagnose_as_given(params, main ? *main : rec, opts);
    if (auto note = soc_outside_range(params, d.baseline_trace, rec.source); !note.empty()) notes.push_back(std::move(note));
    d.notes = std::move(notes);
    return d;
}

namespace {
Diagnosis diagnose_as_given(const ParameterSet& params, const Recording& rec_full, const DiagnoseOptions& options) {
    // Progress: the baseline up to 5 %, the candidate rounds (at most max_accepted) to 95 %, then the final
    // simulation of the improved model. A search that stops early jumps to 95 %.
    ProgressReporter progress(options.progress);
    if (rec_full.size() < 2) throw InputError(rec_full.source + ": recording has fewer than two rows");
    if (!(options.voltage_floor_v > 0 && options.temperature_floor_c > 0 && options.heat_flux_floor_w > 0))
        throw InputError("diagnose: the instrument accuracies (voltage, temperature and heat flux floors) must be positive");
    const double duration = rec_full.time_s.back() - rec_full.time_s.front();
    const std::size_t folds = std::max<std::size_t>(options.folds, 2);
    if (duration < 60.0 * static_cast<double>(folds))
        throw InputError(rec_full.source + ": recording too short to cross-validate (" + printf_text("%.1f", duration) +
                         " s; needs at least " + std::to_string(60 * folds) + " s)");
    for (const Recording* r : options.confirm)
        if (!r || r->size() < 2) throw InputError("diagnose: a recording to confirm the findings on has fewer than two rows");
    if (options.cancel && options.cancel->load()) throw DiagnoseCancelled();
    progress(0.0, "baseline simulation");
    Diagnosis d;
    for (const Recording* r : options.confirm) d.confirm_recordings.push_back(r->source);
    d.baseline = rms_of(params, rec_full, &d.baseline_trace);
    // A model that does not follow the recording at all (its simulation overflows) is no baseline: every error
    // would read as explained, and the summary as adequate.
    for (const auto& [name, rms] : {std::pair<const char*, const std::optional<double>&>{"voltage", d.baseline.voltage_v},
                                    {"temperature", d.baseline.temperature_c},
                                    {"heat flux", d.baseline.heat_flux_w}})
        if (rms && !std::isfinite(*rms))
            throw InputError(rec_full.source + ": the model's " + name +
                             " is not a finite number on this recording (the simulation diverges): the parameter set "
                             "holds values no cell has, or the recording values the model cannot follow");
    d.breakdown = locate_errors(params, rec_full, d.baseline_trace);
    {
        std::vector<ConditionError> combined;
        for (const auto& c : d.breakdown)
            if (c.dimension == "combined") combined.push_back(c);
        std::sort(combined.begin(), combined.end(),
                  [](const auto& a, const auto& b) { return a.share_of_voltage_error > b.share_of_voltage_error; });
        for (std::size_t k = 0; k < std::min<std::size_t>(5, combined.size()); ++k) d.where.push_back(combined[k]);
    }

    const Recording rec = merge_intervals(rec_full, options.search_step_s);
    Problem pb;
    pb.rec = &rec;
    // The confirm recordings merged to at most as many intervals as the diagnosed one (a C/20 discharge of a day
    // logged every second would otherwise cost the searches twenty times the drive's simulation).
    std::vector<Recording> confirm_merged;
    for (const Recording* c : options.confirm) {
        const double span_s = c->time_s.back() - c->time_s.front();
        confirm_merged.push_back(
            merge_intervals(*c, std::max(options.search_step_s, span_s / static_cast<double>(std::max<std::size_t>(rec.size(), 1)))));
    }

    pb.area_m2 = params.thermal.area_m2;
    {
        const Errors e = errors_of(params, rec);
        auto floor2 = [](double x) { return x * x; };
        pb.floor2_v = floor2(options.voltage_floor_v);
        pb.floor2_t = floor2(options.temperature_floor_c);
        pb.floor2_q = floor2(options.heat_flux_floor_w);
        pb.ms_v = std::max(mean_square(e.v), pb.floor2_v);
        pb.ms_t = std::max(mean_square(e.t), pb.floor2_t);
        pb.ms_q = std::max(mean_square(e.q), pb.floor2_q);
    }
    for (const auto& c : confirm_merged) {
        const Errors e = errors_of(carried_over(params), c);
        pb.confirm.push_back({&c, {std::max(mean_square(e.v), pb.floor2_v), std::max(mean_square(e.t), pb.floor2_t),
                                   std::max(mean_square(e.q), pb.floor2_q)}});
    }
    const std::size_t n = rec.size();
    std::vector<char> all(n, 1);
    std::vector<std::vector<char>> train(folds, std::vector<char>(n, 1)), test(folds, std::vector<char>(n, 0));
    // Interleaved blocks: block j belongs to fold j mod K. A drifting recording (a Random Walk through SOC)
    // then puts every SOC, current and temperature range in every fold, instead of one range per fold.
    const double block_s = options.holdout_block_s > 0
                               ? options.holdout_block_s
                               : std::max(60.0, duration / (static_cast<double>(folds) * 8.0));
    for (std::size_t k = 0; k < n; ++k) {
        const auto j = static_cast<std::size_t>((rec.time_s[k] - rec.time_s.front()) / block_s);
        const std::size_t b = j % folds;
        train[b][k] = 0;
        test[b][k] = 1;
    }
    d.holdout = {{"scheme", "interleaved_blocks"},
                 {"folds", folds},
                 {"block_s", block_s},
                 {"rule", "block j = floor((t - t0) / block_s) is held out in fold j mod folds; each fold spans the "
                          "whole recording (its SOC, current and temperature range)"}};
    const double n_eff = std::max(duration / 10.0, 10.0);
    // The recording's own noise (robust scatter in its rests), measured once: the temperature evidence below and
    // the unexplained residual at the end compare with it.
    d.noise = estimate_noise(rec_full, params.capacity_ah);
    if (d.noise.sigma.heat_flux_w) *d.noise.sigma.heat_flux_w *= params.thermal.area_m2;
    // A thermocouple's accuracy class (the thesis bench: +-1.8 to 2.3 degC, 1.0 degC of it the cold junction) is an
    // offset, the same at every row of a recording; the changes it reads are known to its noise. So when no quantity
    // is missed by more than its accuracy, a temperature error whose part beyond its mean exceeds
    // options.temperature_shape_noise_factor x the noise still counts as evidence: a shape no offset of the sensor
    // makes. While another quantity is evidence the temperature inside its accuracy stays out, so that it cannot
    // outweigh what the base misses by far (a hysteresis' heat moving it by a tenth of a degree; session 31).
    const double temperature_shape_c =
        d.noise.sigma.temperature_c ? options.temperature_shape_noise_factor * *d.noise.sigma.temperature_c : kNaN;
    auto evidence_of = [&](const Errors& e) {
        Quantities q{mean_square(e.v) > pb.floor2_v, mean_square(e.t) > pb.floor2_t, mean_square(e.q) > pb.floor2_q};
        if (!q.v && !q.t && !q.q)
            q.t = variance_about_mean(e.t) > temperature_shape_c * temperature_shape_c;  // false where NaN
        return q;
    };

    std::vector<std::string> candidates;
    for (const auto& id : options.effects.empty() ? effect_catalogue() : options.effects) {
        const auto it = std::find_if(specs().begin(), specs().end(), [&](const auto& s) { return s.id == id; });
        if (it == specs().end()) throw InputError("diagnose: unknown effect id \"" + id + "\"");
        if (already_present(*it, params))
            d.skipped.push_back(id);  // the parameter set holds it: not proposed again as missing
        else
            candidates.push_back(id);
    }

    ParameterSet current = params;
    QuantityRms current_rms = d.baseline;
    std::map<std::string, Finding> last_round;
    std::map<std::string, std::vector<double>> previous_x;  // each candidate's fit in the last round
    std::size_t round = 0;
    const double round_share = 0.90 / static_cast<double>(std::max<std::size_t>(options.max_accepted, 1));
    while (round < options.max_accepted) {
        ++round;
        const double round_start = 0.05 + round_share * static_cast<double>(round - 1);
        progress(round_start, "round " + std::to_string(round) + " candidates");
        const Errors base_e = errors_of(current, rec, pb.start_soc_offset);
        // Evidence comes from the quantities the current base misses by more than the instrument's accuracy
        // (DiagnoseOptions' floors): a change that only moves an error already inside the accuracy class (a
        // 1.5 mV voltage residual against a cycler's 5 mV) is not evidence of physics, however large its share
        // of that small error; the temperature also by its shape when nothing else is (evidence_of). With none
        // left, no candidate can be significant.
        // (mean_square is NaN for a quantity the recording does not measure: never above its floor)
        const Quantities evidence = evidence_of(base_e);
        if (round == 1) {
            auto names = nlohmann::json::array();
            if (evidence.v && rec.size()) names.push_back("voltage");
            if (evidence.t && rec.has_surface()) names.push_back("temperature");
            if (evidence.q && rec.has_heat_flux()) names.push_back("heat_flux");
            d.holdout["evidence_quantities"] = std::move(names);
            d.holdout["floors"] = {{"voltage_v", options.voltage_floor_v},
                                   {"temperature_c", options.temperature_floor_c},
                                   {"heat_flux_w", options.heat_flux_floor_w},
                                   {"temperature_shape_c", std::isfinite(temperature_shape_c)
                                                               ? nlohmann::json(temperature_shape_c)
                                                               : nlohmann::json(nullptr)}};
        }
        const double j_base_all = objective(pb, base_e, all, evidence);
        std::vector<double> j_base_test(folds);
        for (std::size_t f = 0; f < folds; ++f) j_base_test[f] = objective(pb, base_e, test[f], evidence);

        // The confirm recordings under the current base: each candidate is compared with it.
        std::vector<QuantityRms> confirm_base;
        for (const Recording* r : options.confirm) confirm_base.push_back(rms_of(carried_over(current), *r));

        std::vector<std::string> todo;
        for (const auto& id : candidates)
            if (std::find(d.accepted.begin(), d.accepted.end(), id) == d.accepted.end()) todo.push_back(id);
        std::vector<Finding> round_findings(todo.size());
        std::vector<std::vector<double>> round_x(todo.size());
        std::atomic<std::size_t> next{0}, done{0};
        // Candidates are independent: one per worker thread.
        auto worker = [&] {
            for (std::size_t c; (c = next.fetch_add(1)) < todo.size();) {
                if (options.cancel && options.cancel->load()) break;
                const auto& id = todo[c];
                const auto& spec = *std::find_if(specs().begin(), specs().end(), [&](const auto& s) { return s.id == id; });
                Finding& fd = round_findings[c];
                fd.effect = id;
                // A parameter set with its own dU/dT table (the characterization measured it) gets that table
                // corrected by entropic_heat: parameters wrong, not physics missing.
                fd.kind = spec.id == "entropic_heat" && has_entropic_table(current) ? "parameters_wrong" : spec.kind;
                fd.parameters_count = spec.params.size();
                // From the catalogue's starts and, after the first round, from where this candidate ended last
                // round (the base moved by one accepted effect).
                auto starts = spec.starts;
                if (const auto prev = previous_x.find(id); prev != previous_x.end()) starts.insert(starts.begin(), prev->second);
                const Fit full = fit_effect(pb, current, spec, all, std::move(starts), 25);
                if (!std::isfinite(full.j)) {
                    fd.explanation = "the fit of this effect did not converge";
                } else {
                    // A harness or contact adds resistance; a negative offset says the parameter set's R0 is too
                    // high for this cell: the base re-identified, not something the bench added.
                    if (spec.id == "series_resistance_offset" && full.x[0] < 0.0) fd.kind = "parameters_wrong";
                    double sum_red = 0;
                    // The fold fits (each leaves one interleaved block set out) give the parameters' uncertainty:
                    // their jackknife spread, which holds with correlated residuals where the Jacobian's would not.
                    // Each starts from the full fit, a small step from its own optimum (a quarter of the rows left
                    // out): three iterations reach it.
                    std::vector<std::vector<double>> fold_x;
                    for (std::size_t f = 0; f < folds; ++f) {
                        const Fit ff = fit_effect(pb, current, spec, train[f], {full.x}, 3);
                        if (std::isfinite(ff.j)) fold_x.push_back(ff.x);
                        const double jt = objective_at(pb, current, spec, test[f], std::isfinite(ff.j) ? ff.x : full.x, evidence);
                        const double red = j_base_test[f] > 0 ? 1.0 - jt / j_base_test[f] : 0.0;
                        sum_red += red;
                        fd.folds_improved += red > 0.0;
                    }
                    fd.score = sum_red / static_cast<double>(folds);
                    const double j_full_evidence = objective_at(pb, current, spec, all, full.x, evidence);
                    fd.delta_bic = (j_base_all > 0 ? n_eff * std::log(std::max(j_full_evidence, 1e-300) / j_base_all) : 0.0) +
                                   static_cast<double>(spec.params.size()) * std::log(n_eff);
                    fd.significant = fd.score >= options.min_cv_improvement && fd.folds_improved + 1 >= folds &&
                                     fd.delta_bic < options.bic_threshold;
                    // A capacity correction within 2 sd of the capacity the characterization measured (its
                    // recordings' disagreement on the charge scale, ParameterSet::capacity_ah_sd) does not show
                    // that capacity wrong, however well it fits this recording: the recording is then as
                    // consistent with the base as the characterization's own data are with each other.
                    const bool within_capacity_sd = spec.id == "capacity_error" && std::isfinite(params.capacity_ah_sd) &&
                                                    std::abs(full.x[0] - 1.0) * params.capacity_ah < 2.0 * params.capacity_ah_sd;
                    if (within_capacity_sd) fd.significant = false;
                    std::string at_limit;  // the parameters on their plausible limit, named in the explanation
                    for (std::size_t j = 0; j < spec.params.size(); ++j) {
                        const auto& ps = spec.params[j];
                        fd.parameters[ps.name] = full.x[j];
                        // A value on its search bound is not an estimate (the optimum may lie beyond): flagged.
                        const double u = to_u(ps, full.x[j]), ulo = to_u(ps, ps.lo), uhi = to_u(ps, ps.hi);
                        if (std::abs(u - ulo) <= 1e-4 * (uhi - ulo) || std::abs(uhi - u) <= 1e-4 * (uhi - ulo)) {
                            auto flags = nlohmann::json::array({"at_bound"});
                            if (ps.bound_is_limit) {
                                flags.push_back("implausible");
                                fd.implausible = true;
                                at_limit += (at_limit.empty() ? "" : " and ") + std::string(ps.name);
                            }
                            fd.parameters[std::string(ps.name) + "_flags"] = std::move(flags);
                        }
                        if (fold_x.size() < 2) continue;  // no spread to judge: the value carries no "_sd"
                        double mean = 0, ss = 0;
                        for (const auto& x : fold_x) mean += x[j];
                        mean /= static_cast<double>(fold_x.size());
                        for (const auto& x : fold_x) ss += (x[j] - mean) * (x[j] - mean);
                        const double k = static_cast<double>(fold_x.size());
                        fd.parameters[std::string(spec.params[j].name) + "_sd"] = std::sqrt((k - 1.0) / k * ss);
                    }
                    ParameterSet p = current;
                    spec.apply(p, full.x);
                    fd.improved = rms_of(p, rec_full, nullptr, start_offset(pb, spec, full.x));
                    fd.explanation = explain(id, full.x, current_rms, fd.improved, fd.score, params);
                    if (!at_limit.empty())
                        fd.explanation += "; implausible: " + at_limit + " on the limit of what this correction "
                                          "plausibly is (the search's bound), so it compensates something else rather "
                                          "than measuring this effect";
                    if (within_capacity_sd)
                        fd.explanation += "; within twice the characterization's capacity uncertainty (+-" +
                                          printf_text("%.2f", 100.0 * params.capacity_ah_sd / params.capacity_ah) +
                                          " % at 1 sd): not evidence that the capacity is wrong";
                    // An OCV correction the characterization's own rests rule out: where the parameter set states
                    // its OCV uncertainty (ocv_v_sd), a correction beyond 5 sd there and beyond the instrument's
                    // accuracy contradicts what the characterization measured. If the cell has not changed
                    // since, the recording's voltage differs there for another reason (its history: a hysteresis;
                    // or its SOC), so the correction is flagged implausible and ranked after plausible findings.
                    if ((id == "ocv_band" || id == "ocv_offset") && params.ocv_v_sd.size() == params.soc.size() &&
                        params.soc.size() >= 2) {
                        double sd = 0;
                        if (id == "ocv_band") {
                            sd = interp_hold(params.soc, params.ocv_v_sd, full.x[1]);
                        } else {  // a plain offset: against the table's typical uncertainty
                            std::vector<double> v;
                            for (double x : params.ocv_v_sd)
                                if (std::isfinite(x)) v.push_back(x);
                            sd = kNaN;
                            if (!v.empty()) {
                                std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
                                sd = v[v.size() / 2];
                            }
                        }
                        const double allowed = std::max(5.0 * sd, options.voltage_floor_v);
                        if (std::isfinite(sd) && std::abs(full.x[0]) > allowed) {
                            fd.implausible = true;
                            fd.parameters["offset_v_flags"] = {"contradicts_characterization", "implausible"};
                            fd.explanation += "; but the characterization measured this OCV to +-" + printf_text("%.1f", sd * 1e3) +
                                              " mV (1 sd): a correction beyond " + printf_text("%.1f", allowed * 1e3) +
                                              " mV contradicts it unless the cell changed since (otherwise its history, "
                                              "e.g. a hysteresis, or its SOC differs)";
                        }
                    }
                    // The recording itself, on what its evidence leaves out: the objective weighs only the
                    // quantities the base misses by more than the instrument's accuracy, so a candidate may trade
                    // one the base has right for them. Pushing it beyond the accuracy is no explanation.
                    {
                        Confirmation self;
                        self.before = current_rms;
                        self.after = fd.improved;
                        confirmation_verdict(self, options.voltage_floor_v, options.temperature_floor_c,
                                             options.heat_flux_floor_w);
                        auto in_evidence = [&](const std::string& q) {
                            return q == "voltage" ? evidence.v : q == "temperature" ? evidence.t : evidence.q;
                        };
                        for (const auto& q : self.worse)
                            if (!in_evidence(q)) fd.worsens.push_back(q);
                        if (!fd.worsens.empty()) {
                            self.worse = fd.worsens;
                            fd.explanation += std::string(fd.significant ? "; it passes the significance test, but"
                                                                         : "; and") +
                                              " it makes what the model had within the instrument's accuracy worse "
                                              "beyond it on this recording (" + changes_in_words(self, true) +
                                              "): not an explanation";
                            fd.significant = false;
                        }
                    }
                    // Another recording of the cell that the correction makes worse contradicts it.
                    if (!spec.recording_state && !options.confirm.empty()) {
                        const ParameterSet carried = carried_over(p);
                        std::string against;
                        for (std::size_t r = 0; r < options.confirm.size(); ++r) {
                            Confirmation cf;
                            cf.recording = options.confirm[r]->source;
                            cf.before = confirm_base[r];
                            cf.after = rms_of(carried, *options.confirm[r]);
                            confirmation_verdict(cf, options.voltage_floor_v, options.temperature_floor_c,
                                                 options.heat_flux_floor_w);
                            if (cf.verdict == "contradicts") {
                                fd.contradicted = true;
                                against += (against.empty() ? "" : "; ") + cf.recording + ": " + changes_in_words(cf, true);
                            }
                            fd.confirmation.push_back(std::move(cf));
                        }
                        if (fd.contradicted) {
                            fd.withdrawn = fd.significant;
                            fd.explanation += std::string(fd.withdrawn ? "; it passes the significance test on this recording, but"
                                                                       : "; and") +
                                              " another recording of the cell contradicts it (" + against + ")";
                            fd.significant = false;
                        }
                    }
                    round_x[c] = full.x;
                }
                const std::size_t k = ++done;
                progress(round_start + round_share * static_cast<double>(k) / static_cast<double>(todo.size()),
                         "round " + std::to_string(round) + " candidates " + std::to_string(k) + "/" +
                             std::to_string(todo.size()));
            }
        };
        {
            const std::size_t n_threads = std::clamp<std::size_t>(
                options.threads ? options.threads : std::thread::hardware_concurrency(), 1, todo.size());
            std::vector<std::thread> pool;
            for (std::size_t t = 1; t < n_threads; ++t) pool.emplace_back(worker);
            worker();
            for (auto& t : pool) t.join();
        }
        if (options.cancel && options.cancel->load()) throw DiagnoseCancelled();
        // Accept the strongest significant one (accepted_in_round) and look again on top of it.
        const std::size_t best = accepted_in_round(round_findings);
        for (auto& f : round_findings) last_round[f.effect] = f;
        for (std::size_t k = 0; k < todo.size(); ++k)
            if (!round_x[k].empty()) previous_x[todo[k]] = round_x[k];
        if (best == round_findings.size()) break;
        const auto& spec =
            *std::find_if(specs().begin(), specs().end(), [&](const auto& s) { return s.id == round_findings[best].effect; });
        spec.apply(current, round_x[best]);
        pb.start_soc_offset = start_offset(pb, spec, round_x[best]);
        current_rms = round_findings[best].improved;
        d.accepted.push_back(round_findings[best].effect);
        d.findings.push_back(round_findings[best]);
        last_round.erase(round_findings[best].effect);
    }
    // Every candidate once: the accepted ones as fitted when accepted, the others from the last round (on top
    // of everything accepted), ordered by score.
    for (auto& [id, f] : last_round) {
        f.significant = false;
        d.findings.push_back(f);
    }
    std::stable_sort(d.findings.begin(), d.findings.end(), [](const auto& a, const auto& b) { return a.score > b.score; });
    progress(0.95, "simulating the improved model");
    d.improved_params = current;
    d.improved = rms_of(current, rec_full, &d.improved_trace, pb.start_soc_offset);
    // No false reassurance: compare what remains with the recording's own noise (d.noise, measured above).
    {
        Unexplained u;
        u.rms = d.improved;
        u.noise = d.noise.sigma;
        auto above = [&](const char* name, const std::optional<double>& r, const std::optional<double>& sg) {
            if (r && sg && *r > options.noise_factor * *sg) u.above_noise.push_back(name);
        };
        above("voltage", u.rms.voltage_v, u.noise.voltage_v);
        above("temperature", u.rms.temperature_c, u.noise.temperature_c);
        above("heat_flux", u.rms.heat_flux_w, u.noise.heat_flux_w);
        if (!u.above_noise.empty()) {
            auto located = locate_errors(current, rec_full, d.improved_trace);
            std::vector<ConditionError> combined;
            for (const auto& c : located)
                if (c.dimension == "combined") combined.push_back(c);
            std::sort(combined.begin(), combined.end(),
                      [](const auto& a, const auto& b) { return a.share_of_voltage_error > b.share_of_voltage_error; });
            for (std::size_t k = 0; k < std::min<std::size_t>(3, combined.size()); ++k) u.where.push_back(combined[k]);
            u.voltage = sparse_residual_model(rec_full, d.improved_trace, current, false);
            if (rec_full.has_surface()) u.temperature = sparse_residual_model(rec_full, d.improved_trace, current, true);
            // Each quantity above the noise with its own numbers (the summary once named temperature and heat flux
            // and then quoted only the voltage's, which was below the bar).
            std::string q, numbers;
            auto quote = [&](const std::string& name, const std::optional<double>& r, const std::optional<double>& sg,
                             double scale, const char* unit, const char* fmt_r, const char* fmt_n) {
                if (std::find(u.above_noise.begin(), u.above_noise.end(), name) == u.above_noise.end()) return;
                const std::string words = name == "heat_flux" ? "heat flux" : name;
                q += (q.empty() ? "" : ", ") + words;
                numbers += (numbers.empty() ? "" : "; ") + words + " " + printf_text(fmt_r, *r * scale) + " " + unit +
                           " RMS against " + printf_text(fmt_n, *sg * scale) + " " + unit + " noise";
            };
            quote("voltage", u.rms.voltage_v, u.noise.voltage_v, 1e3, "mV", "%.2f", "%.2g");
            quote("temperature", u.rms.temperature_c, u.noise.temperature_c, 1.0, "degC", "%.3f", "%.2g");
            quote("heat_flux", u.rms.heat_flux_w, u.noise.heat_flux_w, 1.0, "W", "%.4f", "%.2g");
            u.summary = "after the findings the " + q + " error stays above " + printf_text("%.0f", options.noise_factor) +
                        "x the measurement noise estimated from the recording's rests (" + numbers + ")";
            if (!u.where.empty())
                u.summary += "; the voltage error sits most in " + u.where.front().condition + " (" +
                             pct(u.where.front().share_of_voltage_error) + " of it squared, bias " +
                             printf_text("%+.1f", u.where.front().voltage_bias_v * 1e3) + " mV)";
            if (!u.voltage.terms.empty() && u.voltage.explained >= 0.2) {
                u.summary += "; a sparse model of the voltage residual explains " + pct(u.voltage.explained) + " with";
                for (const auto& t : u.voltage.terms) u.summary += " " + t.term;
                u.summary += " (" + u.voltage.terms.front().meaning + ")";
            }
            d.unexplained = std::move(u);
        }
    }
    if (d.accepted.empty()) {
        d.summary = "No candidate passes the significance test (held-out error reduction >= " +
                    pct(options.min_cv_improvement) + " on average and in " + std::to_string(folds - 1) + " of " +
                    std::to_string(folds) + " interleaved folds, BIC improvement > " +
                    printf_text("%.0f", -options.bic_threshold) + ")";
        if (d.holdout.contains("evidence_quantities") && d.holdout["evidence_quantities"].empty())
            d.summary += "; every error is within its instrument's accuracy (voltage " +
                         printf_text("%.1f", options.voltage_floor_v * 1e3) + " mV, temperature " +
                         printf_text("%.2f", options.temperature_floor_c) + " degC or " +
                         printf_text("%g", options.temperature_shape_noise_factor) + "x its noise about its mean, heat flux " +
                         printf_text("%.3f", options.heat_flux_floor_w) + " W RMS), so no change to the model can be told from it";
        std::string contradicted;
        int n_contradicted = 0;
        for (const auto& f : d.findings)
            if (f.withdrawn) contradicted += (contradicted.empty() ? "" : ", ") + f.effect, ++n_contradicted;
        if (!contradicted.empty())
            d.summary += "; " + contradicted + " would pass it on this recording, but another recording of the cell " +
                         (n_contradicted == 1 ? "contradicts it (see the finding)" : "contradicts them (see the findings)");
        d.summary += d.unexplained ? ". The model is NOT adequate: " + d.unexplained->summary + "."
                                   : " and the residual is at the noise level: the model is adequate for this recording.";
    } else {
        d.summary = "In order of evidence:";
        for (const auto& f : d.findings)
            if (f.significant)
                d.summary += " " + f.effect + (f.kind == "parameters_wrong" ? " [parameters wrong" : " [physics missing") +
                             (f.implausible ? ", implausible]" : "]") + " (" + pct(f.score) + " of the held-out error);";
        if (d.unexplained) d.summary += " Still unexplained: " + d.unexplained->summary + ".";
    }
    progress(1.0, "done");
    return d;
}
}  // namespace

nlohmann::json diagnosis_to_json(const Diagnosis& d) {
    nlohmann::json j;
    j["schema"] = "cellbench.diagnosis/1";
    j["baseline"] = rms_json(d.baseline);
    j["where"] = nlohmann::json::array();
    for (const auto& w : d.where)
        j["where"].push_back({{"condition", w.condition},
                              {"share_of_voltage_error", w.share_of_voltage_error},
                              {"time_share", w.time_share},
                              {"voltage_rms_v", w.voltage_rms_v},
                              {"voltage_bias_v", w.voltage_bias_v}});
    j["findings"] = nlohmann::json::array();
    for (const auto& f : d.findings)
        j["findings"].push_back({{"effect", f.effect},
                                 {"kind", f.kind},
                                 {"significant", f.significant},
                                 {"implausible", f.implausible},
                                 {"score", f.score},
                                 {"folds_improved", f.folds_improved},
                                 {"delta_bic", f.delta_bic},
                                 {"explanation", f.explanation},
                                 {"parameters", f.parameters},
                                 {"improved", rms_json(f.improved)},
                                 {"worsens", f.worsens}});
    if (!d.confirm_recordings.empty()) {
        auto& fj = j["findings"];
        for (std::size_t k = 0; k < d.findings.size() && k < fj.size(); ++k) {
            nlohmann::json c = nlohmann::json::array();
            for (const auto& cf : d.findings[k].confirmation)
                c.push_back({{"recording", cf.recording},
                             {"verdict", cf.verdict},
                             {"before", rms_json(cf.before)},
                             {"after", rms_json(cf.after)},
                             {"better", cf.better},
                             {"worse", cf.worse}});
            fj[k]["confirmation"] = std::move(c);
            fj[k]["contradicted"] = d.findings[k].contradicted;
        }
        j["confirmation"] = {
            {"recordings", d.confirm_recordings},
            {"rule", "each candidate is fitted to the diagnosed recording and these together (each recording's errors "
                     "relative to the parameter set's), then simulated on these with and without its correction; a "
                     "quantity is worse when its RMS rises above the instrument's accuracy by more than 5 % and a tenth of "
                     "that accuracy; a finding any recording makes worse is contradicted and never significant; effects "
                     "that are a state of the diagnosed recording (initial_soc, ambient_drift) are neither fitted to these "
                     "nor checked on them"}};
    }
    j["accepted"] = d.accepted;
    j["skipped_in_baseline"] = d.skipped;
    j["holdout"] = d.holdout.is_null() ? nlohmann::json::object() : d.holdout;
    j["noise"] = {{"voltage_v", d.noise.sigma.voltage_v ? nlohmann::json(*d.noise.sigma.voltage_v) : nlohmann::json(nullptr)},
                  {"temperature_c", d.noise.sigma.temperature_c ? nlohmann::json(*d.noise.sigma.temperature_c) : nlohmann::json(nullptr)},
                  {"heat_flux_w", d.noise.sigma.heat_flux_w ? nlohmann::json(*d.noise.sigma.heat_flux_w) : nlohmann::json(nullptr)},
                  {"rest_pairs", d.noise.rest_pairs},
                  {"method", "robust sample-to-sample scatter of consecutive rest rows (MAD / sqrt 2)"}};
    if (d.unexplained) {
        const auto& u = *d.unexplained;
        auto model = [](const ResidualModel& m) {
            nlohmann::json t = nlohmann::json::array();
            for (const auto& x : m.terms)
                t.push_back({{"term", x.term}, {"meaning", x.meaning}, {"coefficient", x.coefficient}, {"share", x.share}});
            nlohmann::json c = nlohmann::json::object();
            for (const auto& [k, v] : m.correlations) c[k] = v;
            return nlohmann::json{{"quantity", m.quantity}, {"explained", m.explained}, {"terms", t}, {"correlations", c}};
        };
        nlohmann::json w = nlohmann::json::array();
        for (const auto& c : u.where)
            w.push_back({{"condition", c.condition},
                         {"share_of_voltage_error", c.share_of_voltage_error},
                         {"time_share", c.time_share},
                         {"voltage_rms_v", c.voltage_rms_v},
                         {"voltage_bias_v", c.voltage_bias_v}});
        nlohmann::json corr = nlohmann::json::object();
        for (const auto& [k, v] : u.voltage.correlations) corr[k] = v;
        j["unexplained"] = {{"rms", rms_json(u.rms)},
                            {"noise", rms_json(u.noise)},
                            {"above_noise", u.above_noise},
                            {"where", w},
                            {"correlates_with", corr},
                            {"sparse_model", {{"voltage", model(u.voltage)}, {"temperature", model(u.temperature)}}},
                            {"summary", u.summary}};
    } else {
        j["unexplained"] = nullptr;
    }
    j["improved"] = rms_json(d.improved);
    j["summary"] = d.summary;
    if (!d.notes.empty()) j["notes"] = d.notes;
    return j;
}

}  // namespace cellbench::estimator
