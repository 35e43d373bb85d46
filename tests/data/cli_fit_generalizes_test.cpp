// Issue 11's acceptance on real data, through the command line as a user runs it:
//  - the P45B characterization handed in three ways (merged by `import`, as separate files, in another order)
//    gives the same parameters and the same Random-Walk prediction;
//  - a second real cell (Panasonic NCR18650PF: another chemistry, discharge-only pulses at five currents, no
//    heat flux sensor) is fitted with no setting chosen for it, and predicts drive cycles it never saw.
// The bounds below are what the fit holds today; the closing note of the issue states the targets and which are
// met. Every figure is printed.
#include <gtest/gtest.h>

#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "support/command.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const fs::path kShared = fs::path(CELLBENCH_SHARED_DIR) / "data";

using CliRun = cellbench::test::CommandRun;
using cellbench::test::read_json;
CliRun run(const std::string& args) { return cellbench::test::run_cellbench(args); }

fs::path temp_dir(const std::string& name) {
    auto d = fs::temp_directory_path() / ("cellbench-" + name + "-" + std::to_string(::getpid()));
    fs::create_directories(d);
    return d;
}

// Voltage and temperature RMS of `simulate` (NaN for a quantity the recording lacks).
std::pair<double, double> simulate_rms(const fs::path& params, const fs::path& recording, const fs::path& out) {
    const auto r = run("simulate --params " + params.string() + " " + recording.string() + " --json " + out.string());
    EXPECT_EQ(r.status, 0) << r.output;
    if (r.status != 0) return {NAN, NAN};
    const auto m = read_json(out);
    // Issue 11's report by SOC band and current band, from the metrics' bands (each the RMS and the bias).
    for (const char* key : {"voltage_by_soc_band", "voltage_by_current_band"}) {
        EXPECT_TRUE(m.contains(key) && m[key].is_array() && !m[key].empty()) << key;
        if (!m.contains(key)) continue;
        std::printf("%s %s:", recording.filename().string().c_str(), key);
        for (const auto& b : m[key])
            std::printf("  %s %.1f mV (bias %+.1f)", b["band"].get<std::string>().c_str(),
                        1e3 * b["voltage_rms_v"].get<double>(), 1e3 * b["voltage_mean_v"].get<double>());
        std::printf("\n");
    }
    const double v = m["voltage"]["rms_v"].is_number() ? m["voltage"]["rms_v"].get<double>() : NAN;
    const double t = m["temperature"]["rms_c"].is_number() ? m["temperature"]["rms_c"].get<double>() : NAN;
    return {v, t};
}

TEST(FitGeneralizes, EveryArrangementOfTheP45BFilesGivesTheSameParametersAndPrediction) {
    const fs::path d = kShared / "p45b";
    if (!fs::exists(d / "hppc_1c_30degC.bdf.csv")) GTEST_SKIP() << "no P45B data in " << d;
    const auto o = temp_dir("arrangements");
    ASSERT_EQ(run("import --neware " + (d / "hppc_1c_30degC_neware.csv").string() + " --bdf " +
                  (d / "hppc_1c_30degC.bdf.csv").string() + " -o " + (o / "merged.bdf.csv").string())
                  .status,
              0);
    ASSERT_EQ(run("import --neware " + (d / "hppc_1c_30degC_neware.csv").string() + " -o " +
                  (o / "neware.bdf.csv").string())
                  .status,
              0);
    ASSERT_EQ(run("import --neware " + (d / "rw_30degC_neware.csv").string() + " --dewesoft " +
                  (d / "rw_30degC_dewesoft.csv").string() + " -o " + (o / "rw.bdf.csv").string())
                  .status,
              0);
    const std::string cc = (d / "cc_4c_30degC.bdf.csv").string(), bdf = (d / "hppc_1c_30degC.bdf.csv").string();
    const std::vector<std::string> arrangements = {
        (o / "merged.bdf.csv").string() + " " + cc,
        (o / "neware.bdf.csv").string() + " " + bdf + " " + cc,
        cc + " " + bdf + " " + (o / "neware.bdf.csv").string(),
    };
    std::vector<json> params;
    std::vector<double> rw_v;
    for (std::size_t a = 0; a < arrangements.size(); ++a) {
        const auto p = o / ("p" + std::to_string(a) + ".json");
        const auto r = run("fit " + arrangements[a] + " -o " + p.string());
        ASSERT_EQ(r.status, 0) << r.output;
        params.push_back(read_json(p));
        const auto [v, t] = simulate_rms(p, o / "rw.bdf.csv", o / "m.json");
        const auto [v4, t4] = simulate_rms(p, cc, o / "m4.json");
        std::printf("arrangement %zu: Random Walk %.2f mV / %.3f degC, 4C discharge %.2f mV\n", a, 1e3 * v, t, 1e3 * v4);
        rw_v.push_back(v);
        EXPECT_LT(t, 1.0) << "Random Walk temperature RMS (issue 11: <= 1.0 degC)";
        // Issue 11: better than the per-pulse-set fit's 150 mV. It was 19 mV while the global fit let R0 absorb the
        // 4C discharge's slow error (R0 then read 5-9 % above Table 3.2); with R0 held to the steps the error
        // left sits in the last 150 s of the discharge, below 20 % SOC.
        EXPECT_LT(v4, 0.050) << "4C discharge voltage RMS (per-pulse-set fit: 150 mV)";
        EXPECT_LT(v, 0.025) << "Random Walk voltage RMS (issue 11: <= 25 mV; before: 40.0 mV)";
    }
    // The characterization recording itself, simulated with its own fit: the merged HPPC starts rested at 3.303 V
    // (SOC 10.8 % by the OCV table) and charges 3.63 Ah to full before its first pulse, so its start is counted
    // back from that full charge (4 %). From the first voltage it ran 6-7 % high all along, past 100 % at the
    // top, and missed by 83 mV RMS.
    {
        const auto [v, t] = simulate_rms(o / "p0.json", o / "merged.bdf.csv", o / "mh.json");
        const auto m = read_json(o / "mh.json");
        std::printf("merged HPPC with its own fit: voltage %.2f mV, from SOC %.3f (%s)\n", 1e3 * v,
                    m["initial_soc"].get<double>(), m["initial_soc_source"].get<std::string>().c_str());
        EXPECT_EQ(m["initial_soc_source"].get<std::string>().rfind("counted back from the full charge", 0), 0u)
            << m["initial_soc_source"];
        EXPECT_LT(v, 0.025) << "the HPPC simulated with its own fit";
    }
    for (std::size_t a = 1; a < params.size(); ++a) {
        EXPECT_NEAR(rw_v[a], rw_v[0], 1e-3);
        ASSERT_EQ(params[a]["soc"], params[0]["soc"]);
        for (const char* dir : {"discharge", "charge"})
            for (const char* q : {"r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f"})
                for (std::size_t k = 0; k < params[0]["soc"].size(); ++k) {
                    const double x = params[a][dir][q][k], y = params[0][dir][q][k];
                    // Issue 11 asks 1 %. The fit splices the files handed in separately exactly as `import` merges
                    // them (same rows, same microsecond clock), so the arrangements agree far inside it.
                    EXPECT_NEAR(x, y, 0.01 * std::abs(y)) << dir << " " << q << " at " << params[0]["soc"][k];
                }
    }
    // Discharge R0 against the thesis' Table 3.2 (row "R0 DA", mOhm, 20..90 % SOC): issue 11 asks 5 %.
    const std::map<double, double> table32 = {{0.2, 7.37}, {0.3, 7.28}, {0.4, 7.30}, {0.5, 7.34},
                                              {0.6, 7.38}, {0.7, 7.36}, {0.8, 7.39}, {0.9, 7.50}};
    std::size_t compared = 0;
    for (std::size_t a = 0; a < params.size(); ++a) {
        const auto& p = params[a];
        for (std::size_t k = 0; k < p["soc"].size(); ++k) {
            const double s = p["soc"][k];
            for (const auto& [soc, r0] : table32)
                if (std::abs(s - soc) < 1e-6) {
                    const double got = 1e3 * p["discharge"]["r0_ohm"][k].get<double>();
                    if (a == 0) std::printf("R0 discharge at %.0f %%: %.3f mOhm (Table 3.2: %.2f, %+.1f %%)\n", 100 * s, got, r0,
                                            100 * (got / r0 - 1));
                    EXPECT_NEAR(got, r0, 0.05 * r0) << "arrangement " << a << ", SOC " << s;
                    ++compared;
                }
        }
    }
    EXPECT_EQ(compared, table32.size() * params.size());
    std::error_code ec;
    fs::remove_all(o, ec);
}

// A test split into two files (a cycler's export cut in parts): the P45B HPPC cut at the long rest nearest its
// middle, each part's test time from 0 as a cycler writes it, handed in second part first. Before, each part was
// anchored at SOC 1: capacity 1.89 Ah instead of 3.79 and the Random Walk predicted at 1369 mV, with no error.
// The parts are joined as one test and give the whole file's parameters exactly; the second part alone is fitted
// with the stated assumption that it starts full.
TEST(FitGeneralizes, TheP45BHppcSplitIntoTwoFilesFitsAsTheWholeFile) {
    const fs::path d = kShared / "p45b";
    if (!fs::exists(d / "hppc_1c_30degC.bdf.csv")) GTEST_SKIP() << "no P45B data in " << d;
    const auto o = temp_dir("split");
    std::ifstream in(d / "hppc_1c_30degC.bdf.csv");
    std::string header, line;
    std::getline(in, header);
    std::vector<std::string> rows;
    while (std::getline(in, line)) rows.push_back(line);
    auto field = [](const std::string& row, int col) {
        std::size_t b = 0;
        for (int c = 0; c < col; ++c) b = row.find(',', b) + 1;
        return std::stod(row.substr(b, row.find(',', b) - b));
    };
    std::size_t cut = rows.size() / 2;  // inside a rest: 60 s at rest on either side (0.1 s rows)
    auto at_rest = [&](std::size_t k) {
        for (std::size_t j = k - 600; j <= k + 600; ++j)
            if (field(rows[j], 2) != 0.0) return false;
        return true;
    };
    while (cut + 600 < rows.size() && !at_rest(cut)) ++cut;
    ASSERT_LT(cut + 600, rows.size());
    {
        std::ofstream a(o / "part1.bdf.csv"), b(o / "part2.bdf.csv");
        a << header << "\n";
        for (std::size_t k = 0; k < cut; ++k) a << rows[k] << "\n";
        b << header << "\n";
        const double t0 = field(rows[cut], 0);
        for (std::size_t k = cut; k < rows.size(); ++k) {
            char t[32];
            std::snprintf(t, sizeof t, "%.3f", field(rows[k], 0) - t0);
            b << t << rows[k].substr(rows[k].find(',')) << "\n";
        }
    }
    const auto whole = run("fit " + (d / "hppc_1c_30degC.bdf.csv").string() + " -o " + (o / "whole.json").string());
    ASSERT_EQ(whole.status, 0) << whole.output;
    const auto parts = run("fit " + (o / "part2.bdf.csv").string() + " " + (o / "part1.bdf.csv").string() + " -o " +
                           (o / "parts.json").string());
    ASSERT_EQ(parts.status, 0) << parts.output;
    EXPECT_NE(parts.output.find("part2.bdf.csv continues"), std::string::npos) << parts.output;
    const auto pw = read_json(o / "whole.json"), pp = read_json(o / "parts.json");
    std::printf("whole file: capacity %.4f Ah; its two parts: %.4f Ah\n", pw["capacity_ah"].get<double>(),
                pp["capacity_ah"].get<double>());
    EXPECT_EQ(pp, pw) << "the two parts give other parameters than the whole file";
    // The second part alone: nothing in it says it does not start full; the fit says what it took.
    const auto second = run("fit " + (o / "part2.bdf.csv").string() + " -o " + (o / "second.json").string());
    EXPECT_NE(second.output.find("SOC 100 % taken at its first row"), std::string::npos) << second.output;
    std::error_code ec;
    fs::remove_all(o, ec);
}

// The same HPPC as a coarse logger writes it, one row every 10 s (a 10 s pulse is one row): the fit runs, its
// capacity stays near the fine file's, and nothing is printed outside the command's own log. Before, Ceres wrote
// "Terminating: Residual and Jacobian evaluation failed" from pulse fits started where their cost was not finite,
// under glog's "Logging before InitGoogleLogging()" banner.
TEST(FitGeneralizes, TheP45BHppcLoggedEveryTenSecondsFitsWithoutStrayOutput) {
    const fs::path d = kShared / "p45b";
    if (!fs::exists(d / "hppc_1c_30degC.bdf.csv")) GTEST_SKIP() << "no P45B data in " << d;
    const auto o = temp_dir("coarse");
    {
        std::ifstream in(d / "hppc_1c_30degC.bdf.csv");
        std::ofstream out(o / "coarse.bdf.csv");
        std::string line;
        std::getline(in, line);
        out << line << "\n";
        double last = -1e9;
        while (std::getline(in, line)) {
            const double t = std::stod(line.substr(0, line.find(',')));
            if (t - last >= 10.0 - 1e-6) out << line << "\n", last = t;
        }
    }
    const auto r = run("fit " + (o / "coarse.bdf.csv").string() + " -o " + (o / "p.json").string());
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_EQ(r.output.find("Terminating"), std::string::npos) << r.output;
    EXPECT_EQ(r.output.find("InitGoogleLogging"), std::string::npos) << r.output;
    const auto fine = run("fit " + (d / "hppc_1c_30degC.bdf.csv").string() + " -o " + (o / "fine.json").string());
    ASSERT_EQ(fine.status, 0) << fine.output;
    const double coarse_ah = read_json(o / "p.json")["capacity_ah"], fine_ah = read_json(o / "fine.json")["capacity_ah"];
    std::printf("capacity logged every 10 s: %.4f Ah, every 0.1 s: %.4f Ah\n", coarse_ah, fine_ah);
    EXPECT_NEAR(coarse_ah, fine_ah, 0.05 * fine_ah);
    std::error_code ec;
    fs::remove_all(o, ec);
}

void fit_and_predict(const std::string& temperature, const std::vector<std::string>& extra,
                     const std::vector<std::pair<std::string, double>>& cycles, bool check_temperature) {
    const fs::path d = kShared / "panasonic-18650pf";
    if (!fs::exists(d / ("hppc_5pulse_" + temperature + ".bdf.csv"))) GTEST_SKIP() << "no Panasonic data in " << d;
    const auto o = temp_dir("panasonic" + temperature);
    std::string files = (d / ("hppc_5pulse_" + temperature + ".bdf.csv")).string();
    for (const auto& e : extra) files += " " + (d / e).string();
    const auto r = run("fit " + files + " --cell \"Panasonic NCR18650PF\" -o " + (o / "p.json").string() + " --json " +
                       (o / "s.json").string());
    ASSERT_EQ(r.status, 0) << r.output;
    const auto s = read_json(o / "s.json");
    std::printf("%s: capacity %.4f Ah (%s)\n", temperature.c_str(), s["capacity"]["capacity_ah"].get<double>(),
                s["capacity"]["method"].get<std::string>().c_str());
    // The HPPC's long rests (20-60 min) relax for their whole length: the fit identifies a slow pair from them.
    ASSERT_TRUE(s["global"]["extra_rc"].is_object()) << s["global"].dump();
    std::printf("%s: slow pair %s\n", temperature.c_str(), s["global"]["extra_rc"].dump().c_str());
    EXPECT_TRUE(s["global"]["extra_rc"]["used"].get<bool>());
    // Every fitted global value carries its uncertainty, and one larger than the value itself is flagged (the
    // activation energy was not, session 35: P45B 12.0 +- 19.6 kJ/mol shown as fine).
    const auto& g = s["global"];
    auto member = [](const json& parent, const char* key) { return parent.is_object() ? parent.value(key, json()) : json(); };
    const std::vector<std::pair<std::string, json>> globals = {
        {"activation energy", member(g["resistance_temperature"], "activation_energy_j_per_mol")},
        {"exchange current", member(g["resistance_current"], "exchange_current_a")},
        {"slow pair R3", member(g["extra_rc"], "r_ohm")},
        {"step lag", g["step_lag"]}};
    for (const auto& [name, v] : globals) {
        if (v.is_null() && name != "step lag") continue;  // not identified from these recordings (a note says so)
        ASSERT_TRUE(v.is_object() && v.contains("value") && v.contains("sd")) << name << ": " << v.dump();
        std::printf("%s: %s %s\n", temperature.c_str(), name.c_str(), v.dump().c_str());
        if (v["sd"].is_number() && v["value"].get<double>() > 0 && v["sd"].get<double>() > v["value"].get<double>()) {
            const auto flags = v.value("flags", json::array());
            EXPECT_NE(std::find(flags.begin(), flags.end(), "uncertain"), flags.end()) << name << ": " << v.dump();
        }
    }
    for (const auto& [c, bound_v] : cycles) {
        const auto [v, t] = simulate_rms(o / "p.json", d / (c + "_" + temperature + ".bdf.csv"), o / "m.json");
        std::printf("%s %s: voltage RMS %.2f mV, surface temperature RMS %.3f degC\n", c.c_str(), temperature.c_str(),
                    1e3 * v, t);
        EXPECT_LT(v, bound_v) << c;
        if (check_temperature) {
            EXPECT_LT(t, 1.0) << c;
        }
    }
    std::error_code ec;
    fs::remove_all(o, ec);
}

TEST(FitGeneralizes, SecondCellAt25degCPredictsEveryDriveCycle) {
    // Issue 11's target: 25 mV each.
    fit_and_predict("25degC", {"ocv_c20_discharge_25degC.bdf.csv", "discharge_1c_2_25degC.bdf.csv"},
                    {{"us06", 0.025}, {"hwfet_a", 0.025}, {"hwfet_b", 0.025}, {"la92", 0.025}, {"nn", 0.025}}, true);
}

TEST(FitGeneralizes, SecondCellAt25degCWithEveryCharacterizationFilePredictsEveryDriveCycle) {
    // All five 25 degC characterization files, as a user would hand them in. The C/20 charge (a pseudo-OCV
    // test) sits above the discharge OCV by the hysteresis: read as the charge resistances (140 mOhm at
    // 0.145 A) it made every regen pulse of the drive cycles miss (US06 186 mV, LA92 151 mV). The first 1C
    // discharge is logged under load from its first row: its SOC counted from that voltage started 7 % low,
    // and its heat with it (R_th 11.3 instead of 7 K/W; US06 surface temperature 1.7 degC RMS).
    fit_and_predict("25degC",
                    {"ocv_c20_discharge_25degC.bdf.csv", "ocv_c20_charge_25degC.bdf.csv",
                     "discharge_1c_1_25degC.bdf.csv", "discharge_1c_2_25degC.bdf.csv"},
                    {{"us06", 0.025}, {"hwfet_a", 0.025}, {"hwfet_b", 0.025}, {"la92", 0.025}, {"nn", 0.025}}, true);
}

TEST(FitGeneralizes, SecondCellAt25degCWithADriveCycleAmongItsFilesPredictsTheOthers) {
    // A drive cycle handed in with the characterization is used for what it holds. Its log's voltage lags its
    // current by more than a sample (5 mOhm in the first 0.1 s of a step, 16 mOhm in the next): fitted with a
    // step residual at each of its 3000 steps, it pinned the tables to the 5 mOhm and predicted HWFET at 37 mV and
    // LA92 at 32 mV (16.6 and 10.5 without US06). Now its steps are fitted as levels only.
    fit_and_predict("25degC",
                    {"ocv_c20_discharge_25degC.bdf.csv", "discharge_1c_2_25degC.bdf.csv", "us06_25degC.bdf.csv"},
                    {{"hwfet_a", 0.025}, {"hwfet_b", 0.025}, {"la92", 0.025}, {"nn", 0.025}}, true);
}

TEST(FitGeneralizes, SecondCellAt0degCPredictsEveryDriveCycle) {
    // Issue 11's target: 40 mV each. US06 needs both the slow pair the HPPC's long rests show and the temperature
    // dependence its 6C pulses' 4 K of heating show (47.9 mV with neither; docs/model.md).
    // The 0 degC recordings have no ambient column; la92 starts warm (18 degC) and cools in its first rest, from
    // which simulate reads the ambient (0.44 degC). The surface temperature is printed, not checked: US06's misses
    // by 1.16 degC RMS (session 53), above the 1 degC the 25 degC cycles are held to; HWFET and LA92 by 0.23.
    fit_and_predict("0degC", {}, {{"us06", 0.040}, {"hwfet", 0.040}, {"la92", 0.040}}, false);
}

}  // namespace
