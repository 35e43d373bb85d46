// Issue 16, the command-line tool: devices, binary and huge sparse files fail at once with a clear error
// (they used to run past 65 s and 4 GB); physically impossible values and a DAQ export cut mid-line are errors
// naming the file and line instead of exit 0 with a wrong result; `simulate` never prints "RMS inf".
#include <gtest/gtest.h>

#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace fs = std::filesystem;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kDaemon = fs::path(CELLBENCH_BIN_DIR) / "cellbenchd";
const fs::path kConfig = fs::path(CELLBENCH_SOURCE_DIR) / "config";
const fs::path kThesis = kConfig / "cells/p45b-thesis.json";

const std::string kGoodBdf =
    "Test Time / s,Voltage / V,Current / A\n0,3.70,0\n1,3.66,-4.5\n2,3.66,-4.5\n3,3.65,-4.5\n4,3.69,0\n";
const std::string kGoodNeware =
    "DataPoint,Step Type,Time,Total Time,Current(A),Voltage(V),Capacity(Ah),Energy(Wh),Date,Power(W),Time(s)\n"
    "1,Rest,00:00:00,00:00:00,0.0,4.0964,0.0,0.0,2025-05-23 09:35:38,0.0,0.0\n"
    "2,Rest,00:00:01,00:00:01,0.0,4.0964,0.0,0.0,2025-05-23 09:35:39,0.0,1.0\n";

struct Run {
    int status;
    std::string err;  // stderr only (stdout is the command's report)
};

// Runs a command line under `timeout` (a regression that hangs fails with status 124 instead of blocking
// the suite), returning its exit status and stderr.
Run run(const std::string& command) {
    FILE* p = popen(("timeout 60 " + command + " 2>&1 1>/dev/null").c_str(), "r");
    Run r{-1, {}};
    if (!p) return r;
    char buf[4096];
    while (fgets(buf, sizeof buf, p)) r.err += buf;
    const int st = pclose(p);
    r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return r;
}

std::size_t count_lines_starting(const std::string& text, const std::string& prefix) {
    std::istringstream in(text);
    std::size_t n = 0;
    for (std::string line; std::getline(in, line);) n += line.rfind(prefix, 0) == 0;
    return n;
}

// The cellbench contract: status 1 and exactly one error line, which names `what` (a file:line, a path...).
::testing::AssertionResult fails_once_naming(const Run& r, const std::string& what) {
    if (r.status != 1) return ::testing::AssertionFailure() << "status " << r.status << ", stderr:\n" << r.err;
    if (count_lines_starting(r.err, "error: ") != 1)
        return ::testing::AssertionFailure() << "expected one error line, stderr:\n" << r.err;
    if (r.err.find(what) == std::string::npos)
        return ::testing::AssertionFailure() << "message does not name \"" << what << "\":\n" << r.err;
    return ::testing::AssertionSuccess();
}


class CliHostileInput : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("cellbench-hostile-" + std::to_string(::getpid()) + "-" +
                                            ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        fs::create_directories(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }

    fs::path write(const std::string& name, const std::string& text) {
        std::ofstream(dir_ / name, std::ios::binary) << text;
        return dir_ / name;
    }
    std::string at(const std::string& name) const { return (dir_ / name).string(); }

    // No file of the folder but the inputs: no output, no temporary file left behind.
    ::testing::AssertionResult only_inputs_left(std::vector<std::string> inputs) const {
        std::vector<std::string> names;
        for (const auto& e : fs::directory_iterator(dir_)) names.push_back(e.path().filename().string());
        std::sort(names.begin(), names.end());
        std::sort(inputs.begin(), inputs.end());
        if (names == inputs) return ::testing::AssertionSuccess();
        auto f = ::testing::AssertionFailure() << "files left:";
        for (const auto& n : names) f << " " << n;
        return f;
    }

    fs::path dir_;
};

}  // namespace

TEST_F(CliHostileInput, DevicesAndBinaryFilesFailAtOnceWithAClearError) {
    auto r = run(kBin.string() + " simulate --params " + kThesis.string() + " /dev/zero");
    EXPECT_TRUE(fails_once_naming(r, "/dev/zero:1: binary data")) << r.err;
    r = run(kBin.string() + " fit /dev/urandom -o " + at("p.json"));
    EXPECT_TRUE(fails_once_naming(r, "/dev/urandom:")) << r.err;
    r = run(kBin.string() + " import --bdf /dev/zero -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "/dev/zero:1: binary data")) << r.err;

    // A 2 GB sparse file after a valid header: the hole reads as NUL bytes, refused on line 2.
    const auto sparse = write("sparse.bdf.csv", "Test Time / s,Voltage / V,Current / A\n");
    fs::resize_file(sparse, std::uintmax_t{2} << 30);
    r = run(kBin.string() + " simulate --params " + kThesis.string() + " " + sparse.string());
    EXPECT_TRUE(fails_once_naming(r, "sparse.bdf.csv:2: binary data")) << r.err;
    fs::remove(sparse);

    // A file without line ends: refused at the line limit, not read whole.
    const auto oneline = write("oneline.bdf.csv", "Test Time / s,Voltage / V,Current / A," + std::string(300000, '7'));
    r = run(kBin.string() + " fit " + oneline.string() + " -o " + at("p.json"));
    EXPECT_TRUE(fails_once_naming(r, "oneline.bdf.csv:1: a line longer than 65536 bytes")) << r.err;
    EXPECT_TRUE(only_inputs_left({"oneline.bdf.csv"}));
}

TEST_F(CliHostileInput, AnImpossibleVoltageIsAnErrorNamingTheRowNotRmsInf) {
    const auto rec = write("v.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.70,0\n1,3.66,-4.5\n2,1e308,-4.5\n"
                                        "3,3.65,-4.5\n4,3.69,0\n");
    auto r = run(kBin.string() + " simulate --params " + kThesis.string() + " " + rec.string() + " --json " +
                 at("m.json"));
    EXPECT_TRUE(fails_once_naming(r, "v.bdf.csv:4: column \"Voltage / V\": impossible value")) << r.err;
    EXPECT_EQ(r.err.find("inf"), std::string::npos) << r.err;
    EXPECT_TRUE(only_inputs_left({"v.bdf.csv"}));
}

TEST_F(CliHostileInput, ImportOfADaqExportCutMidLineIsAnError) {
    const auto neware = write("neware.csv", kGoodNeware);
    const auto daq = write("daq.csv", "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n0,1e-5,30\n0.1,1e-5,30\n"
                                      "0.2,1e-5,30\n0.3,1e-5,3");
    auto r = run(kBin.string() + " import --neware " + neware.string() + " --dewesoft " + daq.string() + " -o " +
                 at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "daq.csv:5: the export ends mid-line")) << r.err;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv"}));
}

TEST_F(CliHostileInput, DeeplyNestedOrOverflowingParameterFileIsAClearError) {
    const auto rec = write("r.bdf.csv", kGoodBdf);
    const auto deep = write("deep.json", std::string(100000, '[') + std::string(100000, ']'));
    auto r = run(kBin.string() + " simulate --params " + deep.string() + " " + rec.string());
    EXPECT_TRUE(fails_once_naming(r, "deep.json: invalid JSON: nested deeper than 64")) << r.err;
    const auto huge = write("huge.json", R"({"schema": "cellbench.params/1", "capacity_ah": 1e999})");
    r = run(kBin.string() + " simulate --params " + huge.string() + " " + rec.string());
    EXPECT_TRUE(fails_once_naming(r, "huge.json: invalid JSON")) << r.err;
}

TEST_F(CliHostileInput, ImportRefusesADaqRecordWithAGapInsteadOfMisaligningItsTail) {
    const auto neware = write("neware.csv", kGoodNeware);
    std::string daq = "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n";
    for (int i = 0; i < 50; ++i) daq += std::to_string(i * 0.1) + ",1e-5,30\n";
    for (int i = 0; i < 50; ++i) daq += std::to_string(3600 + i * 0.1) + ",1e-5,30\n";
    const auto path = write("daq.csv", daq);
    auto r = run(kBin.string() + " import --neware " + neware.string() + " --dewesoft " + path.string() + " -o " +
                 at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "daq.csv:52: GAP in the DAQ record")) << r.err;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv"}));
}

TEST_F(CliHostileInput, ImportRefusesImpossibleOrCutCyclerExports) {
    std::string huge = kGoodNeware;
    huge.replace(huge.find("0.0,4.0964,0.0,0.0,2025-05-23 09:35:39"), 3, "1e308");
    const auto a = write("huge.csv", huge);
    auto r = run(kBin.string() + " import --neware " + a.string() + " -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "huge.csv")) << r.err;
    EXPECT_TRUE(r.err.find("1e+308") != std::string::npos || r.err.find("1e308") != std::string::npos) << r.err;
    const auto cut = write("cut.csv", kGoodNeware.substr(0, kGoodNeware.size() - 8));
    r = run(kBin.string() + " import --neware " + cut.string() + " -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "cut.csv")) << r.err;
    EXPECT_TRUE(only_inputs_left({"huge.csv", "cut.csv"}));
}
