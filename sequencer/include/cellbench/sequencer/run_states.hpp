#pragma once
// The run engine's states and the one table of the transitions between them (bluesky's RunEngine keeps the
// same: an explicit state table, every change checked against it). The Sequencer changes state only through
// next_state(); a trigger the table does not list for the current state is refused (an operator's pause of a
// finished run, a second end of an ended run), never half-applied.
//
// Waiting for thermal equilibrium is Running in a wait segment (Sequencer::waiting_for_equilibrium()); the
// daemon's API vocabulary (starting, waiting_equilibrium, interrupted, ...) is built on these in daemon/.
#include <array>
#include <optional>

namespace cellbench::sequencer {

enum class RunState { Idle, Running, Paused, Completed, Aborted, Stopped };
const char* to_string(RunState s);

enum class RunTrigger {
    start,          // operator: a program starts (from Idle or after an ended run)
    pause,          // operator
    resume,         // operator
    program_end,    // the last segment finished
    operator_stop,  // operator, or the daemon shutting down
    abort,          // a safety rule, a fatal fault, an equilibrium timeout with abort_on_timeout
};
const char* to_string(RunTrigger t);

struct RunTransition {
    RunState from;
    RunTrigger on;
    RunState to;
};

// Every allowed transition; anything else is refused.
inline constexpr std::array kRunTransitions{
    RunTransition{RunState::Idle, RunTrigger::start, RunState::Running},
    RunTransition{RunState::Completed, RunTrigger::start, RunState::Running},
    RunTransition{RunState::Stopped, RunTrigger::start, RunState::Running},
    RunTransition{RunState::Aborted, RunTrigger::start, RunState::Running},
    RunTransition{RunState::Running, RunTrigger::pause, RunState::Paused},
    RunTransition{RunState::Paused, RunTrigger::resume, RunState::Running},
    RunTransition{RunState::Running, RunTrigger::program_end, RunState::Completed},
    RunTransition{RunState::Running, RunTrigger::operator_stop, RunState::Stopped},
    RunTransition{RunState::Paused, RunTrigger::operator_stop, RunState::Stopped},
    RunTransition{RunState::Running, RunTrigger::abort, RunState::Aborted},
    RunTransition{RunState::Paused, RunTrigger::abort, RunState::Aborted},
};

constexpr std::optional<RunState> next_state(RunState from, RunTrigger on) {
    for (const auto& t : kRunTransitions)
        if (t.from == from && t.on == on) return t.to;
    return std::nullopt;
}

constexpr bool is_terminal(RunState s) {
    return s == RunState::Completed || s == RunState::Aborted || s == RunState::Stopped;
}
constexpr bool is_active(RunState s) { return s == RunState::Running || s == RunState::Paused; }

}  // namespace cellbench::sequencer
