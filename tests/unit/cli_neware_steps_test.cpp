// `cellbench steps`: the step file the daemon would send, in the real BTS Client schema; the file written for
// hppc re-parses to the same program (as the tester carries it), and `import --neware` logs which export
// layout it read.
#include <gtest/gtest.h>

#include "support/command.hpp"

#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "cellbench/daemon/config.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"

namespace fs = std::filesystem;
using namespace cellbench;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kConfig = fs::path(CELLBENCH_SOURCE_DIR) / "config";

using CliRun = cellbench::test::CommandRun;

CliRun run(const std::string& command) { return cellbench::test::run_command(command); }

std::string read(const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

fs::path temp_dir() {
    const fs::path dir = fs::temp_directory_path() / ("cellbench-steps-" + std::to_string(::getpid()));
    fs::create_directories(dir);
    return dir;
}

}  // namespace

TEST(NewareStepsCli, HppcStepFileReparsesToTheSameProgram) {
    const fs::path dir = temp_dir();
    const fs::path out = dir / "hppc.xml";
    const CliRun r = run(kBin.string() + " steps --program hppc --cell p45b --config " + (kConfig / "bench.sim.json").string() +
                      " -o " + out.string());
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_NE(r.output.find("capacity limit 0.1*C4 - C8 + C10"), std::string::npos) << r.output;  // says how eq. 2.4 is written
    const std::string xml = read(out);
    EXPECT_EQ(xml.rfind("<?xml version=\"1.0\" encoding=\"GB2312\"?>\r\n<root>\r\n  <config type=\"Step File\" version=\"17\"", 0), 0u)
        << xml.substr(0, 200);
    const protocol::StepProgram parsed = protocol::parse_step_file(xml);

    // The program as the daemon loads it for that cell, in the form the step file carries.
    const auto bench = daemon::load_bench_config(kConfig / "bench.sim.json");
    const auto cell = daemon::load_cell_config(daemon::cell_file(bench.config_dir, "p45b"));
    const auto program = daemon::load_program(daemon::program_file(bench.config_dir, "hppc"), cell, {}, &bench);
    const protocol::StepProgram* cycler = nullptr;
    for (const auto& s : program.segments)
        if (const auto* c = std::get_if<daemon::CyclerSegment>(&s)) cycler = &c->program;
    ASSERT_NE(cycler, nullptr);
    protocol::StepProgram expected = *cycler;
    expected.settings.nominal_capacity_ah = cell.nominal_capacity_ah;
    EXPECT_EQ(parsed, protocol::as_tester_program(expected));
    ASSERT_EQ(parsed.steps.size(), 17u);
    EXPECT_EQ(parsed.steps[13].type, protocol::StepType::cycle);
    EXPECT_EQ(parsed.steps[13].count, 10);
    // 0.1 x 4.5 Ah - 4.5 A x 30 s + 4.5 A x 10 s
    EXPECT_NEAR(parsed.steps[11].cutoff_capacity_ah->constant_ah, 0.425, 1e-9);
    fs::remove_all(dir);
}

TEST(NewareStepsCli, UnknownProgramIsOneClearError) {
    const fs::path dir = temp_dir();
    const CliRun r = run(kBin.string() + " steps --program no_such_program --cell p45b --config " +
                      (kConfig / "bench.sim.json").string() + " -o " + (dir / "x.xml").string());
    EXPECT_EQ(r.status, 1) << r.output;
    EXPECT_NE(r.output.find("no_such_program"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(dir / "x.xml"));
    EXPECT_EQ(run(kBin.string() + " steps --cell p45b -o x.xml").status, 2);  // usage: --program missing
    fs::remove_all(dir);
}

TEST(NewareStepsCli, ImportSaysWhichNewareLayoutItRead) {
    const fs::path dir = temp_dir();
    std::ofstream(dir / "cumulative.csv") << "Record ID,Step Type,Cumulative Time,Current(A),Voltage(V)\n"
                                             "1,Rest,00:00:00,0,4.1\n2,CC DChg,00:00:01.500,-4.5,4.0\n3,CC DChg,00:01:01,-4.5,3.9\n";
    const CliRun r = run(kBin.string() + " import --neware " + (dir / "cumulative.csv").string() + " -o " +
                      (dir / "out.bdf.csv").string());
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_NE(r.output.find("Cumulative Time"), std::string::npos) << r.output;
    const std::string bdf = read(dir / "out.bdf.csv");
    EXPECT_NE(bdf.find("\n61,"), std::string::npos) << bdf;
    fs::remove_all(dir);
}

TEST(NewareStepsCli, EveryProgramUnderConfigCompilesToAStepFileThatReadsBack) {
    const auto bench = daemon::load_bench_config(kConfig / "bench.sim.json");
    const auto cell = daemon::load_cell_config(daemon::cell_file(bench.config_dir, "p45b"));
    const auto names = daemon::list_programs(bench.config_dir);
    EXPECT_GE(names.size(), 5u);
    for (const auto& name : names) {
        const auto program = daemon::load_program(daemon::program_file(bench.config_dir, name), cell, {}, &bench);
        int files = 0;
        for (const auto& s : program.segments) {
            const auto* c = std::get_if<daemon::CyclerSegment>(&s);
            if (c == nullptr) continue;  // chamber segments are the daemon's, not the tester's
            protocol::StepProgram p = c->program;
            p.settings.nominal_capacity_ah = cell.nominal_capacity_ah;
            const std::string xml = protocol::compile_step_file(p);
            EXPECT_EQ(protocol::parse_step_file(xml), protocol::as_tester_program(p)) << name;
            // What the daemon sends: one or two files (tester_parts), each valid for the tester.
            for (const auto& part : protocol::tester_parts(c->program))
                EXPECT_NO_THROW((void)protocol::parse_step_file(protocol::compile_step_file(
                    protocol::resolve_capacity_limits(part, [](int) { return std::optional<double>(4.0); }))))
                    << name;
            ++files;
        }
        EXPECT_GT(files, 0) << name;
    }
}
