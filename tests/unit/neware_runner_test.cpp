// The simulated tester's step execution against a simple linear cell: exact step times at any call pattern
// (i.e. any time scale), cut-offs, CC->CV, loops, and the HPPC capacity formula removing exactly 10 % per set.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "cellbench/protocol/neware_stepfile.hpp"
#include "cellbench/sim/neware_runner.hpp"

using namespace cellbench::sim;
using namespace cellbench::protocol;

namespace {

// OCV linear in SOC (2.8 V empty .. 4.2 V full) behind a series resistance.
struct LinearCell : RunnerCell {
    double capacity_ah = 4.0, soc = 0.5, r_ohm = 0.01, t_s = 0.0;
    double ocv() const { return 2.8 + 1.4 * soc; }
    double voltage_at(double current_a) override { return ocv() + r_ohm * current_a; }
    CellMeasurement drive(double current_a, double until_s) override {
        soc += current_a * (until_s - t_s) / 3600.0 / capacity_ah;
        t_s = until_s;
        return {current_a, ocv() + r_ohm * current_a};
    }
};

Step rest(double s) {
    Step x;
    x.type = StepType::rest;
    x.time_s = s;
    return x;
}
Step end_step() {
    Step x;
    x.type = StepType::end;
    return x;
}
StepProgram program(std::vector<Step> steps) {
    StepProgram p;
    p.name = "test";
    p.steps = std::move(steps);
    p.steps.push_back(end_step());
    return p;
}

std::vector<ProgramRunner::StepRecord> records_of(const ProgramRunner& r, int step_id) {
    std::vector<ProgramRunner::StepRecord> out;
    for (const auto& h : r.history())
        if (h.step_id == step_id) out.push_back(h);
    return out;
}

}  // namespace

TEST(NewareRunner, TimeLimitsAreExactAndIndependentOfHowOftenItRuns) {
    Step dis;
    dis.type = StepType::cc_discharge;
    dis.current_a = 4.5;
    dis.time_s = 30.0;
    Step chg;
    chg.type = StepType::cc_charge;
    chg.current_a = 4.5;
    chg.time_s = 10.0;
    const StepProgram p = program({rest(10.05), dis, rest(40), chg, rest(40)});

    // One call (time scale "infinite") ...
    LinearCell cell_a;
    ProgramRunner a(p, 0.0, 0.1);
    a.run_until(1e6, cell_a);
    // ... and many irregular calls (a wall timer at some time scale).
    LinearCell cell_b;
    ProgramRunner b(p, 0.0, 0.1);
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> step(0.0, 0.7);
    for (double t = 0; b.state() == RunState::working; t += step(rng)) b.run_until(t, cell_b);

    ASSERT_EQ(a.state(), RunState::finished);
    ASSERT_EQ(b.state(), RunState::finished);
    ASSERT_EQ(a.history().size(), 5u);
    ASSERT_EQ(b.history().size(), 5u);
    const double durations[] = {10.05, 30.0, 40.0, 10.0, 40.0};
    for (std::size_t i = 0; i < 5; ++i) {
        EXPECT_NEAR(a.history()[i].end_s - a.history()[i].start_s, durations[i], 1e-9) << i;
        EXPECT_EQ(a.history()[i].end_reason, "time");
        EXPECT_DOUBLE_EQ(a.history()[i].end_s, b.history()[i].end_s);
        EXPECT_DOUBLE_EQ(a.history()[i].capacity_ah, b.history()[i].capacity_ah);
    }
    EXPECT_NEAR(a.history()[1].capacity_ah, 4.5 * 30 / 3600, 1e-12);
    EXPECT_DOUBLE_EQ(cell_a.soc, cell_b.soc);
    EXPECT_NEAR(a.total_time_s(), 130.05, 1e-9);
}

TEST(NewareRunner, VoltageCutoffEndsTheStepAtTheFirstTickBeyondIt) {
    LinearCell cell;
    cell.soc = 0.2;
    Step dis;
    dis.type = StepType::cc_discharge;
    dis.current_a = 9.0;
    dis.cutoff_voltage_v = 2.9;
    ProgramRunner r(program({dis}), 0.0, 0.1);
    r.run_until(1e6, cell);
    ASSERT_EQ(r.history().size(), 1u);
    const auto& h = r.history()[0];
    EXPECT_EQ(h.end_reason, "voltage");
    EXPECT_LE(h.end_voltage_v, 2.9);
    EXPECT_GT(h.end_voltage_v, 2.9 - 9.0 * 0.1 / 3600 / 4.0 * 1.4 - 1e-12);  // within one tick of the cut-off
    EXPECT_NEAR(h.end_current_a, -9.0, 1e-12);
}

TEST(NewareRunner, CcThenCvThenCurrentCutoff) {
    LinearCell cell;
    cell.soc = 0.8;  // OCV 3.92 V
    Step s;
    s.type = StepType::cccv_charge;
    s.current_a = 4.5;
    s.voltage_v = 4.1;
    s.cutoff_current_a = 0.05;
    ProgramRunner r(program({s}), 0.0, 0.1);
    bool saw_cc = false, saw_cv = false;
    while (r.state() == RunState::working) {
        r.run_until(r.now_s() + 1.0, cell);
        if (r.state() != RunState::working) break;
        if (!r.cv_phase()) {
            saw_cc = true;
            EXPECT_NEAR(r.last().current_a, 4.5, 1e-12);
            EXPECT_EQ(r.step_type_code(), "cc");
        } else {
            saw_cv = true;
            EXPECT_EQ(r.step_type_code(), "cv");
            EXPECT_LT(r.last().current_a, 4.5);
            EXPECT_LE(r.last().voltage_v, 4.1 + 4.5 * 0.1 / 3600 / 4.0 * 1.4 + 1e-9);  // held at the set value
        }
    }
    EXPECT_TRUE(saw_cc);
    EXPECT_TRUE(saw_cv);
    ASSERT_EQ(r.history().size(), 1u);
    EXPECT_EQ(r.history()[0].end_reason, "current");
    EXPECT_LE(r.history()[0].end_current_a, 0.05);
    EXPECT_NEAR(cell.ocv(), 4.1, 0.01);  // charged to the CV voltage
}

TEST(NewareRunner, CapacityLimitLandsExactly) {
    LinearCell cell;
    Step dis;
    dis.type = StepType::cc_discharge;
    dis.current_a = 4.5;
    dis.cutoff_voltage_v = 2.9;
    dis.cutoff_capacity_ah = CapacityExpression{0.1, {}};
    ProgramRunner r(program({dis}), 0.0, 0.1);
    r.run_until(1e6, cell);
    ASSERT_EQ(r.history().size(), 1u);
    EXPECT_EQ(r.history()[0].end_reason, "capacity");
    EXPECT_NEAR(r.history()[0].capacity_ah, 0.1, 1e-12);
    EXPECT_NEAR(r.history()[0].end_s, 80.0, 1e-9);
}

TEST(NewareRunner, HppcRemovesTenPercentOfThePilotCapacityPerSet) {
    LinearCell cell;
    cell.soc = 0.5;
    ProgramRunner r(thesis_hppc_program(), 0.0, 0.1);
    r.run_until(1e7, cell);
    ASSERT_EQ(r.state(), RunState::finished);
    const auto pilot = records_of(r, 4);
    ASSERT_EQ(pilot.size(), 1u);
    EXPECT_EQ(pilot[0].end_reason, "voltage");
    const double c4 = pilot[0].capacity_ah;
    EXPECT_GT(c4, 3.0);
    const auto pulses = records_of(r, 8), back = records_of(r, 10), soc_steps = records_of(r, 12);
    ASSERT_EQ(pulses.size(), 10u);  // Cycle count 10 = ten pulse sets (as in the real recording)
    ASSERT_EQ(back.size(), 10u);
    ASSERT_EQ(soc_steps.size(), 10u);
    int by_capacity = 0;
    for (std::size_t k = 0; k < 10; ++k) {
        EXPECT_EQ(pulses[k].end_reason, "time");
        EXPECT_NEAR(pulses[k].end_s - pulses[k].start_s, 30.0, 1e-9);
        EXPECT_NEAR(back[k].end_s - back[k].start_s, 10.0, 1e-9);
        EXPECT_EQ(pulses[k].cycle_id, static_cast<int>(k) + 1);
        if (soc_steps[k].end_reason == "capacity") {
            ++by_capacity;
            // eq. 2.4: pulse out - pulse back + C12 = 10 % of the pilot capacity
            EXPECT_NEAR(pulses[k].capacity_ah - back[k].capacity_ah + soc_steps[k].capacity_ah, 0.1 * c4, 1e-9) << k;
        } else {
            EXPECT_EQ(soc_steps[k].end_reason, "voltage");  // the empty end
        }
    }
    EXPECT_GE(by_capacity, 8);
    EXPECT_EQ(records_of(r, 15).size(), 1u);
    EXPECT_EQ(records_of(r, 16).size(), 1u);
}

TEST(NewareRunner, RandomWalkRunsTheBlockSevenTimes) {
    LinearCell cell;
    cell.soc = 0.95;
    ProgramRunner r(thesis_random_walk_program(), 0.0, 0.1);
    r.run_until(1e7, cell);
    ASSERT_EQ(r.state(), RunState::finished);
    EXPECT_EQ(records_of(r, 2).size(), 7u);
    EXPECT_EQ(records_of(r, 13).size(), 7u);
    EXPECT_EQ(records_of(r, 15).size(), 1u);
    EXPECT_EQ(r.cycle_id(), 7);
}

TEST(NewareRunner, PauseFreezesStepTimeAndStopEnds) {
    LinearCell cell;
    Step dis;
    dis.type = StepType::cc_discharge;
    dis.current_a = 4.5;
    dis.time_s = 20.0;
    ProgramRunner r(program({dis, rest(10)}), 0.0, 0.1);
    r.run_until(5.0, cell);
    EXPECT_NEAR(r.step_time_s(), 5.0, 1e-9);
    r.pause();
    EXPECT_EQ(r.state(), RunState::paused);
    EXPECT_EQ(r.run_until(100.0, cell), 0u);  // nothing runs while paused
    cell.t_s = 100.0;                          // the cell rested meanwhile
    r.resume(100.0);
    r.run_until(115.0, cell);
    ASSERT_GE(r.history().size(), 1u);
    EXPECT_NEAR(r.history()[0].end_s, 115.0, 1e-9);  // 5 s before + 15 s after the pause
    EXPECT_NEAR(r.history()[0].capacity_ah, 4.5 * 20 / 3600, 1e-12);
    r.stop();
    EXPECT_EQ(r.state(), RunState::stopped);
    EXPECT_EQ(r.history().back().end_reason, "stopped");
    EXPECT_EQ(r.step_type_code(), "--");
}
