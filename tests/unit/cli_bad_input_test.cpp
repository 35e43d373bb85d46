// Malformed configurations and recordings through the real binaries (INTERFACES.md: exit status 1, one clear
// message on stderr naming the file, line or JSON path, and no partial output: an output that did not exist
// does not exist afterwards, one that existed is unchanged). cli_errors_test covers the basic recording and
// parameter-set messages of `simulate` and `fit`; this adds import, diagnose, cellbenchd --config, several
// outputs of one command, and output paths that cannot be written.
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

std::string slurp(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

class CliBadInput : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("cellbench-badin-" + std::to_string(::getpid()) + "-" +
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

TEST_F(CliBadInput, ImportOfAMalformedNewareExportNamesTheLineAndWritesNothing) {
    const auto bad = write("bad_neware.csv",
                           "Step Type,Total Time,Current(A),Voltage(V)\nRest,00:00:00,0,4\nRest,00:61:00,0,4\n");
    auto r = run(kBin.string() + " import --neware " + bad.string() + " -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "bad_neware.csv:3")) << r.err;
    EXPECT_TRUE(only_inputs_left({"bad_neware.csv"}));

    // A pre-existing output is left exactly as it was.
    const auto old = write("out.bdf.csv", "previous content\n");
    r = run(kBin.string() + " import --neware " + bad.string() + " -o " + old.string());
    EXPECT_EQ(r.status, 1) << r.err;
    EXPECT_EQ(slurp(old), "previous content\n");
    EXPECT_TRUE(only_inputs_left({"bad_neware.csv", "out.bdf.csv"}));
}

TEST_F(CliBadInput, ImportOfAMalformedDewesoftExportWritesNothing) {
    const auto neware = write("neware.csv", kGoodNeware);
    // The time column steps back by 5 s: an error, not a repair.
    const auto daq = write("daq.csv",
                           "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n0,1e-5,30\n10,1e-5,30\n5,1e-5,30\n");
    auto r = run(kBin.string() + " import --neware " + neware.string() + " --dewesoft " + daq.string() + " -o " +
                 at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "daq.csv:4")) << r.err;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv"}));

    // Binary garbage instead of a CSV.
    const auto junk = write("junk.csv", std::string("\x00\x01\x02,\xff\xfe\n\x00\x00", 10));
    r = run(kBin.string() + " import --bdf " + junk.string() + " -o " + at("out2.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "junk.csv")) << r.err;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv", "junk.csv"}));
}

TEST_F(CliBadInput, AnOutputThatCannotBeWrittenIsRefusedBeforeTheWork) {
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    auto r = run(kBin.string() + " import --bdf " + rec.string() + " -o " + at("no/such/folder/out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "does not exist")) << r.err;
    fs::create_directories(dir_ / "a_folder");
    r = run(kBin.string() + " import --bdf " + rec.string() + " -o " + at("a_folder"));
    EXPECT_TRUE(fails_once_naming(r, "a_folder")) << r.err;
    EXPECT_TRUE(fs::is_directory(dir_ / "a_folder"));
    EXPECT_TRUE(fs::is_empty(dir_ / "a_folder"));
}

TEST_F(CliBadInput, ACommandWithSeveralOutputsWritesAllOrNone) {
    // simulate --json into a good folder and --out into a missing one: before, the metrics were written
    // and the command then failed on --out, leaving one of its two outputs behind.
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    auto r = run(kBin.string() + " simulate --params " + kThesis.string() + " " + rec.string() + " --json " +
                 at("m.json") + " --out " + at("missing/sim.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "missing")) << r.err;
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv"}));

    // fit: -o fine, --json into a missing folder. Nothing is written (and the fit is not even started).
    r = run(kBin.string() + " fit " + rec.string() + " -o " + at("p.json") + " --json " + at("missing/s.json"));
    EXPECT_TRUE(fails_once_naming(r, "missing")) << r.err;
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv"}));

    // The same simulate with both outputs writable succeeds and writes both.
    r = run(kBin.string() + " simulate --params " + kThesis.string() + " " + rec.string() + " --json " +
            at("m.json") + " --out " + at("sim.bdf.csv"));
    EXPECT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv", "m.json", "sim.bdf.csv"}));
}

TEST_F(CliBadInput, FitWithOneMalformedRecordingAmongGoodOnesNamesItAndKeepsTheOldOutput) {
    const auto good = write("good.bdf.csv", kGoodBdf);
    const auto bad = write("bad.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7,zero\n");
    const auto old = write("p.json", "{\"previous\": true}\n");
    const auto r = run(kBin.string() + " fit " + good.string() + " " + bad.string() + " -o " + old.string() +
                       " --json " + at("s.json"));
    EXPECT_TRUE(fails_once_naming(r, "bad.bdf.csv:3")) << r.err;
    EXPECT_EQ(slurp(old), "{\"previous\": true}\n");
    EXPECT_TRUE(only_inputs_left({"good.bdf.csv", "bad.bdf.csv", "p.json"}));
}

TEST_F(CliBadInput, SimulateWithAParameterSetThatIsNotJsonKeepsTheOldMetrics) {
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    const auto params = write("p.json", "{\n  \"schema\": \"cellbench.params/1\",\n  \"capacity_ah\": 3.8,,\n}\n");
    const auto old = write("m.json", "old metrics\n");
    auto r = run(kBin.string() + " simulate --params " + params.string() + " " + rec.string() + " --json " +
                 old.string() + " --out " + at("sim.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "p.json:3")) << r.err;
    EXPECT_EQ(slurp(old), "old metrics\n");
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv", "p.json", "m.json"}));

    // A parameter set with a table of the wrong length names the JSON path.
    auto j = nlohmann::json::parse(slurp(kThesis));
    j["ocv_v"].erase(0);
    write("short.json", j.dump());
    r = run(kBin.string() + " simulate --params " + at("short.json") + " " + rec.string() + " --json " + old.string());
    EXPECT_TRUE(fails_once_naming(r, "$.ocv_v")) << r.err;
    EXPECT_EQ(slurp(old), "old metrics\n");
}

TEST_F(CliBadInput, DiagnoseOfAMalformedRecordingWritesNoneOfItsOutputs) {
    const auto bad = write("bad.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7,0\n-3,3.7,0\n");
    const auto old = write("d.json", "old diagnosis\n");
    auto r = run(kBin.string() + " diagnose --params " + kThesis.string() + " " + bad.string() + " --json " +
                 old.string() + " --report " + at("r.html") + " --improved " + at("i.json"));
    EXPECT_TRUE(fails_once_naming(r, "bad.bdf.csv:4")) << r.err;
    EXPECT_EQ(slurp(old), "old diagnosis\n");
    EXPECT_TRUE(only_inputs_left({"bad.bdf.csv", "d.json"}));

    // A parameter set that is a bench configuration, not a parameter set.
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    r = run(kBin.string() + " diagnose --params " + (kConfig / "bench.sim.json").string() + " " + rec.string() +
            " --json " + at("d2.json"));
    EXPECT_TRUE(fails_once_naming(r, "bench.sim.json")) << r.err;
    EXPECT_TRUE(only_inputs_left({"bad.bdf.csv", "d.json", "ok.bdf.csv"}));
}

TEST_F(CliBadInput, CellbenchdRefusesABadConfigurationWithoutCreatingItsDatabase) {
    const std::string db = at("bench.sqlite");
    const auto daemon = [&](const std::string& config) {
        return run(kDaemon.string() + " --config " + config + " --db " + db + " --listen 127.0.0.1:0");
    };

    // Not JSON: the file and the line.
    write("broken.json", "{\n  \"schema\": \"cellbench.bench/1\",\n  \"name\": oops\n}\n");
    auto r = daemon(at("broken.json"));
    EXPECT_EQ(r.status, 1) << r.err;
    EXPECT_NE(r.err.find("broken.json"), std::string::npos) << r.err;
    EXPECT_NE(r.err.find("line 3"), std::string::npos) << r.err;

    // Valid JSON with wrong fields: every problem, each with its JSON path.
    auto j = nlohmann::json::parse(slurp(kConfig / "bench.sim.json"));
    j["instruments"]["cycler"]["port"] = "fifteen";
    j["safety"]["max_temperature_c"] = "hot";
    if (j.contains("simulation") && j["simulation"].contains("params"))
        j["simulation"]["params"] = (kConfig / j["simulation"]["params"].get<std::string>()).string();
    write("wrong.json", j.dump(2));
    r = daemon(at("wrong.json"));
    EXPECT_EQ(r.status, 1) << r.err;
    EXPECT_NE(r.err.find("wrong.json: $.instruments.cycler.port"), std::string::npos) << r.err;
    EXPECT_NE(r.err.find("wrong.json: $.safety.max_temperature_c"), std::string::npos) << r.err;

    // Missing file, a folder, a device that never ends (/dev/zero used to be read forever).
    r = daemon(at("missing.json"));
    EXPECT_EQ(r.status, 1) << r.err;
    EXPECT_NE(r.err.find("no such file"), std::string::npos) << r.err;
    r = daemon(dir_.string());
    EXPECT_EQ(r.status, 1) << r.err;
    EXPECT_NE(r.err.find("not a regular file"), std::string::npos) << r.err;
    r = daemon("/dev/zero");
    EXPECT_EQ(r.status, 1) << r.err;
    EXPECT_NE(r.err.find("not a regular file"), std::string::npos) << r.err;

    EXPECT_FALSE(fs::exists(db));
    EXPECT_TRUE(only_inputs_left({"broken.json", "wrong.json"}));
}
