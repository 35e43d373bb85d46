// Thermal fits, capacity and clock alignment on the real P45B recordings (read-only, under CELLBENCH_SHARED_DIR).
// Asserts the thesis' C_th within 10 %, the pilot capacity, the Random Walk clock offset in the range verified
// when this test was written, and only physically certain bounds for R_th and dU/dT; prints every number.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "cellbench/estimator/align.hpp"
#include "cellbench/estimator/thermal_fit.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/dewesoft_export.hpp"
#include "cellbench/protocol/neware_export.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

constexpr double kArea = 5.311e-3;       // pi*d*L + 2*pi*(d/2)^2, d = 21 mm, L = 70 mm
constexpr double kThesisCth = 63.3;      // J/K (thesis 4.2.1)
constexpr double kThesisRth = 5.26;      // K/W (thesis eq. 4.9)
constexpr double kThesisCapacity = 3.816;  // Ah, 1C pilot discharge (data README)

std::string data_path(const std::string& name) {
    return (std::filesystem::path(CELLBENCH_SHARED_DIR) / "data" / "p45b" / name).string();
}

bool read_text(const std::string& path, std::string& out) {
    std::ifstream f(path, std::ios::binary);
    if (!f) return false;
    std::stringstream ss;
    ss << f.rdbuf();
    out = ss.str();
    return true;
}

#define LOAD_OR_SKIP(var, name)                                                                         \
    std::string var;                                                                                    \
    if (!read_text(data_path(name), var)) GTEST_SKIP() << "real data not found: " << data_path(name)    \
                                                       << " (CELLBENCH_SHARED_DIR=" CELLBENCH_SHARED_DIR ")"

// Rows with zero current lasting at least min_s (the HPPC's 1 h rests). Simple on purpose: the test should not
// depend on the segmentation under test elsewhere.
std::vector<RowRange> zero_current_runs(const Recording& rec, double min_s) {
    std::vector<RowRange> out;
    std::size_t begin = 0;
    bool in = false;
    for (std::size_t k = 0; k <= rec.size(); ++k) {
        const bool rest = k < rec.size() && std::abs(rec.current_a[k]) < 1e-3;
        if (rest && !in) begin = k, in = true;
        if (!rest && in) {
            if (rec.time_s[k - 1] - rec.time_s[begin] >= min_s) out.push_back({begin, k});
            in = false;
        }
    }
    return out;
}

// Thesis OCV table (thesis_ocv_by_soc.csv), ascending SOC.
const std::vector<double> kOcvSoc{0.10418993620455092, 0.20376210042271843, 0.3033356198712842, 0.40290933538585776,
                                  0.5024834976236387,  0.6020573378184588,  0.7013378793330925, 0.8009138101656997,
                                  0.9004905452206128,  1.000000181634838};
const std::vector<double> kOcvV{3.2899, 3.4568, 3.5318, 3.631, 3.716, 3.7923, 3.8721, 3.958, 4.05, 4.0975};

}  // namespace

TEST(ThermalData, HppcRestsGiveThesisThermalCapacityAndResistance) {
    LOAD_OR_SKIP(text, "hppc_1c_30degC.bdf.csv");
    const Recording rec = protocol::parse_bdf_csv(text, "hppc_1c_30degC.bdf.csv");
    const auto rests = zero_current_runs(rec, 1800.0);
    ASSERT_EQ(rests.size(), 11u);  // the 1 h rest after the full charge and after each 10 % SOC step

    const auto c = fit_thermal_capacity(rec, rests, kArea);
    std::printf("[thermal] C_th = %.2f +- %.2f J/K (thesis %.1f), R^2 %.4f, %zu rows, %zu dropped\n  %s\n  per rest:",
                c.c_th_j_per_k, c.c_th_se_j_per_k, kThesisCth, c.r_squared, c.points, c.points_rejected,
                c.note.c_str());
    for (double v : c.per_rest_c_th_j_per_k) std::printf(" %.1f", v);
    std::printf("\n");
    EXPECT_NEAR(c.c_th_j_per_k, kThesisCth, 0.10 * kThesisCth);
    EXPECT_GT(c.r_squared, 0.95);
    EXPECT_EQ(c.rests_used, 11u);
    // Specific heat c = C_th / m (m = 70 g) must be a solid's: the literature spans 775..1182 J/(kg K) (Table 4.3).
    EXPECT_GT(c.c_th_j_per_k / 0.070, 700.0);
    EXPECT_LT(c.c_th_j_per_k / 0.070, 1300.0);

    ThermalResistanceOptions ro;
    ro.c_th_se_j_per_k = c.c_th_se_j_per_k;
    const auto r = fit_thermal_resistance(rec, rests, kArea, c.c_th_j_per_k, ro);
    std::printf("[thermal] 1C-HPPC rests: R_th (a) heat flow %.3f +- %.3f K/W (R^2 %.3f, ambient %s), (b) tau %.1f +- "
                "%.1f s -> %.3f +- %.3f K/W from %zu rests; thesis %.2f K/W\n  %s\n",
                r.r_th_flux_k_per_w, r.r_th_flux_se_k_per_w, r.flux_r_squared, r.ambient_source.c_str(), r.tau_s,
                r.tau_se_s, r.r_th_tau_k_per_w, r.r_th_tau_se_k_per_w, r.rests_used, kThesisRth, r.note.c_str());
    for (const auto& x : r.rests)
        std::printf("  rest at row %zu: tau %.1f +- %.1f s, T_inf %.3f degC, dT %.3f K %s\n", x.range.begin, x.tau_s,
                    x.tau_se_s, x.t_inf_c, x.delta_t_k, x.used ? "" : x.reason.c_str());
    // Physically certain: a 21700 cell in a chamber with fans has h between ~15 and ~100 W/(m^2 K), i.e.
    // R_th = 1/(h A) between ~1.9 and ~12.5 K/W, and a lumped cooling time constant of minutes.
    EXPECT_GT(r.r_th_flux_k_per_w, 1.9);
    EXPECT_LT(r.r_th_flux_k_per_w, 12.5);
    EXPECT_GT(r.r_th_tau_k_per_w, 1.9);
    EXPECT_LT(r.r_th_tau_k_per_w, 12.5);
    EXPECT_GE(r.rests_used, 3u);
    for (const auto& x : r.rests)
        if (x.used) {
            EXPECT_NEAR(x.t_inf_c, 29.5, 1.0);  // the chamber at 30 degC setpoint
        }
}

TEST(ThermalData, FourCDischargeResistanceAndEntropicCoefficient) {
    LOAD_OR_SKIP(text, "cc_4c_30degC.bdf.csv");
    const Recording rec = protocol::parse_bdf_csv(text, "cc_4c_30degC.bdf.csv");
    const RowRange all{0, rec.size()};

    // (a) only: a discharge has no rest. The cell starts in equilibrium with the chamber, so the first surface
    // temperature is the ambient; the intercept alternative is printed for comparison.
    ThermalResistanceOptions ro;
    ro.ambient_c = rec.surface_c.front();
    const auto r = fit_thermal_resistance(rec, {all}, kArea, kThesisCth, ro);
    const auto ri = fit_thermal_resistance(rec, {all}, kArea, kThesisCth);
    std::printf("[thermal] 4C discharge: R_th (a) %.3f +- %.3f K/W with ambient = initial %.2f degC (R^2 %.3f); "
                "%.3f K/W with the ambient fitted as intercept (%.2f degC)\n",
                r.r_th_flux_k_per_w, r.r_th_flux_se_k_per_w, ro.ambient_c, r.flux_r_squared, ri.r_th_flux_k_per_w,
                ri.ambient_per_range_c.empty() ? kNaN : ri.ambient_per_range_c[0]);
    EXPECT_GT(r.r_th_flux_k_per_w, 1.9);
    EXPECT_LT(r.r_th_flux_k_per_w, 12.5);
    EXPECT_TRUE(std::isnan(r.r_th_tau_k_per_w));

    // Entropic heat coefficient, SOC by Coulomb counting from full with the pilot capacity.
    std::vector<double> soc(rec.size());
    soc[0] = 1.0;
    for (std::size_t k = 1; k < rec.size(); ++k)
        soc[k] = soc[k - 1] + charge_throughput_ah(rec, {k, k + 1}) / kThesisCapacity;
    std::vector<double> grid;
    for (int k = 0; k <= 10; ++k) grid.push_back(0.1 * k);
    const auto e = fit_entropic_coefficient(rec, all, soc, kOcvSoc, kOcvV, kThesisCth, kArea, grid);
    std::printf("[thermal] 4C entropic heat coefficient (mV/K), median [spread] n:\n");
    for (std::size_t j = 0; j < grid.size(); ++j)
        std::printf("  SOC %.1f: %+.3f [%.3f] n=%zu%s\n", grid[j], 1e3 * e.ehc_v_per_k[j], 1e3 * e.spread_v_per_k[j],
                    e.samples[j], e.extrapolated_ocv[j] ? " (OCV extrapolated)" : "");
    std::printf("  %s\n", e.note.c_str());
    EXPECT_GT(e.joule_share, 0.6);
    EXPECT_NE(e.note.find("Joule heat dominates"), std::string::npos);
    for (std::size_t j = 1; j <= 9; ++j) {
        ASSERT_TRUE(e.has_data[j]) << "SOC " << grid[j];
        EXPECT_LE(std::abs(e.ehc_v_per_k[j]), 1e-3);  // bounded
    }
    // The sign pattern the thesis finds at every C-rate (Figure 4.5): exothermic on discharge at low SOC,
    // endothermic at high SOC.
    EXPECT_LT(e.ehc_v_per_k[2], 0.0);
    EXPECT_GT(e.ehc_v_per_k[8], 0.0);
}

TEST(ThermalData, PilotDischargeCapacity) {
    LOAD_OR_SKIP(text, "hppc_1c_30degC_neware.csv");
    const Recording rec = protocol::parse_neware_export(text, "hppc_1c_30degC_neware.csv");
    // The pilot: the first discharge longer than 10 min.
    std::size_t begin = 0, end = 0;
    for (std::size_t k = 0; k < rec.size() && end == 0; ++k) {
        if (rec.current_a[k] < -1.0 && (k == 0 || rec.current_a[k - 1] >= -1.0)) begin = k;
        if (rec.current_a[k] < -1.0 && (k + 1 == rec.size() || rec.current_a[k + 1] >= -1.0) &&
            rec.time_s[k] - rec.time_s[begin] > 600.0)
            end = k + 1;
    }
    ASSERT_GT(end, begin);
    const double hold = pilot_discharge_capacity_ah(rec, {begin, end});
    const double trap = pilot_discharge_capacity_ah(rec, {begin, end}, CurrentIntegration::Trapezoid);
    std::printf("[thermal] pilot 1C discharge rows [%zu, %zu), %.0f s, ends at %.3f V: %.4f Ah (hold), %.4f Ah "
                "(trapezoid); README %.3f Ah\n",
                begin, end, rec.time_s[end - 1] - rec.time_s[begin], rec.voltage_v[end - 1], hold, trap,
                kThesisCapacity);
    EXPECT_NEAR(rec.voltage_v[end - 1], 2.9, 0.02);
    EXPECT_NEAR(hold, kThesisCapacity, 0.01 * kThesisCapacity);
    EXPECT_NEAR(hold, trap, 1e-3);
}

TEST(ThermalData, RandomWalkClockOffset) {
    LOAD_OR_SKIP(neware_text, "rw_30degC_neware.csv");
    LOAD_OR_SKIP(dewe_text, "rw_30degC_dewesoft.csv");
    const Recording cyc = protocol::parse_neware_export(neware_text, "rw_30degC_neware.csv");
    const auto daq = protocol::parse_dewesoft_export(dewe_text, "rw_30degC_dewesoft.csv");
    ASSERT_FALSE(daq.type_t_c.empty());
    ASSERT_FALSE(daq.heat_flux_w_per_m2.empty());
    const auto al = estimate_clock_offset(cyc.time_s, cyc.current_a, daq.time_s, daq.type_t_c, daq.heat_flux_w_per_m2,
                                          kThesisCth, kArea, 1800.0);
    std::printf("[thermal] RW clock offset (cycler = DAQ + offset): %+.2f s +- %.1f s, r = %.4f, lag %.0f s; "
                "plain I^2: %+.2f s (r = %.4f)\n  %s\n",
                al.offset_s, al.uncertainty_s, al.correlation, al.lag_s, al.offset_no_lag_s, al.correlation_no_lag,
                al.note.c_str());
    // Verified when written: +5.6 s (r 0.905, lag 15 s, ridge +-3.6 s); plain I^2 -6.2 s (r 0.865). The 4C file
    // (one clock) shows the surface heat lagging the current step by ~13 s as a first-order response, which
    // puts the offset at ~+4.5 s on the same ridge.
    EXPECT_GT(al.offset_s, -2.0);
    EXPECT_LT(al.offset_s, 12.0);
    EXPECT_GT(al.correlation, 0.88);
    EXPECT_GT(al.offset_no_lag_s, -12.0);
    EXPECT_LT(al.offset_no_lag_s, 0.0);
    EXPECT_FALSE(al.at_search_limit);
    // The DAQ keeps recording ~1180 s of cool-down after the cycler stops: the overlap is the cycler's record.
    EXPECT_GT(al.overlap_s, 2500.0);
    EXPECT_LT(al.overlap_s, 2700.0);
}
