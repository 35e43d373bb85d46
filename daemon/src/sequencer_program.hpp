#pragma once
// The one conversion of a program as config reads it into the program the sequencer runs (the daemon's runs
// and `cellbench fit --db` replays both start their sequencer with it).
#include <variant>

#include "cellbench/daemon/config.hpp"
#include "cellbench/sequencer/sequencer.hpp"

namespace cellbench::daemon {

inline sequencer::Program to_sequencer_program(const Program& p) {
    sequencer::Program out;
    out.name = p.name;
    for (const auto& seg : p.segments) {
        sequencer::Segment s;
        if (const auto* c = std::get_if<CyclerSegment>(&seg)) {
            s.kind = sequencer::Segment::Kind::Cycler;
            s.program = c->program;
            s.name = c->program.name;
        } else if (const auto* sp = std::get_if<ChamberSetpointSegment>(&seg)) {
            s.kind = sequencer::Segment::Kind::ChamberSetpoint;
            s.setpoint_c = sp->setpoint_c;
            s.name = "chamber set point";
        } else if (const auto* w = std::get_if<WaitEquilibriumSegment>(&seg)) {
            s.kind = sequencer::Segment::Kind::WaitEquilibrium;
            s.tolerance_c = w->tolerance_c;
            s.hold_s = w->hold_s;
            s.timeout_s = w->timeout_s;
            s.abort_on_timeout = w->abort_on_timeout;
            s.name = "wait for thermal equilibrium";
        }
        out.segments.push_back(std::move(s));
    }
    return out;
}

}  // namespace cellbench::daemon
