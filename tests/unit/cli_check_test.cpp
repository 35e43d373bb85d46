// `cellbench check --program P --cell C [--config BENCH] [--param K=V]...`: a dry run with the daemon's own
// loaders. A good program prints its compiled plan (exit 0); every problem of the bench, the cell, the program
// and the overrides is reported at once (exit 1); nothing is started (no daemon is involved at all).
#include <gtest/gtest.h>

#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "support/command.hpp"

namespace fs = std::filesystem;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kConfig = fs::path(CELLBENCH_SOURCE_DIR) / "config";

using CliRun = cellbench::test::CommandRun;

CliRun run(const std::string& command) { return cellbench::test::run_command(command); }

std::string check(const std::string& args) {
    return kBin.string() + " check --config " + (kConfig / "bench.sim.json").string() + " " + args;
}

bool has(const std::string& text, const std::string& words) { return text.find(words) != std::string::npos; }

// A copy of the shipped config folder (bench, cells, programs) to break on purpose.
fs::path config_copy(const std::string& tag) {
    const fs::path dir = fs::temp_directory_path() / ("cellbench-check-" + tag + "-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    fs::create_directories(dir);
    fs::copy(kConfig, dir, fs::copy_options::recursive);
    return dir;
}

}  // namespace

TEST(CheckCli, AGoodProgramPrintsItsCompiledPlan) {
    const auto r = run(check("--program hppc_short --cell p45b --param c_rate=2 --param pulse_sets=2"));
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_TRUE(has(r.output, "ok: program hppc_short for cell p45b")) << r.output;
    EXPECT_TRUE(has(r.output, "c_rate         2 C")) << r.output;     // the override, with its unit
    EXPECT_TRUE(has(r.output, "chamber set point 30 degC")) << r.output;
    EXPECT_TRUE(has(r.output, "cccv_discharge  9 A")) << r.output;   // 2C of the 4.5 Ah cell, evaluated
    EXPECT_TRUE(has(r.output, "back to step 4, 2 times")) << r.output;
    EXPECT_TRUE(has(r.output, "largest current 9 A")) << r.output;
    EXPECT_TRUE(has(r.output, "expected duration about")) << r.output;

    // --json: the expanded program, as the run record stores it.
    const auto j = run(check("--program hppc_short --cell p45b --param c_rate=2 --json"));
    ASSERT_EQ(j.status, 0) << j.output;
    const auto doc = nlohmann::json::parse(j.output);
    EXPECT_EQ(doc["ok"], true);
    EXPECT_EQ(doc["program"]["parameters"]["c_rate"]["default"], 2.0);
}

// Whether the daemon will fit while the run goes: the plan counts the pulse sets the online fitter detects (loops
// unrolled), the USABC manual's form too (a regen pulse straight into the SOC step), and says so when there are
// none (pulses after rests too short to read the OCV), so that a lab engineer knows before the run that only
// `cellbench fit` afterwards characterizes it.
TEST(CheckCli, ThePlanSaysHowManyPulseSetsTheDaemonWillFitOnline) {
    const auto r = run(check("--program hppc_short --cell p45b --param pulse_sets=2"));
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_TRUE(has(r.output, "online fits: 2 pulse sets")) << r.output;
    const auto j = run(check("--program hppc_short --cell p45b --param pulse_sets=4 --json"));
    ASSERT_EQ(j.status, 0) << j.output;
    EXPECT_EQ(nlohmann::json::parse(j.output)["online_pulse_sets"], 4);

    const fs::path dir = config_copy("online");
    {
        auto prog = nlohmann::json::parse(std::ifstream(dir / "programs" / "hppc_short.json"));
        auto& steps = prog["segments"][2]["steps"];
        ASSERT_EQ(steps[6]["type"], "rest");
        steps.erase(6);  // no rest after the charge pulse: the SOC step follows at once
        std::ofstream(dir / "programs" / "usabc_like.json") << prog.dump(2);
        steps[2]["time_s"] = 300;  // rests before the pulses too short for an OCV
        steps[7]["time_s"] = 300;
        std::ofstream(dir / "programs" / "short_rests.json") << prog.dump(2);
    }
    const auto u = run(kBin.string() + " check --config " + (dir / "bench.sim.json").string() +
                       " --program usabc_like --cell p45b");
    ASSERT_EQ(u.status, 0) << u.output;
    EXPECT_TRUE(has(u.output, "online fits: 3 pulse sets")) << u.output;
    const auto s = run(kBin.string() + " check --config " + (dir / "bench.sim.json").string() +
                       " --program short_rests --cell p45b");
    ASSERT_EQ(s.status, 0) << s.output;
    EXPECT_TRUE(has(s.output, "online fits: none")) << s.output;
    fs::remove_all(dir);
}

TEST(CheckCli, EveryProblemOfTheOverridesIsReportedAtOnce) {
    const auto r = run(check("--program hppc_short --cell p45b --param c_rate=fast --param soc_step=0.9 "
                             "--param crate=2 --param pulse_sets=1.5 --param bogus"));
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_TRUE(has(r.output, "nothing was started")) << r.output;
    EXPECT_TRUE(has(r.output, "--param: expected NAME=VALUE")) << r.output;  // "bogus"
    EXPECT_TRUE(has(r.output, "$.parameters.c_rate: override: expected a number (C), got \"fast\"")) << r.output;
    EXPECT_TRUE(has(r.output, "$.parameters.soc_step: override: 0.9 is out of the declared range 0.01..0.5")) << r.output;
    EXPECT_TRUE(has(r.output, "override \"crate\" is not a parameter of this program")) << r.output;
    EXPECT_TRUE(has(r.output, "$.parameters.pulse_sets: override: expected a whole number, got 1.5")) << r.output;
    EXPECT_TRUE(has(r.output, "5 problems")) << r.output;
}

TEST(CheckCli, ProblemsOfTheBenchTheCellAndTheProgramComeTogether) {
    const fs::path dir = config_copy("files");
    // The bench: a bad port. The cell: fine. The program: a step beyond the cell's charge limit and a bad type.
    {
        auto bench = nlohmann::json::parse(std::ifstream(dir / "bench.sim.json"));
        bench["listen"] = "127.0.0.1:99999";
        std::ofstream(dir / "bench.sim.json") << bench.dump(2);
        auto prog = nlohmann::json::parse(std::ifstream(dir / "programs" / "cc.json"));
        prog["segments"][2]["steps"][1]["current_a"] = 30;   // 30 A charge > 13.5 A
        prog["segments"][1]["hold_s"] = "long";
        std::ofstream(dir / "programs" / "cc.json") << prog.dump(2);
    }
    const auto r = run(kBin.string() + " check --config " + (dir / "bench.sim.json").string() + " --program cc --cell p45b");
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_TRUE(has(r.output, "bench.sim.json: $.listen")) << r.output;
    EXPECT_TRUE(has(r.output, "cc.json: $.segments[2].steps[1].current_a")) << r.output;
    EXPECT_TRUE(has(r.output, "cc.json: $.segments[1].hold_s")) << r.output;

    // An unknown cell: said, and the program is not silently passed.
    const auto r2 = run(check("--program cc --cell nosuchcell"));
    EXPECT_EQ(r2.status, 1) << r2.output;
    EXPECT_TRUE(has(r2.output, "nosuchcell")) << r2.output;
    EXPECT_TRUE(has(r2.output, "not checked (the cell did not load)")) << r2.output;
    fs::remove_all(dir);
}
