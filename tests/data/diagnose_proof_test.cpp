// Proof of `diagnose` on recordings where one effect is hidden and concealed from the characterization:
// generate (characterization HPPC + randomized drive profile), fit the characterization, diagnose the drive
// profile. The diagnoser never sees the generator's truth. Prints the confusion matrix it measured. This is the
// cheaper second table of `make prove` (CATALOGUE=1); the proof on physics diagnose was not written with is the
// independent plant's (tests/validation/diagnose_plant_test.cpp).
#include <gtest/gtest.h>

#include <cstdio>
#include <fstream>
#include <algorithm>
#include <map>
#include <sstream>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/generate.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

ParameterSet nominal_cell() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    std::stringstream ss;
    ss << in.rdbuf();
    return ParameterSet::from_json(nlohmann::json::parse(ss.str()), "p45b-thesis.json");
}

struct Outcome {
    std::string named_first = "none";
    std::vector<std::string> significant;
    QuantityRms before, after;
    double characterization_rms_v = 0;
};

Outcome run_case(const std::string& effect, std::uint32_t seed) {
    GeneratorOptions g;
    g.seed = seed;
    g.hidden_effect = effect;
    const auto c = generate_case(nominal_cell(), g);
    // The proof was designed with the per-pulse-set baseline. The global fit (the default) identifies current and
    // temperature dependence from characterization data itself, so its baseline already holds part of what this
    // catalogue looks for; proving diagnose on that baseline and on the independent plant is issue 13's work.
    CharacterizationOptions co;
    co.global_fit = false;
    const auto fit = characterize({c.characterization}, co);
    Outcome o;
    {
        const CellModel m(fit.params);
        o.characterization_rms_v = *compare(fit.params, c.characterization, simulate(m, c.characterization)).voltage_v.rms;
    }
    // The catalogue against itself: only the catalogue's effect ids compete (the re-identifications of the base
    // set, ocv_offset / ocv_band / thermal_parameters, are proven on the independent plant:
    // tests/validation/diagnose_plant_test.cpp and `make prove`).
    DiagnoseOptions opt;
    opt.effects = {"entropic_heat", "thermal_second_order", "resistance_temperature", "resistance_current",
                   "ocv_hysteresis", "extra_rc", "capacity_error", "series_resistance_offset",
                   "heat_flux_sensor_gain", "ambient_drift"};
    const auto d = diagnose(fit.params, c.validation, opt);
    for (const auto& f : d.findings)
        if (f.significant) o.significant.push_back(f.effect);
    if (!o.significant.empty()) o.named_first = o.significant.front();
    o.before = d.baseline;
    o.after = d.improved;
    return o;
}

double cut(const std::optional<double>& a, const std::optional<double>& b) { return 1.0 - *b / *a; }

// Every effect an HPPC fit cannot capture (see below for ocv_hysteresis).
const std::vector<std::string> kConcealed = {
    "entropic_heat",  "thermal_second_order", "resistance_temperature", "resistance_current",   "extra_rc",
    "capacity_error", "series_resistance_offset", "heat_flux_sensor_gain", "ambient_drift"};

}  // namespace

// ocv_hysteresis is not in the list: a discharge-only HPPC is not blind to it (its pilot discharge starts at
// +M after the charge and ends at -M, so the measured capacity and the OCV table absorb it), so it is not
// concealed; `make prove` still reports what diagnose names for it.
TEST(DiagnoseProof, NamesTheHiddenEffectFirstAndLeavesTheControlAlone) {
    std::map<std::string, Outcome> results;
    results["none"] = run_case("", 1);
    for (const auto& effect : kConcealed) results[effect] = run_case(effect, 1);

    std::printf("\n| hidden | named first | all significant | HPPC fit V RMS | V RMS before -> after | T RMS before -> after | "
                "heat flux RMS before -> after |\n|---|---|---|---|---|---|---|\n");
    for (const auto& [effect, o] : results) {
        std::string all;
        for (const auto& s : o.significant) all += (all.empty() ? "" : ", ") + s;
        std::printf("| %s | %s | %s | %.1f mV | %.1f -> %.1f mV | %.2f -> %.2f degC | %.3f -> %.3f W |\n",
                    effect.c_str(), o.named_first.c_str(), all.empty() ? "-" : all.c_str(), o.characterization_rms_v * 1e3,
                    *o.before.voltage_v * 1e3, *o.after.voltage_v * 1e3, *o.before.temperature_c, *o.after.temperature_c,
                    *o.before.heat_flux_w, *o.after.heat_flux_w);
    }
    std::size_t correct = 0;
    for (const auto& [effect, o] : results) correct += o.named_first == effect;
    std::printf("diagonal of the confusion matrix: %zu of %zu\n", correct, results.size());

    EXPECT_TRUE(results["none"].significant.empty()) << "control cell: " << results["none"].named_first;
    for (const auto& effect : kConcealed) {
        SCOPED_TRACE(effect);
        const auto& o = results[effect];
        EXPECT_EQ(o.named_first, effect);
        // The RMS of the quantity the effect perturbs most must drop (an extra RC pair, say, shows in the
        // voltage and heats the cell too).
        const double c = std::max({cut(o.before.voltage_v, o.after.voltage_v),
                                   cut(o.before.temperature_c, o.after.temperature_c),
                                   cut(o.before.heat_flux_w, o.after.heat_flux_w)});
        EXPECT_GT(c, 0.30) << "the improved model must cut the affected RMS error substantially";
    }
}

// A capacity correction is judged against what the characterization could measure: the fit states the capacity's
// uncertainty (ParameterSet::capacity_ah_sd, its recordings' disagreement on the charge scale), and a correction
// within twice it is no finding (independent plant, control seed 5: the fit's recordings disagreed by 0.46 % and
// the drive wanted +0.43 %, which was reported as "the capacity is wrong"). The same small error, stated more
// precisely by the base set or not stated at all, stays a finding.
TEST(DiagnoseProof, ACapacityCorrectionWithinTheCharacterizationsUncertaintyIsNoFinding) {
    GeneratorOptions g;
    g.seed = 3;
    g.hidden_effect = "capacity_error";
    g.magnitude = 0.15;  // 0.9-1.5 % less capacity in the drive than in the characterization
    const auto c = generate_case(nominal_cell(), g);
    const double error = 1.0 - c.truth_validation.extensions.capacity_error->capacity_scale;
    DiagnoseOptions opt;
    opt.effects = {"entropic_heat", "thermal_second_order", "resistance_temperature", "resistance_current",
                   "ocv_hysteresis", "extra_rc", "capacity_error", "series_resistance_offset",
                   "heat_flux_sensor_gain", "ambient_drift"};
    auto capacity_finding = [&](double sd_fraction) {
        ParameterSet base = c.truth_characterization;
        if (sd_fraction > 0) base.capacity_ah_sd = sd_fraction * base.capacity_ah;
        const auto d = diagnose(base, c.validation, opt);
        const auto f = std::find_if(d.findings.begin(), d.findings.end(), [](const auto& x) { return x.effect == "capacity_error"; });
        if (f == d.findings.end()) {
            ADD_FAILURE() << "capacity_error missing from the findings (every candidate is reported)";
            return Finding{};
        }
        std::printf("capacity %.2f %% low, stated sd %.2f %%: capacity_error %s (scale %.4f, held out %.3f): %s\n",
                    100 * error, 100 * sd_fraction, f->significant ? "significant" : "not significant",
                    f->parameters["capacity_scale"].get<double>(), f->score, f->explanation.c_str());
        return *f;
    };
    const auto unstated = capacity_finding(0.0);
    EXPECT_TRUE(unstated.significant) << "a capacity error of " << 100 * error << " % must be found";
    EXPECT_NEAR(unstated.parameters["capacity_scale"].get<double>(), 1.0 - error, 0.3 * error);
    EXPECT_TRUE(capacity_finding(0.2 * error).significant) << "an error of five stated sd is a finding";
    const auto within = capacity_finding(error);
    EXPECT_FALSE(within.significant) << "an error of one stated sd is not";
    EXPECT_NE(within.explanation.find("capacity uncertainty"), std::string::npos) << within.explanation;
}
