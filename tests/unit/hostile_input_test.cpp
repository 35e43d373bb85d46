// Issue 16: what a client, a file or a config can send must never crash a process nor yield a silently wrong
// result. Each test holds one hostile input found by hand (the issue's "What was found") to the behaviour the
// users rely on: a clear error naming the file, line or JSON path (or a 400 for the API), never an abort.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/config.hpp"
#include "cellbench/daemon/http_handler.hpp"
#include "cellbench/estimator/align.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/dewesoft_export.hpp"
#include "cellbench/protocol/json_input.hpp"
#include "unit/api_test_support.hpp"
#include "unit/config_test_support.hpp"

using namespace cellbench;
using namespace cellbench::testing;
using daemon::handle_http_request;
using http::verb;

namespace {

std::string error_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const InputError& e) {
        return e.what();
    }
    return "(no error)";
}

std::string nested(std::size_t depth, const std::string& open, const std::string& inner, const std::string& close) {
    std::string s;
    for (std::size_t i = 0; i < depth; ++i) s += open;
    s += inner;
    for (std::size_t i = 0; i < depth; ++i) s += close;
    return s;
}

daemon::CellConfig p45b() { return daemon::load_cell_config(kConfigDir / "cells/p45b.json"); }
daemon::BenchConfig sim_bench() { return daemon::load_bench_config(kConfigDir / "bench.sim.json"); }

std::string bench_text_with(const std::function<void(nlohmann::json&)>& edit) {
    auto j = read_json(kConfigDir / "bench.sim.json");
    edit(j);
    return j.dump();
}

}  // namespace

// ---- JSON: numbers beyond a double and deep nesting, wherever JSON is parsed.

TEST(HostileJson, NumberBeyondADoubleIsAnInputErrorNotAnException) {
    // nlohmann reports 1e999 as out_of_range, which the parse_error handlers did not catch.
    const auto msg = error_of([] { protocol::parse_json_input(R"({"program": 1e999})", "body"); });
    EXPECT_NE(msg.find("body: invalid JSON"), std::string::npos) << msg;
    EXPECT_NE(msg.find("1e999"), std::string::npos) << msg;
}

TEST(HostileJson, NestingIsBoundedBeforeParsing) {
    EXPECT_EQ(protocol::json_nesting_depth(R"({"a": [1, {"b": "[[[[{{{"}]})"), 3u);  // brackets in strings do not count
    const auto deep = nested(100000, "[", "1", "]");
    const auto msg = error_of([&] { protocol::parse_json_input(deep, "deep.json"); });
    EXPECT_NE(msg.find("deep.json: invalid JSON: nested deeper than 64"), std::string::npos) << msg;
    EXPECT_NO_THROW(protocol::parse_json_input(nested(60, "{\"a\":", "1", "}"), "ok.json"));
}

// ---- Bench configs and programs.

TEST(HostileConfig, TimeScaleBeyondADoubleIsAClearConfigError) {
    const std::string text = R"({"schema": "cellbench.bench/1", "simulation": {"time_scale": 1e400}})";
    const auto msg = error_of([&] { daemon::parse_bench_config_text(text, "bench.json", kConfigDir); });
    EXPECT_NE(msg.find("bench.json: invalid JSON"), std::string::npos) << msg;
    EXPECT_NE(msg.find("1e400"), std::string::npos) << msg;
}

TEST(HostileConfig, DeeplyNestedConfigIsAClearError) {
    const std::string text = "{\"schema\": \"cellbench.bench/1\", \"x\": " + nested(20000, "[", "0", "]") + "}";
    const auto msg = error_of([&] { daemon::parse_bench_config_text(text, "bench.json", kConfigDir); });
    EXPECT_NE(msg.find("nested deeper than"), std::string::npos) << msg;
}

TEST(HostileConfig, DeeplyNestedCurrentExpressionIsAClearErrorNotAStackOverflow) {
    const auto cell = p45b();
    for (const auto& [depth, words] : {std::pair<std::size_t, const char*>{20000, "longer than 4096"},
                                        {65, "nested deeper than 64"}}) {
        const std::string expr = nested(depth, "(", "one_c_a", ")");
        const nlohmann::json program = {
            {"schema", "cellbench.bench-program/1"},
            {"name", "deep"},
            {"segments",
             {{{"type", "cycler"},
               {"steps", {{{"type", "cc_discharge"}, {"current_a", expr}, {"cutoff_voltage_v", 3.0}}, {{"type", "end"}}}}}}}};
        const auto issues = issues_of([&] { daemon::parse_program_text(program.dump(), "deep.json", cell); });
        EXPECT_TRUE(has_issue(issues, "$.segments[0].steps[0].current_a", words)) << depth;
    }
    // 64 levels is still an expression.
    const nlohmann::json ok = {
        {"schema", "cellbench.bench-program/1"},
        {"name", "ok"},
        {"segments",
         {{{"type", "cycler"},
           {"steps", {{{"type", "cc_discharge"}, {"current_a", nested(60, "(", "one_c_a", ")")}, {"cutoff_voltage_v", 3.0}},
                      {{"type", "end"}}}}}}}};
    EXPECT_NO_THROW(daemon::parse_program_text(ok.dump(), "ok.json", cell));
}

TEST(HostileConfig, ProgramReportsEveryProblemAtOnce) {
    // Four problems in four places: an unknown key, a set point outside the cell's range, a current above the
    // cell's limit, and a wait whose timeout is shorter than its hold. Only the first was reported before.
    const nlohmann::json program = {
        {"schema", "cellbench.bench-program/1"},
        {"name", "four"},
        {"colour", "red"},
        {"segments",
         {{{"type", "chamber_setpoint"}, {"setpoint_c", 95.0}},
          {{"type", "wait_equilibrium"}, {"hold_s", 600}, {"timeout_s", 60}},
          {{"type", "cycler"},
           {"steps", {{{"type", "cc_discharge"}, {"current_a", 400.0}, {"cutoff_voltage_v", 3.0}}, {{"type", "end"}}}}}}}};
    const auto issues = issues_of([&] { daemon::parse_program_text(program.dump(), "four.json", p45b()); });
    EXPECT_TRUE(has_issue(issues, "$.colour")) << ::testing::PrintToString(issues.size());
    EXPECT_TRUE(has_issue(issues, "$.segments[1]", "timeout_s > hold_s"));
    EXPECT_TRUE(has_issue(issues, "$.segments[0].setpoint_c", "cell's temperature range"));
    EXPECT_TRUE(has_issue(issues, "$.segments[2].steps[0].current_a", "max_discharge_current_a"));
}

TEST(HostileConfig, SafetyMaximumBelowTheChambersSafeSetPointIsRefusedAtLoad) {
    // The issue's case: max_temperature_c 20 degC, below the simulated chamber's 30 degC and below the
    // safe set point of 25 degC (every run would abort at once and heat the cell to 25 degC on the way out).
    const auto text = bench_text_with([](nlohmann::json& j) {
        j["safety"]["max_temperature_c"] = 20.0;
        j["simulation"]["params"] = "cells/p45b-thesis.json";
    });
    const auto issues = issues_of([&] { daemon::parse_bench_config_text(text, "bench.json", kConfigDir); });
    EXPECT_TRUE(has_issue(issues, "$.safety.max_temperature_c", "safe_setpoint_c (25 degC)"));
    EXPECT_TRUE(has_issue(issues, "$.safety.max_temperature_c", "initial_temperature_c (30 degC)"));

    // A cell whose maximum is below the bench's safe set point: every program for it is refused.
    auto cell = p45b();
    cell.max_temperature_c = 22.0;
    const auto bench = sim_bench();
    const auto issues2 = issues_of([&] {
        daemon::load_program(kConfigDir / "programs/hppc_short.json", cell, {{"temperature_c", 20.0}}, &bench);
    });
    EXPECT_TRUE(has_issue(issues2, "$", "safe_setpoint_c (25 degC) is outside the cell's temperature range"));
}

// ---- The HTTP handler boundary.

namespace {
struct ThrowingBackend : FakeBackend {
    json health() override { throw 42; }  // not even a std::exception
};
}  // namespace

TEST(HostileHttp, HugeNumbersInBodiesAre400NotAnAbort) {
    FakeBackend be;
    daemon::HttpServerOptions o;
    o.token = "t";
    auto r = handle_http_request(handler_request(verb::post, "/api/v1/runs", R"({"program": 1e999, "cell": "p45b"})", "t"),
                                 be, o);
    EXPECT_TRUE(is_json_error(r, 400));
    r = handle_http_request(
        handler_request(verb::post, "/api/v1/runs/1/diagnose", R"({"params": "p45b-thesis", "x": -1e999})", "t"), be, o);
    EXPECT_TRUE(is_json_error(r, 400));
    r = handle_http_request(
        handler_request(verb::post, "/api/v1/runs", "{\"program\": \"hppc\", \"cell\": \"p45b\", \"x\": " +
                                                        nested(100000, "[", "", "]") + "}", "t"),
        be, o);
    EXPECT_TRUE(is_json_error(r, 400));
    EXPECT_NE(r.body().find("nested deeper"), std::string::npos) << r.body();
    EXPECT_EQ(be.start_calls.load(), 0);
}

TEST(HostileHttp, AnythingThrownOnTheRequestPathIsA500) {
    ThrowingBackend be;
    const auto r = handle_http_request(handler_request(verb::get, "/api/v1/health"), be, {});
    EXPECT_TRUE(is_json_error(r, 500));
}

// ---- Recording readers.

TEST(HostileRecording, ImpossibleRequiredValueIsAnErrorNamingTheRow) {
    const std::string head = "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n0.1,3.7,0\n";
    auto msg = error_of([&] { protocol::parse_bdf_csv(head + "0.2,1e308,0\n", "r.csv"); });
    EXPECT_NE(msg.find("r.csv:4: column \"Voltage / V\": impossible value \"1e308\""), std::string::npos) << msg;
    msg = error_of([&] { protocol::parse_bdf_csv(head + "0.2,3.7,-2e4\n", "r.csv"); });
    EXPECT_NE(msg.find("r.csv:4: column \"Current / A\""), std::string::npos) << msg;
    msg = error_of([&] { protocol::parse_bdf_csv(head + "1e300,3.7,0\n", "r.csv"); });
    EXPECT_NE(msg.find("r.csv:4: column \"Test Time / s\""), std::string::npos) << msg;
}

TEST(HostileRecording, ImpossibleOptionalValuesAreCountedAndReadAsEmpty) {
    const std::string text =
        "Test Time / s,Voltage / V,Current / A,Surface Temperature / degC,Heat Flux Density / W/m^2\n"
        "0,3.7,0,30,1\n0.1,3.7,0,1e308,2\n0.2,3.7,0,31,-7e9\n0.3,3.7,0,-273.15,3\n";
    protocol::BdfReadReport report;
    const auto rec = protocol::parse_bdf_csv(text, "r.csv", &report);
    EXPECT_EQ(report.dropped_values, 3u);
    EXPECT_EQ(report.first_dropped, "3: column \"Surface Temperature / degC\": 1e+308");
    EXPECT_TRUE(std::isnan(rec.surface_c[1]));
    EXPECT_TRUE(std::isnan(rec.heat_flux_w_per_m2[2]));
    EXPECT_TRUE(std::isnan(rec.surface_c[3]));
    EXPECT_EQ(rec.surface_c[2], 31.0);
}

TEST(HostileRecording, ForwardGapIsReportedNotRepaired) {
    std::string text = "Test Time / s,Voltage / V,Current / A\n";
    for (int i = 0; i < 100; ++i) text += std::to_string(i * 0.1) + ",3.7,0\n";
    for (int i = 0; i < 100; ++i) text += std::to_string(5000 + i * 0.1) + ",3.7,0\n";
    protocol::BdfReadReport report;
    const auto rec = protocol::parse_bdf_csv(text, "r.csv", &report);
    EXPECT_NEAR(report.gap_s, 5000 - 9.9, 1e-6);
    EXPECT_EQ(report.gap_line, 102u);
    EXPECT_EQ(report.repaired_timestamps, 0u);
    EXPECT_EQ(rec.time_s.back(), 5000 + 99 * 0.1);
    // A logger that slows down (60 s steps in a rest among 1 s steps) is no gap.
    std::string slow = "Test Time / s,Voltage / V,Current / A\n";
    for (int i = 0; i < 100; ++i) slow += std::to_string(i) + ",3.7,0\n";
    for (int i = 0; i < 10; ++i) slow += std::to_string(160 + 60 * i) + ",3.7,0\n";
    protocol::parse_bdf_csv(slow, "s.csv", &report);
    EXPECT_EQ(report.gap_s, 0.0);
}

TEST(HostileRecording, OverlongLineOrBinaryIsRejectedAtTheFirstRecord) {
    const std::string junk(200000, 'x');
    auto msg = error_of([&] { protocol::parse_bdf_csv(junk, "junk.csv"); });
    EXPECT_NE(msg.find("junk.csv:1: a line of 200000 bytes"), std::string::npos) << msg;
    msg = error_of([&] { protocol::parse_dewesoft_export("Time,Heat Flux Density (W/m^2)\n0," + junk + "\n", "d.csv"); });
    EXPECT_NE(msg.find("d.csv:2: a line of"), std::string::npos) << msg;
}

TEST(HostileRecording, DaqExportCutMidLineIsAnError) {
    const std::string text = "Time,Heat Flux Density (W/m^2),Temperature (C)\n0,1,30\n0.1,1,30\n0.2,1,3";
    const auto msg = error_of([&] { protocol::parse_dewesoft_export(text, "daq.csv"); });
    EXPECT_NE(msg.find("daq.csv:4: the export ends mid-line"), std::string::npos) << msg;
    // A BDF file without a final line end is read, and the report says so.
    protocol::BdfReadReport report;
    protocol::parse_bdf_csv("Test Time / s,Voltage / V,Current / A\n0,3.7,0\n0.1,3.7,0", "r.csv", &report);
    EXPECT_TRUE(report.ends_mid_line);
}

TEST(HostileRecording, DaqValuesOutsidePhysicsAreDroppedAndCounted) {
    const std::string text =
        "Time,Thermal Flux Sensor Voltage (V),Temperature (C)\n0,1e-5,30\n0.1,1e308,30\n0.2,1e-5,900\n0.3,1e-5,30\n";
    const auto d = protocol::parse_dewesoft_export(text, "daq.csv");
    EXPECT_EQ(d.dropped_values, 2u);
    EXPECT_TRUE(std::isnan(d.thermopile_v[1]));
    EXPECT_TRUE(std::isnan(d.type_t_c[2]));
    EXPECT_EQ(d.type_t_c[3], 30.0);
}

// ---- Clock alignment: weak or far-off evidence is refused with the numbers.

TEST(HostileAlignment, WeakOrFarOffAlignmentIsRefused) {
    estimator::ClockAlignment al;
    al.offset_s = 5.7;
    al.correlation = 0.95;
    al.uncertainty_s = 1.0;
    al.start_mismatch_s = 5.7;
    al.end_mismatch_s = 40.0;
    EXPECT_NO_THROW(estimator::check_clock_alignment(al, "daq.csv"));

    auto far = al;  // the cut export of the issue: -1074 s, r = 0.948
    far.offset_s = -1074.3;
    far.correlation = 0.948;
    far.start_mismatch_s = -1073.5;
    far.end_mismatch_s = -2500.0;
    auto msg = error_of([&] { estimator::check_clock_alignment(far, "daq.csv"); });
    EXPECT_NE(msg.find("daq.csv: clock alignment refused: neither end"), std::string::npos) << msg;
    EXPECT_NE(msg.find("-1074.3 s"), std::string::npos) << msg;

    auto weak = al;
    weak.correlation = 0.31;
    msg = error_of([&] { estimator::check_clock_alignment(weak, "daq.csv"); });
    EXPECT_NE(msg.find("weak evidence"), std::string::npos) << msg;
    EXPECT_NE(msg.find("r = 0.310"), std::string::npos) << msg;

    auto edge = al;
    edge.at_search_limit = true;
    EXPECT_NE(error_of([&] { estimator::check_clock_alignment(edge, "daq.csv"); }).find("edge of the search"),
              std::string::npos);
}

// ---- Slow clients and expensive reads cannot lock others out.

TEST(HostileHttp, SlowClientsAtTheConnectionLimitDoNotLockOutAPromptOne) {
    FakeBackend be;
    daemon::HttpServerOptions o;
    o.max_connections = 16;
    o.header_timeout = std::chrono::minutes(5);  // the test must not depend on the timeout
    TestServer server(be, o);
    std::vector<std::unique_ptr<Connection>> slow;
    for (int i = 0; i < 16; ++i) {
        slow.push_back(std::make_unique<Connection>(server.port()));
        slow.back()->send("GET /api/v1/health HTTP/1.1\r\nHo");  // a header that never completes
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // let the server accept them (setup only)
    for (int i = 0; i < 3; ++i) {
        const auto r = request(server.port(), verb::get, "/api/v1/health");
        EXPECT_EQ(r.result_int(), 200u);
    }
    // The one that waited longest for its header made room.
    EXPECT_TRUE(slow.front()->closed_by_peer());
}

namespace {
struct BlockingSamplesBackend : FakeBackend {
    std::atomic<int> inside{0};
    std::atomic<bool> release{false};
    json samples(RunId id, const daemon::SampleQuery& q) override {
        ++inside;
        for (int i = 0; i < 300 && !release; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(10));
        return FakeBackend::samples(id, q);
    }
};
}  // namespace

TEST(HostileHttp, SampleReadsBeyondTheCapAre503NotQueued) {
    BlockingSamplesBackend be;
    daemon::HttpServerOptions o;
    o.max_concurrent_sample_reads = 1;
    TestServer server(be, o, 3);
    std::optional<Response> first;
    std::thread t([&] { first = request(server.port(), verb::get, "/api/v1/runs/1/samples?max_points=2000"); });
    while (be.inside.load() == 0) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    const auto busy = request(server.port(), verb::get, "/api/v1/runs/1/samples?max_points=2000");
    be.release = true;
    t.join();
    EXPECT_TRUE(is_json_error(busy, 503));
    EXPECT_EQ(busy[http::field::retry_after], "1");
    ASSERT_TRUE(first);
    EXPECT_EQ(first->result_int(), 200u);
    EXPECT_EQ(be.inside.load(), 1);
    // Served again once the first is done.
    EXPECT_EQ(request(server.port(), verb::get, "/api/v1/runs/1/samples").result_int(), 200u);
}
