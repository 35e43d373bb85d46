#pragma once
// What the sequencer needs from the bench, as interfaces: the daemon adapts concrete drivers (or anything
// else, e.g. test doubles) to them. Readings flow the other way, into Sequencer::on_* (sequencer.hpp).
#include <cstdint>
#include <string>

#include "cellbench/protocol/neware_stepfile.hpp"

namespace cellbench::sequencer {

// One reading of the (possibly parallel-grouped) cycler channel. Times on the daemon's monotonic clock.
struct CyclerSample {
    double t_mono_s = 0.0, t_wall_s = 0.0;
    double voltage_v = 0.0, current_a = 0.0;  // + = charge
    double capacity_ah = 0.0, energy_wh = 0.0;  // of the running step
    int step_id = 0, cycle_id = 0;
    std::string step_type;  // as the tester reports it (rest, cc, dc, cv, ...)
    std::string status;     // working, stop, finish, protect, pause
    // A live reading of a period the tester records itself (its rows arrive through on_cycler_record): for
    // supervision only, not part of the recording.
    bool covered_by_records = false;
};

struct DaqSample {
    double t_mono_s = 0.0, t_wall_s = 0.0;
    double thermopile_v = 0.0;
    double surface_c = 0.0;           // Type-T inside the heat flux sensor
    double t1_c = 0.0, t2_c = 0.0;    // Type-K at the terminals
    double heat_flux_w_per_m2 = 0.0;  // Type-T corrected (protocol/heat_flux.hpp)
};

struct ChamberSample {
    double t_mono_s = 0.0, t_wall_s = 0.0;
    double air_c = 0.0, setpoint_c = 0.0;
    bool running = false;
    std::uint32_t alarm_bits = 0;
};

class Cycler {
public:
    virtual ~Cycler() = default;
    // Compiles and starts the program on the tester (the tester switches steps itself).
    virtual void start(const protocol::StepProgram& program, const std::string& barcode) = 0;
    virtual void stop() = 0;
    virtual void pause() = 0;
    virtual void resume() = 0;
};

class Chamber {
public:
    virtual ~Chamber() = default;
    virtual void set_setpoint(double setpoint_c) = 0;
    virtual void set_running(bool running) = 0;
};

}  // namespace cellbench::sequencer
