#pragma once
// The simulated Neware tester's step execution: runs a StepProgram against a cell in bench-time ticks,
// with the tester's behaviour (protocol/neware_stepfile.hpp has the step semantics): CC -> CV transition,
// cut-offs on voltage / current / time / capacity, capacity counted per step, loops, capacity limits that
// reference earlier steps (thesis eq. 2.4).
//
// Exactness: the runner only ever executes whole ticks of tick_s bench seconds, never "whatever wall time
// passed", so a run gives the same result at any time scale. A tick is shortened only to land exactly on a
// step's time limit or (in CC) on its capacity limit; voltage and CV-current cut-offs end the step at the
// first tick that crosses them, as a sampling tester does.
//
// No clocks, no I/O: the caller (NewareServer) decides up to which bench time to run.
#include <cstdint>
#include <deque>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "cellbench/protocol/neware_stepfile.hpp"

namespace cellbench::sim {

struct CellMeasurement {
    double current_a = 0.0;  // what the channels measure, + = charge
    double voltage_v = 0.0;
};

// What the runner drives: the cell behind the tester's channel(s).
class RunnerCell {
public:
    virtual ~RunnerCell() = default;
    // Terminal voltage the cell would show at once if the channels were set to this current (no state change).
    virtual double voltage_at(double current_a) = 0;
    // Sets the current, holds it until bench time until_s, and measures at the end.
    virtual CellMeasurement drive(double current_a, double until_s) = 0;
};

enum class RunState { working, paused, stopped, finished };
std::string_view to_string(RunState state);

class ProgramRunner {
public:
    struct StepRecord {
        int step_id = 0;
        int cycle_id = 0;
        double start_s = 0.0, end_s = 0.0;  // bench time
        double capacity_ah = 0.0, energy_wh = 0.0;
        double end_voltage_v = 0.0, end_current_a = 0.0;
        std::string end_reason;  // "time", "voltage", "current", "capacity", "stopped"
    };

    // The program must be valid (validate() is called again; throws InputError).
    ProgramRunner(protocol::StepProgram program, double start_s, double tick_s = 0.1);

    // Executes whole ticks while the next one ends at or before t_s. Returns the number of ticks run.
    std::size_t run_until(double t_s, RunnerCell& cell);

    void pause();                  // no current until resume(); step time stops
    void resume(double now_s);     // continues the paused step from bench time now_s
    void stop();                   // ends the run ("stop")

    [[nodiscard]] RunState state() const { return state_; }
    [[nodiscard]] const protocol::StepProgram& program() const { return program_; }
    [[nodiscard]] int step_id() const { return step_index_ + 1; }
    [[nodiscard]] const protocol::Step& step() const { return program_.steps[static_cast<std::size_t>(step_index_)]; }
    [[nodiscard]] std::string_view step_type_code() const;  // "--" when not working/paused
    [[nodiscard]] int cycle_id() const { return cycle_id_; }
    [[nodiscard]] bool cv_phase() const { return cv_phase_; }
    [[nodiscard]] double now_s() const { return now_s_; }
    [[nodiscard]] double step_time_s() const { return step_time_s_; }
    [[nodiscard]] double total_time_s() const { return total_time_s_; }
    [[nodiscard]] double step_capacity_ah() const { return step_capacity_ah_; }
    [[nodiscard]] double step_energy_wh() const { return step_energy_wh_; }
    [[nodiscard]] CellMeasurement last() const { return last_; }
    [[nodiscard]] double capacity_limit_ah() const { return capacity_limit_ah_; }  // of the current step (inf: none)
    // Increments whenever a step starts (also when a loop re-enters the same step).
    [[nodiscard]] std::uint64_t step_serial() const { return step_serial_; }
    // Completed steps, oldest first (the last 10000).
    [[nodiscard]] const std::deque<StepRecord>& history() const { return history_; }
    // Capacity of a step's latest execution (0 if it has not run).
    [[nodiscard]] double capacity_of_step(int step_id) const;

private:
    void enter_step(int index);               // starts step `index` or follows cycle/end steps from there
    void finish_step(const std::string& reason);
    double cv_current(RunnerCell& cell, double set_current_a, double set_voltage_v);

    protocol::StepProgram program_;
    double tick_s_;
    RunState state_ = RunState::working;
    int step_index_ = 0;
    int cycle_id_ = 1;
    double now_s_ = 0.0, step_start_s_ = 0.0;
    double step_time_s_ = 0.0, total_time_s_ = 0.0;
    double step_capacity_ah_ = 0.0, step_energy_wh_ = 0.0;
    double capacity_limit_ah_ = 0.0;
    bool cv_phase_ = false;
    CellMeasurement last_;
    std::uint64_t step_serial_ = 0;
    std::map<int, double> last_capacity_ah_;   // by step id
    std::map<int, int> loop_passes_;           // by cycle step id
    std::deque<StepRecord> history_;
};

}  // namespace cellbench::sim
