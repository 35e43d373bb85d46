// The shared simulated bench plant: the chamber air's ramp limits and ripple, the cell as the estimator's
// model (heat flux, thermopile voltage), the harness resistance, determinism by seed.
#include "cellbench/sim/plant.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <thread>

#include "cellbench/estimator/model.hpp"
#include "cellbench/protocol/heat_flux.hpp"

namespace {

using cellbench::estimator::CellModel;
using cellbench::estimator::CellState;
using cellbench::estimator::ParameterSet;
using cellbench::sim::BenchPlant;
using cellbench::sim::PlantOptions;

ParameterSet thesis_params() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    return ParameterSet::from_json(nlohmann::json::parse(in), "p45b-thesis.json");
}

// A plant without noise or ripple, so the physics can be checked exactly.
PlantOptions quiet_options() {
    PlantOptions o;
    o.cell = thesis_params();
    o.initial_soc = 0.8;
    o.initial_temperature_c = 30.0;
    o.chamber_setpoint_c = 30.0;
    o.chamber_ripple_c = 0.0;
    o.voltage_noise_v = 0.0;
    o.current_noise_a = 0.0;
    o.temperature_noise_c = 0.0;
    o.thermopile_noise_v = 0.0;
    return o;
}

TEST(Plant, ChamberHeatsAtMostSevenDegreesPerMinute) {
    BenchPlant plant(quiet_options());
    plant.set_chamber_setpoint(80.0);
    double previous = plant.read().chamber_air_c;
    double max_rate_c_per_min = 0.0;
    for (int t = 1; t <= 3600; ++t) {
        plant.advance_to(t);
        const double air = plant.read().chamber_air_c;
        max_rate_c_per_min = std::max(max_rate_c_per_min, (air - previous) * 60.0);
        previous = air;
        if (t == 60) {
            EXPECT_NEAR(air, 37.0, 1e-9) << "far from the set point the air ramps at the limit";
        }
    }
    EXPECT_LE(max_rate_c_per_min, 7.0 + 1e-9);
    EXPECT_NEAR(previous, 80.0, 0.01) << "and settles on the set point";
}

TEST(Plant, ChamberCoolsAtMostFourDegreesPerMinuteThenFollowsFirstOrder) {
    BenchPlant plant(quiet_options());
    plant.set_chamber_setpoint(-20.0);
    double previous = plant.read().chamber_air_c;
    for (int t = 1; t <= 600; ++t) {
        plant.advance_to(t);
        const double air = plant.read().chamber_air_c;
        EXPECT_GE(air - previous, -4.0 / 60.0 - 1e-9) << "at t = " << t;
        previous = air;
        if (t == 60) {
            EXPECT_NEAR(air, 26.0, 1e-9);
        }
    }
    // Within rate * tau = 8 degC of the set point the limit is no longer active: plain first order, tau 120 s.
    BenchPlant near(quiet_options());
    near.set_chamber_setpoint(25.0);
    near.advance_to(120.0);
    EXPECT_NEAR(near.read().chamber_air_c, 25.0 + 5.0 * std::exp(-1.0), 1e-9);
}

TEST(Plant, RippleStaysWithinTheConstancyBand) {
    PlantOptions o = quiet_options();
    o.chamber_ripple_c = 0.5;
    BenchPlant plant(o);
    double lo = 1e9, hi = -1e9;
    for (int t = 0; t <= 1200; t += 5) {
        plant.advance_to(t);
        const double air = plant.read().chamber_air_c;
        lo = std::min(lo, air);
        hi = std::max(hi, air);
    }
    EXPECT_GE(lo, 29.5 - 1e-9);
    EXPECT_LE(hi, 30.5 + 1e-9);
    EXPECT_GT(hi - lo, 0.9) << "the ripple is there";
}

TEST(Plant, StoppedChamberAndFailedHeaterDriftTowardsTheLab) {
    BenchPlant stopped(quiet_options());
    stopped.set_chamber_running(false);
    stopped.advance_to(20000.0);
    EXPECT_NEAR(stopped.read().chamber_air_c, 22.0, 0.1);
    EXPECT_FALSE(stopped.read().chamber_running);

    BenchPlant broken(quiet_options());
    broken.set_chamber_heater_failed(true);
    broken.set_chamber_setpoint(60.0);
    double max_air = 0.0;
    for (int t = 60; t <= 3600; t += 60) {
        broken.advance_to(t);
        max_air = std::max(max_air, broken.read().chamber_air_c);
    }
    EXPECT_LE(max_air, 30.0) << "without the heater the air never rises towards 60 degC";
    EXPECT_NEAR(broken.read().chamber_air_c, 22.0, 0.5);
}

TEST(Plant, CellIsTheEstimatorModelAndHeatFluxIsItsHeatFlowOverTheArea) {
    PlantOptions o = quiet_options();
    BenchPlant plant(o);
    const CellModel model(o.cell);
    CellState state;
    state.soc = o.initial_soc;
    state.temperature_c = o.initial_temperature_c;
    const auto& th = o.cell.thermal;

    double t = 0.0;
    auto run = [&](double current_a, double duration_s) {
        plant.set_current(current_a);
        for (int k = 0; k < static_cast<int>(duration_s * 10); ++k) {
            t += 0.1;
            const auto out = model.step(state, current_a, 30.0, 0.1);
            if (k % 100 == 99) {
                plant.advance_to(t);
                const auto r = plant.read();
                ASSERT_NEAR(r.cell_temperature_c, state.temperature_c, 1e-9);
                ASSERT_NEAR(r.terminal_voltage_v, out.voltage_v, 1e-9);
                ASSERT_NEAR(r.soc, state.soc, 1e-12);
                ASSERT_NEAR(r.heat_flux_w_per_m2 * th.area_m2, out.heat_flow_out_w, 1e-9);
                // What the DAQ converts back with eq. 2.2 is the true heat flux (no noise, gain 1).
                ASSERT_NEAR(cellbench::protocol::heat_flux_density_w_per_m2(r.thermopile_v, r.surface_type_t_c,
                                                                            o.heat_flux_sensitivity_v_per_w_per_m2),
                            r.heat_flux_w_per_m2, 1e-9);
            }
        }
    };
    run(-20.0, 300.0);  // 5C discharge: the cell warms up and loses heat to the air
    EXPECT_GT(plant.read().heat_flux_w_per_m2, 20.0);
    run(0.0, 300.0);
    EXPECT_NEAR(plant.read().charge_ah, -20.0 * 300.0 / 3600.0, 1e-9);
    EXPECT_LT(plant.read().energy_wh, 0.0);
}

TEST(Plant, SensorGainScalesTheThermopileOnly) {
    PlantOptions o = quiet_options();
    o.heat_flux_sensor_gain = 1.1;
    BenchPlant plant(o);
    plant.set_current(-20.0);
    plant.advance_to(200.0);
    const auto r = plant.read();
    const double measured = cellbench::protocol::heat_flux_density_w_per_m2(r.thermopile_v, r.surface_type_t_c,
                                                                            o.heat_flux_sensitivity_v_per_w_per_m2);
    EXPECT_NEAR(measured, 1.1 * r.heat_flux_w_per_m2, 1e-9);
}

TEST(Plant, HarnessResistanceAddsToTheTerminalVoltageOnly) {
    PlantOptions with = quiet_options();
    with.harness_resistance_ohm = 0.005;
    BenchPlant plain(quiet_options()), harnessed(with);
    for (auto* p : {&plain, &harnessed}) {
        p->set_current(-20.0);
        p->advance_to(60.0);
    }
    const auto a = plain.read(), b = harnessed.read();
    EXPECT_NEAR(b.terminal_voltage_v - a.terminal_voltage_v, 0.005 * -20.0, 1e-12);
    EXPECT_NEAR(harnessed.voltage_at(10.0) - plain.voltage_at(10.0), 0.005 * 10.0, 1e-12);
    EXPECT_DOUBLE_EQ(b.cell_temperature_c, a.cell_temperature_c) << "harness heat stays outside the cell";
    EXPECT_DOUBLE_EQ(b.soc, a.soc);
}

TEST(Plant, SameSeedSameReadingsOtherSeedOtherNoise) {
    PlantOptions o;
    o.cell = thesis_params();
    o.seed = 42;
    BenchPlant a(o), b(o);
    o.seed = 43;
    BenchPlant c(o);
    bool differs = false;
    for (int t = 1; t <= 50; ++t) {
        for (auto* p : {&a, &b, &c}) {
            p->set_current(t % 10 < 5 ? -8.0 : 4.0);
            p->advance_to(t * 0.7);
        }
        const auto ra = a.read(), rb = b.read(), rc = c.read();
        ASSERT_EQ(ra.terminal_voltage_v, rb.terminal_voltage_v);
        ASSERT_EQ(ra.current_a, rb.current_a);
        ASSERT_EQ(ra.surface_type_t_c, rb.surface_type_t_c);
        ASSERT_EQ(ra.thermopile_v, rb.thermopile_v);
        ASSERT_EQ(ra.chamber_air_c, rb.chamber_air_c);
        differs = differs || ra.terminal_voltage_v != rc.terminal_voltage_v;
        EXPECT_EQ(ra.cell_temperature_c, rc.cell_temperature_c) << "noise never changes the physics";
    }
    EXPECT_TRUE(differs);
}

TEST(Plant, CopiesShareOnePlantAndConcurrentUseIsSafe) {
    BenchPlant plant(quiet_options());
    BenchPlant other = plant;  // e.g. the Neware server's handle
    std::vector<std::thread> threads;
    for (int i = 0; i < 4; ++i)
        threads.emplace_back([&, i] {
            for (int k = 1; k <= 500; ++k) {
                (i % 2 ? plant : other).advance_to(k * 0.5);
                (void)(i % 2 ? other : plant).read();
                if (i == 0) plant.set_current(-(k % 7));
            }
        });
    for (auto& t : threads) t.join();
    EXPECT_DOUBLE_EQ(other.now_s(), 250.0);
    EXPECT_DOUBLE_EQ(plant.now_s(), 250.0);
}

// A tester executing a program holds each tick's current only up to the tick's end: another instrument reading
// the plant at a later "now" (the tester's thread lagging the bench clock) does not integrate the cell on with
// that current; the plant waits for the tester's next tick. A current set without a hold is kept for any time.
TEST(Plant, CurrentHeldUntilATimeIsNotIntegratedPastIt) {
    BenchPlant plant(quiet_options());
    plant.advance_to(10.0);
    plant.set_current(4.5, 10.1);  // one 0.1 s tick of a 1C charge
    plant.advance_to(10.1);
    const double soc_tick = plant.read().soc;
    EXPECT_DOUBLE_EQ(plant.now_s(), 10.1);
    plant.advance_to(1000.0);  // the chamber or the DAQ at the clock's "now"
    EXPECT_DOUBLE_EQ(plant.now_s(), 10.1) << "integrated past the tester's tick";
    EXPECT_DOUBLE_EQ(plant.read().soc, soc_tick);
    plant.set_current(4.5, 10.2);  // the tester's next tick
    plant.advance_to(1000.0);
    EXPECT_DOUBLE_EQ(plant.now_s(), 10.2);
    EXPECT_GT(plant.read().soc, soc_tick);
    plant.set_current(0.0);  // the program ended: 0 A for as long as time goes on
    plant.advance_to(1000.0);
    EXPECT_DOUBLE_EQ(plant.now_s(), 1000.0);
}

// The cycler drives the cell's time: each tick's current is held up to the tick's end (set_current), so
// another instrument's advance (the DAQ's, the chamber's, at the clock's "now") stops at the cycler's last tick;
// a late tick still finds the cell where the cycler left it, and the cell under the cycler's current is the
// same whoever advanced it in between.
TEST(Plant, OtherInstrumentsNeverAdvanceTheCellPastTheCyclersLastTick) {
    BenchPlant reference(quiet_options()), shared(quiet_options());
    for (BenchPlant* p : {&reference, &shared}) {
        p->set_current(-4.5, 10.0);  // the cycler's tick up to 10 s
        p->advance_to(10.0);
    }
    shared.advance_to(12.0);  // the DAQ, ahead of the cycler's next tick
    EXPECT_DOUBLE_EQ(shared.now_s(), 10.0);
    for (BenchPlant* p : {&reference, &shared}) {
        p->set_current(0.0, 10.1);  // the cycler's late tick: the pulse ended at 10 s
        p->advance_to(10.1);
    }
    EXPECT_DOUBLE_EQ(shared.now_s(), 10.1);
    EXPECT_DOUBLE_EQ(shared.read().terminal_voltage_v, reference.read().terminal_voltage_v);
    // Without a cycler holding its current, the plant advances for anyone (a chamber or DAQ simulated alone).
    BenchPlant alone(quiet_options());
    alone.advance_to(12.0);
    EXPECT_DOUBLE_EQ(alone.now_s(), 12.0);
}

TEST(BenchClock, MapsWallTimeByTheTimeScale) {
    const cellbench::sim::BenchClock clock(100.0, 5.0);
    const auto wall = clock.wall_at(15.0);
    EXPECT_NEAR(clock.at(wall), 15.0, 1e-6);
    EXPECT_NEAR(clock.at(wall + std::chrono::milliseconds(10)), 16.0, 1e-6);
}

}  // namespace
