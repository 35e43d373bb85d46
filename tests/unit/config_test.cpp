// cellbenchd configuration: every shipped file loads, every problem of a bad file is reported at once (file,
// JSON path, what was expected), and programs expand to the thesis' step tables (C-rate, HPPC's C12 formula).
#include <gtest/gtest.h>

#include <unistd.h>

#include <fstream>
#include <random>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/config.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "config_test_support.hpp"

using namespace cellbench;
using namespace cellbench::daemon;
using namespace cellbench::testing;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

CellConfig p45b() { return load_cell_config(kConfigDir / "cells" / "p45b.json"); }
BenchConfig sim_bench() { return load_bench_config(kConfigDir / "bench.sim.json"); }

const protocol::StepProgram& cycler_of(const Program& p, std::size_t segment) {
    return std::get<CyclerSegment>(p.segments.at(segment)).program;
}

std::string dump(const std::vector<ConfigIssue>& issues) {
    std::string s;
    for (const auto& i : issues) s += i.to_string() + "\n";
    return s;
}

class TempDir {
public:
    TempDir() {
        std::random_device rd;
        path_ = fs::temp_directory_path() / ("cellbench-config-test-" + std::to_string(::getpid()) + "-" + std::to_string(rd()));
        fs::create_directories(path_);
    }
    ~TempDir() {
        std::error_code ec;
        fs::remove_all(path_, ec);
    }
    [[nodiscard]] const fs::path& path() const { return path_; }
    fs::path write(const std::string& name, const std::string& text) const {
        const fs::path p = path_ / name;
        fs::create_directories(p.parent_path());
        std::ofstream(p) << text;
        return p;
    }

private:
    fs::path path_;
};

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Shipped files

TEST(Config, EveryShippedBenchFileLoads) {
    const auto sim = sim_bench();
    EXPECT_TRUE(sim.any_simulated());
    ASSERT_TRUE(sim.simulation.has_value());
    EXPECT_TRUE(fs::exists(sim.simulation->params_path)) << sim.simulation->params_path;
    EXPECT_EQ(sim.cycler.channels.size(), 3u);
    EXPECT_DOUBLE_EQ(sim.cycler.group_max_current_a(), 60.0);
    EXPECT_EQ(sim.cycler.poll_period_ms, 100);
    EXPECT_EQ(sim.listen.to_string(), "127.0.0.1:8750");
    EXPECT_EQ(sim.token_env, "CELLBENCH_TOKEN");
    EXPECT_DOUBLE_EQ(sim.daq.sensitivity_v_per_w_per_m2, 17.39e-6);
    EXPECT_NEAR(sim.daq.sensor_area_m2, 0.036 * 0.036, 1e-12);
    EXPECT_DOUBLE_EQ(sim.daq.cell_area_m2, 5.311e-3);
    EXPECT_EQ(sim.daq.layout.at("schema"), "cellbench.dewe-can/1");  // the default layout, filled in
    EXPECT_EQ(sim.chamber.register_map.at("schema"), "cellbench.chamber-modbus/1");
    EXPECT_EQ(sim.config_dir, kConfigDir);

    // HIL: the daemon talks to `cellbench sim` at the addresses it prints (INTERFACES.md).
    const auto hil = load_bench_config(kConfigDir / "bench.hil.json");
    EXPECT_FALSE(hil.any_simulated());
    EXPECT_EQ(hil.cycler.mode, CyclerConfig::Mode::tcp);
    EXPECT_EQ(hil.cycler.endpoint.to_string(), "127.0.0.1:15020");
    EXPECT_EQ(hil.chamber.mode, ChamberConfig::Mode::modbus_tcp);
    EXPECT_EQ(hil.chamber.endpoint.to_string(), "127.0.0.1:15021");
    EXPECT_EQ(hil.daq.transport, DaqConfig::Transport::can_dgram);
    EXPECT_FALSE(hil.daq.socket_path.empty());

    const auto lab = load_bench_config(kConfigDir / "bench.lab.json");
    EXPECT_EQ(lab.daq.transport, DaqConfig::Transport::socketcan);
    EXPECT_EQ(lab.daq.interface, "can0");
    EXPECT_EQ(lab.chamber.unit_id, 1);
    EXPECT_FALSE(lab.simulation.has_value());
}

TEST(Config, ShippedCellLoadsAndParameterSetsAreNotListedAsCells) {
    const auto cell = p45b();
    EXPECT_EQ(cell.id, "p45b");
    EXPECT_DOUBLE_EQ(cell.nominal_capacity_ah, 4.5);
    EXPECT_DOUBLE_EQ(cell.min_voltage_v, 2.9);
    EXPECT_DOUBLE_EQ(cell.max_voltage_v, 4.1);
    EXPECT_DOUBLE_EQ(cell.max_temperature_c, 60.0);
    ASSERT_TRUE(cell.params_path.has_value());
    EXPECT_TRUE(fs::exists(*cell.params_path));
    EXPECT_EQ(list_cells(kConfigDir), std::vector<std::string>{"p45b"});

    // The thesis parameter set beside it is not a cell file, and says so.
    try {
        load_cell_config(kConfigDir / "cells" / "p45b-thesis.json");
        FAIL() << "a parameter set loaded as a cell";
    } catch (const ConfigError& e) {
        EXPECT_TRUE(has_issue(e.issues(), "$.schema", "parameter set")) << e.what();
    }
}

TEST(Config, EveryShippedProgramLoadsForTheCellOnEveryBench) {
    const auto cell = p45b();
    const auto programs = list_programs(kConfigDir);
    for (const char* expected : {"cc", "hppc", "rw", "hppc_short", "gitt"})
        EXPECT_NE(std::find(programs.begin(), programs.end(), expected), programs.end()) << expected;
    for (const char* bench_file : {"bench.sim.json", "bench.hil.json", "bench.lab.json"}) {
        const auto bench = load_bench_config(kConfigDir / bench_file);
        for (const auto& name : programs) {
            SCOPED_TRACE(std::string(bench_file) + " / " + name);
            Program p;
            ASSERT_NO_THROW(p = load_program(program_file(kConfigDir, name), cell, {}, &bench));
            EXPECT_FALSE(p.segments.empty());
            EXPECT_LE(p.max_current_a(), bench.safety.max_current_a);
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// Errors: all of them, with paths

TEST(Config, ABenchFileWithSeveralErrorsReportsThemAll) {
    json j = read_json(kConfigDir / "bench.sim.json");
    j["instruments"]["cycler"]["port"] = "fifteen";
    j["instruments"]["cycler"]["channels"][1].erase("chlid");
    j["instruments"]["daq"]["transport"] = "udp";
    j["instruments"]["daq"]["layout"] = json{{"frames", json::array()}};
    j["instruments"]["chamber"]["unit_id"] = 300;
    j["safety"].erase("max_current_a");
    j["database"]["flush_period_ms"] = 5000;
    j["listen"] = "localhost";
    j["instrumnets"] = json::object();  // a typo
    const auto issues = issues_of([&] { parse_bench_config(j, "broken.json", kConfigDir); });
    const std::string all = dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.instruments.cycler.port", "expected an integer")) << all;
    EXPECT_TRUE(has_issue(issues, "$.instruments.cycler.channels[1].chlid", "missing")) << all;
    EXPECT_TRUE(has_issue(issues, "$.instruments.daq.transport", "\"can-dgram\" or \"socketcan\"")) << all;
    EXPECT_TRUE(has_issue(issues, "$.instruments.daq.layout.frames", "")) << all;
    EXPECT_TRUE(has_issue(issues, "$.instruments.chamber.unit_id", "0..247")) << all;
    EXPECT_TRUE(has_issue(issues, "$.safety.max_current_a", "missing")) << all;
    EXPECT_TRUE(has_issue(issues, "$.database.flush_period_ms", "10..500")) << all;
    EXPECT_TRUE(has_issue(issues, "$.listen", "HOST:PORT")) << all;
    EXPECT_TRUE(has_issue(issues, "$.instrumnets", "unknown field")) << all;
    for (const auto& i : issues) EXPECT_EQ(i.file, "broken.json");
    // One message for the user: every problem on its own line, each naming the file.
    try {
        parse_bench_config(j, "broken.json", kConfigDir);
    } catch (const InputError& e) {
        const std::string what = e.what();
        EXPECT_NE(what.find("broken.json: $.instruments.cycler.port: expected an integer 0..65535, got \"fifteen\""),
                  std::string::npos)
            << what;
        EXPECT_EQ(static_cast<std::size_t>(std::count(what.begin(), what.end(), '\n')) + 1, issues.size());
    }
}

TEST(Config, SimulatedInstrumentsNeedASimulationSectionAndAValidParameterSet) {
    json j = read_json(kConfigDir / "bench.sim.json");
    j.erase("simulation");
    EXPECT_TRUE(has_issue(issues_of([&] { parse_bench_config(j, "b.json", kConfigDir); }), "$.simulation", "missing"));
    j = read_json(kConfigDir / "bench.sim.json");
    j["simulation"]["params"] = "cells/no-such-file.json";
    EXPECT_TRUE(has_issue(issues_of([&] { parse_bench_config(j, "b.json", kConfigDir); }), "$.simulation.params", "no such file"));
}

TEST(Config, InvalidJsonNamesTheFileLineAndColumn) {
    TempDir dir;
    const auto f = dir.write("bench.json", "{\n  \"schema\": \"cellbench.bench/1\",\n  \"name\": oops\n}\n");
    try {
        load_bench_config(f);
        FAIL() << "invalid JSON accepted";
    } catch (const InputError& e) {
        const std::string what = e.what();
        EXPECT_NE(what.find(f.string()), std::string::npos) << what;
        EXPECT_NE(what.find("line 3"), std::string::npos) << what;
    }
    try {
        load_bench_config(dir.path() / "missing.json");
        FAIL() << "a missing file loaded";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("no such file"), std::string::npos) << e.what();
    }
}

TEST(Config, ACellFileWithSeveralErrorsReportsThemAll) {
    json j = read_json(kConfigDir / "cells" / "p45b.json");
    j["nominal_capacity_ah"] = -1;
    j["min_voltage_v"] = 4.2;  // above max_voltage_v
    j.erase("max_temperature_c");
    const auto issues = issues_of([&] { parse_cell_config(j, "c.json", kConfigDir / "cells"); });
    EXPECT_TRUE(has_issue(issues, "$.nominal_capacity_ah", "in (0, 10000], got -1")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$", "min_voltage_v < max_voltage_v")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.max_temperature_c", "missing")) << dump(issues);
}

TEST(Config, AProgramWithSeveralErrorsReportsThemAll) {
    const auto cell = p45b();
    json j = read_json(kConfigDir / "programs" / "cc.json");
    auto& steps = j["segments"][2]["steps"];
    steps[1]["current_a"] = "one_c_b";                   // unknown name
    steps[3]["current_a"] = "C2 * 4.5";                  // step capacity outside cutoff_capacity_ah
    steps[4]["time_s"] = "600 / (c_rate - 1)";           // division by zero at c_rate 1
    j["segments"][0]["setpoint_c"] = "temperature_c +";  // syntax
    j["segments"][1]["hold_s"] = 99999;                  // longer than the timeout
    const auto issues = issues_of([&] { parse_program(j, "cc.json", cell); });
    const std::string all = dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[1].current_a", "unknown name \"one_c_b\"")) << all;
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[3].current_a", "only allowed in cutoff_capacity_ah")) << all;
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[4].time_s", "division by zero")) << all;
    EXPECT_TRUE(has_issue(issues, "$.segments[0].setpoint_c", "")) << all;
    EXPECT_TRUE(has_issue(issues, "$.segments[1]", "timeout_s > hold_s")) << all;
}

TEST(Config, StepProgramProblemsAreReportedUnderTheSegmentPath) {
    json j = read_json(kConfigDir / "programs" / "cc.json");
    j["segments"][2]["steps"][0]["type"] = "jog";
    const auto issues = issues_of([&] { parse_program(j, "cc.json", p45b()); });
    ASSERT_EQ(issues.size(), 1u) << dump(issues);
    EXPECT_EQ(issues[0].path, "$.segments[2].steps[0].type");
    EXPECT_NE(issues[0].message.find("jog"), std::string::npos);
}

TEST(Config, ProgramsAreCheckedAgainstTheCellAndTheBench) {
    const auto cell = p45b();
    const auto bench = sim_bench();
    // 13C = 58.5 A: above the P45B's 45 A continuous discharge limit.
    auto issues = issues_of([&] { load_program(program_file(kConfigDir, "cc"), cell, {{"c_rate", 13.0}}, &bench); });
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[3].current_a", "max_discharge_current_a (45 A)")) << dump(issues);
    // 70 degC: above the cell's 60 degC and the bench's max_temperature_c.
    issues = issues_of([&] { load_program(program_file(kConfigDir, "cc"), cell, {{"temperature_c", 70.0}}, &bench); });
    EXPECT_TRUE(has_issue(issues, "$.segments[0].setpoint_c", "cell's temperature range")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.segments[0].setpoint_c", "max_temperature_c")) << dump(issues);
    // A cut-off outside the cell's window.
    json j = read_json(kConfigDir / "programs" / "cc.json");
    j["segments"][2]["steps"][3]["cutoff_voltage_v"] = 2.5;
    issues = issues_of([&] { parse_program(j, "cc.json", cell, {}, &bench); });
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[3].cutoff_voltage_v", "2.9..4.1 V")) << dump(issues);
    // A CC step without a voltage limit.
    j = read_json(kConfigDir / "programs" / "cc.json");
    j["segments"][2]["steps"][3].erase("cutoff_voltage_v");
    j["segments"][2]["steps"][3]["time_s"] = 60;
    issues = issues_of([&] { parse_program(j, "cc.json", cell, {}, &bench); });
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[3]", "cutoff_voltage_v")) << dump(issues);
}

TEST(Config, OverridesMustBeDeclaredParameters) {
    const auto issues = issues_of([&] { load_program(program_file(kConfigDir, "cc"), p45b(), {{"crate", 2.0}}); });
    ASSERT_FALSE(issues.empty());
    EXPECT_NE(issues[0].message.find("\"crate\" is not a parameter"), std::string::npos) << dump(issues);
    EXPECT_NE(issues[0].message.find("c_rate"), std::string::npos) << dump(issues);
}

TEST(Config, OverridesAreValidatedLikeTheProgramEveryProblemAtOnce) {
    const auto cell = p45b();
    const auto bench = sim_bench();
    // Wrong type, not a whole number, outside the declared range, unknown name, and a value that passes its
    // declaration but takes a step beyond the cell (c_rate 10 = 45 A charge pulse > 13.5 A): all in one error.
    const auto issues = issues_of([&] {
        load_program(program_file(kConfigDir, "hppc_short"), cell,
                     {{"temperature_c", "warm"}, {"pulse_sets", 2.5}, {"soc_step", 0.9}, {"crate", 2}, {"c_rate", 10}},
                     &bench);
    });
    EXPECT_TRUE(has_issue(issues, "$.parameters.temperature_c", "expected a number (degC), got \"warm\"")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters.pulse_sets", "expected a whole number, got 2.5")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters.soc_step", "0.9 is out of the declared range 0.01..0.5")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters", "\"crate\" is not a parameter")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[5].current_a", "max_charge_current_a")) << dump(issues);
    EXPECT_EQ(issues.size(), 5u) << dump(issues);
}

TEST(Config, OverridesInTheDeclaredRangeAreUsed) {
    const auto bench = sim_bench();
    const auto p = load_program(program_file(kConfigDir, "hppc_short"), p45b(),
                                {{"c_rate", 2}, {"pulse_sets", 2}, {"temperature_c", 25.5}}, &bench);
    EXPECT_DOUBLE_EQ(p.parameters.at("c_rate"), 2.0);
    EXPECT_DOUBLE_EQ(*cycler_of(p, 2).steps[3].current_a, 9.0);  // the discharge pulse at 2C
    EXPECT_EQ(cycler_of(p, 2).steps[9].count, 2);                  // the loop runs the pulse sets asked for
    EXPECT_DOUBLE_EQ(std::get<ChamberSetpointSegment>(p.segments[0]).setpoint_c, 25.5);
    // The declaration travels with the expanded program (the run record) and reads back unchanged.
    const auto& spec = p.parameter_specs.at("c_rate");
    EXPECT_EQ(spec.unit, "C");
    ASSERT_TRUE(spec.max.has_value());
    EXPECT_DOUBLE_EQ(*spec.max, 10.0);
    EXPECT_EQ(parse_program(p.to_json(), "expanded.json", p45b()), p);
}

TEST(Config, ExpectedDurationFollowsTheProgramsSteps) {
    const auto cell = p45b();
    const auto two = estimate_duration(load_program(program_file(kConfigDir, "hppc_short"), cell, {{"pulse_sets", 2}}), cell);
    const auto three = estimate_duration(load_program(program_file(kConfigDir, "hppc_short"), cell, {{"pulse_sets", 3}}), cell);
    // One more pass of the loop body: 30 s pulse, 40 s rest, 10 s pulse, 40 s rest, the SOC step
    // (0.1 * 4.5 Ah - C4 + C6 = 0.425 Ah at 4.5 A = 340 s) and its 600 s rest.
    EXPECT_NEAR(three.total_s - two.total_s, 30 + 40 + 10 + 40 + 340 + 600, 1e-6);
    ASSERT_EQ(three.segment_s.size(), 3u);
    EXPECT_DOUBLE_EQ(three.segment_s[0], 0.0);   // a set point
    EXPECT_DOUBLE_EQ(three.segment_s[1], 60.0);  // the wait's hold
    // cc: full charge from 50 % at 1C (1800 s + the CV tail), 600 s rest, the discharge to empty at c_rate.
    const auto one_c = estimate_duration(load_program(program_file(kConfigDir, "cc"), cell), cell);
    const auto two_c = estimate_duration(load_program(program_file(kConfigDir, "cc"), cell, {{"c_rate", 2}}), cell);
    EXPECT_NEAR(one_c.total_s - two_c.total_s, 1800.0, 1e-6);
}

TEST(Config, ParameterDeclarationsAreCheckedInTheFile) {
    json j = read_json(kConfigDir / "programs" / "cc.json");
    j["parameters"]["c_rate"] = {{"default", 20}, {"min", 0.1}, {"max", 10}};
    j["parameters"]["temperature_c"] = {{"default", 25}, {"min", 30}, {"max", 20}, {"maximum", 1}};
    j["parameters"]["n"] = {{"default", 1.5}, {"integer", true}};
    j["parameters"]["m"] = {{"min", 1}};
    const auto issues = issues_of([&] { parse_program(j, "cc.json", p45b()); });
    EXPECT_TRUE(has_issue(issues, "$.parameters.c_rate.default", "outside min..max")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters.temperature_c", "min 30 is above max 20")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters.temperature_c.maximum", "unknown field")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters.n.default", "whole number")) << dump(issues);
    EXPECT_TRUE(has_issue(issues, "$.parameters.m.default", "missing")) << dump(issues);
}

TEST(Config, CommandLineOverridesAreTyped) {
    EXPECT_EQ(parse_override_argument("c_rate=2"), (std::pair<std::string, json>{"c_rate", 2.0}));
    EXPECT_EQ(parse_override_argument("soc_step=5e-2").second, json(0.05));
    EXPECT_EQ(parse_override_argument("flag=true").second, json(true));
    EXPECT_EQ(parse_override_argument("c_rate=fast").second, json("fast"));  // the loader names the wrong type
    EXPECT_EQ(parse_override_argument("c_rate=1e999").second, json("1e999"));
    EXPECT_EQ(parse_override_argument("c_rate=").second, json(""));
    EXPECT_THROW(parse_override_argument("c_rate"), InputError);
    EXPECT_THROW(parse_override_argument("=2"), InputError);
}

// ---------------------------------------------------------------------------------------------------------
// Expansion

TEST(Config, CcExpandsToTable210AtTheRequestedCRate) {
    const auto cell = p45b();
    const auto p1 = load_program(program_file(kConfigDir, "cc"), cell);
    ASSERT_EQ(p1.segments.size(), 3u);
    EXPECT_DOUBLE_EQ(std::get<ChamberSetpointSegment>(p1.segments[0]).setpoint_c, 30.0);
    const auto& wait = std::get<WaitEquilibriumSegment>(p1.segments[1]);
    EXPECT_DOUBLE_EQ(wait.tolerance_c, 0.5);
    EXPECT_DOUBLE_EQ(wait.hold_s, 1800.0);
    EXPECT_EQ(cycler_of(p1, 2).steps, protocol::thesis_cc_discharge_program(1.0).steps);

    const auto p2 = load_program(program_file(kConfigDir, "cc"), cell, {{"c_rate", 2.0}, {"temperature_c", 25.0}});
    EXPECT_EQ(cycler_of(p2, 2).steps, protocol::thesis_cc_discharge_program(2.0).steps);
    EXPECT_DOUBLE_EQ(*cycler_of(p2, 2).steps[3].current_a, 9.0);
    EXPECT_DOUBLE_EQ(*cycler_of(p2, 2).steps[1].current_a, 4.5);  // the charge stays at 1C
    EXPECT_DOUBLE_EQ(std::get<ChamberSetpointSegment>(p2.segments[0]).setpoint_c, 25.0);
    EXPECT_DOUBLE_EQ(p2.parameters.at("c_rate"), 2.0);
}

TEST(Config, HppcExpandsToTable212WithTheC12Formula) {
    const auto cell = p45b();
    const auto p = load_program(program_file(kConfigDir, "hppc"), cell);
    const auto& sp = cycler_of(p, 2);
    EXPECT_EQ(sp.steps, protocol::thesis_hppc_program().steps);
    ASSERT_EQ(sp.steps.size(), 17u);
    // Step 12: C12 = 0.1*C4 - C8 + C10 (thesis eq. 2.4), evaluated by the tester from the step capacities.
    const auto& c12 = sp.steps[11].cutoff_capacity_ah;
    ASSERT_TRUE(c12.has_value());
    EXPECT_EQ(*c12, (protocol::CapacityExpression{0.0, {{4, 0.1}, {8, -1.0}, {10, 1.0}}}));
    const auto capacity = [](int step) { return step == 4 ? 4.3 : step == 8 ? 0.0375 : step == 10 ? 0.0125 : 0.0; };
    EXPECT_NEAR(c12->evaluate(capacity), 0.43 - 0.0375 + 0.0125, 1e-12);
    // Step 14 loops back to the discharge pulse: 10 pulse sets.
    EXPECT_EQ(sp.steps[13].type, protocol::StepType::cycle);
    EXPECT_EQ(sp.steps[13].start_step, 8);
    EXPECT_EQ(sp.steps[13].count, 10);

    // Parameters reach the formula and the loop.
    const auto q = load_program(program_file(kConfigDir, "hppc"), cell, {{"soc_step", 0.05}, {"pulse_sets", 20}, {"c_rate", 2.0}});
    const auto& sq = cycler_of(q, 2);
    EXPECT_EQ(*sq.steps[11].cutoff_capacity_ah, (protocol::CapacityExpression{0.0, {{4, 0.05}, {8, -1.0}, {10, 1.0}}}));
    EXPECT_EQ(sq.steps[13].count, 20);
    EXPECT_DOUBLE_EQ(*sq.steps[7].current_a, 9.0);
    EXPECT_DOUBLE_EQ(*sq.steps[9].current_a, 9.0);
}

TEST(Config, HppcShortMixesCellConstantsWithStepCapacities) {
    const auto p = load_program(program_file(kConfigDir, "hppc_short"), p45b());
    const auto& sp = cycler_of(p, 2);
    // 0.1 * 4.5 Ah - C4 + C6
    EXPECT_EQ(*sp.steps[7].cutoff_capacity_ah, (protocol::CapacityExpression{0.45, {{4, -1.0}, {6, 1.0}}}));
    EXPECT_EQ(sp.steps[9].count, 3);
    EXPECT_EQ(sp.steps[9].start_step, 4);
}

TEST(Config, RandomWalkExpandsToTable51) {
    const auto p = load_program(program_file(kConfigDir, "rw"), p45b());
    EXPECT_EQ(cycler_of(p, 2).steps, protocol::thesis_random_walk_program().steps);
}

TEST(Config, ACampaignRepeatsItsSegmentsForEachValue) {
    const auto cell = p45b();
    const auto p = load_program(program_file(kConfigDir, "cc_temperatures"), cell);
    ASSERT_EQ(p.segments.size(), 9u);
    std::vector<double> setpoints;
    for (const auto& s : p.segments)
        if (const auto* c = std::get_if<ChamberSetpointSegment>(&s)) setpoints.push_back(c->setpoint_c);
    EXPECT_EQ(setpoints, (std::vector<double>{10.0, 25.0, 40.0}));
    // Overriding the repeated parameter runs that one value.
    const auto one = load_program(program_file(kConfigDir, "cc_temperatures"), cell, {{"temperature_c", 40.0}});
    ASSERT_EQ(one.segments.size(), 3u);
    EXPECT_DOUBLE_EQ(std::get<ChamberSetpointSegment>(one.segments[0]).setpoint_c, 40.0);
}

TEST(Config, ExpandedProgramsRoundTripThroughJson) {
    const auto cell = p45b();
    for (const char* name : {"cc", "hppc", "rw", "hppc_short", "cc_temperatures", "gitt"}) {
        SCOPED_TRACE(name);
        const auto p = load_program(program_file(kConfigDir, name), cell);
        const auto again = parse_program(p.to_json(), "expanded.json", cell);
        EXPECT_EQ(again, p);
    }
}

TEST(Config, ABareStepProgramIsAOneSegmentProgram) {
    const auto sp = protocol::thesis_hppc_program();
    const auto p = parse_program(sp.to_json(), "steps.json", p45b());
    ASSERT_EQ(p.segments.size(), 1u);
    EXPECT_EQ(cycler_of(p, 0), sp);
}

TEST(Config, Expressions) {
    const std::map<std::string, double> names{{"c_rate", 2.0}, {"one_c_a", 4.5}};
    EXPECT_DOUBLE_EQ(evaluate_expression("c_rate * one_c_a", names), 9.0);
    EXPECT_DOUBLE_EQ(evaluate_expression("1 + 2 * 3", names), 7.0);
    EXPECT_DOUBLE_EQ(evaluate_expression("(1 + 2) * 3", names), 9.0);
    EXPECT_DOUBLE_EQ(evaluate_expression("-c_rate / 4", names), -0.5);
    EXPECT_DOUBLE_EQ(evaluate_expression(" 1.5e1 - 5 ", names), 10.0);
    EXPECT_THROW(evaluate_expression("1 / (c_rate - 2)", names), InputError);
    EXPECT_THROW(evaluate_expression("c_rate *", names), InputError);
    EXPECT_THROW(evaluate_expression("nope", names), InputError);
    EXPECT_THROW(evaluate_expression("2 c_rate", names), InputError);
    EXPECT_THROW(evaluate_expression("", names), InputError);
}

TEST(Config, FilesAreNamedNotPathed) {
    EXPECT_EQ(program_file(kConfigDir, "hppc"), kConfigDir / "programs" / "hppc.json");
    EXPECT_EQ(cell_file(kConfigDir, "p45b"), kConfigDir / "cells" / "p45b.json");
    for (const char* bad : {"../bench.sim", "/etc/passwd", "a/b", "", ".hidden", "x y"})
        EXPECT_THROW(program_file(kConfigDir, bad), InputError) << bad;
}

TEST(Config, Endpoints) {
    EXPECT_EQ(parse_endpoint("127.0.0.1:8750"), (Endpoint{"127.0.0.1", 8750}));
    EXPECT_EQ(parse_endpoint("[::1]:80"), (Endpoint{"::1", 80}));
    EXPECT_FALSE(parse_endpoint("localhost"));
    EXPECT_FALSE(parse_endpoint("host:99999"));
    EXPECT_FALSE(parse_endpoint(":80"));
}
