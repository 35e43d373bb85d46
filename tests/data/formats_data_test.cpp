// The format parsers on the real P45B bench recordings in shared/data/p45b (see its README.md).
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/dewesoft_export.hpp"
#include "cellbench/protocol/heat_flux.hpp"
#include "cellbench/protocol/neware_export.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <sstream>
#include <string>

namespace {

namespace fs = std::filesystem;
using cellbench::Recording;
using namespace cellbench::protocol;

const fs::path kDataDir = fs::path(CELLBENCH_SHARED_DIR) / "data" / "p45b";

// Skips the test when the shared recordings are not on this machine.
#define REQUIRE_DATA(file)                                                                                     \
    do {                                                                                                       \
        if (!fs::exists(kDataDir / (file)))                                                                    \
            GTEST_SKIP() << "real recordings not found: " << (kDataDir / (file)).string()                      \
                         << " (set CELLBENCH_SHARED_DIR to the shared/ folder that holds data/p45b)";          \
    } while (0)

std::string slurp(const std::string& file) {
    std::ifstream in(kDataDir / file, std::ios::binary);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

::testing::AssertionResult strictly_increasing(const std::vector<double>& t) {
    for (std::size_t i = 1; i < t.size(); ++i)
        if (!(t[i] > t[i - 1]))
            return ::testing::AssertionFailure() << "time not increasing at row " << i << ": " << t[i - 1] << " -> " << t[i];
    return ::testing::AssertionSuccess();
}

TEST(FormatsData, HppcBdfParsesWhole) {
    REQUIRE_DATA("hppc_1c_30degC.bdf.csv");
    const std::string text = slurp("hppc_1c_30degC.bdf.csv");
    BdfReadReport report;
    const auto start = std::chrono::steady_clock::now();
    const Recording rec = parse_bdf_csv(text, "hppc_1c_30degC.bdf.csv", &report);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::cout << "parse_bdf_csv: " << text.size() / 1e6 << " MB, " << rec.size() << " rows in " << seconds * 1e3
              << " ms\n";
    RecordProperty("parse_ms", static_cast<int>(seconds * 1e3));

    EXPECT_EQ(rec.size(), 436250u);
    EXPECT_EQ(report.rows, 436250u);
    EXPECT_TRUE(report.ignored_columns.empty());
    EXPECT_EQ(rec.repaired_timestamps, 0u);
    EXPECT_TRUE(strictly_increasing(rec.time_s));
    EXPECT_EQ(rec.time_s.front(), 0.0);
    EXPECT_NEAR(rec.time_s.back(), 0.1 * 436249, 1e-6);  // one clock, 0.1 s
    EXPECT_EQ(rec.step_type.size(), rec.size());
    EXPECT_EQ(rec.step_type.front(), "Rest");
    EXPECT_TRUE(rec.has_surface());
    EXPECT_TRUE(rec.has_heat_flux());
    EXPECT_FALSE(rec.has_ambient());
    // HPPC at 1C = 4.5 A: pulses are within a few per cent of +-4.5 A.
    const auto [lo, hi] = std::minmax_element(rec.current_a.begin(), rec.current_a.end());
    EXPECT_NEAR(*lo, -4.5, 0.2);
    EXPECT_NEAR(*hi, 4.5, 0.2);
}

TEST(FormatsData, Cc4cBdf) {
    REQUIRE_DATA("cc_4c_30degC.bdf.csv");
    const Recording rec = parse_bdf_csv(slurp("cc_4c_30degC.bdf.csv"), "cc_4c_30degC.bdf.csv");
    EXPECT_EQ(rec.size(), 7508u);
    EXPECT_EQ(rec.repaired_timestamps, 0u);
    EXPECT_TRUE(strictly_increasing(rec.time_s));
    // Discharge at 4C = 18 A is negative current (BDF: + charges the cell).
    EXPECT_NEAR(rec.current_a[rec.size() / 2], -18.0, 0.1);
    // README: the cell heats from 29.4 to 45.9 degC.
    const auto [cold, hot] = std::minmax_element(rec.surface_c.begin(), rec.surface_c.end());
    EXPECT_NEAR(*cold, 29.4, 0.1);
    EXPECT_NEAR(*hot, 45.9, 0.1);
}

TEST(FormatsData, HppcNewareExport) {
    REQUIRE_DATA("hppc_1c_30degC_neware.csv");
    const Recording rec = parse_neware_export(slurp("hppc_1c_30degC_neware.csv"), "hppc_1c_30degC_neware.csv");
    EXPECT_EQ(rec.size(), 75991u);
    // 31 rows repeat the stamp of the row before (step ends at 1 s resolution).
    EXPECT_EQ(rec.repaired_timestamps, 31u);
    EXPECT_TRUE(strictly_increasing(rec.time_s));
    ASSERT_EQ(rec.step_count.size(), rec.size());
    EXPECT_EQ(rec.step_count.front(), 1.0);

    // The pilot discharge is the first CC DChg step: integrating its current over the repaired time axis
    // must give the README's capacity (3.816 Ah; the export's own Capacity(Ah) column says 3.797 Ah).
    const auto first = std::find(rec.step_type.begin(), rec.step_type.end(), "CC DChg");
    ASSERT_NE(first, rec.step_type.end());
    const auto begin = static_cast<std::size_t>(first - rec.step_type.begin());
    double charge_as = 0.0;
    std::size_t i = begin + 1;
    for (; i < rec.size() && rec.step_count[i] == rec.step_count[begin]; ++i)
        charge_as += 0.5 * (rec.current_a[i] + rec.current_a[i - 1]) * (rec.time_s[i] - rec.time_s[i - 1]);
    std::cout << "pilot discharge: " << -charge_as / 3600.0 << " Ah over " << rec.time_s[i - 1] - rec.time_s[begin]
              << " s\n";
    EXPECT_NEAR(-charge_as / 3600.0, 3.816, 0.04);
    EXPECT_LT(rec.voltage_v[i - 1], 2.95) << "the pilot discharge ends at 2.9 V";
}

TEST(FormatsData, RandomWalkNewareExportGetsItsStampsRepairedWithoutDrift) {
    REQUIRE_DATA("rw_30degC_neware.csv");
    const Recording rec = parse_neware_export(slurp("rw_30degC_neware.csv"), "rw_30degC_neware.csv");
    EXPECT_EQ(rec.size(), 26505u);
    // 83 repeated stamps, the 0.1 s step back near row 1213 and the row after it that repeats 121.1 s.
    EXPECT_EQ(rec.repaired_timestamps, 85u);
    EXPECT_TRUE(strictly_increasing(rec.time_s));
    // No drift: the first and last stamps are as recorded, and Total Time ends at 00:44:01.
    EXPECT_EQ(rec.time_s.front(), 0.0);
    EXPECT_EQ(rec.time_s.back(), 2641.9);
    // Data rows 1212..1215 (file lines 1213..1216) hold Time(s) 121.0, 121.1, 121.0, 121.1 before repair.
    EXPECT_EQ(rec.time_s[1211], 121.0);
    EXPECT_EQ(rec.time_s[1212], 121.1);
    EXPECT_GT(rec.time_s[1213], 121.1);
    EXPECT_LT(rec.time_s[1214], 121.2);
    EXPECT_EQ(rec.time_s[1215], 121.2);
    // Date is read as UTC: 2025-05-23 09:35:38.
    ASSERT_EQ(rec.unix_time_s.size(), rec.size());
    EXPECT_EQ(rec.unix_time_s.front(), 1747992938.0);
    EXPECT_NEAR(rec.unix_time_s.back() - rec.unix_time_s.front(), rec.time_s.back(), 2.0);
    ASSERT_EQ(rec.step_count.size(), rec.size());
    EXPECT_EQ(rec.step_type.front(), "Rest");
    EXPECT_GT(rec.step_count.back(), 20.0);  // a random walk of many steps
}

TEST(FormatsData, DewesoftHeatFluxRecomputedFromTheThermopileAgreesWithDewesoft) {
    REQUIRE_DATA("rw_30degC_dewesoft.csv");
    const DewesoftExport d = parse_dewesoft_export(slurp("rw_30degC_dewesoft.csv"), "rw_30degC_dewesoft.csv");
    EXPECT_EQ(d.time_s.size(), 38241u);
    EXPECT_EQ(d.repaired_timestamps, 0u);
    EXPECT_TRUE(strictly_increasing(d.time_s));
    EXPECT_TRUE(d.t1_c.empty());
    EXPECT_TRUE(d.t2_c.empty());
    ASSERT_EQ(d.thermopile_v.size(), d.time_s.size());
    ASSERT_EQ(d.type_t_c.size(), d.time_s.size());
    ASSERT_EQ(d.heat_flux_w_per_m2.size(), d.time_s.size());

    // Relative error where the flux is clearly above the sensor's noise floor (|q| > 3 W/m^2; the recording
    // spans about -2 .. 374 W/m^2), absolute error everywhere.
    constexpr double kSignificantFluxWPerM2 = 3.0;
    double max_rel = 0.0, sum_rel = 0.0, max_abs = 0.0;
    std::size_t compared = 0;
    for (std::size_t i = 0; i < d.time_s.size(); ++i) {
        const double q = heat_flux_density_w_per_m2(d.thermopile_v[i], d.type_t_c[i], kFhf05ThesisSensitivityVPerWPerM2);
        const double q_dewe = d.heat_flux_w_per_m2[i];
        ASSERT_TRUE(std::isfinite(q)) << "row " << i;
        max_abs = std::max(max_abs, std::abs(q - q_dewe));
        if (std::abs(q_dewe) > kSignificantFluxWPerM2) {
            const double rel = std::abs(q - q_dewe) / std::abs(q_dewe);
            max_rel = std::max(max_rel, rel);
            sum_rel += rel;
            ++compared;
        }
    }
    std::cout << "heat flux vs DewesoftX: " << compared << " rows with |q| > 3 W/m^2, max relative error "
              << max_rel * 100 << " %, mean " << sum_rel / static_cast<double>(compared) * 100
              << " %; max absolute error over all rows " << max_abs << " W/m^2\n";
    EXPECT_GT(compared, d.time_s.size() / 2) << "most of the random walk carries a clear heat flux";
    EXPECT_LT(max_rel, 0.005);
    EXPECT_LT(max_abs, 0.05);
}

TEST(FormatsData, BdfWriteParseRoundTripOnARealRecording) {
    REQUIRE_DATA("cc_4c_30degC.bdf.csv");
    const Recording rec = parse_bdf_csv(slurp("cc_4c_30degC.bdf.csv"), "cc_4c_30degC.bdf.csv");
    std::ostringstream out;
    write_bdf_csv(out, rec);
    const Recording back = parse_bdf_csv(out.str(), "again.bdf.csv");
    EXPECT_EQ(back.time_s, rec.time_s);
    EXPECT_EQ(back.voltage_v, rec.voltage_v);
    EXPECT_EQ(back.current_a, rec.current_a);
    EXPECT_EQ(back.surface_c, rec.surface_c);
    EXPECT_EQ(back.heat_flux_w_per_m2, rec.heat_flux_w_per_m2);
}

}  // namespace
