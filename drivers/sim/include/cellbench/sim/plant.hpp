#pragma once
// The simulated bench's physical world, shared by every simulated instrument (Neware server, DEWE CAN
// publisher, Modbus chamber): one cell (the estimator's CellModel, so the plant is exactly the model the
// fitter identifies, plus switchable hidden physics and sensor noise) inside one chamber of air.
//
// Time is bench time in seconds (the simulated instruments map wall time to bench time with their time
// scale). The plant is thread-safe: instruments on different threads/strands call it concurrently.
#include <chrono>
#include <cmath>
#include <cstdint>
#include <deque>
#include <limits>
#include <utility>
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
    // A stopped chamber (or one whose heater failed) drifts towards the lab air through its insulation.
    double lab_temperature_c = 22.0;
    double chamber_stopped_time_constant_s = 1800.0;
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
    bool chamber_running = true;
};

// Copies of a BenchPlant share one plant (the handle is a shared pointer), so every instrument can hold one.
class BenchPlant {
public:
    explicit BenchPlant(PlantOptions options);

    // Integrates the plant up to bench time t (no-op if t is not later than the current time), but never past
    // the time the cycler's current is held until (set_current): that hold is the one limit on how far anyone
    // -- the cycler itself, the chamber, the DAQ -- may integrate the cell. Current is held between calls (the
    // exact ZOH of the model), ambient = chamber air.
    void advance_to(double bench_time_s);

    // Cycler output. Without hold_until_s it is held until changed (a current the cycler keeps whatever time
    // does: 0 A from an idle, paused or stopped tester). With it, the cycler vouches for this current only up
    // to that bench time -- a tester executing a program sets each tick's current, and what the cell gets after
    // the tick is the tester's next decision (CV limit, cut-offs, step changes) -- so no advance_to() integrates
    // the cell beyond it until the cycler sets the next current. A tester whose thread lags the bench clock then
    // holds the other instruments' view of the plant back instead of having its cell charged on with a stale
    // current past its CV limit or a cut-off, and its late tick finds the cell where its previous tick left it,
    // so its rows are the cell's under the current they record (without the hold, at 400x: voltage steps of
    // 2-7 mV 1-2 s after a current step, where the DAQ or the chamber had moved the cell on under the previous
    // current).
    void set_current(double current_a, double hold_until_s = std::numeric_limits<double>::infinity());
    void set_chamber_setpoint(double setpoint_c);
    void set_chamber_running(bool running);      // a stopped chamber drifts towards the lab at 22 degC
    // Fault of the simulated chamber: the heater no longer heats, so the air cannot rise above the lab
    // temperature (cooling still works) and a set point above it is never reached.
    void set_chamber_heater_failed(bool failed);

    // Terminal voltage the cell would show now at a given current (no state change): for CV control.
    double voltage_at(double current_a) const;

    PlantReading read() const;                   // at the current bench time (sensor noise drawn per call)
    double now_s() const;

private:
    // implementation detail, see plant.cpp
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

// Bench time of the simulated instruments. One clock is shared by all simulated instruments of a bench so
// they agree on "now" (each one calls BenchPlant::advance_to(clock.now_s()) before reading; the plant may stay
// behind that while the cycler's current is held only until an earlier time, see set_current).
//
// Two modes:
//  - free (the default): bench = start + time_scale * (wall - wall at construction). A pure function of wall
//    time, so two processes (a daemon and `cellbench sim`) started with the same scale agree on durations.
//  - paced (BenchClock::Paced): bench time advances only through pace(), called regularly by the process that
//    hosts the simulation and consumes its readings (cellbenchd's io threads), by at most max_step_wall_s *
//    time_scale bench seconds per call. A starved process (no CPU for seconds) does not jump hundreds of bench
//    seconds: the simulated bench slows down with it and never outruns the daemon. Readers between two pace()
//    calls see time move on smoothly, but never more than one bounded step past the last pace().
// Thread-safe (a mutex; every call is a few arithmetic operations).
class BenchClock {
public:
    using WallClock = std::chrono::steady_clock;
    struct Paced {
        double max_step_wall_s = 0.1;  // wall time one pace() may turn into bench time (x time_scale)
    };

    explicit BenchClock(double time_scale = 1.0, double bench_start_s = 0.0);
    BenchClock(double time_scale, double bench_start_s, Paced paced);

    [[nodiscard]] double time_scale() const { return time_scale_; }  // target bench seconds per wall second
    [[nodiscard]] bool paced() const { return paced_; }
    [[nodiscard]] double max_step_s() const;  // bench seconds one pace() may add (infinite when free)

    [[nodiscard]] double now_s() const { return at(WallClock::now()); }
    // Bench time at a wall instant: now, or in the recent past (a reading's arrival).
    [[nodiscard]] double at(WallClock::time_point wall) const;
    // Wall instant at which the bench reaches bench_time_s (for scheduling; an estimate when paced).
    [[nodiscard]] WallClock::time_point wall_at(double bench_time_s) const;

    // Paced mode: moves bench time to `wall` (by at most one bounded step) and returns it. No-op when free.
    double pace(WallClock::time_point wall = WallClock::now());
    // Paced mode: the same step at another rate (bench seconds per wall second, at most the time scale; 0 is
    // hold()): the bench slows down while the consumer catches up (sim::PaceGate). Readers until the next call
    // see time move at that rate. No-op when free.
    double pace(WallClock::time_point wall, double scale);
    // Paced mode: the consumer is behind (its queue of readings is late): wall time up to `wall` passes without
    // bench time (readers still never see it go back). No-op when free.
    double hold(WallClock::time_point wall = WallClock::now());

    // Bench seconds per wall second actually achieved over about the last 10 s of wall time (the target scale
    // when free, or before 1 s has passed).
    [[nodiscard]] double achieved_scale() const;
    // Wall seconds the paced clock did not turn into bench time (the host was starved), since construction.
    [[nodiscard]] double lost_wall_s() const;

private:
    double read_locked(WallClock::time_point wall) const;
    double advance_locked(WallClock::time_point wall, double rate);

    double time_scale_;
    double bench_start_s_;
    WallClock::time_point wall_start_;
    bool paced_ = false;
    double max_step_wall_s_ = 0.0;

    mutable std::mutex mutex_;
    WallClock::time_point anchor_wall_;  // last pace()
    double anchor_bench_ = 0.0;
    mutable double last_read_ = 0.0;     // readers never see time go back
    std::deque<std::pair<WallClock::time_point, double>> trail_;  // (wall, bench) of recent pace()/hold()
    std::deque<std::pair<WallClock::time_point, double>> history_;  // (wall, bench) about once a second
    double lost_wall_s_ = 0.0;
    double rate_ = 0.0;  // bench s per wall s of the last pace() (0 after hold(): readers see no time pass)
};

}  // namespace cellbench::sim
