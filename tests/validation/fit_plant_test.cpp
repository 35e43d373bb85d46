// Acceptance of the characterization on data this project's model did not make: the independent validation plant
// (tests/plant: its own continuous-time equations, adaptive ODE integration, smooth SOC functions, other OCV
// shapes, noise and quantization) in the thesis' Table 2.12 layout, in the USABC manual layout (no pilot
// discharge, no rest after the regen pulse), in layouts drawn by seed (random) and in a GITT (titration steps, no
// pulses; session 46). For every seed the fitted parameter set is compared with the plant's
// truth at SOC 10..90 %; the table printed is what the closing figures quote.
//
// Seeds: CELLBENCH_VALIDATION_SEEDS (default 3 per layout, to keep `make test` short; the closing figures use 20),
// from CELLBENCH_VALIDATION_FIRST_SEED (default 1). CELLBENCH_VALIDATION_VERBOSE=1 prints every SOC level's
// signed errors and the global fit's windows (where the worst-level errors come from).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/model.hpp"
#include "cellbench/estimator/segment.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "cellbench/estimator/thermal_characterization.hpp"
#include "cellbench/plant/plant.hpp"
#include "validation/plant_recording.hpp"

namespace {

using cellbench::Recording;
namespace est = cellbench::estimator;
namespace plant = cellbench::plant;

using cellbench::test::to_recording;

int seeds_per_layout() {
    if (const char* e = std::getenv("CELLBENCH_VALIDATION_SEEDS")) return std::max(1, std::atoi(e));
    return 3;
}

struct Errors {
    double ocv_mv = 0, r0 = 0, r12 = 0, tau1 = 0, tau2 = 0, capacity = 0, c_th = 0, r_th = 0, dudt_mv_per_k = 0;
    double capacity_vs_cell = 0;  // the fitted capacity against the plant cell's own (Truth::capacity_ah)
    // Worst discharge R0 at the HPPC's own SOC levels (where its discharge pulses start, within 10-90 %), against
    // the plant's R0 there: what the pulses measure. The R0 column above is held on the truth's 5 % grid, whose
    // midpoints between levels the fitted table reaches by its straight line between two levels (a chord over the
    // convex rise towards empty). Reported beside it, not held.
    double r0_at_levels = 0;
    double drive_rms_mv = 0;
    // The worst discharge R0 error over the 5 % grid in units of the sd the fit reports there (`fit --json`'s
    // knots[].discharge.r0_ohm_sd): whether the fit says how well it knows each value, between levels too.
    double r0_z = 0;
    // The same over the grid points where R0 misses issue 11's 2 %: a miss must be one the fit's sd admits
    // (between two levels far apart, where the straight line cuts a bend, the sd carries the line's error).
    double r0_z_large = 0;
    // The worst RC value beyond issue 11's bounds (tau1, tau2: 25 %; R1+R2: 10 %) that the fit does not flag
    // (uncertain, unidentified, implausible) at that SOC, in units of its reported sd (R1+R2: R1's and R2's sds
    // combined as if independent): 0 when every such miss is flagged or none occurs.
    double rc_z_unflagged = 0;
};

// The sd the global fit reports for one discharge quantity (0 = R0) at SOC s, linear between its grid points.
double reported_sd(const est::Characterization& c, double s, int q) {
    if (!c.global || c.global->discharge.empty()) return NAN;
    const auto& soc = c.params.soc;
    const auto& t = c.global->discharge;
    const auto hi = static_cast<std::size_t>(std::lower_bound(soc.begin(), soc.end(), s) - soc.begin());
    if (hi == 0) return t.front()[q].sd;
    if (hi >= soc.size()) return t.back()[q].sd;
    const double w = (s - soc[hi - 1]) / (soc[hi] - soc[hi - 1]);
    return t[hi - 1][q].sd + w * (t[hi][q].sd - t[hi - 1][q].sd);
}

// The global fit's reported value of one discharge quantity (q: 0 R0, 5 tau1, 6 tau2) at the grid point nearest to
// SOC s: its sd and flags say how far the fit itself trusts it.
const est::FittedValue& reported_at(const est::Characterization& c, double s, int q) {
    const auto& soc = c.params.soc;
    std::size_t k = static_cast<std::size_t>(std::lower_bound(soc.begin(), soc.end(), s) - soc.begin());
    if (k >= soc.size() || (k > 0 && s - soc[k - 1] < soc[k] - s)) k = k > 0 ? k - 1 : 0;
    return c.global->discharge[k][q];
}

// Worst errors over SOC 10..90 % (relative values as fractions).
//
// SOC scales: the plant's SOC runs over the charge between the OCV window's ends; the fit's over the charge a
// test measures between full charge and the cut-off (less: the cut-off comes under current). Both count the
// same charge from full, so the truth at plant SOC s is compared with the fit at
//     s_fit = 1 - (s_full - s) * C_truth / C_fit,
// s_full being the plant's SOC at full charge (the highest of the HPPC). The capacity is compared with the charge
// the HPPC itself moved between full charge and its cut-off (`cap %`, at the HPPC's rates), and with the cell's
// own capacity (`cap/cell %`: the charge between OCV = v_min and OCV = v_max, which a capacity test at a low rate
// approaches from below: its charge ends on the CV taper, its discharge at the cut-off under load).
// The SOC levels whose truth the fit is held to: 10-90 % (issue 11), and in the random layout only those between
// its lowest and highest pulse level (beyond them only the SOC steps and discharges pass: the tables there are the
// fit's extrapolation; an upward test ends where a step's charge meets the voltage limit).
// The plant's SOC where each discharge pulse of the HPPC starts (a discharge of at most 60 s that ran its time).
std::vector<double> pulse_start_socs(const plant::Dataset& d) {
    std::vector<double> socs;
    for (const auto& s : d.hppc.steps) {
        if (s.type != "CCCV DChg" || s.end_reason != "time" || s.end_s - s.start_s > 60.0) continue;
        const auto row = static_cast<std::size_t>(std::lower_bound(d.hppc.time_s.begin(), d.hppc.time_s.end(), s.start_s) -
                                                  d.hppc.time_s.begin());
        if (row < d.hppc.true_soc.size()) socs.push_back(d.hppc.true_soc[row]);
    }
    return socs;
}

std::pair<double, double> compared_soc_range(const plant::Dataset& d, plant::Layout layout) {
    if (layout != plant::Layout::random) return {0.1, 0.9};
    double lo = 1.0, hi = 0.0;
    for (const double soc : pulse_start_socs(d)) lo = std::min(lo, soc), hi = std::max(hi, soc);
    // A level's pulses start a little off its nominal SOC (the 10 % level of a 10 % step test at 10.3 %): 2.5 % slack.
    return {std::max(0.1, lo - 0.025), std::min(0.9, hi + 0.025)};
}

Errors compare(const est::Characterization& c, const plant::Dataset& d, const Recording& drive,
               std::pair<double, double> soc_range = {0.1, 0.9}) {
    const auto& t = d.truth;
    const auto& p = c.params;
    Errors e;
    double dudt_sq = 0;
    int n = 0;
    const double s_full = *std::max_element(d.hppc.true_soc.begin(), d.hppc.true_soc.end());
    const double s_empty = *std::min_element(d.hppc.true_soc.begin(), d.hppc.true_soc.end());
    const double measured_capacity_ah = t.capacity_ah * (s_full - s_empty);
    const bool verbose = std::getenv("CELLBENCH_VALIDATION_VERBOSE") != nullptr;
    for (std::size_t k = 0; k < t.soc.size(); ++k) {
        const double st = t.soc[k];
        if (st < soc_range.first - 0.001 || st > soc_range.second + 0.001) continue;
        const double s = 1.0 - (s_full - st) * t.capacity_ah / p.capacity_ah;
        const auto rc = p.rc_at(s, -1);
        auto rel = [](double fit, double truth) { return std::abs(fit / truth - 1.0); };
        if (verbose)
            std::printf("   soc %.2f (fit %.3f): OCV %+7.2f mV  R0 %+6.2f %%  R1+R2 %+6.2f %%  tau1 %+6.1f %%  tau2 %+6.1f %%"
                        "  (R0 %.2f mOhm, tau1 %.2f s, tau2 %.1f s; R0 sd %.2f %%)\n",
                        st, s, 1e3 * (p.ocv_at(s) - t.ocv_v[k]), 100 * (rc.r0_ohm / t.discharge.r0_ohm[k] - 1),
                        100 * ((rc.r1_ohm + rc.r2_ohm) / (t.discharge.r1_ohm[k] + t.discharge.r2_ohm[k]) - 1),
                        100 * (rc.tau1_s / t.discharge.tau1_s[k] - 1), 100 * (rc.tau2_s / t.discharge.tau2_s[k] - 1),
                        1e3 * t.discharge.r0_ohm[k], t.discharge.tau1_s[k], t.discharge.tau2_s[k],
                        100 * reported_sd(c, s, 0) / rc.r0_ohm);
        const double r0_z = std::abs(rc.r0_ohm - t.discharge.r0_ohm[k]) / reported_sd(c, s, 0);
        e.r0_z = std::max(e.r0_z, r0_z);
        if (rel(rc.r0_ohm, t.discharge.r0_ohm[k]) > 0.02) e.r0_z_large = std::max(e.r0_z_large, r0_z);
        e.ocv_mv = std::max(e.ocv_mv, 1e3 * std::abs(p.ocv_at(s) - t.ocv_v[k]));
        e.r0 = std::max(e.r0, rel(rc.r0_ohm, t.discharge.r0_ohm[k]));
        e.r12 = std::max(e.r12, rel(rc.r1_ohm + rc.r2_ohm, t.discharge.r1_ohm[k] + t.discharge.r2_ohm[k]));
        e.tau1 = std::max(e.tau1, rel(rc.tau1_s, t.discharge.tau1_s[k]));
        e.tau2 = std::max(e.tau2, rel(rc.tau2_s, t.discharge.tau2_s[k]));
        if (c.global && !c.global->discharge.empty()) {
            const std::pair<double, double> taus[2] = {{rc.tau1_s, t.discharge.tau1_s[k]}, {rc.tau2_s, t.discharge.tau2_s[k]}};
            for (int i = 0; i < 2; ++i) {
                const auto& [fit, truth] = taus[i];
                const auto& v = reported_at(c, s, 5 + i);
                if (rel(fit, truth) > 0.25 && v.flags.empty())
                    e.rc_z_unflagged = std::max(e.rc_z_unflagged, std::abs(fit - truth) / v.sd);
            }
            const auto &r1 = reported_at(c, s, 1), &r2 = reported_at(c, s, 3);
            const double r12_truth = t.discharge.r1_ohm[k] + t.discharge.r2_ohm[k];
            if (rel(rc.r1_ohm + rc.r2_ohm, r12_truth) > 0.10 && r1.flags.empty() && r2.flags.empty())
                e.rc_z_unflagged = std::max(e.rc_z_unflagged,
                                            std::abs(rc.r1_ohm + rc.r2_ohm - r12_truth) / std::hypot(r1.sd, r2.sd));
        }
        const double dd = 1e3 * (p.ehc_at(s) - t.entropic_v_per_k[k]);
        dudt_sq += dd * dd, ++n;
    }
    e.dudt_mv_per_k = std::sqrt(dudt_sq / std::max(n, 1));
    for (const double sp : pulse_start_socs(d)) {
        if (sp < soc_range.first - 0.005 || sp > soc_range.second + 0.005) continue;
        const double s = 1.0 - (s_full - sp) * t.capacity_ah / p.capacity_ah;
        const double level_error = p.rc_at(s, -1).r0_ohm / d.cell.r0_ohm(sp, plant::Direction::discharge) - 1.0;
        if (verbose)
            std::printf("   discharge pulse at soc %.3f (fit %.3f): R0 %+6.2f %% (sd %.2f %%)\n", sp, s, 100 * level_error,
                        100 * reported_sd(c, s, 0) / p.rc_at(s, -1).r0_ohm);
        e.r0_at_levels = std::max(e.r0_at_levels, std::abs(level_error));
    }
    e.capacity = std::abs(p.capacity_ah / measured_capacity_ah - 1.0);
    e.capacity_vs_cell = std::abs(p.capacity_ah / t.capacity_ah - 1.0);
    e.c_th = std::abs(p.thermal.c_th_j_per_k / t.c_th_j_per_k - 1.0);
    e.r_th = std::abs(p.thermal.r_th_k_per_w / t.r_th_k_per_w - 1.0);
    const est::CellModel model(p);
    const auto trace = est::simulate(model, drive);
    const auto m = est::compare(p, drive, trace);
    e.drive_rms_mv = m.voltage_v.rms ? 1e3 * *m.voltage_v.rms : NAN;
    return e;
}

// The default characterization of the plant's three characterization recordings, with what a user gives: the
// cell's surface and its nominal capacity. The CELLBENCH_VALIDATION_* variables below are diagnostics.
est::Characterization characterize_plant(const plant::Dataset& d) {
    std::vector<Recording> recs = {to_recording(d.hppc, "hppc"), to_recording(d.cc_low, "cc_low"),
                                   to_recording(d.cc_high, "cc_high")};
    // diagnostics: the characterization without the fast (heating) discharge
    if (std::getenv("CELLBENCH_VALIDATION_NO_CC_HIGH")) recs.pop_back();
    est::CharacterizationOptions co;
    co.area_m2 = d.truth.area_m2;
    co.fallback_capacity_ah = d.truth.nominal_capacity_ah;  // what a user gives (nominal)
    // diagnostics: another knot spacing than characterize() derives from the test's SOC levels
    if (const char* k = std::getenv("CELLBENCH_VALIDATION_KNOT_SPACING")) co.global.knot_spacing = std::atof(k);
    if (const char* k = std::getenv("CELLBENCH_VALIDATION_SMOOTHNESS")) co.global.smoothness = std::atof(k);
    if (const char* k = std::getenv("CELLBENCH_VALIDATION_OCV_SMOOTHNESS")) co.global.ocv_smoothness = std::atof(k);
    if (const char* k = std::getenv("CELLBENCH_VALIDATION_DIRECTION_PRIOR")) co.global.direction_prior = std::atof(k);
    if (std::getenv("CELLBENCH_VALIDATION_NO_CURRENT_DEPENDENCE")) co.global.current_dependence = false;
    if (std::getenv("CELLBENCH_VALIDATION_NO_SLOW_PAIR")) co.global.slow_relaxation = false;
    if (std::getenv("CELLBENCH_VALIDATION_FREE_STEP_LAG")) co.global.hold_unidentified_step_lag = false;
    return est::characterize(recs, co);
}

class FitOnIndependentPlant : public ::testing::TestWithParam<plant::Layout> {};

TEST_P(FitOnIndependentPlant, RecoversTheCellItWasNotWrittenWith) {
    const int seeds = seeds_per_layout();
    std::vector<Errors> all;
    std::printf("layout %s: seed | OCV mV | R0 %% | R1+R2 %% | tau1 %% | tau2 %% | cap %% | cap/cell %% | C_th %% | "
                "R_th %% | dU/dT mV/K | drive mV | R0 at levels %%\n",
                std::string(plant::layout_name(GetParam())).c_str());
    const char* first_env = std::getenv("CELLBENCH_VALIDATION_FIRST_SEED");  // diagnostics: another seed range
    const int first = first_env ? std::max(1, std::atoi(first_env)) : 1;
    for (int seed = first; seed < first + seeds; ++seed) {
        plant::PlantOptions o;
        o.seed = static_cast<std::uint64_t>(seed);
        o.layout = GetParam();
        // diagnostics: another cell size (e.g. 60 for a pouch cell), the seed's cell scaled
        if (const char* k = std::getenv("CELLBENCH_VALIDATION_CAPACITY_AH")) o.capacity_ah = std::atof(k);
        const auto d = plant::generate(o);
        const auto c = characterize_plant(d);
        if (std::getenv("CELLBENCH_VALIDATION_VERBOSE")) {
            std::printf("seed %d: capacity %.4f Ah (%s), truth %.4f Ah, sample %.2f s\n", seed, c.capacity.capacity_ah,
                        c.capacity.method.c_str(), d.truth.capacity_ah, d.cell.measurement.sample_s);
            if (c.global) {
                std::printf("   global: Ea %.0f J/mol (T dep %d), I0 %.3f A ref %.3f A (I dep %d), T_ref %.2f C, smoothness %.0f, step lag %.3f +- %.3f\n",
                            c.global->activation_energy_j_per_mol.value, c.global->temperature_dependence,
                            c.global->exchange_current_a.value, c.global->reference_current_a, c.global->current_dependence,
                            c.params.reference_temperature_c, c.global->smoothness, c.global->step_lag.value, c.global->step_lag.sd);
                std::printf("   cross-validation (weight: held-out RMS):");
                for (const auto& [weight, rms] : c.global->cross_validation) std::printf(" %.0f: %.4f mV", weight, 1e3 * rms);
                std::printf("\n");
                for (const auto& note : c.global->notes) std::printf("   note: %s\n", note.c_str());
                for (const auto& w : c.global->windows)
                    std::printf("   window rec %zu %s soc %.3f..%.3f offset %+.4f scale %.4f rms %.2f mV\n", w.recording,
                                w.kind.c_str(), w.soc_min, w.soc_max, w.soc_offset, w.capacity_scale, 1e3 * w.rms_v);
            }
            {
                const double s_full = *std::max_element(d.hppc.true_soc.begin(), d.hppc.true_soc.end());
                for (const auto& pt : c.ocv_points) {
                    const double st = s_full - (1.0 - pt.soc) * c.params.capacity_ah / d.truth.capacity_ah;
                    std::printf("   rest point fit soc %.3f (truth %.3f): rested %.4f V, truth OCV %.4f V (%+.2f mV), table %+.2f mV\n",
                                pt.soc, st, pt.ocv_v, d.cell.ocv_ref_v(st), 1e3 * (pt.ocv_v - d.cell.ocv_ref_v(st)),
                                1e3 * (c.params.ocv_at(pt.soc) - d.cell.ocv_ref_v(st)));
                }
            }
            std::printf("   thermal: C_th %.2f +- %.2f J/K (truth %.2f), R_th %.3f +- %.3f K/W (truth %.3f)\n",
                        c.thermal.c_th_j_per_k, c.thermal.c_th_sigma_j_per_k, d.truth.c_th_j_per_k,
                        c.thermal.r_th_k_per_w, c.thermal.r_th_sigma_k_per_w, d.truth.r_th_k_per_w);
        }
        const auto e = compare(c, d, to_recording(d.drive, "drive"), compared_soc_range(d, GetParam()));
        std::printf("%4d | %6.2f | %5.2f | %7.2f | %6.1f | %6.1f | %5.2f | %10.2f | %6.2f | %6.2f | %10.3f | %8.2f | %5.2f  (%s, %s, %zu pulse sets; R0's worst error %.1f of its reported sd, %.1f over its misses > 2 %%; unflagged RC misses: %.1f sd)\n",
                    seed, e.ocv_mv, 100 * e.r0, 100 * e.r12, 100 * e.tau1, 100 * e.tau2, 100 * e.capacity,
                    100 * e.capacity_vs_cell, 100 * e.c_th, 100 * e.r_th, e.dudt_mv_per_k, e.drive_rms_mv,
                    100 * e.r0_at_levels, d.truth.chemistry.c_str(),
                    c.capacity.method.c_str(), c.pulse_fits.size(), e.r0_z, e.r0_z_large, e.rc_z_unflagged);
        // Layout-agnostic detection (issue 11): every layout the plant draws has pulse sets the per-pulse-set
        // comparison and the daemon's online fits find, and its drive profile (after a long rest too) has none.
        // A GITT has no pulses: the fit says its tables come from the titration steps alone.
        if (GetParam() == plant::Layout::gitt)
            EXPECT_TRUE(std::any_of(c.warnings.begin(), c.warnings.end(),
                                    [](const std::string& w) { return w.rfind("no pulses:", 0) == 0; }))
                << "seed " << seed;
        else
            EXPECT_FALSE(c.pulse_fits.empty()) << "seed " << seed << ": no pulse set found in the HPPC";
        // Uncertainty on every fitted value that a user can take at its word: an R0 more than 2 % off lies within
        // 5 of its reported sd (session 40, seeds 1-20 of the thesis and USABC layouts and 1-10 of the random
        // one: at most 4.0, random seed 5; before the sd carried the straight line's error between two levels,
        // thesis seed 2's R0 at 10 % SOC was 2.03 % off with an sd of 0.31 %, 6.5 sd). Smaller misses can be a
        // few sd: a bias of the model's form, e.g. random seed 4's R0 1.4 % low at every level, 0.33 % sd.
        EXPECT_LT(e.r0_z_large, 5.0) << "seed " << seed << ": R0 off by more than its reported uncertainty admits";
        // The same for the RC pairs: a time constant beyond 25 % or an R1+R2 beyond 10 % is flagged at that SOC or
        // lies within 5 of its reported sd. Session 41: thesis and USABC seeds 1-20 have no such miss; of random
        // seeds 1-30 only seed 19, an LFP cell whose layout has 2 s discharge pulses and charges between its
        // levels: its discharge tau2 is 35-49 % off at every level, flagged uncertain (sd 90-216 s on 80-125 s)
        // but at 20 % SOC (84 +- 53 s against 145 s: 1.1 sd), R1+R2 up to 15 % off within 1 sd. The layout does not
        // identify the discharge tau2, and the fit says so.
        EXPECT_LT(e.rc_z_unflagged, 5.0) << "seed " << seed << ": an RC value off, unflagged, beyond its reported sd";
        EXPECT_TRUE(est::segment_recording(to_recording(d.drive, "drive")).pulse_sets.empty())
            << "seed " << seed << ": the drive profile taken for pulse sets";
        all.push_back(e);
    }
    auto median = [&](auto member) {
        std::vector<double> v;
        for (const auto& e : all) v.push_back(e.*member);
        std::sort(v.begin(), v.end());
        return v[v.size() / 2];
    };
    const double ocv = median(&Errors::ocv_mv), r0 = median(&Errors::r0), r12 = median(&Errors::r12);
    const double cap = median(&Errors::capacity), drive = median(&Errors::drive_rms_mv);
    std::printf("median worst-level error: OCV %.2f mV, R0 %.2f %%, R1+R2 %.2f %%, capacity %.2f %%, drive %.2f mV\n",
                ocv, 100 * r0, 100 * r12, 100 * cap, drive);
    // What the fit holds today on every layout (issue 11's targets are tighter; the closing note reports both).
    // Measured (3 seeds, medians thesis / usabc): OCV 7.3 / 9.0 mV (before the OCV had its own finer grid between
    // the pulse levels where low-rate data pass: 28.8 / 17.8 mV, the knee at 10 % SOC cut by the 10 % knots'
    // chord), R0 1.9 / 1.2 % (before the step residuals: 7.3 / 6.1 %), R1+R2 3.7 / 6.9 %, capacity 5.2 / 1.8 %,
    // drive 2.4 / 4.4 mV (before: 5.1 / 4.0 mV).
    EXPECT_LT(ocv, 15.0);
    EXPECT_LT(r0, 0.04);
    EXPECT_LT(r12, 0.10);
    EXPECT_LT(cap, 0.07);
    EXPECT_LT(drive, 6.0);
    // C_th and R_th: issue 11's 5 % at every seed (before the energy-balance C_th: 17-97 % and 1-55 % off, the
    // derivative's noise in the regressor of eq. 4.8; measured since: C_th within 0.1 %, R_th within 2 %).
    for (const auto& e : all) {
        EXPECT_LT(e.c_th, 0.05);
        EXPECT_LT(e.r_th, 0.05);
    }
    // The capacity against the cell's own (issue 11: within 0.5 %): the lowest-rate full discharge handed in (the
    // plant's C/20) delivered 0.07-0.60 % less on seeds 1-20 (17 of 20 within 0.5 %; seed 1: 0.60 %) until the
    // charge between its cut-off under load and OCV = cut-off was counted (charge_below_cutoff_ah); the 1C pilot
    // discharge in the thesis layout's HPPC delivers 7.8 % less on seed 1 (the cut-off's share at 1C).
    for (std::size_t k = 0; k < all.size(); ++k)
        EXPECT_LT(all[k].capacity_vs_cell, 0.005) << "seed " << first + static_cast<int>(k);
    // The RC pairs keep their roles: every time constant within a factor 1.5 of the truth at every level. A
    // collapse (one pair taking both roles, the other's tau on its bound) is off by 5-250x: USABC seed 2 from
    // the generic start was 1133 % (tau1) and 2745 % (tau2) off at 10 % SOC before the fit tried other starts;
    // now 7 % and 9 %. Issue 11's 25 % is missed on some seeds of 20 (the closing note's table).
    for (std::size_t k = 0; k < all.size(); ++k) {
        EXPECT_LT(all[k].tau1, 0.5) << "seed " << first + static_cast<int>(k);
        EXPECT_LT(all[k].tau2, 0.5) << "seed " << first + static_cast<int>(k);
    }
}

// The plant's seed 15 is an LFP cell: a flat plateau with two steps and an OCV that bends within a few % of SOC
// at both ends. With the OCV on a 5 % grid (before session 16) the fitted OCV was 95 mV high at 6 % SOC and the
// second RC pair turned into an integrator standing in for the missing slope: tau2 off by 2353 %, R0 by 29 %,
// the drive at 14.8 mV RMS. On the 2 % grid (GlobalFitOptions::ocv_spacing_soc) measured: OCV 3.9 mV, R0 9.5 %,
// R1+R2 13 %, tau1 10 %, tau2 18 %, drive 4.9 mV at the worst level.
TEST(FitOnIndependentPlantLfp, SteepOcvEndsDoNotCollapseTheRcPairs) {
    plant::PlantOptions o;
    o.seed = 15;
    o.layout = plant::Layout::thesis;
    const auto d = plant::generate(o);
    ASSERT_EQ(d.truth.chemistry, "lfp");
    const auto c = characterize_plant(d);
    ASSERT_TRUE(c.global.has_value());
    EXPECT_GE(c.global->ocv_knots_per_interval, 5);  // 10 % levels, OCV knots 2 % apart
    const auto e = compare(c, d, to_recording(d.drive, "drive"));
    std::printf("seed 15 (lfp): OCV %.2f mV, R0 %.1f %%, R1+R2 %.1f %%, tau1 %.1f %%, tau2 %.1f %%, drive %.2f mV\n",
                e.ocv_mv, 100 * e.r0, 100 * e.r12, 100 * e.tau1, 100 * e.tau2, e.drive_rms_mv);
    EXPECT_LT(e.tau1, 0.5);
    EXPECT_LT(e.tau2, 0.5);
    EXPECT_LT(e.r12, 0.25);
    EXPECT_LT(e.ocv_mv, 10.0);
    EXPECT_LT(e.drive_rms_mv, 8.0);
}

// The random layout's seed 63 is an LFP cell whose HPPC ends with a discharge to the cut-off 0.7 % of SOC below its
// lowest pulse level (1.0 %), where its OCV falls 150 mV. The table's breakpoints ended at that level and a stretch
// less than 1 % beyond it got none, so the OCV there was the last interval's straight line: the fit bent the OCV at
// the level 27 mV below its own rest to absorb the stretch, the pulse window at 1-11 % was fitted at 11.8 mV, and the
// second pair took the rest: tau2 257 % and R1+R2 37 % off at 10-20 % SOC (found in session 54 on seeds 61-80).
// Such a stretch now gets an OCV knot of its own (not one of the tables': no pulse there identifies the pairs):
// OCV 0.45 mV, R1+R2 3.5 %, tau2 11 %.
TEST(FitOnIndependentPlantLfp, ADischargeJustBelowTheLowestLevelGetsAnOcvKnotOfItsOwn) {
    plant::PlantOptions o;
    o.seed = 63;
    o.layout = plant::Layout::random;
    const auto d = plant::generate(o);
    ASSERT_EQ(d.truth.chemistry, "lfp");
    const auto c = characterize_plant(d);
    ASSERT_TRUE(c.global.has_value());
    const auto e = compare(c, d, to_recording(d.drive, "drive"), compared_soc_range(d, plant::Layout::random));
    std::printf("random seed 63 (lfp): OCV %.2f mV, R0 %.2f %%, R1+R2 %.1f %%, tau1 %.1f %%, tau2 %.1f %%, drive %.2f mV\n",
                e.ocv_mv, 100 * e.r0, 100 * e.r12, 100 * e.tau1, 100 * e.tau2, e.drive_rms_mv);
    EXPECT_LT(e.ocv_mv, 5.0);
    EXPECT_LT(e.r0, 0.02);
    EXPECT_LT(e.r12, 0.10);
    EXPECT_LT(e.tau1, 0.25);
    EXPECT_LT(e.tau2, 0.25);
    EXPECT_LT(e.drive_rms_mv, 6.0);
}

// Another cell than an 18650: the plant's seed 5 scaled to a 60 Ah pouch (resistances / 16, C_th x 16, R_th 0.41 K/W
// instead of 6.5). The thermal fit searched R_th from 0.5 K/W up and held it there (22.8 % off, unflagged); the
// tables, the capacity and the drive must come out as on the small cell.
TEST(FitOnIndependentPlantLargeCell, APouchCellIsRecoveredAsWellAsAnEighteen650) {
    plant::PlantOptions o;
    o.seed = 5;
    o.layout = plant::Layout::thesis;
    o.capacity_ah = 60.0;
    const auto d = plant::generate(o);
    ASSERT_EQ(d.truth.format, "pouch");
    ASSERT_LT(d.truth.r_th_k_per_w, 0.5);
    const auto c = characterize_plant(d);
    const auto e = compare(c, d, to_recording(d.drive, "drive"));
    std::printf("seed 5 as a 60 Ah pouch: OCV %.2f mV, R0 %.2f %%, R1+R2 %.1f %%, tau1 %.1f %%, tau2 %.1f %%, capacity/cell "
                "%.2f %%, C_th %.2f %%, R_th %.2f %% (%.3f K/W, flags %zu), drive %.2f mV\n",
                e.ocv_mv, 100 * e.r0, 100 * e.r12, 100 * e.tau1, 100 * e.tau2, 100 * e.capacity_vs_cell, 100 * e.c_th,
                100 * e.r_th, c.thermal.r_th_k_per_w, c.thermal.r_th_flags.size(), e.drive_rms_mv);
    EXPECT_LT(e.c_th, 0.05);
    EXPECT_LT(e.r_th, 0.05);
    EXPECT_TRUE(c.thermal.r_th_flags.empty()) << "a pouch cell's R_th is plausible";
    EXPECT_LT(e.ocv_mv, 5.0);
    EXPECT_LT(e.r0, 0.03);
    EXPECT_LT(e.r12, 0.10);
    EXPECT_LT(e.capacity_vs_cell, 0.005);
    EXPECT_LT(e.drive_rms_mv, 6.0);
    // Its channel's current noise (0.1 A, 16x the 18650's) is no current step: the global fit merges a CC phase's
    // rows into ticks as on the small cell (5 800 voltage residuals) instead of fitting every row (96 000, 17x the
    // time) when a 50 mA change counted as a step.
    ASSERT_TRUE(c.global.has_value());
    std::size_t residuals = 0;
    for (const auto& w : c.global->windows) residuals += w.residuals;
    EXPECT_LT(residuals, 15000u);
    // Its drive diagnosed against its own fit (no hidden effect): nothing significant. With the heat flux floor of a
    // 21700 (0.05 W) the drive's 0.10 W heat flux error over the pouch's 0.039 m^2 counted as evidence and extra_rc
    // came out significant (seed 3 scaled, by hand); the floor now scales with the surface.
    const auto diag = est::diagnose(c.params, to_recording(d.drive, "drive"), est::DiagnoseOptions{});
    for (const auto& f : diag.findings) EXPECT_FALSE(f.significant) << f.effect << " significant on a clean pouch cell";
    // The thermal fit over a 21700's surface, as `cellbench fit` without --area-m2: C_th reads low by the ratio of the
    // surfaces, is flagged implausible, and a note says which surface was used and how to give the cell's.
    std::vector<Recording> recs = {to_recording(d.hppc, "hppc"), to_recording(d.cc_low, "cc_low"),
                                   to_recording(d.cc_high, "cc_high")};
    std::vector<est::RecordingSegments> segs;
    for (const auto& r : recs) segs.push_back(est::segment_recording(r));
    const auto small_surface = est::fit_thermal_parameters(recs, segs, {}, c.params, est::CharacterizationOptions{});
    std::printf("over a 21700's surface: C_th %.1f J/K (cell %.1f)\n", small_surface.c_th_j_per_k, d.truth.c_th_j_per_k);
    const auto& flags = small_surface.c_th_flags;
    EXPECT_NE(std::find(flags.begin(), flags.end(), "implausible"), flags.end());
    EXPECT_TRUE(std::any_of(small_surface.notes.begin(), small_surface.notes.end(),
                            [](const std::string& n) { return n.find("--area-m2") != std::string::npos; }));
}

// On uniformly sampled steps (the USABC layout logged every 1 s) when a current step happens within its sample
// interval trades against R0 and R1 exactly, so the data do not tell it. Left free, the fitted lag went where
// the model's other errors pushed it: USABC seed 15 (LFP) 0.14 +- 0.59 of an interval, R0 3.4 % low at every SOC.
// The fit now reports the lag's uncertainty, flags it, holds it at 0 (a record at the step's start, as cyclers
// and the plant log) and says so: R0 0.96 % at its worst level.
TEST(FitOnIndependentPlantStepTiming, AnUnidentifiedStepLagIsHeldAtARecordOnTheStep) {
    plant::PlantOptions o;
    o.seed = 15;
    o.layout = plant::Layout::usabc;
    const auto d = plant::generate(o);
    const auto c = characterize_plant(d);
    ASSERT_TRUE(c.global.has_value());
    const auto& lag = c.global->step_lag;
    EXPECT_EQ(lag.value, 0.0);
    EXPECT_GT(lag.sd, 0.25);
    // ... but no more than a lag within its sample interval can be (uniform over [0, 1]: sd 0.289), nor carry more
    // into R0 (its linearized sd, 0.59 of an interval, had made R0's sd twice as large).
    EXPECT_LE(lag.sd, 1.0 / std::sqrt(12.0) + 1e-9);
    EXPECT_LT(reported_sd(c, 0.5, 0) / c.params.rc_at(0.5, -1).r0_ohm, 0.10);
    EXPECT_NE(std::find(lag.flags.begin(), lag.flags.end(), "uncertain"), lag.flags.end());
    EXPECT_TRUE(std::any_of(c.global->notes.begin(), c.global->notes.end(),
                            [](const std::string& n) { return n.find("held at 0") != std::string::npos; }));
    const auto e = compare(c, d, to_recording(d.drive, "drive"));
    std::printf("usabc seed 15: R0 %.2f %% (at the levels %.2f %%), R1+R2 %.2f %%, drive %.2f mV\n", 100 * e.r0,
                100 * e.r0_at_levels, 100 * e.r12, e.drive_rms_mv);
    EXPECT_LT(e.r0, 0.02);
    EXPECT_LT(e.r0_at_levels, 0.02);
}

// A cycler's record conditions (plant::log_on_change: a row at each step's start and end, and between those when the
// voltage has moved by 5 mV, the current by 50 mA, or 60 s have passed), applied to the plant's recordings written at
// 0.1 s: 30-60 times fewer rows, a CV taper and every rest a row a minute, a relaxation a row per 5 mV. Before
// session 47 the Coulomb count took such a taper's rows for current steps, `simulate` ran every step an interval
// early and the taper as a staircase (the dense fit's model 16.8 mV RMS off the thinned HPPC of seed 1, 0.7 mV on
// the dense one), and the heat flux's energy balance found no rest it could use. What a user relies on: the fit
// of such recordings recovers what the dense ones hold, within the uncertainties it reports.
// Seeds: CELLBENCH_VALIDATION_SEEDS (default 2 here), thesis layout.
TEST(FitOnIndependentPlantLoggedOnChange, RecoversTheCellFromACyclersRecordConditions) {
    const int seeds = std::getenv("CELLBENCH_VALIDATION_SEEDS") ? seeds_per_layout() : 2;
    const plant::RecordConditions conditions{0.005, 0.05, 60.0};
    std::printf("logged on 5 mV / 50 mA / 60 s: seed | rows | OCV mV | R0 %% | R1+R2 %% | tau1 %% | tau2 %% | "
                "cap/cell %% | C_th %% (sd %%) | R_th %% | dU/dT mV/K | drive mV | HPPC mV\n");
    for (int seed = 1; seed <= seeds; ++seed) {
        plant::PlantOptions o;
        o.seed = static_cast<std::uint64_t>(seed);
        o.layout = plant::Layout::thesis;
        o.sample_s = 0.1;
        auto d = plant::generate(o);
        const std::size_t dense_rows = d.hppc.size();
        for (auto* r : {&d.hppc, &d.cc_low, &d.cc_high, &d.drive}) *r = plant::log_on_change(*r, conditions);
        ASSERT_LT(d.hppc.size() * 20, dense_rows) << "seed " << seed << ": the logger should keep few rows";
        const auto c = characterize_plant(d);
        const auto e = compare(c, d, to_recording(d.drive, "drive"));
        // The parameter set simulated on the HPPC it was fitted to (`cellbench simulate`).
        const auto hppc = to_recording(d.hppc, "hppc");
        const est::CellModel model(c.params);
        const auto hppc_rms = est::compare(c.params, hppc, est::simulate(model, hppc)).voltage_v.rms;
        ASSERT_TRUE(hppc_rms.has_value());
        const double hppc_rms_mv = 1e3 * *hppc_rms;
        const double c_th_sd = c.thermal.c_th_sigma_j_per_k / d.truth.c_th_j_per_k;
        std::printf("%4d | %zu of %zu | %6.2f | %5.2f | %7.2f | %6.1f | %6.1f | %10.2f | %6.2f (%.2f) | %6.2f | %10.3f | %8.2f | "
                    "%7.2f  (R0's worst error %.1f of its reported sd over its misses > 2 %%; unflagged RC misses: %.1f sd)\n",
                    seed, d.hppc.size(), dense_rows, e.ocv_mv, 100 * e.r0, 100 * e.r12, 100 * e.tau1, 100 * e.tau2,
                    100 * e.capacity_vs_cell, 100 * e.c_th, 100 * c_th_sd, 100 * e.r_th, e.dudt_mv_per_k,
                    e.drive_rms_mv, hppc_rms_mv, e.r0_z_large, e.rc_z_unflagged);
        EXPECT_LT(e.ocv_mv, 5.0) << "seed " << seed;
        EXPECT_LT(e.r0, 0.04) << "seed " << seed;
        EXPECT_LT(e.r0_z_large, 5.0) << "seed " << seed;
        EXPECT_LT(e.rc_z_unflagged, 5.0) << "seed " << seed;
        EXPECT_LT(e.r12, 0.10) << "seed " << seed;
        EXPECT_LT(e.tau1, 0.5) << "seed " << seed;
        EXPECT_LT(e.tau2, 0.5) << "seed " << seed;
        EXPECT_LT(e.capacity_vs_cell, 0.005) << "seed " << seed;
        EXPECT_LT(e.drive_rms_mv, 6.0) << "seed " << seed;
        // Seed 1 0.57 mV, seed 2 3.85 mV (31.0 mV before session 47): a logger that writes the sample crossing a
        // 50 mA threshold writes currents biased in the direction of the taper by the current's noise, so the count
        // of each thinned CV taper falls 0.6 mAh short of the dense one, 0.13 % of SOC by the HPPC's end, where the
        // OCV is steep (the fit absorbs it in its windows' SOC offsets; `simulate` integrates from the start).
        EXPECT_LT(hppc_rms_mv, 5.0) << "seed " << seed << ": the fit's own HPPC simulated";
        // C_th from the heat flux of rests logged once a minute: within 5 % or within 3 of its reported sd.
        EXPECT_TRUE(e.c_th < 0.05 || e.c_th < 3.0 * c_th_sd) << "seed " << seed << ": C_th " << 100 * e.c_th << " % off";
        EXPECT_LT(e.r_th, 0.05) << "seed " << seed;
        EXPECT_LT(e.dudt_mv_per_k, 0.05) << "seed " << seed;
    }
}

INSTANTIATE_TEST_SUITE_P(Layouts, FitOnIndependentPlant,
                         ::testing::Values(plant::Layout::thesis, plant::Layout::usabc, plant::Layout::random,
                                           plant::Layout::gitt),
                         [](const auto& info) { return std::string(plant::layout_name(info.param)); });

}  // namespace
