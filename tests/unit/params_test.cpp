// Parameter set JSON (cellbench.params/1): round trip, table look-ups, clear errors with JSON paths.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <functional>
#include <sstream>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"

using namespace cellbench;
using namespace cellbench::estimator;
using nlohmann::json;

namespace {

json thesis_json() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    std::stringstream ss;
    ss << in.rdbuf();
    return json::parse(ss.str());
}

std::string error_of(const json& j) {
    try {
        ParameterSet::from_json(j, "p.json");
    } catch (const InputError& e) {
        return e.what();
    }
    return "";
}

}  // namespace

TEST(ParameterSet, ThesisSetLoadsAndRoundTrips) {
    const auto p = ParameterSet::from_json(thesis_json(), "p45b-thesis.json");
    EXPECT_EQ(p.soc.size(), 11u);
    EXPECT_DOUBLE_EQ(p.capacity_ah, 4.0);
    EXPECT_NEAR(p.thermal.c_th_j_per_k, 63.28, 1e-9);
    EXPECT_NEAR(p.ocv_at(0.5), 3.72, 1e-12);
    EXPECT_NEAR(p.ocv_at(0.55), (3.72 + 3.79) / 2, 1e-12);
    EXPECT_NEAR(p.rc_at(0.5, -1).r0_ohm, 0.00734, 1e-12);
    EXPECT_NEAR(p.rc_at(0.5, +1).r0_ohm, 0.00741, 1e-12);
    EXPECT_NEAR(p.rc_at(0.5, -1).tau1_s, 0.00170 * 1215, 1e-9);
    EXPECT_NEAR(p.ehc_at(0.10), -1.4e-4, 1e-12);
    const auto again = ParameterSet::from_json(p.to_json(), "again");
    EXPECT_EQ(again.to_json(), p.to_json());
}

TEST(ParameterSet, LookupsHoldOutsideTheTableAndOcvExtrapolates) {
    auto p = ParameterSet::from_json(thesis_json(), "t");
    p.soc = {0.1, 0.9};
    p.ocv_v = {3.3, 4.1};
    for (auto* t : {&p.discharge, &p.charge}) *t = RcTable{{0.008, 0.007}, {0.002, 0.001}, {1000, 1000}, {0.01, 0.01}, {2000, 2000}};
    p.validate();
    EXPECT_DOUBLE_EQ(p.rc_at(0.0, -1).r0_ohm, 0.008);
    EXPECT_DOUBLE_EQ(p.rc_at(1.0, -1).r0_ohm, 0.007);
    EXPECT_NEAR(p.ocv_at(1.0), 4.2, 1e-12);
    EXPECT_NEAR(p.soc_from_ocv(3.7), 0.5, 1e-12);
    EXPECT_DOUBLE_EQ(p.soc_from_ocv(5.0), 1.0);
}

TEST(ParameterSet, ExtensionsArePreservedAndUnderstood) {
    auto j = thesis_json();
    j["extensions"]["resistance_temperature"] = {{"activation_energy_j_per_mol", 25000.0}};
    j["extensions"]["future_effect"] = {{"k", 1}};
    const auto p = ParameterSet::from_json(j, "t");
    ASSERT_TRUE(p.extensions.resistance_temperature.has_value());
    EXPECT_DOUBLE_EQ(p.extensions.resistance_temperature->activation_energy_j_per_mol, 25000.0);
    EXPECT_EQ(p.to_json()["extensions"]["future_effect"]["k"], 1);
}

TEST(ParameterSet, ErrorsNameTheJsonPathAndWhatWasExpected) {
    auto j = thesis_json();
    j["discharge"]["r1_ohm"].erase(3);
    EXPECT_NE(error_of(j).find("$.discharge.r1_ohm"), std::string::npos) << error_of(j);
    EXPECT_NE(error_of(j).find("one per soc entry"), std::string::npos);

    j = thesis_json();
    j["thermal"]["r_th_k_per_w"] = "five";
    EXPECT_NE(error_of(j).find("$.thermal.r_th_k_per_w: expected a number"), std::string::npos) << error_of(j);

    j = thesis_json();
    j["schema"] = "other/2";
    EXPECT_NE(error_of(j).find("$.schema"), std::string::npos);

    j = thesis_json();
    j.erase("capacity_ah");
    EXPECT_NE(error_of(j).find("$.capacity_ah: missing"), std::string::npos);

    j = thesis_json();
    j["soc"][2] = 0.05;  // not ascending
    EXPECT_NE(error_of(j).find("ascending"), std::string::npos);

    j = thesis_json();
    j["charge"]["c2_f"][0] = -1.0;
    EXPECT_NE(error_of(j).find("$.charge.c2_f[0]: expected a positive value"), std::string::npos) << error_of(j);
}

// A hand-edited set with a value no cell has (a typo, mOhm written in Ohm times 1000) used to load: 1e300 Ohm or
// an activation energy of 1e300 J/mol made simulate overflow, and diagnose then called the model adequate; a
// reference temperature of -1e300 degC simulated to a 4 V error without a word. Each is refused naming its member.
TEST(ParameterSet, ValuesNoCellHasAreRefusedNamingTheMember) {
    auto refused = [](const std::function<void(json&)>& edit, const std::string& path) {
        json j = thesis_json();
        edit(j);
        const std::string e = error_of(j);
        EXPECT_NE(e.find("p.json: " + path + ": expected"), std::string::npos) << path << " -> '" << e << "'";
    };
    refused([](json& j) { j["capacity_ah"] = 1e-300; }, "$.capacity_ah");
    refused([](json& j) { j["capacity_ah"] = 1e300; }, "$.capacity_ah");
    refused([](json& j) { j["reference_temperature_c"] = -1e300; }, "$.reference_temperature_c");
    refused([](json& j) { j["reference_temperature_c"] = -300.0; }, "$.reference_temperature_c");  // below 0 K
    refused([](json& j) { j["discharge"]["r0_ohm"][2] = 1e300; }, "$.discharge.r0_ohm[2]");
    refused([](json& j) { j["charge"]["r2_ohm"][0] = 5e3; }, "$.charge.r2_ohm[0]");
    refused([](json& j) { j["thermal"]["r_th_k_per_w"] = 1e300; }, "$.thermal.r_th_k_per_w");
    refused([](json& j) { j["thermal"]["area_m2"] = 1e6; }, "$.thermal.area_m2");
    refused([](json& j) { j["thermal"]["ehc_soc"] = {0.0, 0.5}, j["thermal"]["ehc_v_per_k"] = {1e-4, 0.5}; },
            "$.thermal.ehc_v_per_k[1]");
    refused([](json& j) { j["thermal"]["ehc_soc"] = {0.0, 1.5}, j["thermal"]["ehc_v_per_k"] = {1e-4, 2e-4}; },
            "$.thermal.ehc_soc[1]");
    refused([](json& j) { j["extensions"]["resistance_temperature"] = {{"activation_energy_j_per_mol", 1e300}}; },
            "$.extensions.resistance_temperature.activation_energy_j_per_mol");
    refused([](json& j) { j["extensions"]["entropic_heat"] = {{"ehc_v_per_k", 0.2}, {"ehc_slope_v_per_k", 0.0}}; },
            "$.extensions.entropic_heat.ehc_v_per_k");
    refused([](json& j) { j["extensions"]["series_resistance_offset"] = {{"r_ohm", -1e9}}; },
            "$.extensions.series_resistance_offset.r_ohm");
    refused([](json& j) { j["extensions"]["ocv_hysteresis"] = {{"magnitude_v", 30.0}, {"rate_per_capacity", 20.0}}; },
            "$.extensions.ocv_hysteresis.magnitude_v");
    refused([](json& j) { j["extensions"]["ambient_drift"] = {{"offset_c", 0.5}, {"rate_c_per_h", 1e300}}; },
            "$.extensions.ambient_drift.rate_c_per_h");

    // What a cell can have, however unusual, still loads: a 2 Ohm coin cell, -40 degC, 45 kJ/mol, +-1 mV/K.
    json j = thesis_json();
    for (auto& r : j["discharge"]["r0_ohm"]) r = 2.0;
    j["reference_temperature_c"] = -40.0;
    j["thermal"]["ehc_soc"] = {0.0, 1.0};
    j["thermal"]["ehc_v_per_k"] = {-1e-3, 1e-3};
    j["extensions"]["resistance_temperature"] = {{"activation_energy_j_per_mol", 45000.0}};
    EXPECT_EQ(error_of(j), "");
}

TEST(ParameterSet, CapacityUncertaintyIsOptionalAndRoundTrips) {
    auto p = ParameterSet::from_json(thesis_json(), "p45b-thesis.json");
    EXPECT_TRUE(std::isnan(p.capacity_ah_sd)) << "a set without it states none";
    EXPECT_FALSE(p.to_json().contains("capacity_ah_sd")) << "not written as a number it is not";
    p.capacity_ah_sd = 0.012;
    const auto again = ParameterSet::from_json(p.to_json(), "again");
    EXPECT_DOUBLE_EQ(again.capacity_ah_sd, 0.012);

    auto j = thesis_json();
    j["capacity_ah_sd"] = -0.01;
    EXPECT_NE(error_of(j).find("$.capacity_ah_sd: expected a non-negative uncertainty"), std::string::npos) << error_of(j);
    j["capacity_ah_sd"] = nullptr;  // null: not stated
    EXPECT_EQ(error_of(j), "");
}

TEST(ParameterSet, OcvUncertaintyIsOptionalOnePerSocAndRoundTrips) {
    auto p = ParameterSet::from_json(thesis_json(), "p45b-thesis.json");
    EXPECT_TRUE(p.ocv_v_sd.empty()) << "a set without it states none";
    EXPECT_FALSE(p.to_json().contains("ocv_v_sd"));
    p.ocv_v_sd.assign(p.soc.size(), 4e-4);
    p.ocv_v_sd.back() = 1.5e-3;
    const auto again = ParameterSet::from_json(p.to_json(), "again");
    ASSERT_EQ(again.ocv_v_sd.size(), p.soc.size());
    EXPECT_DOUBLE_EQ(again.ocv_v_sd.back(), 1.5e-3);

    auto j = thesis_json();
    j["ocv_v_sd"] = nlohmann::json::array({1e-3, 1e-3});
    EXPECT_NE(error_of(j).find("$.ocv_v_sd: expected " + std::to_string(p.soc.size()) + " values"), std::string::npos)
        << error_of(j);
    j["ocv_v_sd"] = p.to_json()["ocv_v_sd"];
    j["ocv_v_sd"][1] = -1e-3;
    EXPECT_NE(error_of(j).find("$.ocv_v_sd[1]: expected a non-negative uncertainty"), std::string::npos) << error_of(j);
    j["ocv_v_sd"] = nullptr;  // null: not stated
    EXPECT_EQ(error_of(j), "");
}
