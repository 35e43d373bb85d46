// The command line's contract for bad input (INTERFACES.md): exit 1 with one message naming the file and
// what was expected, no output file left behind; exit 2 for usage errors.
#include <gtest/gtest.h>

#include "support/command.hpp"

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>
#include <string>

namespace fs = std::filesystem;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kThesis = fs::path(CELLBENCH_SOURCE_DIR) / "config/cells/p45b-thesis.json";

using CliRun = cellbench::test::CommandRun;

// `cellbench ARGS`, stdout and stderr.
CliRun run(const std::string& args) { return cellbench::test::run_cellbench(args, 60); }

class CliErrors : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("cellbench-cli-" + std::to_string(::getpid()) + "-" +
                                            ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::create_directories(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }
    fs::path write(const std::string& name, const std::string& text) {
        std::ofstream(dir_ / name) << text;
        return dir_ / name;
    }
    fs::path dir_;
};

}  // namespace

TEST_F(CliErrors, UsageErrorsExitWithTwo) {
    EXPECT_EQ(run("").status, 2);
    EXPECT_EQ(run("frobnicate").status, 2);
    EXPECT_EQ(run("simulate --params").status, 2);
    EXPECT_EQ(run("--help").status, 0);
    EXPECT_NE(run("simulate --help").output.find("--params"), std::string::npos);
}

TEST_F(CliErrors, RecordingWithoutRequiredColumnIsRejectedWithoutOutput) {
    const auto rec = write("bad.bdf.csv", "Test Time / s,Voltage / V\n0,3.7\n1,3.7\n");
    const auto r = run("simulate --params " + kThesis.string() + " " + rec.string() + " --json " +
                       (dir_ / "m.json").string());
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("bad.bdf.csv"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("Current / A"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(dir_ / "m.json"));
}

TEST_F(CliErrors, UnsortedTimeAndNaNAreClearErrors) {
    auto rec = write("back.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n5,3.7,0\n2,3.7,0\n");
    auto r = run("simulate --params " + kThesis.string() + " " + rec.string());
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.output.find("back.bdf.csv:4"), std::string::npos) << r.output;
    rec = write("nan.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,nan,0\n");
    r = run("simulate --params " + kThesis.string() + " " + rec.string());
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.output.find("nan.bdf.csv:3"), std::string::npos) << r.output;
}

TEST_F(CliErrors, MalformedParameterSetNamesTheJsonPath) {
    const auto rec = write("ok.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.69,-1\n");
    auto params = write("p.json", "{\"schema\": \"cellbench.params/1\", \"capacity_ah\": \"four\"}");
    auto r = run("simulate --params " + params.string() + " " + rec.string());
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.output.find("$.capacity_ah"), std::string::npos) << r.output;
    params = write("broken.json", "{\n  \"schema\": \"cellbench.params/1\",\n  oops\n}");
    r = run("simulate --params " + params.string() + " " + rec.string());
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.output.find("broken.json:3"), std::string::npos) << r.output;
}

TEST_F(CliErrors, FitWithoutPulseSetsSaysWhatIsMissingAndWritesNothing) {
    std::string text = "Test Time / s,Voltage / V,Current / A\n";
    for (int k = 0; k < 100; ++k) text += std::to_string(k) + ",3.7,0\n";
    const auto rec = write("rest.bdf.csv", text);
    const auto r = run("fit " + rec.string() + " -o " + (dir_ / "p.json").string());
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("no recording holds pulses"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(dir_ / "p.json"));
}

TEST_F(CliErrors, SimulateWritesMetricsJsonWithNullForUnmeasuredQuantities) {
    const auto rec = write("v.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.70,0\n1,3.66,-4.5\n2,3.66,-4.5\n");
    const auto r = run("simulate --params " + kThesis.string() + " " + rec.string() + " --json " +
                       (dir_ / "m.json").string());
    ASSERT_EQ(r.status, 0) << r.output;
    std::ifstream in(dir_ / "m.json");
    std::stringstream ss;
    ss << in.rdbuf();
    const auto j = ss.str();
    EXPECT_NE(j.find("\"temperature\": null"), std::string::npos) << j;
    EXPECT_NE(j.find("\"rms_v\""), std::string::npos) << j;
}

// A BDF file as the Battery Data Alliance publishes them (machine-readable names, a vendor's extra columns, one
// thermocouple in T1, no surface temperature) is a recording every command reads: the cell temperature comes
// from T1, and a test time kept in ms under the seconds name is read as ms with a warning.
// A recording of another cell (here a sodium-ion cell resting at 2.6 V, below the P45B's whole OCV table) simulated
// with the P45B's parameter set: no SOC explains its voltage, and the user is told so instead of reading a 500 mV
// "model error". The same recording within the table's range gets no such warning.
TEST_F(CliErrors, SimulateSaysWhenTheRecordingStartsOutsideTheParameterSetsOcvRange) {
    auto recording = [&](const char* name, double v0) {
        std::string text = "Test Time / s,Voltage / V,Current / A\n";
        for (int k = 0; k < 120; ++k)
            text += std::to_string(k) + "," + std::to_string(v0 - (k < 60 ? 0.0 : 0.05)) + "," + (k < 60 ? "0" : "-2.0") + "\n";
        return write(name, text);
    };
    const auto other = run("simulate --params " + kThesis.string() + " " + recording("sodium.bdf.csv", 2.604).string());
    ASSERT_EQ(other.status, 0) << other.output;
    EXPECT_NE(other.output.find("it starts at 2.604 V (0.000 A), outside the parameter set's OCV range"), std::string::npos)
        << other.output;
    EXPECT_NE(other.output.find("Is the parameter set this cell's?"), std::string::npos) << other.output;
    const auto same = run("simulate --params " + kThesis.string() + " " + recording("p45b.bdf.csv", 3.7).string());
    ASSERT_EQ(same.status, 0) << same.output;
    EXPECT_EQ(same.output.find("outside the parameter set's OCV range"), std::string::npos) << same.output;
}

// A drive at 0 degC simulated with a parameter set characterized at 30 degC that holds no temperature dependence
// (the thesis set): its resistances are 30 degC's, and the user is told why the error is large and what to do. At
// the characterization's temperature, and with the dependence in the set, there is no such warning.
TEST_F(CliErrors, SimulateSaysWhenTheCellRunsFarFromTheCharacterizationTemperature) {
    auto recording = [&](const char* name, double surface_c) {
        std::string text = "Test Time / s,Voltage / V,Current / A,Surface Temperature / degC\n";
        for (int k = 0; k < 600; ++k)
            text += std::to_string(k) + "," + (k < 60 ? "3.700" : "3.650") + "," + (k < 60 ? "0" : "-2.0") + "," +
                    std::to_string(surface_c + 0.002 * k) + "\n";
        return write(name, text);
    };
    const char* warning = "K below the parameter set's characterization (30.0 degC), and the set holds no temperature "
                          "dependence of its resistances";
    const auto cold = run("simulate --params " + kThesis.string() + " " + recording("cold.bdf.csv", 0.0).string());
    ASSERT_EQ(cold.status, 0) << cold.output;
    EXPECT_NE(cold.output.find("its cell is at 0.6 degC (median surface temperature), 29.4 " + std::string(warning)),
              std::string::npos)
        << cold.output;
    const auto warm = run("simulate --params " + kThesis.string() + " " + recording("warm.bdf.csv", 28.0).string());
    ASSERT_EQ(warm.status, 0) << warm.output;
    EXPECT_EQ(warm.output.find("parameter set's characterization"), std::string::npos) << warm.output;
    // The same set with an activation energy: the model follows the temperature, nothing to warn about.
    auto with_ea = nlohmann::json::parse(std::ifstream(kThesis));
    with_ea["extensions"]["resistance_temperature"] = {{"activation_energy_j_per_mol", 30000.0}};
    const auto p = dir_ / "with-ea.json";
    std::ofstream(p) << with_ea.dump();
    const auto followed = run("simulate --params " + p.string() + " " + (dir_ / "cold.bdf.csv").string());
    ASSERT_EQ(followed.status, 0) << followed.output;
    EXPECT_EQ(followed.output.find("parameter set's characterization"), std::string::npos) << followed.output;

    // diagnose says it too, and its report and JSON carry it beside the figures it qualifies.
    const auto d = run("diagnose --params " + kThesis.string() + " " + (dir_ / "cold.bdf.csv").string() +
                       " --effects series_resistance_offset --json " + (dir_ / "d.json").string() + " --report " +
                       (dir_ / "r.html").string());
    ASSERT_EQ(d.status, 0) << d.output;
    EXPECT_NE(d.output.find(warning), std::string::npos) << d.output;
    std::ifstream report(dir_ / "r.html");
    const std::string html((std::istreambuf_iterator<char>(report)), std::istreambuf_iterator<char>());
    EXPECT_NE(html.find("Read the figures with these notes"), std::string::npos);
    EXPECT_NE(html.find("and the set holds no temperature dependence of its resistances"), std::string::npos);
    std::ifstream json_in(dir_ / "d.json");
    const auto j = nlohmann::json::parse(json_in);
    ASSERT_TRUE(j.contains("notes")) << j.dump(2);
    EXPECT_NE(j["notes"].dump().find(warning), std::string::npos) << j["notes"].dump(2);
}

// A recording that draws twice the parameter set's capacity (another cell's set, or a capacity far off): the
// simulated SOC runs far below 0, where the model extrapolates its tables, and the user is told so rather than left
// with a "model error" of volts. A discharge within the capacity gets no such warning.
TEST_F(CliErrors, SimulateSaysWhenTheSimulatedSocLeavesItsRange) {
    auto recording = [&](const char* name, double discharge_s) {
        std::string text = "Test Time / s,Voltage / V,Current / A\n";
        for (int k = 0; k <= 600; ++k) {
            const double t = k * 20.0;
            text += std::to_string(t) + "," + (k == 0 ? "4.05" : "3.60") + "," + (k > 0 && t <= discharge_s ? "-9.0" : "0") + "\n";
        }
        return write(name, text);
    };
    const auto beyond = run("simulate --params " + kThesis.string() + " " + recording("beyond.bdf.csv", 3600).string());
    ASSERT_EQ(beyond.status, 0) << beyond.output;
    EXPECT_NE(beyond.output.find("the simulated SOC leaves 0-100 % (it reaches -"), std::string::npos) << beyond.output;
    EXPECT_NE(beyond.output.find("the recording draws more than the parameter set's capacity"), std::string::npos)
        << beyond.output;
    const auto within = run("simulate --params " + kThesis.string() + " " + recording("within.bdf.csv", 900).string());
    ASSERT_EQ(within.status, 0) << within.output;
    EXPECT_EQ(within.output.find("the simulated SOC leaves"), std::string::npos) << within.output;
}

TEST_F(CliErrors, ReferenceFormBdfWithMachineNamesAndOnlyT1IsSimulated) {
    std::string text = "test_time_second,voltage_volt,current_ampere,unix_time_second,step_id,temperature_t1_celsius\n";
    for (int k = 0; k < 300; ++k)
        text += std::to_string(1000 * k) + "," + (k < 100 ? "3.70" : "3.66") + "," + (k <= 100 ? "0" : "-4.5") + "," +
                std::to_string(1700000000 + k) + ",1,30.0\n";  // row 100: the pulse's voltage, the rest's current
    const auto rec = write("reference.bdf.csv", text);
    const auto r = run("simulate --params " + kThesis.string() + " " + rec.string() + " --json " +
                       (dir_ / "m.json").string());
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_NE(r.output.find("read as milliseconds"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("read from Temperature T1"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("1 row at a current step shows the step's new voltage with the current before it (at t = "
                            "100.000 s): its current is taken from the next row"),
              std::string::npos)
        << r.output;
    std::ifstream in(dir_ / "m.json");
    std::stringstream ss;
    ss << in.rdbuf();
    const auto j = ss.str();
    EXPECT_EQ(j.find("\"temperature\": null"), std::string::npos) << "T1 is the cell temperature: " << j;
    EXPECT_NE(r.output.find("(299 s)"), std::string::npos) << "299 s, not 299000 s: " << r.output;
}
