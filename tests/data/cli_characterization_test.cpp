// Acceptance of the foundation on the real P45B recordings, through the `cellbench` command line exactly as a
// user runs it: import -> fit -> simulate, and the comparison with the thesis (Tables 3.2 and 5.2).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include <nlohmann/json.hpp>

#include "support/command.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const fs::path kData = fs::path(CELLBENCH_SHARED_DIR) / "data" / "p45b";
const fs::path kSource = CELLBENCH_SOURCE_DIR;

using CliRun = cellbench::test::CommandRun;
using cellbench::test::read_json;
CliRun run(const std::string& args) { return cellbench::test::run_cellbench(args); }

// One pipeline run shared by the tests of this file (it takes a few seconds).
class Characterization : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        if (!fs::exists(kData / "hppc_1c_30degC.bdf.csv")) return;
        dir_ = fs::temp_directory_path() / ("cellbench-data-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        const std::string d = kData.string() + "/", o = dir_.string() + "/";
        steps_.push_back(run("import --neware " + d + "hppc_1c_30degC_neware.csv --bdf " + d +
                             "hppc_1c_30degC.bdf.csv -o " + o + "hppc.bdf.csv"));
        steps_.push_back(run("import --neware " + d + "rw_30degC_neware.csv --dewesoft " + d +
                             "rw_30degC_dewesoft.csv -o " + o + "rw.bdf.csv"));
        steps_.push_back(run("fit " + o + "hppc.bdf.csv " + d + "cc_4c_30degC.bdf.csv -o " + o + "params.json --json " +
                             o + "summary.json"));
        steps_.push_back(run("simulate --params " + (kSource / "config/cells/p45b-thesis.json").string() + " " + o +
                             "rw.bdf.csv --json " + o + "thesis.metrics.json"));
        steps_.push_back(run("simulate --params " + o + "params.json " + o + "rw.bdf.csv --json " + o +
                             "fitted.metrics.json --out " + o + "fitted.sim.bdf.csv"));
    }
    static void TearDownTestSuite() {
        std::error_code ec;
        if (!dir_.empty()) fs::remove_all(dir_, ec);
    }
    void SetUp() override {
        if (dir_.empty()) GTEST_SKIP() << "real recordings not found in " << kData << " (../shared beside the repo)";
        for (const auto& s : steps_) ASSERT_EQ(s.status, 0) << s.output;
    }
    static inline fs::path dir_;
    static inline std::vector<CliRun> steps_;
};

// Thesis Table 3.2, 90 % ... 10 % SOC.
constexpr double kSoc[] = {0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.1};
constexpr double kOcvV[] = {4.05, 3.96, 3.87, 3.79, 3.72, 3.63, 3.53, 3.46, 3.29};
constexpr double kR0DischargeAvgMohm[] = {7.50, 7.39, 7.36, 7.38, 7.34, 7.30, 7.28, 7.37, 7.85};

double at_soc(const json& p, const std::string& table, const std::string& key, double soc) {
    const auto& s = p["soc"];
    for (std::size_t k = 0; k < s.size(); ++k)
        if (std::abs(s[k].get<double>() - soc) < 0.01) return key.empty() ? p[table][k].get<double>() : p[table][key][k].get<double>();
    ADD_FAILURE() << "no SOC breakpoint near " << soc;
    return NAN;
}

}  // namespace

TEST_F(Characterization, ImportAlignsTheClocksAndSaysSo) {
    EXPECT_NE(steps_[0].output.find("clock offset applied"), std::string::npos) << steps_[0].output;
    EXPECT_NE(steps_[1].output.find("clock offset applied"), std::string::npos) << steps_[1].output;
    EXPECT_NE(steps_[1].output.find("Type-T corrected"), std::string::npos);
}

TEST_F(Characterization, FittedParametersAgreeWithTheThesisTable32) {
    const auto p = read_json(dir_ / "params.json");
    EXPECT_EQ(p["schema"], "cellbench.params/1");
    for (std::size_t k = 0; k < 9; ++k) {
        SCOPED_TRACE("SOC " + std::to_string(kSoc[k]));
        // Table 3.2 rounds the OCV to 10 mV: its half step plus issue 11's 5 mV.
        EXPECT_NEAR(at_soc(p, "ocv_v", "", kSoc[k]), kOcvV[k], 0.010);
        if (kSoc[k] >= 0.2) {
            // Issue 11: the global fit's discharge R0 (the default tables) within 5 % of Table 3.2 at 20-90 % SOC.
            // It holds since the voltage jump across each current step is a residual of its own (before: 7-15 % high).
            const double r0 = at_soc(p, "discharge", "r0_ohm", kSoc[k]) * 1e3;
            EXPECT_NEAR(r0, kR0DischargeAvgMohm[k], 0.05 * kR0DischargeAvgMohm[k]);
        }
    }
    EXPECT_NEAR(p["thermal"]["c_th_j_per_k"].get<double>(), 63.3, 0.10 * 63.3);
    EXPECT_NEAR(p["capacity_ah"].get<double>(), 3.816, 0.02 * 3.816);
    const auto s = read_json(dir_ / "summary.json");
    std::size_t checked = 0;
    for (const auto& ps : s["pulse_sets"]) {
        const double soc = ps["soc"];
        for (std::size_t k = 0; k < 9; ++k)
            if (kSoc[k] >= 0.2 && std::abs(soc - kSoc[k]) < 0.02 && ps["r0_steps_ohm"]["discharge_sampling_corrected"].is_number()) {
                const double r0 = ps["r0_steps_ohm"]["discharge_sampling_corrected"].get<double>() * 1e3;
                EXPECT_NEAR(r0, kR0DischargeAvgMohm[k], 0.05 * kR0DischargeAvgMohm[k]) << "pulse set at SOC " << soc;
                ++checked;
            }
    }
    EXPECT_GE(checked, 7u);
}

TEST_F(Characterization, SummaryReportsBothMethodsAndUncertainty) {
    const auto s = read_json(dir_ / "summary.json");
    ASSERT_GE(s["pulse_sets"].size(), 9u);
    std::size_t with_sigma = 0;
    for (const auto& ps : s["pulse_sets"]) {
        EXPECT_TRUE(ps["thesis"]["rms_v"].is_number());
        EXPECT_TRUE(ps["joint"]["rms_v"].is_number());
        EXPECT_TRUE(ps["chosen"] == "joint" || ps["chosen"] == "thesis");
        with_sigma += ps["joint"]["discharge_sigma"]["r1_ohm"].is_number();
    }
    EXPECT_GT(with_sigma, 0u);
    EXPECT_TRUE(s["thermal"]["r_th_estimates"].is_array());
}

TEST_F(Characterization, ThesisParametersReproduceTable52OnTheRandomWalk) {
    // Table 5.2, Random Walk: voltage RMS 45 mV, temperature RMS 2.4 degC, heat flux RMS 0.20 W.
    const auto m = read_json(dir_ / "thesis.metrics.json");
    EXPECT_EQ(m["schema"], "cellbench.metrics/1");
    EXPECT_EQ(m["samples"], 26505);
    EXPECT_NEAR(m["voltage"]["rms_v"].get<double>(), 0.045, 0.010);
    EXPECT_NEAR(m["temperature"]["rms_c"].get<double>(), 2.4, 0.3);
    EXPECT_NEAR(m["heat_flux"]["rms_w"].get<double>(), 0.20, 0.03);
}

TEST_F(Characterization, FittedParametersBeatTheThesisOnTheRandomWalk) {
    const auto m = read_json(dir_ / "fitted.metrics.json");
    std::printf("fitted parameters on the Random Walk: voltage RMS %.1f mV, temperature RMS %.2f degC, heat flux RMS "
                "%.3f W\n",
                m["voltage"]["rms_v"].get<double>() * 1e3, m["temperature"]["rms_c"].get<double>(),
                m["heat_flux"]["rms_w"].get<double>());
    EXPECT_LT(m["voltage"]["rms_v"].get<double>(), 0.045);
    EXPECT_LT(m["temperature"]["rms_c"].get<double>(), 2.4);
    EXPECT_LT(m["heat_flux"]["rms_w"].get<double>(), 0.20);
    EXPECT_TRUE(fs::exists(dir_ / "fitted.sim.bdf.csv"));
}
