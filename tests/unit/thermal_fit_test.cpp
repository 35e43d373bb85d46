// Thermal fits on synthetic data from the first-order thermal model (thesis eq. 4.1-4.2) with known C_th, R_th
// and entropic heat coefficient, plus sensor noise.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>
#include <utility>
#include <vector>

#include "cellbench/estimator/thermal_fit.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

constexpr double kC = 63.3;      // J/K
constexpr double kR = 5.26;      // K/W
constexpr double kA = 5.311e-3;  // m^2
constexpr double kAmb = 29.5;    // degC
constexpr double kRint = 0.025;  // ohm, V - OCV = I * R_int
constexpr double kCap = 4.5;     // Ah

double ocv_of(double soc) { return 3.0 + 1.2 * soc - 0.15 * std::sin(6.0 * soc); }
// A made-up but Li-ion-like EHC (V/K): negative at low SOC, positive above ~40 %.
double ehc_of(double soc) { return 1.5e-4 * std::sin(3.0 * (soc - 0.4)) + 2e-5; }

struct Synth {
    Recording rec;
    std::vector<double> soc;
    std::vector<RowRange> rests, discharges;
    std::vector<double> ambient;  // the chamber air per row (kept out of rec unless a test wants it)
};

struct Phase {
    double duration_s, current_a;
};

// Chamber air: the setpoint with a slow control ripple (as in the real chamber, ~20 min period).
double ambient_at(double t) { return kAmb + 0.03 * std::sin(2.0 * std::numbers::pi * t / 1150.0); }
constexpr double kFluxOffset = 0.3;  // W/m^2 sensor zero offset

// Exact integration of C dT/dt = Q - (T - T_amb)/R for Q and T_amb held over each step (Q uses the temperature at
// the start of the step for the reversible term). q'' = (T - T_amb)/(R*A) + offset: all heat leaves through the
// measured surface. White noise on T and q''.
Synth make(const std::vector<Phase>& phases, double dt, double t_noise_k, double q_noise_w_per_m2, unsigned seed,
           double flux_gain = 1.0) {
    std::mt19937 rng(seed);
    std::normal_distribution<double> nt(0.0, t_noise_k), nq(0.0, q_noise_w_per_m2);
    Synth s;
    s.rec.source = "synthetic";
    double T = kAmb, soc = 1.0, t = 0.0;
    const double tau = kR * kC;
    auto push = [&](double i) {
        s.rec.time_s.push_back(t);
        s.rec.current_a.push_back(i);
        s.rec.voltage_v.push_back(ocv_of(soc) + i * kRint);
        s.rec.surface_c.push_back(T + nt(rng));
        s.rec.heat_flux_w_per_m2.push_back(flux_gain * (T - ambient_at(t)) / (kR * kA) + kFluxOffset + nq(rng));
        s.rec.ambient_c.push_back(ambient_at(t));
        s.soc.push_back(soc);
    };
    push(0.0);
    for (const auto& ph : phases) {
        const std::size_t begin = s.rec.size();
        const auto n = static_cast<std::size_t>(std::llround(ph.duration_s / dt));
        for (std::size_t k = 0; k < n; ++k) {
            const double i = ph.current_a;
            // Heat generation, BDF sign (eq. 4.1): Q = I (V - OCV) + I T[K] dU/dT.
            const double q_gen = i * (i * kRint) + i * (T + kZeroCelsiusK) * ehc_of(soc);
            const double t_ss = ambient_at(t + 0.5 * dt) + kR * q_gen;
            T = t_ss + (T - t_ss) * std::exp(-dt / tau);
            soc += i * dt / 3600.0 / kCap;
            t += dt;
            push(i);
        }
        (ph.current_a == 0.0 ? s.rests : s.discharges).push_back({begin, s.rec.size()});
    }
    s.ambient = s.rec.ambient_c;
    s.rec.ambient_c.clear();  // recordings without a chamber channel, unless a test puts it back
    return s;
}

// The cell's OCV every 5 % of SOC, as the entropic fit is given it.
std::pair<std::vector<double>, std::vector<double>> ocv_table() {
    std::vector<double> soc, v;
    for (int k = 0; k <= 20; ++k) soc.push_back(0.05 * k), v.push_back(ocv_of(0.05 * k));
    return {soc, v};
}

// Rest 10 min, discharge 2C 10 min, rest 1 h, discharge 1C 15 min, rest 1 h, discharge 2C 8 min, rest 1 h.
Synth standard(unsigned seed, double flux_gain = 1.0) {
    return make({{600, 0}, {600, -9.0}, {3600, 0}, {900, -4.5}, {3600, 0}, {480, -9.0}, {3600, 0}}, 0.2, 0.003, 1.5,
                seed, flux_gain);
}

}  // namespace

TEST(SmoothDerivative, ExactForLinesOnNonUniformTime) {
    std::vector<double> t, y;
    double tt = 0;
    std::mt19937 rng(1);
    std::uniform_real_distribution<double> u(0.05, 0.5);
    for (int k = 0; k < 2000; ++k) {
        t.push_back(tt);
        y.push_back(3.0 - 0.25 * tt);
        tt += u(rng);
    }
    const auto d = smooth_derivative(t, y, 100, 1900, 20.0);
    ASSERT_EQ(d.size(), 1800u);
    for (double v : d) EXPECT_NEAR(v, -0.25, 1e-9);  // truncated windows at the range ends stay exact
}

TEST(SmoothDerivative, SurvivesNoiseAndSkipsNaN) {
    std::mt19937 rng(2);
    std::normal_distribution<double> n(0.0, 0.005);
    std::vector<double> t, y;
    for (int k = 0; k < 36000; ++k) {
        t.push_back(0.1 * k);
        y.push_back(30.0 + 2.0 * std::exp(-t.back() / 330.0) + n(rng));
    }
    for (int k = 5000; k < 5050; ++k) y[k] = kNaN;  // a DAQ gap
    const auto d = smooth_derivative(t, y, 0, t.size(), 60.0);
    for (int k = 3000; k < 30000; k += 997) {
        const double truth = -2.0 / 330.0 * std::exp(-t[k] / 330.0);
        EXPECT_NEAR(d[k], truth, 2e-5 + 0.01 * std::abs(truth)) << "t=" << t[k];
    }
    EXPECT_TRUE(std::isfinite(d[5025]));
    // A plain finite difference would have noise ~0.005*sqrt(2)/0.1 = 0.07 K/s: 10^4 x the signal here.
}

TEST(SmoothDerivative, TooFewSamplesGiveNaN) {
    const std::vector<double> t{0, 1, 2, 3}, y{0, 1, 2, 3};
    const auto d = smooth_derivative(t, y, 0, 4, 0.5);  // windows hold one sample
    for (double v : d) EXPECT_TRUE(std::isnan(v));
    EXPECT_TRUE(smooth_derivative(t, y, 2, 2, 10).empty());
}

TEST(ThermalCapacity, RecoversCthFromRests) {
    const Synth s = standard(11);
    const auto fit = fit_thermal_capacity(s.rec, s.rests, kA);
    EXPECT_NEAR(fit.c_th_j_per_k, kC, 0.03 * kC) << fit.note;
    EXPECT_GT(fit.r_squared, 0.95);
    EXPECT_GT(fit.c_th_se_j_per_k, 0.0);
    EXPECT_LT(fit.c_th_se_j_per_k, 0.05 * kC);
    EXPECT_EQ(fit.rests_used, 4u);  // the first rest (no cooling) still contributes rows
    EXPECT_GT(fit.points, 10000u);
    ASSERT_EQ(fit.per_rest_c_th_j_per_k.size(), 4u);
    for (std::size_t r = 1; r < 4; ++r) EXPECT_NEAR(fit.per_rest_c_th_j_per_k[r], kC, 0.05 * kC);
}

// A cycler's "record every 60 s": the rests' end values need windows of five rows, which at a minute's rows span a
// good part of the cooling (tau = R C here); they come from parabolas there. Before, such rests held "no usable
// rest rows" and the fit fell back on the surface temperature alone, saying no heat flux had been measured.
TEST(ThermalCapacity, RestsLoggedOnceAMinuteStillGiveTheirEnergyBalance) {
    const Synth s = make({{600, 0}, {600, -9.0}, {3600, 0}, {900, -4.5}, {3600, 0}, {480, -9.0}, {3600, 0}}, 60.0,
                         0.003, 1.5, 12);
    const auto fit = fit_thermal_capacity(s.rec, s.rests, kA);
    ASSERT_TRUE(std::isfinite(fit.c_th_j_per_k)) << fit.note;
    EXPECT_NEAR(fit.c_th_j_per_k, kC, 0.03 * kC) << fit.note;
    EXPECT_NE(fit.note.find("logged sparsely"), std::string::npos) << fit.note;
}

TEST(ThermalCapacity, RobustToHeatSmearedIntoRestEnds) {
    // The real HPPC file's DAQ channels anticipate the next step by ~4 min (filtering); imitate it: the last
    // 240 s of each rest warm up with heat leaving the surface, which violates eq. 4.7.
    Synth s = standard(12);
    for (const auto& r : s.rests) {
        const double t_end = s.rec.time_s[r.end - 1];
        for (std::size_t k = r.begin; k < r.end; ++k) {
            const double x = s.rec.time_s[k] - (t_end - 240.0);
            if (x <= 0) continue;
            s.rec.surface_c[k] += 0.2 * (x / 240.0) * (x / 240.0);
            s.rec.heat_flux_w_per_m2[k] += 8.0 * x / 240.0;
        }
    }
    const auto fit = fit_thermal_capacity(s.rec, s.rests, kA);
    EXPECT_NEAR(fit.c_th_j_per_k, kC, 0.04 * kC) << fit.note;
    EXPECT_GT(fit.points_rejected, 0u);
}

TEST(ThermalCapacity, NoUsableRowsIsReportedNotThrown) {
    const Synth s = standard(13);
    const auto fit = fit_thermal_capacity(s.rec, {{s.rests[1].begin, s.rests[1].begin + 100}}, kA);
    EXPECT_TRUE(std::isnan(fit.c_th_j_per_k));
    EXPECT_FALSE(fit.note.empty());
}

TEST(ThermalCapacity, MissingChannelsThrow) {
    Synth s = standard(14);
    s.rec.heat_flux_w_per_m2.clear();
    EXPECT_THROW(fit_thermal_capacity(s.rec, s.rests, kA), InputError);
    s = standard(14);
    EXPECT_THROW(fit_thermal_capacity(s.rec, s.rests, 0.0), InputError);
}

TEST(ThermalResistance, BothWaysAgreeOnLumpedData) {
    const Synth s = standard(21);
    std::vector<RowRange> all = s.rests;
    all.insert(all.end(), s.discharges.begin(), s.discharges.end());
    const auto fit = fit_thermal_resistance(s.rec, all, kA, kC);
    EXPECT_EQ(fit.ambient_source, "intercept per range");
    EXPECT_NEAR(fit.r_th_flux_k_per_w, kR, 0.02 * kR) << fit.note;
    EXPECT_GT(fit.r_th_flux_se_k_per_w, 0.0);
    EXPECT_NEAR(fit.r_th_tau_k_per_w, kR, 0.03 * kR) << fit.note;
    EXPECT_NEAR(fit.tau_s, kR * kC, 0.03 * kR * kC);
    EXPECT_GT(fit.r_th_tau_se_k_per_w, 0.0);
    EXPECT_EQ(fit.rests_used, 3u);  // the first rest does not cool: left out of (b)
    ASSERT_EQ(fit.rests.size(), 4u);
    EXPECT_FALSE(fit.rests[0].used);
    EXPECT_FALSE(fit.rests[0].reason.empty());
    for (std::size_t r = 1; r < 4; ++r) EXPECT_NEAR(fit.rests[r].t_inf_c, kAmb, 0.02);
    EXPECT_FALSE(fit.disagree) << fit.note;
    EXPECT_LT(std::abs(fit.relative_difference), 0.05);
    ASSERT_EQ(fit.ambient_per_range_c.size(), all.size());
    for (std::size_t r = 1; r < all.size(); ++r) EXPECT_NEAR(fit.ambient_per_range_c[r], kAmb, 0.1);
}

TEST(ThermalResistance, GivenAmbientAndAmbientColumn) {
    Synth s = standard(22);
    ThermalResistanceOptions opt;
    opt.ambient_c = kAmb;
    auto fit = fit_thermal_resistance(s.rec, s.discharges, kA, kC, opt);  // heating only: (a) works, (b) needs a rest
    EXPECT_EQ(fit.ambient_source, "given");
    EXPECT_NEAR(fit.r_th_flux_k_per_w, kR, 0.02 * kR);
    EXPECT_TRUE(std::isnan(fit.r_th_tau_k_per_w));
    EXPECT_NE(fit.note.find("needs a rest"), std::string::npos) << fit.note;

    s.rec.ambient_c = s.ambient;
    fit = fit_thermal_resistance(s.rec, s.discharges, kA, kC);
    EXPECT_EQ(fit.ambient_source, "ambient column");
    EXPECT_NEAR(fit.r_th_flux_k_per_w, kR, 0.02 * kR);
}

TEST(ThermalResistance, SensorGainErrorIsFlaggedAsDisagreement) {
    // The sensor reads 70 % of the real flux: R_th from the flux is 1/0.7 too high; the time constant is not.
    const Synth s = standard(23, 0.7);
    const auto fit = fit_thermal_resistance(s.rec, s.rests, kA, kC);
    EXPECT_NEAR(fit.r_th_flux_k_per_w, kR / 0.7, 0.03 * kR / 0.7);
    EXPECT_NEAR(fit.r_th_tau_k_per_w, kR, 0.03 * kR);
    EXPECT_TRUE(fit.disagree);
    EXPECT_GT(fit.relative_difference, 0.15);
    EXPECT_NE(fit.note.find("DISAGREE"), std::string::npos) << fit.note;
}

TEST(ThermalResistance, PropagatesCthUncertainty) {
    const Synth s = standard(24);
    ThermalResistanceOptions opt;
    opt.c_th_se_j_per_k = 0.1 * kC;
    const auto fit = fit_thermal_resistance(s.rec, s.rests, kA, kC, opt);
    EXPECT_GT(fit.r_th_tau_se_k_per_w, 0.09 * fit.r_th_tau_k_per_w);
}

TEST(EntropicCoefficient, RecoversEhcAtOneC) {
    // 1C discharge from full to ~5 %: here the reversible heat is comparable to the Joule heat.
    const Synth s = make({{300, 0}, {3420, -4.5}, {600, 0}}, 0.2, 0.002, 1.0, 31);
    const auto [ocv_soc, ocv_v] = ocv_table();
    std::vector<double> grid;
    for (int k = 0; k <= 10; ++k) grid.push_back(0.1 * k);
    const auto fit = fit_entropic_coefficient(s.rec, s.discharges[0], s.soc, ocv_soc, ocv_v, kC, kA, grid);
    ASSERT_EQ(fit.ehc_v_per_k.size(), grid.size());
    EXPECT_FALSE(fit.has_data[0]) << fit.note;  // SOC 0..5 % never reached
    EXPECT_TRUE(std::isnan(fit.ehc_v_per_k[0]));
    for (std::size_t j = 1; j < grid.size(); ++j) {
        ASSERT_TRUE(fit.has_data[j]) << "SOC " << grid[j];
        // Bin medians of a curved EHC: compare with the truth at the grid point; 0.02 mV/K.
        EXPECT_NEAR(fit.ehc_v_per_k[j], ehc_of(grid[j]), 2e-5) << "SOC " << grid[j];
        EXPECT_GE(fit.spread_v_per_k[j], 0.0);
        EXPECT_GT(fit.samples[j], 100u);
    }
    EXPECT_LT(fit.joule_share, 0.9);
}

// The same 1C discharge logged every 20 s (a cycler's time condition): the 30 s derivative window held a single row;
// it now spans four, and every 20 % bin keeps its 36 rows.
TEST(EntropicCoefficient, RecoversEhcFromADischargeLoggedEveryTwentySeconds) {
    const Synth s = make({{300, 0}, {3420, -4.5}, {600, 0}}, 20.0, 0.002, 1.0, 32);
    const auto [ocv_soc, ocv_v] = ocv_table();
    std::vector<double> grid;
    for (int k = 0; k <= 5; ++k) grid.push_back(0.2 * k);
    const auto fit = fit_entropic_coefficient(s.rec, s.discharges[0], s.soc, ocv_soc, ocv_v, kC, kA, grid);
    ASSERT_EQ(fit.ehc_v_per_k.size(), grid.size());
    for (std::size_t j = 1; j + 1 < grid.size(); ++j) {
        ASSERT_TRUE(fit.has_data[j]) << "SOC " << grid[j] << ": " << fit.note;
        EXPECT_NEAR(fit.ehc_v_per_k[j], ehc_of(grid[j]), 3e-5) << "SOC " << grid[j];
    }
}

// A C/40 discharge (a slow capacity or OCV test) with a thermocouple's noise: the cell warms by a few hundredths of
// a kelvin, so each row's dU/dT scatters by most of 1 mV/K, several times the value.
// Every bin's median must still be the cell's: rows must not be cut at a bound around zero (that cut more of the
// tail on the true value's side and pulled the bins towards zero, to a third of the truth on the plant).
TEST(EntropicCoefficient, RecoversEhcFromANoisySlowDischarge) {
    const double c40_a = kCap / 40.0;
    const Synth s = make({{300, 0}, {0.9 * 40 * 3600, -c40_a}, {600, 0}}, 0.5, 0.03, 0.3, 33);
    const auto [ocv_soc, ocv_v] = ocv_table();
    std::vector<double> grid;
    for (int k = 2; k <= 9; ++k) grid.push_back(0.1 * k);
    const auto fit = fit_entropic_coefficient(s.rec, s.discharges[0], s.soc, ocv_soc, ocv_v, kC, kA, grid);
    for (std::size_t j = 0; j < grid.size(); ++j) {
        ASSERT_TRUE(fit.has_data[j]) << "SOC " << grid[j];
        EXPECT_GT(fit.spread_v_per_k[j], 6e-4) << "the case: rows scatter far beyond the value";
        // The synthetic sensor's zero offset (kFluxOffset, 1.6 mW over the can) reads as reversible heat at this
        // current (-0.047 mV/K): nothing in one discharge tells the two apart. The rest must be the cell's.
        const double offset_v_per_k = -kFluxOffset * kA / (c40_a * (kAmb + kZeroCelsiusK));
        std::printf("SOC %.1f: fit %+.4f truth %+.4f with the offset %+.4f mV/K\n", grid[j], 1e3 * fit.ehc_v_per_k[j],
                    1e3 * ehc_of(grid[j]), 1e3 * (ehc_of(grid[j]) + offset_v_per_k));
        EXPECT_NEAR(fit.ehc_v_per_k[j], ehc_of(grid[j]) + offset_v_per_k, 2e-5) << "SOC " << grid[j];
    }
}

TEST(EntropicCoefficient, FourCIsFlaggedAndStaysBounded) {
    const Synth s = make({{300, 0}, {840, -18.0}, {600, 0}}, 0.2, 0.003, 3.0, 32);
    std::vector<double> ocv_soc{0.1, 0.5, 1.0}, ocv_v;
    for (double x : ocv_soc) ocv_v.push_back(ocv_of(x));  // a coarse table: the OCV error shows up as EHC error
    std::vector<double> grid;
    for (int k = 0; k <= 10; ++k) grid.push_back(0.1 * k);
    const auto fit = fit_entropic_coefficient(s.rec, s.discharges[0], s.soc, ocv_soc, ocv_v, kC, kA, grid);
    EXPECT_GT(fit.joule_share, 0.6);
    EXPECT_NE(fit.note.find("Joule heat dominates"), std::string::npos) << fit.note;
    EXPECT_TRUE(fit.extrapolated_ocv[0]);
    for (std::size_t j = 0; j < grid.size(); ++j)
        if (fit.has_data[j]) {
            EXPECT_LE(std::abs(fit.ehc_v_per_k[j]), 1e-3);
        }
}

TEST(EntropicCoefficient, RejectsInconsistentInput) {
    const Synth s = make({{100, 0}, {100, -4.5}}, 0.5, 0.0, 0.0, 33);
    const std::vector<double> grid{0.5};
    EXPECT_THROW(fit_entropic_coefficient(s.rec, s.discharges[0], {0.5}, {0, 1}, {3, 4}, kC, kA, grid), InputError);
    EXPECT_THROW(fit_entropic_coefficient(s.rec, s.discharges[0], s.soc, {1, 0}, {3, 4}, kC, kA, grid), InputError);
    EXPECT_THROW(fit_entropic_coefficient(s.rec, s.discharges[0], s.soc, {0, 1}, {3, 4}, kC, kA, {}), InputError);
}

TEST(ChargeThroughput, HoldAndTrapezoid) {
    Recording rec;
    // Rest row, then 3600 s at -4.5 A sampled every 1 s, then a rest row.
    for (int k = 0; k <= 3602; ++k) {
        rec.time_s.push_back(k);
        rec.current_a.push_back(k >= 1 && k <= 3601 ? -4.5 : 0.0);
        rec.voltage_v.push_back(3.7);
    }
    // Hold: I[k] over (t[k-1], t[k]]: rows 1..3601 give 3601 s of current.
    EXPECT_NEAR(charge_throughput_ah(rec, {0, rec.size()}), -4.5 * 3601 / 3600.0, 1e-12);
    EXPECT_NEAR(charge_throughput_ah(rec, {1, 3602}), -4.5 * 3601 / 3600.0, 1e-12);  // row 1's interval counts
    // Trapezoid: the two edge intervals count half.
    EXPECT_NEAR(charge_throughput_ah(rec, {0, rec.size()}, CurrentIntegration::Trapezoid), -4.5 * 3601 / 3600.0,
                1e-12);
    EXPECT_NEAR(charge_throughput_ah(rec, {1, 3602}, CurrentIntegration::Trapezoid), -4.5, 1e-12);
    EXPECT_EQ(charge_throughput_ah(rec, {5, 5}), 0.0);
    EXPECT_NEAR(pilot_discharge_capacity_ah(rec, {1, 3602}), 4.5 * 3601 / 3600.0, 1e-12);
    rec.current_a.assign(rec.size(), 1.0);
    EXPECT_THROW(pilot_discharge_capacity_ah(rec, {1, 3602}), InputError);
}
