#pragma once
// Heat flux density from a Hukseflux FHF05 thermopile: the one conversion used by `import` and by the
// DEWE-43A driver, so offline and online numbers agree.

namespace cellbench::protocol {

// Certificate sensitivity of the thesis sensor at the reference temperature, V per W/m^2.
inline constexpr double kFhf05ThesisSensitivityVPerWPerM2 = 17.39e-6;  // certificate value of the thesis sensor, at 20 degC
// The FHF05 sensitivity rises by 0.2 %/K above the calibration temperature (Hukseflux manual, thesis eq. 2.2).
inline constexpr double kFhf05SensitivityTempCoeffPerK = 0.002;
inline constexpr double kFhf05CalibrationTemperatureC = 20.0;

// Thesis eq. 2.2: q = U / (S * (1 + 0.002 * (T - 20 degC))).
// thermopile_v: sensor output in V; sensor_temperature_c: the sensor's own Type-T in degC (pass 20 degC for
// no correction); sensitivity > 0. Positive q = heat leaving the cell surface. NaN inputs give NaN.
constexpr double heat_flux_density_w_per_m2(double thermopile_v, double sensor_temperature_c,
                                            double sensitivity_v_per_w_per_m2) {
    const double sensitivity_at_t =
        sensitivity_v_per_w_per_m2 *
        (1.0 + kFhf05SensitivityTempCoeffPerK * (sensor_temperature_c - kFhf05CalibrationTemperatureC));
    return thermopile_v / sensitivity_at_t;
}

}  // namespace cellbench::protocol
