#include "cellbench/estimator/generate.hpp"

#include <algorithm>
#include <cmath>
#include <random>

#include "cellbench/estimator/model.hpp"

namespace cellbench::estimator {

namespace {

enum class StepKind { Rest, Cc, Cccv };

struct Step {
    StepKind kind = StepKind::Rest;
    double current_a = 0.0;       // + charge
    double voltage_limit_v = 0.0; // cut-off (CC) or CV level (CCCV)
    double time_limit_s = 0.0;    // 0 = none
    double cutoff_current_a = 0.05;  // CCCV ends when |I| falls below
    double capacity_limit_ah = 0.0;  // 0 = none
    double sample_s = 1.0;
    const char* type = "Rest";
};

class Runner {
public:
    Runner(const ParameterSet& p, const GeneratorOptions& o, std::uint32_t seed, double soc0, double t0_c)
        : model_(p), opt_(o), rng_(seed) {
        state_.soc = soc0;
        state_.temperature_c = t0_c;
        if (const auto& h = p.extensions.ocv_hysteresis)  // same convention as simulate(): above half, charged last
            state_.hysteresis_v = (soc0 > 0.5 ? 1.0 : -1.0) * h->magnitude_v;
        ambient_c_ = t0_c;
        rec_.source = "generated";
        push(0.0, 0.0, "Rest");
    }

    // Runs one step; returns the charge it moved (Ah, signed) and whether it ended on its voltage limit.
    double run(const Step& s, bool* hit_voltage = nullptr) {
        ++step_no_;
        double elapsed = 0, moved_ah = 0;
        bool cv = false;
        if (hit_voltage) *hit_voltage = false;
        while (true) {
            double dt = s.sample_s;
            if (s.time_limit_s > 0) dt = std::min(dt, s.time_limit_s - elapsed);
            if (dt <= 1e-9) break;
            double i = s.kind == StepKind::Rest ? 0.0 : s.current_a;
            if (s.kind == StepKind::Cccv && cv) i = cv_current(s, dt);
            CellState trial = state_;
            auto out = model_.step(trial, i, ambient_c_, dt);
            const bool beyond = s.kind != StepKind::Rest &&
                                ((s.current_a > 0 && out.voltage_v > s.voltage_limit_v) ||
                                 (s.current_a < 0 && out.voltage_v < s.voltage_limit_v));
            if (beyond && s.kind == StepKind::Cc) {
                if (hit_voltage) *hit_voltage = true;
                break;
            }
            if (beyond && s.kind == StepKind::Cccv && !cv) {
                cv = true;
                continue;  // redo this sample at the CV current
            }
            state_ = trial;
            elapsed += dt;
            moved_ah += i * dt / 3600.0;
            push(dt, i, s.type, &out);
            if (s.kind == StepKind::Cccv && cv && std::abs(i) < s.cutoff_current_a) break;
            if (s.capacity_limit_ah > 0 && std::abs(moved_ah) >= s.capacity_limit_ah) break;
            if (s.time_limit_s > 0 && elapsed >= s.time_limit_s - 1e-9) break;
            if (elapsed > 5 * 3600.0) break;  // a step of the generator never runs away
        }
        return moved_ah;
    }

    Recording take() { return std::move(rec_); }
    const CellState& state() const { return state_; }

private:
    // Current that holds the terminal voltage at the CV limit over the next sample (secant on the model).
    double cv_current(const Step& s, double dt) {
        auto v_at = [&](double i) {
            CellState trial = state_;
            return model_.step(trial, i, ambient_c_, dt).voltage_v - s.voltage_limit_v;
        };
        double a = 0.0, b = s.current_a;
        // Bisection: keeps the root between a and b by the sign of the residual at a.
        double fa = v_at(a);
        for (int k = 0; k < 30 && std::abs(b - a) > 1e-6; ++k) {
            const double m = 0.5 * (a + b), fm = v_at(m);
            if ((fm > 0) == (fa > 0)) a = m, fa = fm;
            else b = m;
        }
        return 0.5 * (a + b);
    }

    void push(double dt, double i, const char* type, const CellOutputs* out = nullptr) {
        std::normal_distribution<double> n(0.0, 1.0);
        const double t = rec_.time_s.empty() ? 0.0 : rec_.time_s.back() + dt;
        CellOutputs o;
        if (out) {
            o = *out;
        } else {
            CellState copy = state_;
            o = model_.step(copy, i, ambient_c_, 0.0);
        }
        rec_.time_s.push_back(t);
        rec_.current_a.push_back(i + opt_.current_noise_a * n(rng_));
        rec_.voltage_v.push_back(o.voltage_v + opt_.voltage_noise_v * n(rng_));
        rec_.surface_c.push_back(state_.temperature_c + opt_.temperature_noise_c * n(rng_));
        rec_.heat_flux_w_per_m2.push_back(o.sensor_heat_flow_w / model_.params().thermal.area_m2 +
                                          opt_.heat_flux_noise_w_per_m2 * n(rng_));
        rec_.step_type.push_back(type);
        rec_.step_count.push_back(step_no_);
    }

    CellModel model_;
    GeneratorOptions opt_;
    std::mt19937 rng_;
    CellState state_;
    double ambient_c_ = 30.0;
    double step_no_ = 1;
    Recording rec_;
};

// Thesis Table 2.12 (with the pilot of Table 2.10), 1C = the cell's nominal capacity.
Recording characterization(const ParameterSet& truth, const GeneratorOptions& o, std::uint32_t seed) {
    const double c1 = 4.5;  // 1C of the P45B (nominal 4.5 Ah), as in the thesis programs
    Runner r(truth, o, seed, 0.35, 30.0);
    r.run({StepKind::Rest, 0, 0, 10, 0.05, 0, 1.0, "Rest"});
    r.run({StepKind::Cccv, c1, 4.1, 0, 0.05, 0, 1.0, "CCCV Chg"});
    r.run({StepKind::Rest, 0, 0, 600, 0.05, 0, 1.0, "Rest"});
    const double pilot_ah = -r.run({StepKind::Cc, -c1, 2.9, 0, 0.05, 0, 1.0, "CC DChg"});
    r.run({StepKind::Rest, 0, 0, 3600, 0.05, 0, 1.0, "Rest"});
    r.run({StepKind::Cccv, c1, 4.1, 0, 0.05, 0, 1.0, "CCCV Chg"});
    r.run({StepKind::Rest, 0, 0, 3600, 0.05, 0, 1.0, "Rest"});
    for (int k = 0; k < 10; ++k) {
        r.run({StepKind::Cccv, -c1, 2.9, 30, 0.05, 0, 0.1, "CCCV DChg"});
        r.run({StepKind::Rest, 0, 0, 40, 0.05, 0, 0.1, "Rest"});
        r.run({StepKind::Cccv, c1, 4.1, 10, 0.05, 0, 0.1, "CCCV Chg"});
        r.run({StepKind::Rest, 0, 0, 40, 0.05, 0, 0.1, "Rest"});
        // C12 = 0.1*C4 - C8 + C10: 10 % of the pilot capacity, net of the pulses (Table 2.12).
        const double step_ah = std::max(0.01, 0.1 * pilot_ah - (30.0 - 10.0) * c1 / 3600.0);
        r.run({StepKind::Cc, -c1, 2.9, 0, 0.05, step_ah, 1.0, "CC DChg"});
        r.run({StepKind::Rest, 0, 0, 3600, 0.05, 0, 1.0, "Rest"});
    }
    r.run({StepKind::Cc, -c1, 2.9, 0, 0.05, 0, 1.0, "CC DChg"});
    r.run({StepKind::Rest, 0, 0, 1800, 0.05, 0, 1.0, "Rest"});
    return r.take();
}

// Random walk in the spirit of Table 5.1: discharge 1-4C for 20-60 s, charge 1-3C for 10-20 s, short rests,
// from full until the cut-off is reached twice, then a 1C discharge to the cut-off and a rest.
Recording validation(const ParameterSet& truth, const GeneratorOptions& o, std::uint32_t seed) {
    const double c1 = 4.5;
    Runner r(truth, o, seed, 1.0, 30.0);
    std::mt19937 rng(seed * 7919u + 13u);
    std::uniform_int_distribution<int> dis_c(1, 4), chg_c(1, 3);
    std::uniform_real_distribution<double> dis_t(20, 60), chg_t(10, 20), rest_t(5, 20);
    r.run({StepKind::Rest, 0, 0, 60, 0.05, 0, 0.2, "Rest"});
    int cutoffs = 0;
    for (int k = 0; k < 400 && cutoffs < 2; ++k) {
        bool hit = false;
        r.run({StepKind::Cc, -c1 * dis_c(rng), 2.9, dis_t(rng), 0.05, 0, 0.2, "CC DChg"}, &hit);
        cutoffs += hit;
        r.run({StepKind::Cc, c1 * chg_c(rng), 4.1, chg_t(rng), 0.05, 0, 0.2, "CC Chg"});
        r.run({StepKind::Rest, 0, 0, rest_t(rng), 0.05, 0, 0.2, "Rest"});
    }
    r.run({StepKind::Cc, -c1, 2.9, 0, 0.05, 0, 0.2, "CC DChg"});
    r.run({StepKind::Rest, 0, 0, 600, 0.05, 0, 0.5, "Rest"});
    return r.take();
}

}  // namespace

GeneratedCase generate_case(const ParameterSet& base, const GeneratorOptions& o) {
    std::mt19937 rng(o.seed);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    ParameterSet cell = base;
    cell.extensions = ModelExtensions{};
    cell.thermal.ehc_soc.clear();  // entropic heat is one of the hidden effects: the base cell has none
    cell.thermal.ehc_v_per_k.clear();
    nlohmann::json truth = {{"seed", o.seed}, {"hidden_effect", o.hidden_effect.empty() ? nlohmann::json(nullptr) : nlohmann::json(o.hidden_effect)}};
    if (o.vary_base) {
        const double fr = 1.0 + 0.10 * u(rng), fc = 1.0 + 0.10 * u(rng);
        for (auto* t : {&cell.discharge, &cell.charge}) {
            for (auto& x : t->r0_ohm) x *= fr;
            for (auto* v : {&t->r1_ohm, &t->r2_ohm})
                for (auto& x : *v) x *= fr;
            for (auto* v : {&t->c1_f, &t->c2_f})
                for (auto& x : *v) x *= fc;
        }
        cell.capacity_ah *= 1.0 + 0.03 * u(rng);
        cell.thermal.c_th_j_per_k *= 1.0 + 0.05 * u(rng);
        cell.thermal.r_th_k_per_w *= 1.0 + 0.10 * u(rng);
        truth["base_scale"] = {{"resistance", fr}, {"capacitance", fc}};
    }
    ParameterSet val = cell;
    const double m = o.magnitude;
    auto between = [&](double lo, double hi) { return lo + (hi - lo) * 0.5 * (1.0 + u(rng)); };
    const std::string& e = o.hidden_effect;
    if (e.empty()) {
    } else if (e == "entropic_heat") {
        cell.extensions.entropic_heat = EntropicHeatExt{m * between(2.0e-4, 3.0e-4), 0.0};
    } else if (e == "thermal_second_order") {
        cell.extensions.thermal_second_order = ThermalSecondOrderExt{between(0.65, 0.8), m * between(1.5, 2.5)};
    } else if (e == "resistance_temperature") {
        cell.extensions.resistance_temperature = ResistanceTemperatureExt{m * between(30e3, 45e3)};
    } else if (e == "resistance_current") {
        cell.extensions.resistance_current = ResistanceCurrentExt{between(2.0, 3.5) / m, 4.5};
    } else if (e == "ocv_hysteresis") {
        cell.extensions.ocv_hysteresis = OcvHysteresisExt{m * between(0.015, 0.025), between(20.0, 40.0)};
    } else if (e == "extra_rc") {
        cell.extensions.extra_rc = ExtraRcExt{m * between(4e-3, 7e-3), between(500.0, 1000.0)};
    } else if (e == "capacity_error") {
        val.extensions.capacity_error = CapacityErrorExt{1.0 - m * between(0.06, 0.10)};
    } else if (e == "series_resistance_offset") {
        val.extensions.series_resistance_offset = SeriesResistanceOffsetExt{m * between(2.5e-3, 4e-3)};
    } else if (e == "heat_flux_sensor_gain") {
        val.extensions.heat_flux_sensor_gain = HeatFluxSensorGainExt{1.0 - m * between(0.2, 0.3)};
    } else if (e == "ambient_drift") {
        val.extensions.ambient_drift = AmbientDriftExt{0.0, m * between(2.0, 3.0)};
    } else {
        throw InputError("generate: unknown effect id \"" + e + "\"");
    }
    // Effects of the cell itself are in both recordings.
    if (!e.empty() && val.extensions.empty()) val.extensions = cell.extensions;
    truth["characterization_extensions"] = cell.extensions.to_json();
    truth["validation_extensions"] = val.extensions.to_json();

    GeneratedCase out;
    out.truth_characterization = cell;
    out.truth_validation = val;
    out.characterization = characterization(cell, o, o.seed * 2u + 1u);
    out.characterization.source = "generated characterization (seed " + std::to_string(o.seed) + ")";
    out.validation = validation(val, o, o.seed * 2u + 2u);
    out.validation.source = "generated validation (seed " + std::to_string(o.seed) + ")";
    out.truth = truth;
    return out;
}

}  // namespace cellbench::estimator
