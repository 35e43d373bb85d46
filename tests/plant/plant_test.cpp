// The independent validation plant (tests/plant): what the fitter's and the diagnosis' acceptance tests rely on.
#include "cellbench/plant/plant.hpp"

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <numeric>
#include <set>
#include <sstream>

namespace {

namespace plant = cellbench::plant;
using plant::Direction;
using plant::Effect;
using plant::Layout;
using plant::PlantOptions;
using plant::Recording;

PlantOptions options(std::uint64_t seed, Layout layout = Layout::thesis, std::vector<Effect> effects = {}) {
    PlantOptions o;
    o.seed = seed;
    o.layout = layout;
    o.effects = std::move(effects);
    o.sample_s = 0.1;
    return o;
}

// Coulomb count of the measured current as a fraction of `capacity_ah`: trapezoids inside a step (the CV taper),
// the last sample's current held across a step change.
std::vector<double> coulomb_soc(const Recording& r, double soc0, double capacity_ah) {
    std::vector<double> soc(r.size(), soc0);
    for (std::size_t k = 1; k < r.size(); ++k) {
        const double i =
            r.step_count[k] == r.step_count[k - 1] ? 0.5 * (r.current_a[k - 1] + r.current_a[k]) : r.current_a[k - 1];
        soc[k] = soc[k - 1] + i * (r.time_s[k] - r.time_s[k - 1]) / (3600.0 * capacity_ah);
    }
    return soc;
}

// Row ranges [first, last] of each step count.
std::vector<std::pair<std::size_t, std::size_t>> step_rows(const Recording& r) {
    std::vector<std::pair<std::size_t, std::size_t>> rows(r.steps.size() + 1, {SIZE_MAX, 0});
    for (std::size_t k = 0; k < r.size(); ++k) {
        auto& [a, b] = rows[static_cast<std::size_t>(r.step_count[k])];
        a = std::min(a, k);
        b = std::max(b, k);
    }
    return rows;
}

struct Thesis {
    plant::CellSpec cell;
    plant::Truth truth;
    Recording hppc;
};
const Thesis& thesis_cell(std::uint64_t seed = 7) {
    static std::map<std::uint64_t, Thesis> cache;
    auto it = cache.find(seed);
    if (it == cache.end()) {
        const auto o = options(seed);
        Thesis t{plant::make_cell(o), {}, {}};
        t.truth = plant::make_truth(t.cell, o.layout);
        t.hppc = plant::generate_hppc(t.cell, o);
        it = cache.emplace(seed, std::move(t)).first;
    }
    return it->second;
}
constexpr std::uint64_t kSeeds[] = {7, 21, 42, 77};

TEST(PlantCell, ParametersStayInTheirPlausibleRangesForManySeeds) {
    for (std::uint64_t seed = 1; seed <= 300; ++seed) {
        const auto c = plant::make_cell(options(seed));  // throws when an OCV curve is not monotonic
        ASSERT_GE(c.capacity_ah, 2.0);
        ASSERT_LE(c.capacity_ah, 5.0);
        ASSERT_GE(c.r0_ref_ohm, 0.008);
        ASSERT_LE(c.r0_ref_ohm, 0.06);
        ASSERT_GE(c.c_th_j_per_k, 40.0);
        ASSERT_LE(c.c_th_j_per_k, 120.0);
        ASSERT_GE(c.r_th_k_per_w, 3.0);
        ASSERT_LE(c.r_th_k_per_w, 15.0);
        for (double s = 0.0; s <= 1.0; s += 0.01) {
            for (Direction d : {Direction::discharge, Direction::charge}) {
                ASSERT_GE(c.tau1_s(s, d), 1.0) << seed;
                ASSERT_LE(c.tau1_s(s, d), 10.0) << seed;
                ASSERT_GE(c.tau2_s(s, d), 20.0) << seed;
                ASSERT_LE(c.tau2_s(s, d), 300.0) << seed;
                ASSERT_GE(c.tau2_s(s, d) / c.tau1_s(s, d), 5.0) << seed;
                ASSERT_GT(c.r1_ohm(s, d), 0.0);
                ASSERT_GT(c.r2_ohm(s, d), 0.0);
            }
            ASSERT_LE(std::abs(c.entropic_v_per_k(s)), 3e-4);
        }
        // resistances rise towards low SOC
        ASSERT_GT(c.r1_ohm(0.05, Direction::discharge), c.r1_ohm(0.5, Direction::discharge));
        ASSERT_NEAR(c.ocv_ref_v(0.0), c.v_min_v, 1e-12);
        ASSERT_NEAR(c.ocv_ref_v(1.0), c.v_max_v, 1e-12);
    }
}

TEST(PlantCell, SeedsCoverEveryChemistry) {
    std::set<plant::Chemistry> seen;
    for (std::uint64_t seed = 1; seed <= 40; ++seed) seen.insert(plant::make_cell(options(seed)).chemistry);
    EXPECT_EQ(seen.size(), 4u);
}

TEST(PlantRecording, AfterALongRestTheVoltageIsTheTruthOcvAtTheCoulombCountedSoc) {
    for (std::uint64_t seed : kSeeds) {
        SCOPED_TRACE("seed " + std::to_string(seed));
        const auto& t = thesis_cell(seed);
        const auto& r = t.hppc;
        const auto soc = coulomb_soc(r, r.initial_soc, t.cell.capacity_ah);
        const auto rows = step_rows(r);
        int checked = 0;
        for (const auto& step : r.steps) {
            if (step.type != "Rest" || step.end_s - step.start_s < 3000.0) continue;
            const std::size_t k = rows[static_cast<std::size_t>(step.count)].second;  // last row of the rest
            if (soc[k] < 0.05 || soc[k] > 0.98) continue;
            const double ocv = t.cell.ocv_v(soc[k], r.surface_c[k]);
            EXPECT_NEAR(r.voltage_v[k], ocv, 1.5e-3) << "rest ending at " << step.end_s << " s, SOC " << soc[k];
            EXPECT_NEAR(soc[k], r.true_soc[k], 2e-4);
            ++checked;
        }
        EXPECT_GE(checked, 9);
    }
}

TEST(PlantRecording, PilotDischargeMeasuresTheTruthCapacityUpToTheCutOffShare) {
    for (std::uint64_t seed : kSeeds) {
        SCOPED_TRACE("seed " + std::to_string(seed));
        const auto& t = thesis_cell(seed);
        const auto& r = t.hppc;
        const auto& pilot = r.steps.at(3);
        ASSERT_EQ(pilot.type, "CC DChg");
        ASSERT_EQ(pilot.end_reason, "voltage");
        const auto rows = step_rows(r);
        const auto [a, b] = rows[4];
        double ah = 0.0;  // what a user counts from the recording
        for (std::size_t k = a; k <= b; ++k) ah += -r.current_a[k] * (r.time_s[k + 1] - r.time_s[k]) / 3600.0;
        EXPECT_NEAR(ah, -pilot.ah, 1e-3 * t.cell.capacity_ah);
        // The cut-off's share: the SOC where OCV minus the quasi-steady drop at 1C reaches v_min.
        const double i = t.cell.current_1c_a();
        double s_cut = 0.0;
        for (double s = 0.0; s < 0.5; s += 1e-4) {
            const double drop = i * (t.cell.r0_ohm(s, Direction::discharge) + t.cell.r1_ohm(s, Direction::discharge) +
                                     t.cell.r2_ohm(s, Direction::discharge));
            if (t.cell.ocv_ref_v(s) - drop > t.cell.v_min_v) {
                s_cut = s;
                break;
            }
        }
        EXPECT_LE(ah, t.truth.capacity_ah);
        EXPECT_GE(ah, t.truth.capacity_ah * (1.0 - s_cut - 0.01));
        EXPECT_LT(s_cut, 0.1);
    }
}

TEST(PlantRecording, CurrentStepGivesAnInstantaneousDropOfR0TimesTheCurrentStep) {
    for (std::uint64_t seed : kSeeds) {
        SCOPED_TRACE("seed " + std::to_string(seed));
        const auto& t = thesis_cell(seed);
        const auto& r = t.hppc;
        const double noise = t.cell.measurement.voltage_noise_v;
        int checked = 0;
        for (std::size_t k = 1; k < r.size(); ++k) {
            if (r.step_count[k] == r.step_count[k - 1] || r.step_type[k] != "CCCV DChg" || r.current_a[k - 1] != 0.0)
                continue;
            if (r.true_soc[k] < 0.1) continue;
            const double di = r.current_a[k] - r.current_a[k - 1];
            const double dv = r.voltage_v[k] - r.voltage_v[k - 1];
            const double r0 = t.cell.r0_ohm(r.true_soc[k], Direction::discharge);
            EXPECT_NEAR(dv, r0 * di, 6.0 * noise + 2e-4 + 0.002 * std::abs(r0 * di))
                << "pulse at " << r.time_s[k] << " s";
            ++checked;
        }
        EXPECT_GE(checked, 9);
    }
}

TEST(PlantRecording, LumpedEnergyBalanceHoldsOnTheHotDischarge) {
    for (std::uint64_t seed : {11u, 12u, 13u}) {
        SCOPED_TRACE("seed " + std::to_string(seed));
        const auto o = options(seed);
        const auto cell = plant::make_cell(o);
        const auto r = plant::generate_cc_high(cell, o);
        const auto& dis = r.steps.at(3);
        ASSERT_EQ(dis.type, "CC DChg");
        const auto rows = step_rows(r);
        const std::size_t a = rows[4].first, b = r.size() - 1;  // discharge and cool-down
        const auto soc = coulomb_soc(r, r.initial_soc, cell.capacity_ah);
        double heat_in = 0.0, heat_out = 0.0, peak = -1e9;
        for (std::size_t k = a; k < b; ++k) {
            const double dt = r.time_s[k + 1] - r.time_s[k], i = r.current_a[k], tc = r.surface_c[k];
            heat_in +=
                (i * (r.voltage_v[k] - cell.ocv_v(soc[k], tc)) + i * (tc + 273.15) * cell.entropic_v_per_k(soc[k])) *
                dt;
            heat_out += r.heat_flux_w_per_m2[k] * cell.area_m2 * dt;
            peak = std::max(peak, r.surface_c[k]);
        }
        const double stored = cell.c_th_j_per_k * (r.surface_c[b] - r.surface_c[a]);
        EXPECT_GT(peak - r.surface_c[a], 10.0) << "the high-rate discharge heats the cell by more than 10 K";
        EXPECT_NEAR(heat_in - heat_out, stored, 0.02 * heat_in + cell.c_th_j_per_k * 0.05);
    }
}

TEST(PlantRecording, SameSeedGivesIdenticalOutputAndAnotherSeedDoesNot) {
    const auto o = options(5, Layout::usabc);
    const auto cell = plant::make_cell(o);
    const auto a = plant::generate_drive(cell, o), b = plant::generate_drive(plant::make_cell(o), o);
    EXPECT_EQ(a.time_s, b.time_s);
    EXPECT_EQ(a.voltage_v, b.voltage_v);
    EXPECT_EQ(a.current_a, b.current_a);
    EXPECT_EQ(a.surface_c, b.surface_c);
    EXPECT_EQ(a.heat_flux_w_per_m2, b.heat_flux_w_per_m2);
    EXPECT_EQ(plant::to_json(plant::make_truth(cell, o.layout)),
              plant::to_json(plant::make_truth(plant::make_cell(o), o.layout)));
    const auto dir = std::filesystem::temp_directory_path() / ("plant_test_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    plant::write_bdf_csv(a, dir / "a.csv");
    plant::write_bdf_csv(b, dir / "b.csv");
    auto slurp = [](const std::filesystem::path& p) {
        std::ifstream f(p);
        std::stringstream s;
        s << f.rdbuf();
        return s.str();
    };
    const std::string text = slurp(dir / "a.csv");
    EXPECT_EQ(text, slurp(dir / "b.csv"));
    EXPECT_EQ(text.substr(0, text.find('\n')),
              "Test Time / s,Unix Time / s,Voltage / V,Current / A,Step Count / 1,Step Type,Ambient Temperature / degC,"
              "Surface Temperature / degC,Heat Flux Density / W/m^2");
    std::filesystem::remove_all(dir);
    const auto other = options(6, Layout::usabc);
    EXPECT_NE(plant::generate_drive(plant::make_cell(other), other).voltage_v, a.voltage_v);
}

double rms_difference(const std::vector<double>& a, const std::vector<double>& b) {
    const std::size_t n = std::min(a.size(), b.size());
    double s = 0.0;
    for (std::size_t k = 0; k < n; ++k) s += (a[k] - b[k]) * (a[k] - b[k]);
    return n ? std::sqrt(s / static_cast<double>(n)) : 0.0;
}
double max_difference(const std::vector<double>& a, const std::vector<double>& b) {
    double m = 0.0;
    for (std::size_t k = 0; k < std::min(a.size(), b.size()); ++k) m = std::max(m, std::abs(a[k] - b[k]));
    return m;
}

TEST(PlantEffects, EachEffectChangesTheDriveRecordingMeasurablyAndNoneChangesNothing) {
    for (std::uint64_t seed : {3u, 4u}) {
        const auto base_o = options(seed);
        const auto base_cell = plant::make_cell(base_o);
        const auto base = plant::generate_drive(base_cell, base_o);
        const auto base_hppc = plant::generate_hppc(base_cell, base_o);
        {
            const auto o = options(seed, Layout::thesis, {Effect::none});
            const auto none = plant::generate_drive(plant::make_cell(o), o);
            EXPECT_EQ(none.voltage_v, base.voltage_v);
            EXPECT_EQ(none.surface_c, base.surface_c);
            EXPECT_EQ(none.heat_flux_w_per_m2, base.heat_flux_w_per_m2);
            EXPECT_TRUE(plant::make_truth(plant::make_cell(o), o.layout).effects.empty());
        }
        for (Effect e : plant::all_effects()) {
            const auto o = options(seed, Layout::thesis, {e});
            const auto cell = plant::make_cell(o);
            const auto drive = plant::generate_drive(cell, o);
            ASSERT_EQ(drive.size(), base.size()) << plant::effect_id(e);
            const double dv = rms_difference(drive.voltage_v, base.voltage_v);
            const double dv_max = max_difference(drive.voltage_v, base.voltage_v);
            const double dt = max_difference(drive.surface_c, base.surface_c);
            const double dq = rms_difference(drive.heat_flux_w_per_m2, base.heat_flux_w_per_m2);
            const bool measurable = dv > 3e-3 || dv_max > 10e-3 || dt > 0.3 || dq > 3.0;
            EXPECT_TRUE(measurable) << plant::effect_id(e) << " seed " << seed << ": voltage RMS " << dv * 1e3
                                    << " mV (max " << dv_max * 1e3 << "), surface max " << dt << " K, heat flux RMS "
                                    << dq << " W/m2";
            // Bench effects are the drive's alone: the characterization is the base cell's.
            if (plant::is_bench_effect(e)) {
                const auto hppc = plant::generate_hppc(cell, o);
                EXPECT_EQ(hppc.voltage_v, base_hppc.voltage_v) << plant::effect_id(e);
                EXPECT_EQ(hppc.heat_flux_w_per_m2, base_hppc.heat_flux_w_per_m2) << plant::effect_id(e);
            }
            // The base tables of the truth do not move with an effect.
            const auto truth = plant::make_truth(cell, o.layout), base_truth = plant::make_truth(base_cell, o.layout);
            EXPECT_EQ(truth.ocv_v, base_truth.ocv_v);
            EXPECT_EQ(truth.discharge.r0_ohm, base_truth.discharge.r0_ohm);
            EXPECT_EQ(truth.effects, std::vector<std::string>{std::string(plant::effect_id(e))});
        }
    }
}

TEST(PlantEffects, TwoEffectsAtOnceAreBothInTheTruthAndTheRecording) {
    const auto o = options(9, Layout::thesis, {Effect::extra_rc, Effect::heat_flux_sensor_gain});
    const auto cell = plant::make_cell(o);
    EXPECT_TRUE(cell.extra_rc.enabled);
    EXPECT_NE(cell.bench.heat_flux_gain, 1.0);
    const auto truth = plant::make_truth(cell, o.layout);
    EXPECT_EQ(truth.effects, (std::vector<std::string>{"extra_rc", "heat_flux_sensor_gain"}));
    const auto j = plant::to_json(truth);
    EXPECT_TRUE(j["options"]["extra_rc"]["enabled"].get<bool>());
    EXPECT_NE(j["options"]["heat_flux_sensor_gain"]["offset_w_per_m2"].get<double>(), 0.0);
}

TEST(PlantLayouts, ThesisLayoutFollowsTable212) {
    const auto& r = thesis_cell().hppc;
    ASSERT_GE(r.steps.size(), 7u);
    EXPECT_EQ(r.steps[1].type, "CCCV Chg");
    EXPECT_EQ(r.steps[3].type, "CC DChg");  // pilot discharge to the cut-off
    EXPECT_NEAR(r.steps[4].end_s - r.steps[4].start_s, 3600.0, 1e-6);
    int sets = 0;
    for (std::size_t k = 7; k + 5 < r.steps.size(); ++k) {
        const auto& s = r.steps;
        if (s[k].type != "CCCV DChg") continue;
        ++sets;
        EXPECT_EQ(s[k + 1].type, "Rest");
        EXPECT_NEAR(s[k + 1].end_s - s[k + 1].start_s, 40.0, 1e-6);
        EXPECT_EQ(s[k + 2].type, "CCCV Chg");
        EXPECT_EQ(s[k + 3].type, "Rest");
        EXPECT_NEAR(s[k + 3].end_s - s[k + 3].start_s, 40.0, 1e-6);
        EXPECT_EQ(s[k + 4].type, "CC DChg");
        EXPECT_EQ(s[k + 5].type, "Rest");
        EXPECT_NEAR(s[k + 5].end_s - s[k + 5].start_s, 3600.0, 1e-6);
        if (sets >= 2 && sets <= 9) {  // away from the voltage limits the pulses run their full time
            EXPECT_NEAR(s[k].end_s - s[k].start_s, 30.0, 1e-6);
            EXPECT_NEAR(s[k + 2].end_s - s[k + 2].start_s, 10.0, 1e-6);
            EXPECT_EQ(s[k + 4].end_reason, "ah");
            // each SOC step brings the SOC down by 10 % of the pilot's capacity, pulses included
            EXPECT_NEAR(s[k].ah + s[k + 2].ah + s[k + 4].ah, 0.1 * s[3].ah, 1e-6);
        }
    }
    EXPECT_EQ(sets, 11);
    // 0.1 s inside the pulses
    for (std::size_t k = 1; k < r.size(); ++k)
        if (r.step_type[k] == "CCCV DChg" && r.step_count[k] == r.step_count[k - 1]) {
            ASSERT_NEAR(r.time_s[k] - r.time_s[k - 1], 0.1, 1.5e-3);
        }
}

TEST(PlantLayouts, UsabcLayoutHasNoPilotAndNoRestAfterTheRegenPulse) {
    const auto o = options(8, Layout::usabc);
    const auto cell = plant::make_cell(o);
    const auto r = plant::generate_hppc(cell, o);
    int regen = 0;
    for (std::size_t k = 0; k < r.steps.size(); ++k) {
        const auto& s = r.steps[k];
        EXPECT_FALSE(k < 3 && s.type == "CC DChg") << "no pilot discharge";
        if (s.type != "CCCV Chg" || k < 3) continue;
        ++regen;
        const auto& pulse = r.steps[k - 2];
        EXPECT_EQ(pulse.type, "CCCV DChg");
        EXPECT_NEAR(pulse.end_s - pulse.start_s, 30.0, 1e-6);
        EXPECT_NEAR(s.end_s - s.start_s, 10.0, 1e-6);
        EXPECT_EQ(r.steps[k - 1].type, "Rest");
        EXPECT_NEAR(r.steps[k - 1].end_s - r.steps[k - 1].start_s, 40.0, 1e-6);
        ASSERT_LT(k + 1, r.steps.size());
        EXPECT_EQ(r.steps[k + 1].type, "CC DChg") << "the SOC step follows the regen pulse at once";
        EXPECT_DOUBLE_EQ(r.steps[k + 1].start_s, s.end_s);
        if (!s.reached_cv && !pulse.reached_cv) {
            EXPECT_NEAR(s.ah / (s.end_s - s.start_s), -0.75 * pulse.ah / (pulse.end_s - pulse.start_s), 1e-9);
        }
    }
    EXPECT_GE(regen, 9);
    // in the recording: the row after the regen pulse's last row discharges
    for (std::size_t k = 1; k < r.size(); ++k)
        if (r.step_type[k - 1] == "CCCV Chg" && r.step_count[k - 1] > 3 && r.step_count[k] != r.step_count[k - 1]) {
            EXPECT_LT(r.current_a[k], 0.0);
        }
}

TEST(PlantLayouts, MultiLayoutPulsesAtFiveCurrentsPerLevel) {
    const auto o = options(12, Layout::multi);
    const auto cell = plant::make_cell(o);
    const auto r = plant::generate_hppc(cell, o);
    std::vector<double> currents;
    int full_levels = 0;
    for (std::size_t k = 0; k + 9 < r.steps.size(); ++k) {
        bool level = true;
        for (std::size_t j = 0; j < 5; ++j)
            level = level && r.steps[k + 2 * j].type == "CC DChg" && r.steps[k + 2 * j].end_reason == "time" &&
                    r.steps[k + 2 * j + 1].type == "Rest";
        if (!level) continue;
        ++full_levels;
        std::set<long> distinct;
        for (std::size_t j = 0; j < 5; ++j) {
            const auto& p = r.steps[k + 2 * j];
            EXPECT_NEAR(p.end_s - p.start_s, 10.0, 1e-6);
            distinct.insert(std::lround(p.ah * 1e6));
        }
        EXPECT_EQ(distinct.size(), 5u);
        k += 9;
    }
    EXPECT_GE(full_levels, 7);
}

// The random layout draws what labs run: over 60 seeds every option appears, and each recording follows its draw
// (pulse lengths, a level every SOC step from one end to one step from the other).
TEST(PlantLayouts, RandomLayoutsCoverWhatLabsRunAndFollowTheirDraw) {
    std::set<double> steps, discharge_pulses;
    std::set<int> currents;
    std::set<bool> upward, pilot, charge_first, charge_pulse;
    for (std::uint64_t seed = 1; seed <= 60; ++seed) {
        const auto cell = plant::make_cell(options(seed, Layout::random));
        const auto l = plant::draw_random_layout(seed, cell.measurement.sample_s);
        steps.insert(l.soc_step), discharge_pulses.insert(l.discharge_pulse_s), currents.insert(l.currents_per_level);
        upward.insert(l.upward), pilot.insert(l.pilot), charge_first.insert(l.charge_first);
        charge_pulse.insert(l.charge_pulse_s > 0);
        EXPECT_GE(l.discharge_pulse_s, 10.0 * cell.measurement.sample_s - 1e-9) << "seed " << seed;
        EXPECT_TRUE(l.charge_pulse_s == 0.0 || l.charge_pulse_s >= 10.0 * cell.measurement.sample_s - 1e-9);
        EXPECT_GT(l.charge_rate_c, 0.0);
        EXPECT_LE(l.charge_rate_c, l.discharge_rate_c + 1e-9);
    }
    EXPECT_EQ(steps, (std::set<double>{0.05, 0.1, 0.2}));
    EXPECT_GE(discharge_pulses.size(), 3u);
    EXPECT_EQ(currents, (std::set<int>{1, 2}));
    EXPECT_EQ(upward.size(), 2u);
    EXPECT_EQ(pilot.size(), 2u);
    EXPECT_EQ(charge_first.size(), 2u);
    EXPECT_EQ(charge_pulse.size(), 2u);

    for (std::uint64_t seed : {1u, 9u, 12u}) {  // upward, two currents; downward, two currents; downward, one
        const auto o = options(seed, Layout::random);
        const auto cell = plant::make_cell(o);
        const auto l = plant::draw_random_layout(seed, cell.measurement.sample_s);
        const auto r = plant::generate_hppc(cell, o);
        std::vector<double> level_soc;  // the true SOC at the start of each level's first discharge pulse
        int pulses = 0;
        for (const auto& s : r.steps) {
            if (s.type != "CCCV DChg" || s.end_reason != "time") continue;
            const double length = s.end_s - s.start_s;
            const bool first = std::abs(length - l.discharge_pulse_s) < 1e-6;
            EXPECT_TRUE(first || l.currents_per_level == 2) << "seed " << seed << ": a " << length << " s pulse";
            ++pulses;
            const auto row = std::lower_bound(r.time_s.begin(), r.time_s.end(), s.start_s) - r.time_s.begin();
            const double soc = r.true_soc[static_cast<std::size_t>(row)];
            if (level_soc.empty() || std::abs(soc - level_soc.back()) > 0.5 * l.soc_step) level_soc.push_back(soc);
        }
        // Down: a level every step from full to one step from empty. Up: from one step above empty until a SOC
        // step's charge meets the voltage limit (under current, some steps below full), as a cycler's limit ends it.
        const int levels = static_cast<int>(std::lround(1.0 / l.soc_step));
        EXPECT_EQ(pulses, static_cast<int>(level_soc.size()) * l.currents_per_level) << "seed " << seed;
        if (l.upward) {
            EXPECT_GE(static_cast<double>(level_soc.size()), 0.8 * levels) << "seed " << seed;
            EXPECT_LE(static_cast<int>(level_soc.size()), levels) << "seed " << seed;
        } else {
            ASSERT_EQ(static_cast<int>(level_soc.size()), levels) << "seed " << seed;
        }
        const double step = l.soc_step * cell.nominal_capacity_ah / cell.capacity_ah;  // in the plant's SOC
        for (std::size_t k = 1; k < level_soc.size(); ++k)
            EXPECT_NEAR(std::abs(level_soc[k] - level_soc[k - 1]), step, 0.02) << "seed " << seed << " level " << k;
        // one step from the end the test starts from, and at the other end one step from it
        const double lowest = *std::min_element(level_soc.begin(), level_soc.end());
        EXPECT_NEAR(lowest, l.upward ? step : 1.0 - (levels - 1) * step, 0.05) << "seed " << seed;
    }
}

TEST(PlantLayouts, DriveProfileStaysInsideTheVoltageWindowAndSpansTheSocRange) {
    const auto o = options(13);
    const auto cell = plant::make_cell(o);
    const auto r = plant::generate_drive(cell, o);
    const auto [lo, hi] = std::minmax_element(r.true_voltage_v.begin(), r.true_voltage_v.end());
    EXPECT_GE(*lo, cell.v_min_v - 1e-6);
    EXPECT_LE(*hi, cell.v_max_v + 1e-6);
    EXPECT_GT(r.true_soc.front(), 0.85);
    EXPECT_LT(r.true_soc.back(), 0.4);
    const auto [imin, imax] = std::minmax_element(r.current_a.begin(), r.current_a.end());
    EXPECT_LT(*imin, -2.0 * cell.current_1c_a());
    EXPECT_GT(*imax, 0.5 * cell.current_1c_a());
    EXPECT_GT(r.time_s.back(), 3600.0);
}

TEST(PlantCli, WritesTheFourRecordingsAndTheTruth) {
    const auto dir = std::filesystem::temp_directory_path() / ("plant_cli_" + std::to_string(::getpid()));
    const std::string exe = std::string(CELLBENCH_BIN_DIR) + "/cellbench_plant";
    const std::string cmd = exe +
                            " --seed 2 --layout usabc --effect extra_rc --effect capacity_error --sample-s 0.5 -o " +
                            dir.string() + " > " + (dir.string() + ".log");
    ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
    for (const char* f : {"hppc.bdf.csv", "cc_low.bdf.csv", "cc_high.bdf.csv", "drive.bdf.csv", "truth.json"})
        EXPECT_TRUE(std::filesystem::exists(dir / f)) << f;
    std::ifstream truth_file(dir / "truth.json");
    const auto truth = nlohmann::json::parse(truth_file);
    EXPECT_EQ(truth["layout"], "usabc");
    EXPECT_EQ(truth["effects"], (nlohmann::json{"extra_rc", "capacity_error"}));
    EXPECT_EQ(truth["soc"].size(), 19u);
    EXPECT_EQ(truth["discharge"]["tau2_s"].size(), 19u);
    EXPECT_NE(truth["drive_capacity_ah"].get<double>(), truth["capacity_ah"].get<double>());
    std::ifstream log(dir.string() + ".log");
    std::stringstream printed;
    printed << log.rdbuf();
    EXPECT_NE(printed.str().find("drive.bdf.csv"), std::string::npos);
    std::filesystem::remove_all(dir);
    std::filesystem::remove(dir.string() + ".log");
    EXPECT_NE(std::system((exe + " --seed 2 --effect no_such_effect -o " + dir.string() + " 2> /dev/null").c_str()), 0);
    EXPECT_FALSE(std::filesystem::exists(dir / "truth.json"));
}

}  // namespace

// The cycler's record conditions (log_on_change): a row at every step's first and last sample, and between those
// only when the voltage or the current has moved by its threshold since the last row written, or the time has
// passed; every column (the true values too) thinned alike.
TEST(PlantLogger, KeepsEachStepsEndsAndTheRowsThatMovedEnough) {
    plant::Recording r;
    auto add = [&](double t, double v, double i, int step) {
        r.time_s.push_back(t), r.voltage_v.push_back(v), r.current_a.push_back(i), r.step_count.push_back(step);
        r.step_type.push_back(step == 2 ? "CC DChg" : "Rest");
        r.true_soc.push_back(0.5 - 1e-4 * t);
    };
    for (int k = 0; k <= 200; ++k) add(k, 3.700, 0.0, 1);                      // rest: flat
    for (int k = 1; k <= 100; ++k) add(200 + k, 3.650 - 0.0011 * k, -2.0, 2);   // discharge: 1.1 mV/s
    for (int k = 1; k <= 100; ++k) add(300 + k, 3.600 + 0.00012 * k, 0.0, 3);  // relaxation: 0.12 mV/s
    for (int k = 1; k <= 30; ++k) add(400 + k, 4.200, 2.0 - 0.011 * k, 4);     // CV taper: 11 mA/s
    const auto out = plant::log_on_change(r, {0.005, 0.05, 60.0});
    std::vector<double> t = out.time_s;
    // Rest: its first row, a row a minute, its last row. Discharge: its first row, one per 5 mV (5 s), its last
    // row. Relaxation: its first row, one per 5 mV (42 s), its last row. Taper: one per 50 mA (5 s).
    const std::vector<double> expected = {0,   60,  120, 180, 200, 201, 206, 211, 216, 221, 226, 231, 236, 241,
                                          246, 251, 256, 261, 266, 271, 276, 281, 286, 291, 296, 300, 301, 343,
                                          385, 400, 401, 406, 411, 416, 421, 426, 430};
    EXPECT_EQ(t, expected);
    ASSERT_EQ(out.true_soc.size(), out.time_s.size());
    ASSERT_EQ(out.step_count.size(), out.time_s.size());
    for (std::size_t k = 0; k < out.size(); ++k) EXPECT_DOUBLE_EQ(out.true_soc[k], 0.5 - 1e-4 * out.time_s[k]);
}
