// DewesoftX heat flux export -> DewesoftExport.
#include "cellbench/protocol/dewesoft_export.hpp"

#include "cellbench/core/recording.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

namespace {

using cellbench::InputError;
using cellbench::protocol::DewesoftExport;
using cellbench::protocol::parse_dewesoft_export;

std::string error_of(const std::string& text) {
    try {
        (void)parse_dewesoft_export(text, "rw_dewe.csv");
    } catch (const InputError& e) {
        return e.what();
    }
    return "";
}

TEST(DewesoftExport, ReadsTheBenchExport) {
    const std::string text =
        "Time,Thermal Flux Sensor Voltage (V),Temperature (C),Heat Flux Density (W/m^2),Heat Flux Test Area (W),"
        "Heat Flux Lateral Surface Area (W)\r\n"
        "0.8,-4.656410209008754e-06,29.45379431152344,-0.2627885229558065,-0.00034,-0.0024\r\n"
        "0.9,-4.838761823871137e-06,29.453839922708177,-0.2730798519674027,-0.00035,-0.0025\r\n";
    const DewesoftExport d = parse_dewesoft_export(text, "rw_dewe.csv");
    EXPECT_EQ(d.source, "rw_dewe.csv");
    EXPECT_EQ(d.time_s, (std::vector<double>{0.8, 0.9}));
    EXPECT_EQ(d.thermopile_v, (std::vector<double>{-4.656410209008754e-06, -4.838761823871137e-06}));
    EXPECT_EQ(d.type_t_c, (std::vector<double>{29.45379431152344, 29.453839922708177}));
    // The area-scaled columns must not be mistaken for the density.
    EXPECT_EQ(d.heat_flux_w_per_m2, (std::vector<double>{-0.2627885229558065, -0.2730798519674027}));
    EXPECT_TRUE(d.t1_c.empty());
    EXPECT_TRUE(d.t2_c.empty());
    EXPECT_EQ(d.repaired_timestamps, 0u);
}

TEST(DewesoftExport, MapsTypeKColumnsByNumberOrOrder) {
    const std::string text =
        "Time (s),Thermocouple K2 (C),Temperature (C),Temperature T1 (C),Thermal Flux Sensor Voltage (V)\n"
        "0,40,30,41,1e-5\n";
    const DewesoftExport d = parse_dewesoft_export(text, "x");
    EXPECT_EQ(d.t1_c, (std::vector<double>{41}));
    EXPECT_EQ(d.t2_c, (std::vector<double>{40}));
    EXPECT_EQ(d.type_t_c, (std::vector<double>{30}));
    EXPECT_TRUE(d.heat_flux_w_per_m2.empty());

    const DewesoftExport unnumbered = parse_dewesoft_export(
        "Time,Type K Thermocouple (C),Type K Thermocouple (C),Heat Flux Density (W/m^2)\n0,35,36,1.5\n", "x");
    EXPECT_EQ(unnumbered.t1_c, (std::vector<double>{35}));
    EXPECT_EQ(unnumbered.t2_c, (std::vector<double>{36}));
    EXPECT_TRUE(unnumbered.thermopile_v.empty());
    EXPECT_EQ(unnumbered.heat_flux_w_per_m2, (std::vector<double>{1.5}));
}

TEST(DewesoftExport, ScalesAThermopileVoltageInMillivolts) {
    const DewesoftExport d =
        parse_dewesoft_export("Time,Thermal Flux Sensor Voltage (mV),Temperature (C)\n0,0.25,30\n", "x");
    ASSERT_EQ(d.thermopile_v.size(), 1u);
    EXPECT_DOUBLE_EQ(d.thermopile_v[0], 0.25e-3);
}

TEST(DewesoftExport, EmptyDataCellsAreNaNButTimeIsRequired) {
    const DewesoftExport d = parse_dewesoft_export(
        "Time,Thermal Flux Sensor Voltage (V),Temperature (C),Heat Flux Density (W/m^2)\n0,1e-5,,0.5\n0.1,,30,\n", "x");
    EXPECT_TRUE(std::isnan(d.type_t_c.at(0)));
    EXPECT_TRUE(std::isnan(d.thermopile_v.at(1)));
    EXPECT_TRUE(std::isnan(d.heat_flux_w_per_m2.at(1)));
    EXPECT_EQ(error_of("Time,Heat Flux Density (W/m^2)\n0,1\n,2\n"),
              "rw_dewe.csv:3: column \"Time\": expected a number, got an empty cell");
    EXPECT_EQ(error_of("Time,Heat Flux Density (W/m^2)\n0,1\n0.1,2x\n"),
              "rw_dewe.csv:3: column \"Heat Flux Density (W/m^2)\": expected a number, got \"2x\"");
}

TEST(DewesoftExport, TimeIsRepairedOrRejectedLikeBdf) {
    const DewesoftExport d =
        parse_dewesoft_export("Time,Heat Flux Density (W/m^2)\n0.0,1\n0.1,1\n0.1,1\n0.2,1\n0.15,1\n0.3,1\n", "x");
    EXPECT_EQ(d.repaired_timestamps, 2u);
    EXPECT_DOUBLE_EQ(d.time_s[2], 0.15);
    EXPECT_DOUBLE_EQ(d.time_s[4], 0.25);
    EXPECT_EQ(d.time_s[5], 0.3);
    EXPECT_EQ(error_of("Time,Heat Flux Density (W/m^2)\n5,1\n3.9,1\n"),
              "rw_dewe.csv:3: column \"Time\": time steps back by 1.1 s (from 5 s to 3.9 s); only steps back of less "
              "than 1 s are repaired");
}

TEST(DewesoftExport, MissingColumnsAndEmptyInputAreErrors) {
    std::string msg = error_of("Thermal Flux Sensor Voltage (V),Temperature (C)\n1e-5,30\n");
    EXPECT_EQ(msg.rfind("rw_dewe.csv:1: no time column: expected \"Time\"", 0), 0u) << msg;
    msg = error_of("Time,Thermal Flux Sensor Voltage (V),Heat Flux Test Area (W)\n0,1e-5,0.1\n");
    EXPECT_EQ(msg.rfind("rw_dewe.csv:1: the thermopile voltage needs the sensor's Type-T column", 0), 0u) << msg;
    msg = error_of("");
    EXPECT_EQ(msg.rfind("rw_dewe.csv:1: empty file", 0), 0u) << msg;
    EXPECT_EQ(error_of("Time,Heat Flux Density (W/m^2)\n"),
              "rw_dewe.csv:1: header only: expected data rows after the header");
}

}  // namespace
