// Step programs: the thesis' programs as tables 2.10, 2.12 and 5.1 define them, the capacity formula of
// eq. 2.4, step-file and JSON round trips, and errors that name the step / JSON path.
#include <gtest/gtest.h>

#include <fstream>
#include <map>
#include <sstream>
#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"

using namespace cellbench::protocol;
using cellbench::InputError;
using cellbench::protocol::neware::ProtocolError;
using nlohmann::json;

namespace {

const std::string kReference = std::string(CELLBENCH_SHARED_DIR) + "/reference/neware/bts-client-2024-step-file.xml";

std::string read(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

void expect_round_trips(const StepProgram& program) {
    // The step file carries the program as the tester sees it (limits resolved, no notes): that reads back.
    StepProgram p = program;
    if (!p.settings.nominal_capacity_ah) p.settings.nominal_capacity_ah = 4.5;  // MultCap, for eq. 2.4
    const std::string xml = compile_step_file(p, {"20260101000000"});
    EXPECT_EQ(parse_step_file(xml), as_tester_program(p)) << xml;
    EXPECT_EQ(compile_step_file(parse_step_file(xml), {"20260101000000"}), xml);
    EXPECT_EQ(StepProgram::from_json(program.to_json()), program) << program.to_json().dump(2);
    // and through text, as config/programs/*.json will be read
    EXPECT_EQ(StepProgram::from_json(json::parse(program.to_json().dump())), program);
}

std::string error_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const std::exception& e) {
        return e.what();
    }
    return "(no error)";
}

}  // namespace

TEST(NewareStepFile, HppcIsTable212) {
    const StepProgram p = thesis_hppc_program();
    ASSERT_EQ(p.steps.size(), 17u);
    const auto& s = p.steps;
    EXPECT_EQ(s[0].type, StepType::rest);
    EXPECT_EQ(*s[0].time_s, 10.0);
    EXPECT_EQ(s[1].type, StepType::cccv_charge);
    EXPECT_EQ(*s[1].voltage_v, 4.1);
    EXPECT_EQ(*s[1].current_a, 4.5);
    EXPECT_EQ(*s[1].cutoff_current_a, 0.05);
    EXPECT_EQ(s[3].type, StepType::cc_discharge);  // pilot discharge: C4
    EXPECT_EQ(*s[3].cutoff_voltage_v, 2.9);
    EXPECT_EQ(*s[4].time_s, 3600.0);
    EXPECT_EQ(s[7].type, StepType::cccv_discharge);  // 30 s discharge pulse
    EXPECT_EQ(*s[7].time_s, 30.0);
    EXPECT_EQ(*s[7].voltage_v, 2.9);
    EXPECT_EQ(*s[8].time_s, 40.0);
    EXPECT_EQ(s[9].type, StepType::cccv_charge);  // 10 s charge pulse
    EXPECT_EQ(*s[9].time_s, 10.0);
    EXPECT_EQ(s[11].type, StepType::cc_discharge);
    ASSERT_TRUE(s[11].cutoff_capacity_ah);
    EXPECT_EQ(s[11].cutoff_capacity_ah->to_string(), "0.1*C4 - C8 + C10");
    EXPECT_EQ(*s[11].cutoff_voltage_v, 2.9);
    EXPECT_EQ(s[13].type, StepType::cycle);
    EXPECT_EQ(s[13].start_step, 8);
    EXPECT_EQ(s[13].count, 10);
    EXPECT_EQ(*s[15].time_s, 1800.0);
    EXPECT_EQ(s[16].type, StepType::end);
    expect_round_trips(p);
}

TEST(NewareStepFile, CapacityFormulaOfEquation24) {
    const StepProgram p = thesis_hppc_program();
    const auto& c12 = *p.steps[11].cutoff_capacity_ah;
    // Pilot discharge 3.816 Ah (the real P45B), pulse 30 s at 4.5 A out, 10 s at 4.5 A back in.
    std::map<int, double> capacity{{4, 3.816}, {8, 4.5 * 30 / 3600}, {10, 4.5 * 10 / 3600}};
    const double c12_ah = c12.evaluate([&](int step) { return capacity.count(step) ? capacity[step] : 0.0; });
    EXPECT_NEAR(c12_ah, 0.1 * 3.816 - 0.0375 + 0.0125, 1e-12);
    // The three together remove exactly 10 % of C4 per pulse set.
    EXPECT_NEAR(capacity[8] - capacity[10] + c12_ah, 0.3816, 1e-12);
}

TEST(NewareStepFile, CapacityExpressionGrammar) {
    const CapacityExpression expected{0.0, {{4, 0.1}, {8, -1.0}, {10, 1.0}}};
    EXPECT_EQ(CapacityExpression::parse("0.1*C4 - C8 + C10"), expected);
    EXPECT_EQ(CapacityExpression::parse("C4*0.1-C8+C10"), expected);
    EXPECT_EQ(CapacityExpression::parse("  0.1 * c4 - 1*C8 +C10 "), expected);
    EXPECT_EQ(CapacityExpression::parse("2.5").constant_ah, 2.5);
    EXPECT_TRUE(CapacityExpression::parse("2.5").is_constant());
    EXPECT_EQ(CapacityExpression::parse("1e-1*C4 + 0.05").to_string(), "0.1*C4 + 0.05");
    EXPECT_EQ(CapacityExpression::parse(CapacityExpression{-0.5, {{3, -2.0}}}.to_string()),
              (CapacityExpression{-0.5, {{3, -2.0}}}));
    for (const char* bad : {"", "C", "C0", "0.1*", "C4 C8", "x", "0.1*C4 -", "C4 * ", "1..2", "C-4"})
        EXPECT_THROW(CapacityExpression::parse(bad), InputError) << bad;
}

TEST(NewareStepFile, CcTestIsTable210AtTable211Rates) {
    const std::map<double, double> table_2_11{{0.5, 2.25}, {1, 4.5}, {2, 9}, {4, 18}, {10, 45}};
    for (const auto& [c_rate, current_a] : table_2_11) {
        const StepProgram p = thesis_cc_discharge_program(c_rate);
        ASSERT_EQ(p.steps.size(), 6u);
        EXPECT_EQ(p.steps[1].type, StepType::cccv_charge);
        EXPECT_EQ(*p.steps[1].current_a, 4.5);  // always charged at 1C
        EXPECT_EQ(p.steps[3].type, StepType::cc_discharge);
        EXPECT_DOUBLE_EQ(*p.steps[3].current_a, current_a);
        EXPECT_EQ(*p.steps[3].cutoff_voltage_v, 2.9);
        EXPECT_EQ(*p.steps[2].time_s, 600.0);
        EXPECT_EQ(p.steps[5].type, StepType::end);
        expect_round_trips(p);
    }
    // "13C" ran at the 60 A of three parallel channels.
    const StepProgram p13 = thesis_cc_discharge_program(13, 4.5, 60.0);
    EXPECT_EQ(*p13.steps[3].current_a, 60.0);
    EXPECT_EQ(p13.max_current_a(), 60.0);
}

TEST(NewareStepFile, RandomWalkIsTable51) {
    const StepProgram p = thesis_random_walk_program();
    ASSERT_EQ(p.steps.size(), 16u);
    const double dis[] = {4.5, 9, 13.5, 18}, chg[] = {4.5, 9, 13.5, 13.5};
    for (int k = 0; k < 4; ++k) {
        const auto& d = p.steps[1 + 3 * k];
        const auto& c = p.steps[2 + 3 * k];
        EXPECT_EQ(d.type, StepType::cc_discharge);
        EXPECT_DOUBLE_EQ(*d.current_a, dis[k]);
        EXPECT_EQ(*d.time_s, 60.0);
        EXPECT_EQ(*d.cutoff_voltage_v, 2.9);
        EXPECT_EQ(c.type, StepType::cc_charge);
        EXPECT_DOUBLE_EQ(*c.current_a, chg[k]);  // charge never above 3C
        EXPECT_EQ(*c.time_s, 20.0);
        EXPECT_EQ(*c.cutoff_voltage_v, 4.1);
        EXPECT_EQ(*p.steps[3 + 3 * k].time_s, 10.0);
    }
    EXPECT_EQ(p.steps[13].type, StepType::cycle);
    EXPECT_EQ(p.steps[13].start_step, 2);
    EXPECT_EQ(p.steps[13].count, 7);
    EXPECT_EQ(p.steps[14].type, StepType::cc_discharge);
    EXPECT_FALSE(p.steps[14].time_s);
    expect_round_trips(p);
}

TEST(NewareStepFile, ReferenceBtsClientFileParses) {
    const StepProgram p = parse_step_file(read(kReference));  // version 17, GB2312 declared, CRLF
    EXPECT_EQ(p.name, "2025-02-06 10-59-55");                 // PN
    EXPECT_EQ(p.first_step, 1);
    ASSERT_TRUE(p.settings.nominal_capacity_ah);
    EXPECT_DOUBLE_EQ(*p.settings.nominal_capacity_ah, 0.045);  // MultCap 162000 mA*s
    EXPECT_DOUBLE_EQ(*p.settings.protect_upper_v, 4.3);
    EXPECT_DOUBLE_EQ(*p.settings.protect_lower_v, 2.5);
    EXPECT_DOUBLE_EQ(*p.settings.protect_upper_a, 0.03);
    EXPECT_DOUBLE_EQ(*p.settings.protect_lower_a, -0.03);
    EXPECT_DOUBLE_EQ(*p.settings.protect_capacity_ah, 0.05);
    EXPECT_DOUBLE_EQ(*p.settings.protect_delay_s, 5.0);
    EXPECT_DOUBLE_EQ(*p.settings.record_interval_s, 10.0);
    ASSERT_EQ(p.steps.size(), 5u);
    const auto& s = p.steps;
    EXPECT_EQ(s[0].type, StepType::cc_charge);  // Step_Type 1
    EXPECT_DOUBLE_EQ(*s[0].current_a, 0.0225);  // 22.5 mA
    EXPECT_DOUBLE_EQ(*s[0].time_s, 10800.0);    // 10800000 ms
    EXPECT_DOUBLE_EQ(*s[0].cutoff_voltage_v, 4.2);  // 42000 x 0.1 mV
    EXPECT_DOUBLE_EQ(*s[0].record_interval_s, 10.0);
    EXPECT_DOUBLE_EQ(*s[0].record_delta_v, 0.05);
    EXPECT_DOUBLE_EQ(*s[0].protect_upper_v, 4.5);
    EXPECT_EQ(s[1].type, StepType::cv_charge);  // Step_Type 3
    EXPECT_DOUBLE_EQ(*s[1].voltage_v, 4.2);
    EXPECT_DOUBLE_EQ(*s[1].cutoff_current_a, 0.00225);
    EXPECT_DOUBLE_EQ(*s[1].record_delta_a, 0.005);
    EXPECT_EQ(s[2].type, StepType::cc_discharge);  // Step_Type 2
    EXPECT_DOUBLE_EQ(*s[2].cutoff_voltage_v, 2.75);
    EXPECT_EQ(s[3].type, StepType::cycle);  // Step_Type 5: steps 1..3 five times
    EXPECT_EQ(s[3].start_step, 1);
    EXPECT_EQ(s[3].count, 5);
    EXPECT_EQ(s[4].type, StepType::end);
}

TEST(NewareStepFile, ReferenceFileRoundTrips) {
    const StepProgram p = parse_step_file(read(kReference));
    const std::string again = compile_step_file(p, {"20250207035516"});
    EXPECT_EQ(parse_step_file(again), p) << again;
    // The same schema as the reference: root/config/Head_Info, Whole_Prt, Step_Info, SMBUS, StepK elements.
    for (const char* part : {"<root>", "<config type=\"Step File\" version=\"17\"", "<Head_Info>", "<MultCap Value=\"162000\" />",
                             "<Whole_Prt>", "<Step_Info Num=\"5\">", "<Step1 Step_ID=\"1\" Step_Type=\"1\">",
                             "<Curr Value=\"22.5\" />", "<Stop_Volt Value=\"42000\" />",
                             "<Step2 Step_ID=\"2\" Step_Type=\"3\">", "<Start_Step Value=\"1\" />",
                             "<Cycle_Count Value=\"5\" />", "<Step5 Step_ID=\"5\" Step_Type=\"6\">",
                             "<SMBUS_Info Num=\"0\" AdjacentInterval=\"0\" />"})
        EXPECT_NE(again.find(part), std::string::npos) << part << "\n" << again;
    // Version 18 and a UTF-8 declaration read the same.
    std::string v18 = read(kReference);
    v18.replace(v18.find("version=\"17\""), 12, "version=\"18\"");
    v18.replace(v18.find("GB2312"), 6, "UTF-8");
    EXPECT_EQ(parse_step_file(v18), p);
}

TEST(NewareStepFile, ThesisHppcIsWrittenInTheRealSchema) {
    StepProgram hppc = thesis_hppc_program();
    hppc.settings.nominal_capacity_ah = 4.5;
    const std::string xml = compile_step_file(hppc, {"20260101000000"});
    EXPECT_NE(xml.find("<PN Value=\"hppc_1c\" />"), std::string::npos) << xml;
    EXPECT_NE(xml.find("<MultCap Value=\"16200000\" />"), std::string::npos);
    // Step 2 CCCV charge 4.5 A to 4.1 V, 50 mA cut-off; step 8 the CCCV discharge pulse (code 20).
    EXPECT_NE(xml.find("<Step2 Step_ID=\"2\" Step_Type=\"7\">\r\n        <Limit>\r\n          <Main>\r\n"
                       "            <Curr Value=\"4500\" />\r\n            <Volt Value=\"41000\" />\r\n"
                       "            <Stop_Curr Value=\"50\" />"),
              std::string::npos)
        << xml;
    EXPECT_NE(xml.find("<Step8 Step_ID=\"8\" Step_Type=\"20\">"), std::string::npos);
    EXPECT_NE(xml.find("<Time Value=\"30000\" />"), std::string::npos);
    // The loop: step 14 runs 8..14 ten times.
    EXPECT_NE(xml.find("<Step14 Step_ID=\"14\" Step_Type=\"5\">\r\n        <Limit>\r\n          <Other>\r\n"
                       "            <Start_Step Value=\"8\" />\r\n            <Cycle_Count Value=\"10\" />"),
              std::string::npos);
    // Eq. 2.4 with nominal capacities: 0.1 x 4.5 Ah - 4.5 A x 30 s + 4.5 A x 10 s = 0.425 Ah = 1530000 mA*s.
    EXPECT_NE(xml.find("<Cap Value=\"1530000\" />"), std::string::npos);
    EXPECT_EQ(xml.find("cellbench_steps"), std::string::npos);  // the old format is gone
    // Without a capacity for C4 there is nothing to write: the error names the step and the term.
    EXPECT_NE(error_of([] { compile_step_file(thesis_hppc_program()); }).find("step 12: capacity limit 0.1*C4 - C8 + C10 needs C4"),
              std::string::npos);
}

TEST(NewareStepFile, CapacityFormulaIsResolvedFromTheMeasuredPilot) {
    const StepProgram hppc = thesis_hppc_program();
    // The tester runs it as two files: 1..4 + End, then the program from step 5 with C4 measured.
    const auto parts = tester_parts(hppc);
    ASSERT_EQ(parts.size(), 2u);
    ASSERT_EQ(parts[0].steps.size(), 5u);
    EXPECT_EQ(parts[0].steps[3].note, "Full DChg");
    EXPECT_EQ(parts[0].steps[4].type, StepType::end);
    EXPECT_EQ(parts[1].first_step, 5);
    EXPECT_EQ(parts[1].steps, hppc.steps);  // the same step ids
    // C4 measured 4.0 Ah; C8, C10 inside the loop at nominal (time-limited pulses): 0.4 - 0.0375 + 0.0125.
    const StepProgram r = resolve_capacity_limits(parts[1], [](int id) -> std::optional<double> {
        if (id == 4) return 4.0;
        if (id == 8 || id == 10) return 99.0;  // never used: re-executed in every pulse set
        return std::nullopt;
    });
    ASSERT_TRUE(r.steps[11].cutoff_capacity_ah->is_constant());
    EXPECT_NEAR(r.steps[11].cutoff_capacity_ah->constant_ah, 0.375, 1e-6);
    const std::string xml = compile_step_file(r, {"20260101000000"});
    EXPECT_NE(xml.find("<Start_Step Value=\"5\" Hide_Ctrl_Step=\"0\" />"), std::string::npos);
    EXPECT_NE(xml.find("<Cap Value=\"1350000\" />"), std::string::npos);
    EXPECT_EQ(parse_step_file(xml).first_step, 5);
    // A program whose limits refer only to steps inside the loop (hppc_short) needs one file.
    StepProgram short_hppc = hppc;
    short_hppc.steps[11].cutoff_capacity_ah = CapacityExpression{0.45, {{8, -1.0}, {10, 1.0}}};
    EXPECT_EQ(tester_parts(short_hppc).size(), 1u);
}

TEST(NewareStepFile, MalformedFilesAreProtocolErrors) {
    const std::string good = compile_step_file(thesis_random_walk_program(), {"20260101000000"});
    for (const std::string& bad : {std::string("garbage"), std::string("<root/>"),
                                   std::string("<cellbench_steps format=\"cellbench.neware-steps/1\"/>"),
                                   std::string("<root><config type=\"Step File\" version=\"12\"/></root>"),
                                   good.substr(0, good.size() / 2)}) {
        EXPECT_THROW(parse_step_file(bad), ProtocolError) << bad;
    }
    std::string wrong_number = good;
    wrong_number.replace(wrong_number.find("<Curr Value=\"4500\""), 18, "<Curr Value=\"4,5\"");
    EXPECT_NE(error_of([&] { parse_step_file(wrong_number); }).find("step 2: <Limit/Main/Curr> Value=\"4,5\": expected a number"),
              std::string::npos);
    std::string unknown_type = good;
    unknown_type.replace(unknown_type.find("Step_Type=\"2\""), 13, "Step_Type=\"25\"");
    EXPECT_NE(error_of([&] { parse_step_file(unknown_type); }).find("Step_Type 25 is not supported"), std::string::npos);
    // Well-formed but not a valid program: InputError naming the step.
    std::string no_end = good;
    no_end.replace(no_end.find("Step_Type=\"6\""), 13, "Step_Type=\"4\"");
    EXPECT_NE(error_of([&] { parse_step_file(no_end); }).find("last step must be an end step"), std::string::npos);
}

TEST(NewareStepFile, ValidationNamesTheStep) {
    StepProgram p = thesis_hppc_program();
    p.steps[0].time_s.reset();
    EXPECT_NE(error_of([&] { p.validate(); }).find("steps[0] (step 1).time_s"), std::string::npos);

    p = thesis_hppc_program();
    p.steps[11].cutoff_capacity_ah->terms.push_back({13, 1.0});  // a later step
    EXPECT_NE(error_of([&] { p.validate(); }).find("only earlier steps"), std::string::npos);

    p = thesis_hppc_program();
    p.steps[11].cutoff_capacity_ah->terms[0].step_id = 3;  // a rest step carries no current
    EXPECT_NE(error_of([&] { p.validate(); }).find("carries no current"), std::string::npos);

    p = thesis_hppc_program();
    p.steps[13].start_step = 14;
    EXPECT_NE(error_of([&] { p.validate(); }).find("steps[13] (step 14).start_step"), std::string::npos);

    p = thesis_random_walk_program();
    p.steps[1].current_a = -4.5;
    EXPECT_NE(error_of([&] { p.validate(); }).find("current_a: expected a positive number"), std::string::npos);

    p = thesis_random_walk_program();
    p.steps[1].cutoff_current_a = 0.1;  // no CV phase in a CC step
    EXPECT_NE(error_of([&] { p.validate(); }).find("not used by a cc_discharge step"), std::string::npos);

    p = thesis_hppc_program();
    p.steps[1].cutoff_current_a = 5.0;  // would end at once
    EXPECT_THROW(p.validate(), InputError);

    p = thesis_random_walk_program();
    p.steps.pop_back();
    EXPECT_NE(error_of([&] { p.validate(); }).find("last step must be an end step"), std::string::npos);

    p = thesis_hppc_program();  // overlapping loops
    p.steps[15] = p.steps[13];
    p.steps[15].start_step = 10;
    p.steps[13].start_step = 8;
    EXPECT_NE(error_of([&] { p.validate(); }).find("overlaps"), std::string::npos);
}

TEST(NewareStepFile, JsonErrorsNameThePath) {
    const json good = thesis_random_walk_program().to_json();
    auto err = [&](const std::function<void(json&)>& edit) {
        json j = good;
        edit(j);
        return error_of([&] { StepProgram::from_json(j, "rw.json"); });
    };
    EXPECT_NE(err([](json& j) { j["steps"][2]["curent_a"] = 1; }).find("rw.json: steps[2].curent_a: unknown key"),
              std::string::npos);
    EXPECT_NE(err([](json& j) { j["steps"][1]["current_a"] = "4.5"; }).find("rw.json: steps[1].current_a: expected a number"),
              std::string::npos);
    EXPECT_NE(err([](json& j) { j["steps"][1]["type"] = "cc_dischrge"; }).find("rw.json: steps[1].type: unknown step type"),
              std::string::npos);
    EXPECT_NE(err([](json& j) { j["steps"][3]["id"] = 7; }).find("rw.json: steps[3].id: expected 4"), std::string::npos);
    EXPECT_NE(err([](json& j) { j["steps"][13]["count"] = 1.5; }).find("rw.json: steps[13].count: expected an integer"),
              std::string::npos);
    EXPECT_NE(err([](json& j) { j["steps"][1]["cutoff_capacity_ah"] = "0.1*Cx"; })
                  .find("rw.json: steps[1].cutoff_capacity_ah: capacity expression"),
              std::string::npos);
    EXPECT_NE(err([](json& j) { j["schema"] = "other/2"; }).find("rw.json: schema"), std::string::npos);
    EXPECT_NE(err([](json& j) { j.erase("steps"); }).find("rw.json: steps: missing"), std::string::npos);
    EXPECT_NE(err([](json& j) { j["steps"][0].erase("time_s"); })
                  .find("rw.json: steps[0].time_s: a rest step needs its duration (step 1)"),
              std::string::npos);
    // Hand-written JSON without ids and with a numeric capacity limit is fine.
    const json hand = json::parse(R"({"name": "short", "steps": [
        {"type": "cc_discharge", "current_a": 9, "cutoff_voltage_v": 2.9, "cutoff_capacity_ah": 0.5},
        {"type": "end"}]})");
    const StepProgram p = StepProgram::from_json(hand);
    EXPECT_EQ(p.steps[0].cutoff_capacity_ah->constant_ah, 0.5);
    expect_round_trips(p);
}

TEST(NewareStepFile, StepTypeCodesForInquire) {
    EXPECT_EQ(step_type_code(StepType::rest), "rest");
    EXPECT_EQ(step_type_code(StepType::cc_charge), "cc");
    EXPECT_EQ(step_type_code(StepType::cc_discharge), "dc");
    // What real BTS 8 servers report: cc/dc in the CC phase of a CCCV step (cv in its CV phase), never "cccv".
    EXPECT_EQ(step_type_code(StepType::cccv_charge), "cc");
    EXPECT_EQ(step_type_code(StepType::cccv_discharge), "dc");
    EXPECT_EQ(step_type_code(StepType::cv_charge), "cv");
    EXPECT_EQ(step_direction(StepType::cccv_discharge), -1);
    EXPECT_EQ(step_direction(StepType::cccv_charge), +1);
    EXPECT_EQ(step_direction(StepType::rest), 0);
}
