// Acceptance of `diagnose` on physics it was not written with (issue 13): the independent validation plant
// (tests/plant: its own equations; each effect in another mathematical form than the catalogue's) generates a
// thesis-layout characterization and a ~1 h randomized drive profile with hidden bench/ageing effects (they act
// on the drive only, so the characterization and its fit are the control's). The characterization is fitted with
// the DEFAULT global fit, the drive is diagnosed; what diagnose names first is compared with the truth it never
// sees. `make prove` runs the same on every effect, physics ones included (each needs its own fit), and prints the
// full confusion matrix.
//
// Seeds: CELLBENCH_DIAGNOSE_SEEDS (default 2, ~3 min on 2 busy cores).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <string>
#include <vector>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/plant/plant.hpp"
#include "validation/plant_recording.hpp"

namespace {

using cellbench::Recording;
namespace est = cellbench::estimator;
namespace plant = cellbench::plant;

using cellbench::test::to_recording;

int seeds() {
    if (const char* e = std::getenv("CELLBENCH_DIAGNOSE_SEEDS")) return std::max(1, std::atoi(e));
    return 2;
}

// The quantity each hidden effect perturbs most.
std::optional<double> affected(const est::QuantityRms& q, const std::string& effect) {
    if (effect == "heat_flux_sensor_gain") return q.heat_flux_w;
    if (effect == "ambient_drift" || effect == "thermal_second_order") return q.temperature_c;
    return q.voltage_v;
}

struct Case {
    std::string hidden;
    std::vector<std::string> significant, refit;
    double cut = 0;
    bool unexplained = false;
};

// No false reassurance: with no `unexplained`, every residual is within noise_factor x its noise.
void expect_no_false_reassurance(const est::Diagnosis& d, const std::string& label) {
    if (d.unexplained) return;
    auto within = [&](const std::optional<double>& r, const std::optional<double>& n, const char* q) {
        if (r && n) {
            EXPECT_LE(*r, 2.0 * *n) << label << ": " << q << " above twice the noise but unexplained is null";
        }
    };
    within(d.improved.voltage_v, d.noise.sigma.voltage_v, "voltage");
    within(d.improved.temperature_c, d.noise.sigma.temperature_c, "temperature");
    within(d.improved.heat_flux_w, d.noise.sigma.heat_flux_w, "heat flux");
}

}  // namespace

TEST(DiagnoseOnIndependentPlant, NamesHiddenBenchEffectsAndLeavesControlsAlone) {
    const std::vector<std::vector<plant::Effect>> hidden = {
        {plant::Effect::none},
        {plant::Effect::series_resistance_offset},
        {plant::Effect::heat_flux_sensor_gain},
        {plant::Effect::capacity_error},
        {plant::Effect::ambient_drift},
        {plant::Effect::series_resistance_offset, plant::Effect::ambient_drift},
    };
    std::vector<Case> cases;
    std::printf("seed | hidden | significant (first = named) | affected RMS before -> after | unexplained\n");
    for (int seed = 1; seed <= seeds(); ++seed) {
        plant::PlantOptions o;
        o.seed = static_cast<std::uint64_t>(seed);
        o.layout = plant::Layout::thesis;
        const auto data = plant::generate(o);
        est::CharacterizationOptions co;  // the default global fit
        co.fallback_capacity_ah = data.truth.nominal_capacity_ah;
        // The heat flux density refers to the cell's surface, which a user knows from the format (18650 or
        // 21700 by seed): the fit is told it (`fit --area-m2`; prove.sh does the same).
        co.area_m2 = data.truth.area_m2;
        const auto fit = est::characterize({to_recording(data.hppc, "hppc"), to_recording(data.cc_low, "cc_low"),
                                      to_recording(data.cc_high, "cc_high")},
                                     co);
        // The C/20 discharge beside the HPPC gives the capacity's uncertainty (their disagreement on the charge
        // scale), which diagnose weighs a capacity correction against.
        EXPECT_TRUE(std::isfinite(fit.params.capacity_ah_sd)) << "seed " << seed;
        std::printf("seed %d: capacity %.4f +- %.4f Ah (plant %.4f Ah)\n", seed, fit.params.capacity_ah,
                    fit.params.capacity_ah_sd, data.truth.capacity_ah);
        for (const auto& effects : hidden) {
            plant::PlantOptions oe = o;
            oe.effects = effects;
            const auto cell = plant::make_cell(oe);
            const Recording drive = to_recording(plant::generate_drive(cell, oe), "drive");
            est::DiagnoseOptions dopt;
            dopt.threads = 2;
            const auto d = est::diagnose(fit.params, drive, dopt);
            Case c;
            for (auto e : effects) c.hidden += (c.hidden.empty() ? "" : "+") + std::string(plant::effect_id(e));
            // Re-identifications of the base fit (kind parameters_wrong: OCV table, lumped thermal parameters, dU/dT
            // table) say the characterization's fit is off, not which effect is hidden: listed apart. capacity_error
            // is parameters_wrong too, and one of the hidden effects.
            for (const auto& f : d.findings) {
                if (!f.significant) continue;
                if (f.effect == "ocv_offset" || f.effect == "ocv_band" || f.effect == "thermal_parameters") {
                    EXPECT_EQ(f.kind, "parameters_wrong") << f.effect;
                }
                const bool refit = f.kind == "parameters_wrong" && f.effect != "capacity_error";
                (refit ? c.refit : c.significant).push_back(f.effect);
            }
            const std::string first_hidden(plant::effect_id(effects.front()));
            const auto before = affected(d.baseline, first_hidden), after = affected(d.improved, first_hidden);
            c.cut = before && after && *before > 0 ? 1.0 - *after / *before : 0.0;
            c.unexplained = d.unexplained.has_value();
            std::string sig;
            for (const auto& s : c.significant) sig += (sig.empty() ? "" : ",") + s;
            for (const auto& s : c.refit) sig += " [" + s + "]";
            std::printf("%4d | %s | %s | %.4g -> %.4g (%.0f %%) | %s\n", seed, c.hidden.c_str(), sig.empty() ? "-" : sig.c_str(),
                        before.value_or(NAN), after.value_or(NAN), 100 * c.cut, c.unexplained ? "yes" : "null");
            expect_no_false_reassurance(d, c.hidden + " seed " + std::to_string(seed));
            cases.push_back(c);
        }
    }
    std::size_t single = 0, right = 0, cut_ok = 0, controls = 0, control_fp = 0, pairs = 0, pairs_both = 0;
    for (const auto& c : cases) {
        if (c.hidden == "none") {
            ++controls;
            control_fp += !c.significant.empty();
        } else if (c.hidden.find('+') == std::string::npos) {
            ++single;
            if (!c.significant.empty() && c.significant.front() == c.hidden) {
                ++right;
                cut_ok += c.cut >= 0.5;
            }
        } else {
            ++pairs;
            const auto plus = c.hidden.find('+');
            const std::string a = c.hidden.substr(0, plus), b = c.hidden.substr(plus + 1);
            auto has = [&](const std::string& e) {
                return std::find(c.significant.begin(), c.significant.end(), e) != c.significant.end();
            };
            pairs_both += has(a) && has(b);
        }
    }
    std::printf("right effect first %zu/%zu, RMS cut >= 50 %% in %zu of those, controls with a finding %zu/%zu, "
                "pairs both named %zu/%zu\n",
                right, single, cut_ok, control_fp, controls, pairs_both, pairs);
    // Issue 13's targets: >= 90 % right first, 0 on controls, >= 80 % of pairs both named, >= 50 % RMS cut. On these
    // bench effects they hold (make prove, seeds 1-5, docs/diagnose.md); the physics effects, each with its own
    // characterization and fit, are make prove's alone (too slow for make test).
    EXPECT_EQ(control_fp, 0u);
    EXPECT_GE(static_cast<double>(right), 0.9 * static_cast<double>(single));
    EXPECT_GE(static_cast<double>(cut_ok), 0.9 * static_cast<double>(right));
    EXPECT_GE(static_cast<double>(pairs_both), 0.8 * static_cast<double>(pairs));
}

// A candidate that mends the quantities the base misses by spoiling one the base had within the instrument's
// accuracy is no explanation. On seed 17 with a series resistance and an ambient drift hidden, a slow third RC pair
// (extra_rc, its second pair shortened) took part of the voltage and of the temperature error at once and won the
// first round, pushing the heat flux from 0.049 to 0.086 W against its 0.05 W accuracy; the two true effects were
// then never named (heat_flux_sensor_gain and thermal_parameters came after it). Measured in session 52.
TEST(DiagnoseOnIndependentPlant, AFindingMaySpoilNoQuantityTheBaseHadWithinItsAccuracy) {
    plant::PlantOptions o;
    o.seed = 17;
    o.layout = plant::Layout::thesis;
    const auto data = plant::generate(o);
    est::CharacterizationOptions co;
    co.fallback_capacity_ah = data.truth.nominal_capacity_ah;
    co.area_m2 = data.truth.area_m2;
    const auto fit = est::characterize({to_recording(data.hppc, "hppc"), to_recording(data.cc_low, "cc_low"),
                                        to_recording(data.cc_high, "cc_high")},
                                       co);
    plant::PlantOptions oe = o;
    oe.effects = {plant::Effect::series_resistance_offset, plant::Effect::ambient_drift};
    const Recording drive = to_recording(plant::generate_drive(plant::make_cell(oe), oe), "drive");
    est::DiagnoseOptions dopt;
    dopt.threads = 2;
    const auto d = est::diagnose(fit.params, drive, dopt);
    std::vector<std::string> significant;
    for (const auto& f : d.findings) {
        std::printf("%s: significant %d, score %.3f, worsens %zu; %s\n", f.effect.c_str(), f.significant, f.score,
                    f.worsens.size(), f.explanation.c_str());
        if (!f.significant) continue;
        significant.push_back(f.effect);
        // What the rule promises on every finding: a significant one spoils nothing.
        EXPECT_TRUE(f.worsens.empty()) << f.effect;
        ASSERT_TRUE(f.improved.heat_flux_w && d.baseline.heat_flux_w);
        EXPECT_LE(*f.improved.heat_flux_w, std::max(*d.baseline.heat_flux_w * 1.05, 0.05)) << f.effect;
    }
    auto named = [&](const char* e) { return std::find(significant.begin(), significant.end(), e) != significant.end(); };
    EXPECT_TRUE(named("series_resistance_offset"));
    EXPECT_TRUE(named("ambient_drift"));
    EXPECT_FALSE(named("extra_rc"));
}
