// The sequencer against instrument doubles: a tester that executes the step program on the estimator's cell
// model (the simulated tester's ProgramRunner), a chamber, a DAQ. Checks program flow, online pulse-set fits,
// and that a safety violation stops the current and aborts the run within one sample.
#include <gtest/gtest.h>

#include <cstdio>
#include <utility>

#include <cmath>
#include <fstream>
#include <sstream>

#include "cellbench/estimator/model.hpp"
#include "cellbench/sequencer/sequencer.hpp"
#include "cellbench/sim/neware_runner.hpp"

using namespace cellbench;
using namespace cellbench::sequencer;

namespace {

estimator::ParameterSet cell_params() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    std::stringstream ss;
    ss << in.rdbuf();
    return estimator::ParameterSet::from_json(nlohmann::json::parse(ss.str()));
}

// The cell behind the fake tester starts here (the sequencer's SOC assumes a full cell at the start).
constexpr double kInitialSoc = 0.9;

// The cell behind the fake tester.
struct ModelCell : sim::RunnerCell {
    estimator::CellModel model;
    estimator::CellState state;
    double now_s = 0, ambient_c = 30.0, extra_heat_w = 0;
    explicit ModelCell(estimator::ParameterSet p) : model(std::move(p)) {
        state.soc = kInitialSoc;  // 4.5 A charge pulses stay below the 4.1 V limit
        state.temperature_c = 30.0;
    }
    double voltage_at(double i) override {
        auto copy = state;
        return model.step(copy, i, ambient_c, 0.0).voltage_v;
    }
    sim::CellMeasurement drive(double i, double until_s) override {
        const auto o = model.step(state, i, ambient_c, until_s - now_s);
        state.temperature_c += extra_heat_w * (until_s - now_s) / model.params().thermal.c_th_j_per_k;
        now_s = until_s;
        return {i, o.voltage_v};
    }
};

struct FakeCycler : Cycler {
    std::unique_ptr<sim::ProgramRunner> runner;
    double now_s = 0;
    int stops = 0;
    void start(const protocol::StepProgram& p, const std::string&) override {
        runner = std::make_unique<sim::ProgramRunner>(p, now_s, 0.1);
    }
    void stop() override {
        ++stops;
        if (runner) runner->stop();
    }
    void pause() override { runner->pause(); }
    void resume() override { runner->resume(now_s); }
};

struct FakeChamber : Chamber {
    double setpoint_c = 30.0;
    bool running = true;
    void set_setpoint(double c) override { setpoint_c = c; }
    void set_running(bool r) override { running = r; }
};

struct Recorder : RunSink {
    std::mutex m;
    std::vector<std::pair<RunState, std::string>> states;
    std::vector<estimator::PulseSetFit> fits;
    std::vector<std::string> events;
    int steps = 0;
    bool got_params = false;
    void on_state(RunState s, const std::string& r) override {
        std::lock_guard<std::mutex> l(m);
        states.emplace_back(s, r);
    }
    void on_step(double, int, int, int, const std::string&) override { ++steps; }
    void on_event(double, const std::string& sev, const std::string& kind, const std::string& msg) override {
        std::lock_guard<std::mutex> l(m);
        events.push_back(sev + " " + kind + ": " + msg);
    }
    void on_pulse_fit(const estimator::PulseSetFit& f) override {
        std::lock_guard<std::mutex> l(m);
        fits.push_back(f);
    }
    void on_parameter_set(const estimator::ParameterSet&, const nlohmann::json&) override { got_params = true; }
};

// A short HPPC: full cell, 1 h rest, then 3 pulse sets (Table 2.12 shape).
protocol::StepProgram short_hppc() {
    return protocol::StepProgram::from_json(nlohmann::json::parse(R"({
      "schema": "cellbench.program/1", "name": "hppc_short",
      "steps": [
        {"type": "rest", "time_s": 3600},
        {"type": "cc_discharge", "current_a": 4.5, "time_s": 30, "cutoff_voltage_v": 2.9},
        {"type": "rest", "time_s": 40},
        {"type": "cccv_charge", "current_a": 4.5, "voltage_v": 4.1, "time_s": 10, "cutoff_current_a": 0.05},
        {"type": "rest", "time_s": 40},
        {"type": "cc_discharge", "current_a": 4.5, "cutoff_capacity_ah": 0.38, "cutoff_voltage_v": 2.9},
        {"type": "rest", "time_s": 3600},
        {"type": "cycle", "start_step": 2, "count": 3},
        {"type": "end"}]})"));
}

// Drives the doubles: 0.1 s ticks of bench time, a cycler sample every tick, DAQ and chamber every second.
void run_bench(Sequencer& seq, FakeCycler& cyc, ModelCell& cell, FakeChamber& ch, double until_s,
               const std::function<void(double)>& each_tick = {}) {
    for (double t = 0.1; t <= until_s + 1e-9; t += 0.1) {
        cyc.now_s = t;
        if (cyc.runner) cyc.runner->run_until(t, cell);
        CyclerSample s;
        s.t_mono_s = t;
        const auto m = cyc.runner ? cyc.runner->last() : sim::CellMeasurement{0, cell.voltage_at(0)};
        s.voltage_v = m.voltage_v;
        s.current_a = cyc.runner && cyc.runner->state() == sim::RunState::working ? m.current_a : 0.0;
        s.step_id = cyc.runner ? cyc.runner->step_id() : 0;
        s.cycle_id = cyc.runner ? cyc.runner->cycle_id() : 0;
        s.step_type = cyc.runner ? std::string(cyc.runner->step_type_code()) : "rest";
        s.status = cyc.runner ? std::string(sim::to_string(cyc.runner->state())) : "stop";
        if (s.status == "finished") s.status = "finish";
        if (s.status == "stopped") s.status = "stop";
        seq.on_cycler(s);
        if (std::fmod(t + 1e-9, 1.0) < 0.1) {
            seq.on_daq({t, 0.0, 0.0, cell.state.temperature_c, cell.state.temperature_c, cell.state.temperature_c, 0.0});
            seq.on_chamber({t, 0.0, ch.setpoint_c, ch.setpoint_c, ch.running, 0});
            seq.tick(t);
        }
        if (each_tick) each_tick(t);
        if (seq.state() != RunState::Running) break;
    }
}

// R1, C1, R2, C2 of both directions within 15 % of the simulated cell's values at the pulse set's SOC, and
// nothing a plausibility check would flag: the chosen method's values finite, positive, off their bounds, and
// no joint-fit uncertainty larger than its value.
// soc_offset: the cell's SOC minus the sequencer's (which assumes the run starts full).
void expect_rc_recovered(const estimator::PulseSetFit& f, const estimator::ParameterSet& cell, double soc_offset) {
    for (int dir : {-1, +1}) {
        const auto truth = estimator::to_rc_values(cell.rc_at(f.soc + soc_offset, dir));
        const auto got = estimator::to_rc_values(dir < 0 ? f.chosen_discharge() : f.chosen_charge());
        const char* name = dir < 0 ? "discharge" : "charge";
        std::printf("SOC %.3f %-9s R1 %.3f/%.3f mOhm C1 %.0f/%.0f F R2 %.3f/%.3f mOhm C2 %.0f/%.0f F (%s)\n", f.soc,
                    name, got.r1_ohm * 1e3, truth.r1_ohm * 1e3, got.c1_f, truth.c1_f, got.r2_ohm * 1e3,
                    truth.r2_ohm * 1e3, got.c2_f, truth.c2_f, estimator::to_string(f.chosen));
        EXPECT_NEAR(got.r1_ohm, truth.r1_ohm, 0.15 * truth.r1_ohm) << name << " R1, SOC " << f.soc;
        EXPECT_NEAR(got.c1_f, truth.c1_f, 0.15 * truth.c1_f) << name << " C1, SOC " << f.soc;
        EXPECT_NEAR(got.r2_ohm, truth.r2_ohm, 0.15 * truth.r2_ohm) << name << " R2, SOC " << f.soc;
        EXPECT_NEAR(got.c2_f, truth.c2_f, 0.15 * truth.c2_f) << name << " C2, SOC " << f.soc;
    }
    const bool joint = f.chosen == estimator::PulseSetFit::Method::Joint;
    EXPECT_FALSE(joint ? f.joint_at_bound : f.thesis_at_bound) << "SOC " << f.soc;
    if (joint) {
        for (const auto& [v, sd] : {std::pair{f.joint_discharge, f.joint_discharge_sigma},
                                    std::pair{f.joint_charge, f.joint_charge_sigma}}) {
            for (const auto& [x, sx] : {std::pair{v.r1_ohm, sd.r1_ohm}, std::pair{v.tau1_s, sd.tau1_s},
                                        std::pair{v.r2_ohm, sd.r2_ohm}, std::pair{v.tau2_s, sd.tau2_s}})
                if (std::isfinite(sx)) EXPECT_LT(sx, x) << "uncertainty larger than the value, SOC " << f.soc;
        }
    }
}

}  // namespace

TEST(Sequencer, RunsAShortHppcAndFitsEveryPulseSetOnline) {
    ModelCell cell(cell_params());
    FakeCycler cyc;
    FakeChamber ch;
    Recorder rec;
    SequencerOptions opt;
    opt.capacity_ah = cell.model.params().capacity_ah;
    opt.fit_at_end = false;
    Sequencer seq(cyc, ch, rec, opt);
    Program p{"hppc_short",
              {{Segment::Kind::ChamberSetpoint, {}, 30.0, 0.5, 0, 0, "30 degC"}, {Segment::Kind::Cycler, short_hppc(), 0, 0, 0, 0, "hppc"}}};
    seq.start(p, 0.0);
    run_bench(seq, cyc, cell, ch, 5 * 3600.0);
    seq.wait_for_fits();
    EXPECT_EQ(seq.state(), RunState::Completed) << (rec.events.empty() ? "" : rec.events.back());
    ASSERT_EQ(rec.fits.size(), 3u);
    for (const auto& f : rec.fits) {
        const double truth = cell.model.params().rc_at(f.soc, -1).r0_ohm;
        EXPECT_NEAR(f.chosen_discharge().r0_ohm, truth, 0.03 * truth) << "SOC " << f.soc;
        EXPECT_GT(f.soc, 0.55);
        EXPECT_LE(f.soc, 1.0);
        // Every RC value of both directions within 15 % of the cell's (issue 11, Daemon HIL), none flagged.
        expect_rc_recovered(f, cell.model.params(), kInitialSoc - 1.0);
    }
    EXPECT_GT(rec.fits[0].soc, rec.fits[2].soc);
    EXPECT_GE(rec.steps, 1 + 3 * 6);  // the first rest, then six steps per pulse set
}

TEST(Sequencer, OverTemperatureStopsTheCurrentAtOnceAndAbortsTheRun) {
    ModelCell cell(cell_params());
    FakeCycler cyc;
    FakeChamber ch;
    Recorder rec;
    SequencerOptions opt;
    opt.limits.max_temperature_c = 45.0;
    opt.limits.chamber_safe_setpoint_c = 20.0;
    opt.fit_online = opt.fit_at_end = false;
    Sequencer seq(cyc, ch, rec, opt);
    Program p{"hppc_short", {{Segment::Kind::Cycler, short_hppc(), 0, 0, 0, 0, "hppc"}}};
    seq.start(p, 0.0);
    double violation_at = -1, stopped_at = -1;
    run_bench(seq, cyc, cell, ch, 7200.0, [&](double t) {
        if (t > 3700 && violation_at < 0) {
            cell.state.temperature_c = 46.0;  // injected fault: the cell overheats
            violation_at = t;
        }
        if (cyc.stops > 0 && stopped_at < 0) stopped_at = t;
    });
    EXPECT_EQ(seq.state(), RunState::Aborted);
    ASSERT_GE(stopped_at, 0);
    EXPECT_LE(stopped_at - violation_at, 1.0 + 1e-9);  // the next DAQ sample (1 s period) triggers it
    EXPECT_DOUBLE_EQ(ch.setpoint_c, 20.0);
    ASSERT_FALSE(rec.states.empty());
    EXPECT_EQ(rec.states.back().first, RunState::Aborted);
    EXPECT_NE(rec.states.back().second.find("temperature"), std::string::npos);
}

TEST(Sequencer, SilentInstrumentAbortsAfterItsGracePeriod) {
    ModelCell cell(cell_params());
    FakeCycler cyc;
    FakeChamber ch;
    Recorder rec;
    SequencerOptions opt;
    opt.limits.instrument_loss_grace_s = 5.0;
    opt.fit_online = opt.fit_at_end = false;
    Sequencer seq(cyc, ch, rec, opt);
    seq.start({"hppc_short", {{Segment::Kind::Cycler, short_hppc(), 0, 0, 0, 0, "hppc"}}}, 0.0);
    run_bench(seq, cyc, cell, ch, 100.0);
    // No more DAQ samples: only cycler readings and ticks.
    for (double t = 100.1; t < 120; t += 0.5) seq.tick(t);
    EXPECT_EQ(seq.state(), RunState::Aborted);
    EXPECT_GE(cyc.stops, 1);
}

TEST(Sequencer, OperatorPauseResumeAndStop) {
    ModelCell cell(cell_params());
    FakeCycler cyc;
    FakeChamber ch;
    Recorder rec;
    SequencerOptions opt;
    opt.fit_online = opt.fit_at_end = false;
    Sequencer seq(cyc, ch, rec, opt);
    seq.start({"hppc_short", {{Segment::Kind::Cycler, short_hppc(), 0, 0, 0, 0, "hppc"}}}, 0.0);
    EXPECT_THROW(seq.start({"again", {{Segment::Kind::Cycler, short_hppc(), 0, 0, 0, 0, "x"}}}, 0.0), InputError);
    seq.pause(1.0);
    EXPECT_EQ(seq.state(), RunState::Paused);
    EXPECT_THROW(seq.pause(1.0), InputError);
    seq.resume(2.0);
    EXPECT_EQ(seq.state(), RunState::Running);
    seq.stop("operator", 3.0);
    EXPECT_EQ(seq.state(), RunState::Stopped);
    EXPECT_EQ(cyc.stops, 1);
}
