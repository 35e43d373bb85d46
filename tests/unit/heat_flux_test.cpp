// The FHF05 conversion shared by import and the DEWE-43A driver (thesis eq. 2.2).
#include "cellbench/protocol/heat_flux.hpp"

#include <gtest/gtest.h>

#include <cmath>

namespace {

using cellbench::protocol::heat_flux_density_w_per_m2;
using cellbench::protocol::kFhf05ThesisSensitivityVPerWPerM2;

TEST(HeatFlux, AtTheCalibrationTemperatureIsVoltageOverSensitivity) {
    EXPECT_EQ(kFhf05ThesisSensitivityVPerWPerM2, 17.39e-6);
    EXPECT_DOUBLE_EQ(heat_flux_density_w_per_m2(17.39e-6, 20.0, kFhf05ThesisSensitivityVPerWPerM2), 1.0);
    EXPECT_DOUBLE_EQ(heat_flux_density_w_per_m2(1e-3, 20.0, 20e-6), 50.0);
}

TEST(HeatFlux, SensitivityRisesByPointTwoPercentPerKelvin) {
    // At 30 degC the sensor gives 2 % more voltage per W/m^2, so the same voltage means 2 % less flux.
    const double u = 17.39e-6 * 1.02 * 50.0;
    EXPECT_NEAR(heat_flux_density_w_per_m2(u, 30.0, 17.39e-6), 50.0, 1e-12);
    EXPECT_NEAR(heat_flux_density_w_per_m2(u, 20.0, 17.39e-6), 51.0, 1e-12);
    // Below 20 degC the correction goes the other way.
    EXPECT_NEAR(heat_flux_density_w_per_m2(17.39e-6 * 0.98, 10.0, 17.39e-6), 1.0, 1e-12);
}

TEST(HeatFlux, SignFollowsTheThermopileAndNaNPropagates) {
    EXPECT_LT(heat_flux_density_w_per_m2(-5e-6, 29.5, kFhf05ThesisSensitivityVPerWPerM2), 0.0);
    EXPECT_TRUE(std::isnan(heat_flux_density_w_per_m2(1e-5, std::nan(""), kFhf05ThesisSensitivityVPerWPerM2)));
}

TEST(HeatFlux, MatchesDewesoftOnARowOfTheThesisRecording) {
    // rw_30degC_dewesoft.csv, first row: DewesoftX gave -0.2627885229558065 W/m^2.
    const double q = heat_flux_density_w_per_m2(-4.656410209008754e-06, 29.45379431152344, kFhf05ThesisSensitivityVPerWPerM2);
    EXPECT_NEAR(q, -0.2627885229558065, 0.2627885229558065 * 1e-4);
}

}  // namespace
