// Issue 16, the command-line tool: devices, binary and huge sparse files fail at once with a clear error
// (they used to run past 65 s and 4 GB); physically impossible values and a DAQ export cut mid-line are errors
// naming the file and line instead of exit 0 with a wrong result; `simulate` never prints "RMS inf".
#include <gtest/gtest.h>

#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "unit/cli_input_support.hpp"

namespace fs = std::filesystem;
namespace test = cellbench::test;

namespace {

using test::kCliBin, test::kDaemonBin, test::kConfigDir, test::kThesisParams, test::kGoodBdf, test::kGoodNeware;
using test::fails_once_naming, test::slurp;

class CliHostileInput : public test::CliInputFolder {
protected:
    CliHostileInput() : CliInputFolder("hostile") {}
};

}  // namespace

TEST_F(CliHostileInput, DevicesAndBinaryFilesFailAtOnceWithAClearError) {
    auto r = run(kCliBin.string() + " simulate --params " + kThesisParams.string() + " /dev/zero");
    EXPECT_TRUE(fails_once_naming(r, "/dev/zero:1: binary data")) << r.output;
    r = run(kCliBin.string() + " fit /dev/urandom -o " + at("p.json"));
    EXPECT_TRUE(fails_once_naming(r, "/dev/urandom:")) << r.output;
    r = run(kCliBin.string() + " import --bdf /dev/zero -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "/dev/zero:1: binary data")) << r.output;

    // A 2 GB sparse file after a valid header: the hole reads as NUL bytes, refused on line 2.
    const auto sparse = write("sparse.bdf.csv", "Test Time / s,Voltage / V,Current / A\n");
    fs::resize_file(sparse, std::uintmax_t{2} << 30);
    r = run(kCliBin.string() + " simulate --params " + kThesisParams.string() + " " + sparse.string());
    EXPECT_TRUE(fails_once_naming(r, "sparse.bdf.csv:2: binary data")) << r.output;
    fs::remove(sparse);

    // A file without line ends: refused at the line limit, not read whole.
    const auto oneline = write("oneline.bdf.csv", "Test Time / s,Voltage / V,Current / A," + std::string(300000, '7'));
    r = run(kCliBin.string() + " fit " + oneline.string() + " -o " + at("p.json"));
    EXPECT_TRUE(fails_once_naming(r, "oneline.bdf.csv:1: a line longer than 65536 bytes")) << r.output;
    EXPECT_TRUE(only_inputs_left({"oneline.bdf.csv"}));
}

TEST_F(CliHostileInput, AnImpossibleVoltageIsAnErrorNamingTheRowNotRmsInf) {
    const auto rec = write("v.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.70,0\n1,3.66,-4.5\n2,1e308,-4.5\n"
                                        "3,3.65,-4.5\n4,3.69,0\n");
    auto r = run(kCliBin.string() + " simulate --params " + kThesisParams.string() + " " + rec.string() + " --json " +
                 at("m.json"));
    EXPECT_TRUE(fails_once_naming(r, "v.bdf.csv:4: column \"Voltage / V\": impossible value")) << r.output;
    EXPECT_EQ(r.output.find("inf"), std::string::npos) << r.output;
    EXPECT_TRUE(only_inputs_left({"v.bdf.csv"}));
}

TEST_F(CliHostileInput, ImportOfADaqExportCutMidLineIsAnError) {
    const auto neware = write("neware.csv", kGoodNeware);
    const auto daq = write("daq.csv", "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n0,1e-5,30\n0.1,1e-5,30\n"
                                      "0.2,1e-5,30\n0.3,1e-5,3");
    auto r = run(kCliBin.string() + " import --neware " + neware.string() + " --dewesoft " + daq.string() + " -o " +
                 at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "daq.csv:5: the export ends mid-line")) << r.output;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv"}));
}

TEST_F(CliHostileInput, DeeplyNestedOrOverflowingParameterFileIsAClearError) {
    const auto rec = write("r.bdf.csv", kGoodBdf);
    const auto deep = write("deep.json", std::string(100000, '[') + std::string(100000, ']'));
    auto r = run(kCliBin.string() + " simulate --params " + deep.string() + " " + rec.string());
    EXPECT_TRUE(fails_once_naming(r, "deep.json: invalid JSON: nested deeper than 64")) << r.output;
    const auto huge = write("huge.json", R"({"schema": "cellbench.params/1", "capacity_ah": 1e999})");
    r = run(kCliBin.string() + " simulate --params " + huge.string() + " " + rec.string());
    EXPECT_TRUE(fails_once_naming(r, "huge.json: invalid JSON")) << r.output;
}

TEST_F(CliHostileInput, ImportRefusesADaqRecordWithAGapInsteadOfMisaligningItsTail) {
    const auto neware = write("neware.csv", kGoodNeware);
    std::string daq = "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n";
    for (int i = 0; i < 50; ++i) daq += std::to_string(i * 0.1) + ",1e-5,30\n";
    for (int i = 0; i < 50; ++i) daq += std::to_string(3600 + i * 0.1) + ",1e-5,30\n";
    const auto path = write("daq.csv", daq);
    auto r = run(kCliBin.string() + " import --neware " + neware.string() + " --dewesoft " + path.string() + " -o " +
                 at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "daq.csv:52: GAP in the DAQ record")) << r.output;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv"}));
}

TEST_F(CliHostileInput, ImportRefusesImpossibleOrCutCyclerExports) {
    std::string huge = kGoodNeware;
    huge.replace(huge.find("0.0,4.0964,0.0,0.0,2025-05-23 09:35:39"), 3, "1e308");
    const auto a = write("huge.csv", huge);
    auto r = run(kCliBin.string() + " import --neware " + a.string() + " -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "huge.csv")) << r.output;
    EXPECT_TRUE(r.output.find("1e+308") != std::string::npos || r.output.find("1e308") != std::string::npos) << r.output;
    const auto cut = write("cut.csv", kGoodNeware.substr(0, kGoodNeware.size() - 8));
    r = run(kCliBin.string() + " import --neware " + cut.string() + " -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "cut.csv")) << r.output;
    EXPECT_TRUE(only_inputs_left({"huge.csv", "cut.csv"}));
}
