#pragma once
// The simulated bench's physical world, shared by every simulated instrument (Neware server, DEWE CAN
// publisher, Modbus chamber): one cell (the estimator's CellModel, so the plant is exactly the model the
// fitter identifies, plus switchable hidden physics and sensor noise) inside one chamber of air.
//
// Time is bench time in seconds (the simulated instruments map wall time to bench time with their time
// scale). The plant is thread-safe: instruments on different threads/strands call it concurrently.
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>

#include "cellbench/estimator/model.hpp"

namespace cellbench::sim {

struct PlantOptions {
    estimator::ParameterSet cell;      // with optional extensions (hidden physics)
    double initial_soc = 1.0;
    double initial_temperature_c = 30.0;  // cell and chamber air at start
    double chamber_setpoint_c = 30.0;
    // Chamber air: first-order towards the set point with ramp limits (thesis 2.1.5: 7 degC/min up,
    // 4 degC/min down) and a +-constancy ripple.
    double chamber_time_constant_s = 120.0;
    double chamber_ramp_up_c_per_min = 7.0;
    double chamber_ramp_down_c_per_min = 4.0;
    double chamber_ripple_c = 0.5;
    double chamber_ripple_period_s = 600.0;
    // Sensors.
    double heat_flux_sensitivity_v_per_w_per_m2 = 17.39e-6;  // S at 20 degC
    double heat_flux_sensor_gain = 1.0;    // true/configured sensitivity (hidden effect heat_flux_sensor_gain)
    double harness_resistance_ohm = 0.0;   // extra series resistance seen at the cycler terminals
    double voltage_noise_v = 0.0002;
    double current_noise_a = 0.002;
    double temperature_noise_c = 0.02;
    double thermopile_noise_v = 2e-7;
    std::uint32_t seed = 1;
};

// What the instruments can read at one instant.
struct PlantReading {
    double bench_time_s = 0.0;
    double current_a = 0.0;            // + = charge, as set by the cycler
    double terminal_voltage_v = 0.0;   // at the cycler terminals (harness included), with noise
    double soc = 0.0;                  // truth (not visible to the daemon except through the simulated cycler)
    double charge_ah = 0.0;            // throughput since start, + = charged
    double energy_wh = 0.0;
    double cell_temperature_c = 0.0;   // truth (surface node)
    double surface_type_t_c = 0.0;     // Type-T in the heat flux sensor, with noise
    double terminal_pos_c = 0.0, terminal_neg_c = 0.0;  // Type-K T1, T2, with noise
    double heat_flux_w_per_m2 = 0.0;   // truth, leaving the surface
    double thermopile_v = 0.0;         // what the DAQ measures: q * S * (1 + 0.002 (T - 20)) * gain, with noise
    double chamber_air_c = 0.0;        // process value
    double chamber_setpoint_c = 0.0;
};

class BenchPlant {
public:
    explicit BenchPlant(PlantOptions options);

    // Integrates the plant up to bench time t (no-op if t is not later than the current time). Current is
    // held between calls (the exact ZOH of the model), ambient = chamber air.
    void advance_to(double bench_time_s);

    void set_current(double current_a);          // cycler output (held until changed)
    void set_chamber_setpoint(double setpoint_c);
    void set_chamber_running(bool running);      // a stopped chamber drifts towards the lab at 22 degC

    // Terminal voltage the cell would show now at a given current (no state change): for CV control.
    double voltage_at(double current_a) const;

    PlantReading read() const;                   // at the current bench time (sensor noise drawn per call)
    double now_s() const;

private:
    // implementation detail, see plant.cpp
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

}  // namespace cellbench::sim
