// Step programs: the thesis' programs as tables 2.10, 2.12 and 5.1 define them, the capacity formula of
// eq. 2.4, step-file and JSON round trips, and errors that name the step / JSON path.
#include <gtest/gtest.h>

#include <map>
#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"

using namespace cellbench::protocol;
using cellbench::InputError;
using cellbench::protocol::neware::ProtocolError;
using nlohmann::json;

namespace {

void expect_round_trips(const StepProgram& p) {
    const std::string xml = compile_step_file(p);
    EXPECT_EQ(parse_step_file(xml), p) << xml;
    EXPECT_EQ(StepProgram::from_json(p.to_json()), p) << p.to_json().dump(2);
    // and through text, as config/programs/*.json will be read
    EXPECT_EQ(StepProgram::from_json(json::parse(p.to_json().dump())), p);
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

TEST(NewareStepFile, FileIsTheDocumentedFormat) {
    const std::string xml = compile_step_file(thesis_hppc_program());
    EXPECT_NE(xml.find("<cellbench_steps format=\"cellbench.neware-steps/1\" name=\"hppc_1c\""), std::string::npos);
    EXPECT_NE(xml.find("<step id=\"12\" type=\"cc_discharge\" current_a=\"4.5\" cutoff_voltage_v=\"2.9\" "
                       "cutoff_capacity_ah=\"0.1*C4 - C8 + C10\" note=\"10% SOC DChg\"/>"),
              std::string::npos)
        << xml;
    EXPECT_NE(xml.find("<step id=\"14\" type=\"cycle\" start_step=\"8\" count=\"10\"/>"), std::string::npos);
    // Typographic quotes from a hand-edited file are accepted like the BTS frames.
    std::string edited = xml;
    const auto at = edited.find("time_s=\"10\"");
    edited.replace(at, 11, "time_s=\xE2\x80\x9D" "10\xE2\x80\x9D");
    EXPECT_EQ(parse_step_file(edited), thesis_hppc_program());
}

TEST(NewareStepFile, MalformedFilesAreProtocolErrors) {
    const std::string good = compile_step_file(thesis_random_walk_program());
    for (const std::string& bad : {std::string("garbage"), std::string("<root/>"),
                                   std::string("<cellbench_steps format=\"other/1\"/>"),
                                   good.substr(0, good.size() / 2)}) {
        EXPECT_THROW(parse_step_file(bad), ProtocolError) << bad;
    }
    std::string wrong_number = good;
    wrong_number.replace(wrong_number.find("current_a=\"4.5\""), 15, "current_a=\"4,5\"");
    EXPECT_THROW(parse_step_file(wrong_number), ProtocolError);
    std::string unknown_attr = good;
    unknown_attr.replace(unknown_attr.find("current_a=\"4.5\""), 15, "curent_a=\"4.5\"");
    EXPECT_THROW(parse_step_file(unknown_attr), ProtocolError);
    // Well-formed but not a valid program: InputError naming the step.
    std::string no_end = good;
    no_end.replace(no_end.find("type=\"end\""), 10, "type=\"rest\" time_s=\"1\"");
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
    EXPECT_EQ(step_direction(StepType::cccv_discharge), -1);
    EXPECT_EQ(step_direction(StepType::cccv_charge), +1);
    EXPECT_EQ(step_direction(StepType::rest), 0);
}
