// Malformed configurations and recordings through the real binaries (INTERFACES.md: exit status 1, one clear
// message on stderr naming the file, line or JSON path, and no partial output: an output that did not exist
// does not exist afterwards, one that existed is unchanged). cli_errors_test covers the basic recording and
// parameter-set messages of `simulate` and `fit`; this adds import, diagnose, cellbenchd --config, several
// outputs of one command, and output paths that cannot be written.
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

class CliBadInput : public test::CliInputFolder {
protected:
    CliBadInput() : CliInputFolder("badin") {}
};

}  // namespace

TEST_F(CliBadInput, ImportOfAMalformedNewareExportNamesTheLineAndWritesNothing) {
    const auto bad = write("bad_neware.csv",
                           "Step Type,Total Time,Current(A),Voltage(V)\nRest,00:00:00,0,4\nRest,00:61:00,0,4\n");
    auto r = run(kCliBin.string() + " import --neware " + bad.string() + " -o " + at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "bad_neware.csv:3")) << r.output;
    EXPECT_TRUE(only_inputs_left({"bad_neware.csv"}));

    // A pre-existing output is left exactly as it was.
    const auto old = write("out.bdf.csv", "previous content\n");
    r = run(kCliBin.string() + " import --neware " + bad.string() + " -o " + old.string());
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_EQ(slurp(old), "previous content\n");
    EXPECT_TRUE(only_inputs_left({"bad_neware.csv", "out.bdf.csv"}));
}

TEST_F(CliBadInput, ImportOfAMalformedDewesoftExportWritesNothing) {
    const auto neware = write("neware.csv", kGoodNeware);
    // The time column steps back by 5 s: an error, not a repair.
    const auto daq = write("daq.csv",
                           "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n0,1e-5,30\n10,1e-5,30\n5,1e-5,30\n");
    auto r = run(kCliBin.string() + " import --neware " + neware.string() + " --dewesoft " + daq.string() + " -o " +
                 at("out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "daq.csv:4")) << r.output;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv"}));

    // Binary garbage instead of a CSV.
    const auto junk = write("junk.csv", std::string("\x00\x01\x02,\xff\xfe\n\x00\x00", 10));
    r = run(kCliBin.string() + " import --bdf " + junk.string() + " -o " + at("out2.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "junk.csv")) << r.output;
    EXPECT_TRUE(only_inputs_left({"neware.csv", "daq.csv", "junk.csv"}));
}

TEST_F(CliBadInput, AnOutputThatCannotBeWrittenIsRefusedBeforeTheWork) {
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    auto r = run(kCliBin.string() + " import --bdf " + rec.string() + " -o " + at("no/such/folder/out.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "does not exist")) << r.output;
    fs::create_directories(dir_ / "a_folder");
    r = run(kCliBin.string() + " import --bdf " + rec.string() + " -o " + at("a_folder"));
    EXPECT_TRUE(fails_once_naming(r, "a_folder")) << r.output;
    EXPECT_TRUE(fs::is_directory(dir_ / "a_folder"));
    EXPECT_TRUE(fs::is_empty(dir_ / "a_folder"));
}

TEST_F(CliBadInput, ACommandWithSeveralOutputsWritesAllOrNone) {
    // simulate --json into a good folder and --out into a missing one: before, the metrics were written
    // and the command then failed on --out, leaving one of its two outputs behind.
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    auto r = run(kCliBin.string() + " simulate --params " + kThesisParams.string() + " " + rec.string() + " --json " +
                 at("m.json") + " --out " + at("missing/sim.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "missing")) << r.output;
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv"}));

    // fit: -o fine, --json into a missing folder. Nothing is written (and the fit is not even started).
    r = run(kCliBin.string() + " fit " + rec.string() + " -o " + at("p.json") + " --json " + at("missing/s.json"));
    EXPECT_TRUE(fails_once_naming(r, "missing")) << r.output;
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv"}));

    // The same simulate with both outputs writable succeeds and writes both.
    r = run(kCliBin.string() + " simulate --params " + kThesisParams.string() + " " + rec.string() + " --json " +
            at("m.json") + " --out " + at("sim.bdf.csv"));
    EXPECT_EQ(r.status, 0) << r.output;
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv", "m.json", "sim.bdf.csv"}));
}

TEST_F(CliBadInput, FitWithOneMalformedRecordingAmongGoodOnesNamesItAndKeepsTheOldOutput) {
    const auto good = write("good.bdf.csv", kGoodBdf);
    const auto bad = write("bad.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7,zero\n");
    const auto old = write("p.json", "{\"previous\": true}\n");
    const auto r = run(kCliBin.string() + " fit " + good.string() + " " + bad.string() + " -o " + old.string() +
                       " --json " + at("s.json"));
    EXPECT_TRUE(fails_once_naming(r, "bad.bdf.csv:3")) << r.output;
    EXPECT_EQ(slurp(old), "{\"previous\": true}\n");
    EXPECT_TRUE(only_inputs_left({"good.bdf.csv", "bad.bdf.csv", "p.json"}));
}

TEST_F(CliBadInput, SimulateWithAParameterSetThatIsNotJsonKeepsTheOldMetrics) {
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    const auto params = write("p.json", "{\n  \"schema\": \"cellbench.params/1\",\n  \"capacity_ah\": 3.8,,\n}\n");
    const auto old = write("m.json", "old metrics\n");
    auto r = run(kCliBin.string() + " simulate --params " + params.string() + " " + rec.string() + " --json " +
                 old.string() + " --out " + at("sim.bdf.csv"));
    EXPECT_TRUE(fails_once_naming(r, "p.json:3")) << r.output;
    EXPECT_EQ(slurp(old), "old metrics\n");
    EXPECT_TRUE(only_inputs_left({"ok.bdf.csv", "p.json", "m.json"}));

    // A parameter set with a table of the wrong length names the JSON path.
    auto j = nlohmann::json::parse(slurp(kThesisParams));
    j["ocv_v"].erase(0);
    write("short.json", j.dump());
    r = run(kCliBin.string() + " simulate --params " + at("short.json") + " " + rec.string() + " --json " + old.string());
    EXPECT_TRUE(fails_once_naming(r, "$.ocv_v")) << r.output;
    EXPECT_EQ(slurp(old), "old metrics\n");

    // An OCV no cell has (a value in mV written as V) names the entry; it used to be taken and put the simulation's
    // starting SOC at 12 % instead of 48 %.
    j = nlohmann::json::parse(slurp(kThesisParams));
    j["ocv_v"][3] = 3620.0;
    write("mv.json", j.dump());
    r = run(kCliBin.string() + " simulate --params " + at("mv.json") + " " + rec.string() + " --json " + old.string());
    EXPECT_TRUE(fails_once_naming(r, "$.ocv_v[3]")) << r.output;
    EXPECT_EQ(slurp(old), "old metrics\n");
}

TEST_F(CliBadInput, AnExtensionThisBuildDoesNotModelIsNamedNotSilentlyDropped) {
    // A typo in an effect id (or a newer cellbench's effect): the set still loads, kept verbatim, but the user is
    // told that the model runs without it.
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    auto j = nlohmann::json::parse(slurp(kThesisParams));
    j["extensions"]["resistance_temprature"] = {{"activation_energy_j_per_mol", 30000}};
    write("typo.json", j.dump());
    const auto r = run(kCliBin.string() + " simulate --params " + at("typo.json") + " " + rec.string() + " --json " +
                       at("m.json"));
    EXPECT_EQ(r.status, 0) << r.output;
    EXPECT_NE(r.output.find("typo.json: extension \"resistance_temprature\" is not an effect this cellbench models"),
              std::string::npos)
        << r.output;
    EXPECT_TRUE(fs::exists(at("m.json")));
}

TEST_F(CliBadInput, DiagnoseOfAMalformedRecordingWritesNoneOfItsOutputs) {
    const auto bad = write("bad.bdf.csv", "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7,0\n-3,3.7,0\n");
    const auto old = write("d.json", "old diagnosis\n");
    auto r = run(kCliBin.string() + " diagnose --params " + kThesisParams.string() + " " + bad.string() + " --json " +
                 old.string() + " --report " + at("r.html") + " --improved " + at("i.json"));
    EXPECT_TRUE(fails_once_naming(r, "bad.bdf.csv:4")) << r.output;
    EXPECT_EQ(slurp(old), "old diagnosis\n");
    EXPECT_TRUE(only_inputs_left({"bad.bdf.csv", "d.json"}));

    // A parameter set that is a bench configuration, not a parameter set.
    const auto rec = write("ok.bdf.csv", kGoodBdf);
    r = run(kCliBin.string() + " diagnose --params " + (kConfigDir / "bench.sim.json").string() + " " + rec.string() +
            " --json " + at("d2.json"));
    EXPECT_TRUE(fails_once_naming(r, "bench.sim.json")) << r.output;
    EXPECT_TRUE(only_inputs_left({"bad.bdf.csv", "d.json", "ok.bdf.csv"}));
}

TEST_F(CliBadInput, CellbenchdRefusesABadConfigurationWithoutCreatingItsDatabase) {
    const std::string db = at("bench.sqlite");
    const auto daemon = [&](const std::string& config) {
        return run(kDaemonBin.string() + " --config " + config + " --db " + db + " --listen 127.0.0.1:0");
    };

    // Not JSON: the file and the line.
    write("broken.json", "{\n  \"schema\": \"cellbench.bench/1\",\n  \"name\": oops\n}\n");
    auto r = daemon(at("broken.json"));
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("broken.json"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("line 3"), std::string::npos) << r.output;

    // Valid JSON with wrong fields: every problem, each with its JSON path.
    auto j = nlohmann::json::parse(slurp(kConfigDir / "bench.sim.json"));
    j["instruments"]["cycler"]["port"] = "fifteen";
    j["safety"]["max_temperature_c"] = "hot";
    if (j.contains("simulation") && j["simulation"].contains("params"))
        j["simulation"]["params"] = (kConfigDir / j["simulation"]["params"].get<std::string>()).string();
    write("wrong.json", j.dump(2));
    r = daemon(at("wrong.json"));
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("wrong.json: $.instruments.cycler.port"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("wrong.json: $.safety.max_temperature_c"), std::string::npos) << r.output;

    // Missing file, a folder, a device that never ends (/dev/zero used to be read forever).
    r = daemon(at("missing.json"));
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("no such file"), std::string::npos) << r.output;
    r = daemon(dir_.string());
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("not a regular file"), std::string::npos) << r.output;
    r = daemon("/dev/zero");
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("not a regular file"), std::string::npos) << r.output;

    EXPECT_FALSE(fs::exists(db));
    EXPECT_TRUE(only_inputs_left({"broken.json", "wrong.json"}));
}
