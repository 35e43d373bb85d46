#include "cellbench/sim/neware_runner.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace cellbench::sim {
namespace {

using protocol::Step;
using protocol::StepType;

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kTimeEps = 1e-9;     // s: float slack when landing on a time limit
constexpr std::size_t kHistoryLimit = 10000;

}  // namespace

std::string_view to_string(RunState state) {
    switch (state) {
        case RunState::working: return "working";
        case RunState::paused: return "paused";
        case RunState::stopped: return "stopped";
        case RunState::finished: return "finished";
    }
    return "unknown";
}

ProgramRunner::ProgramRunner(protocol::StepProgram program, double start_s, double tick_s)
    : program_(std::move(program)), tick_s_(tick_s > 0 && std::isfinite(tick_s) ? tick_s : 0.1), now_s_(start_s) {
    program_.validate();
    enter_step(program_.first_step - 1);  // Head_Info Start_Step
}

std::string_view ProgramRunner::step_type_code() const {
    if (state_ != RunState::working && state_ != RunState::paused) return "--";
    // In the CV phase of a CCCV step the tester reports the CV sub-step (field data shows "cv").
    if (cv_phase_) return "cv";
    return protocol::step_type_code(step().type);
}

double ProgramRunner::capacity_of_step(int step_id) const {
    const auto it = last_capacity_ah_.find(step_id);
    return it == last_capacity_ah_.end() ? 0.0 : it->second;
}

void ProgramRunner::enter_step(int index) {
    // Follow cycle and end steps (they take no time) to the next step that runs.
    int guard = 0;
    while (true) {
        if (index < 0 || index >= static_cast<int>(program_.steps.size())) {  // cannot happen for a valid program
            state_ = RunState::finished;
            return;
        }
        const Step& s = program_.steps[static_cast<std::size_t>(index)];
        if (s.type == StepType::end) {
            step_index_ = index;
            state_ = RunState::finished;
            cv_phase_ = false;
            return;
        }
        if (s.type == StepType::cycle) {
            const int id = index + 1;
            int& passes = loop_passes_[id];
            ++passes;
            if (passes < s.count) {
                ++cycle_id_;
                index = s.start_step - 1;
            } else {
                passes = 0;  // so an enclosing loop runs this one again in full
                ++index;
            }
            if (++guard > 1'000'000) throw std::logic_error("step program loops without running a step");
            continue;
        }
        step_index_ = index;
        step_start_s_ = now_s_;
        step_time_s_ = 0.0;
        step_capacity_ah_ = 0.0;
        step_energy_wh_ = 0.0;
        cv_phase_ = false;
        ++step_serial_;
        capacity_limit_ah_ = s.cutoff_capacity_ah
                                 ? s.cutoff_capacity_ah->evaluate([this](int sid) { return capacity_of_step(sid); })
                                 : kInf;
        return;
    }
}

void ProgramRunner::finish_step(const std::string& reason) {
    const int id = step_id();
    last_capacity_ah_[id] = step_capacity_ah_;
    history_.push_back({id, cycle_id_, step_start_s_, now_s_, step_capacity_ah_, step_energy_wh_, last_.voltage_v,
                        last_.current_a, reason});
    if (history_.size() > kHistoryLimit) history_.pop_front();
}

double ProgramRunner::cv_current(RunnerCell& cell, double set_current_a, double set_voltage_v) {
    // The current (between 0 and the set current, in the step's direction) at which the terminal voltage
    // equals the CV set value now. The cell's voltage is linear in the current within one direction, so a
    // secant from the two ends is exact; one refinement guards against a cell that is not.
    const double v0 = cell.voltage_at(0.0);
    const double v1 = cell.voltage_at(set_current_a);
    const double lo = std::min(0.0, set_current_a), hi = std::max(0.0, set_current_a);
    if (std::fabs(v1 - v0) < 1e-12) return set_current_a;
    double i = set_current_a * (set_voltage_v - v0) / (v1 - v0);
    i = std::clamp(i, lo, hi);
    const double vi = cell.voltage_at(i);
    if (std::fabs(vi - set_voltage_v) > 1e-6 && std::fabs(i) > 1e-12) {
        const double slope = (vi - v0) / i;
        if (std::fabs(slope) > 1e-12) i = std::clamp(i + (set_voltage_v - vi) / slope, lo, hi);
    }
    return i;
}

void ProgramRunner::pause() {
    if (state_ == RunState::working) state_ = RunState::paused;
}

void ProgramRunner::resume(double now_s) {
    if (state_ != RunState::paused) return;
    // Step and total time stand still during a pause; the step continues from bench time now_s.
    now_s_ = std::max(now_s_, now_s);
    state_ = RunState::working;
}

void ProgramRunner::stop() {
    if (state_ == RunState::working || state_ == RunState::paused) {
        finish_step("stopped");
        state_ = RunState::stopped;
        cv_phase_ = false;
    }
}

std::size_t ProgramRunner::run_until(double t_s, RunnerCell& cell) {
    std::size_t ticks = 0;
    while (state_ == RunState::working) {
        const Step& s = step();
        const int dir = protocol::step_direction(s.type);
        const double set_current = s.current_a ? dir * *s.current_a : 0.0;

        // Immediate end conditions (a time limit already reached, a capacity limit <= what the step holds).
        if (s.time_s && step_time_s_ >= *s.time_s - kTimeEps) {
            finish_step("time");
            enter_step(step_index_ + 1);
            continue;
        }
        if (step_capacity_ah_ >= capacity_limit_ah_) {
            finish_step("capacity");
            enter_step(step_index_ + 1);
            continue;
        }

        // The current of this tick.
        double current = 0.0;
        if (s.type == StepType::cc_charge || s.type == StepType::cc_discharge) {
            current = set_current;
        } else if (protocol::step_has_cv_phase(s.type)) {
            const double v_set = *s.voltage_v;
            if (!cv_phase_) {
                const double v_cc = cell.voltage_at(set_current);
                if (dir > 0 ? v_cc >= v_set : v_cc <= v_set) cv_phase_ = true;
            }
            current = cv_phase_ ? cv_current(cell, set_current, v_set) : set_current;
        }

        // Tick length: whole ticks, shortened only to land on the time limit or (CC) the capacity limit.
        double dt = tick_s_;
        bool lands_on_time = false, lands_on_capacity = false;
        if (s.time_s && *s.time_s - step_time_s_ <= dt + kTimeEps) {
            dt = *s.time_s - step_time_s_;
            lands_on_time = true;
        }
        if (std::isfinite(capacity_limit_ah_) && std::fabs(current) > 1e-9 && !cv_phase_) {
            const double dt_cap = (capacity_limit_ah_ - step_capacity_ah_) * 3600.0 / std::fabs(current);
            if (dt_cap <= dt + kTimeEps) {
                dt = dt_cap;
                lands_on_capacity = true;
                lands_on_time = lands_on_time && std::fabs(dt_cap - (*s.time_s - step_time_s_)) <= kTimeEps;
            }
        }
        if (now_s_ + dt > t_s + kTimeEps) break;  // the next tick is not due yet

        const CellMeasurement m = cell.drive(current, now_s_ + dt);
        ++ticks;
        now_s_ += dt;
        step_time_s_ += dt;
        total_time_s_ += dt;
        last_ = m;
        if (s.type != StepType::rest) {
            step_capacity_ah_ += std::fabs(m.current_a) * dt / 3600.0;
            step_energy_wh_ += std::fabs(m.current_a * m.voltage_v) * dt / 3600.0;
        }

        // End conditions after the tick.
        std::string reason;
        if (lands_on_time || (s.time_s && step_time_s_ >= *s.time_s - kTimeEps)) reason = "time";
        if (reason.empty() && (lands_on_capacity || step_capacity_ah_ >= capacity_limit_ah_)) reason = "capacity";
        if (reason.empty() && s.cutoff_voltage_v &&
            (dir > 0 ? m.voltage_v >= *s.cutoff_voltage_v : m.voltage_v <= *s.cutoff_voltage_v))
            reason = "voltage";
        if (reason.empty() && protocol::step_has_cv_phase(s.type)) {
            if (cv_phase_ && s.cutoff_current_a && std::fabs(m.current_a) <= *s.cutoff_current_a) reason = "current";
            // The measured voltage reached the set value during a CC tick: CV from the next tick on.
            if (!cv_phase_ && (dir > 0 ? m.voltage_v >= *s.voltage_v : m.voltage_v <= *s.voltage_v)) cv_phase_ = true;
        }
        if (!reason.empty()) {
            finish_step(reason);
            enter_step(step_index_ + 1);
        }
    }
    return ticks;
}

}  // namespace cellbench::sim
