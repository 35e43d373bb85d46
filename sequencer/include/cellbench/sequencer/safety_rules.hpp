#pragma once
// Safety limits as rule objects the run engine evaluates (bluesky's suspenders are the model): each rule sees
// the readings and the clock and names a reason to abort, or nothing. The Sequencer runs every rule on every
// reading and tick of an active run; the first reason aborts the run (current off, chamber to its safe set
// point). default_safety_rules() turns a cell's SafetyLimits into the standard set; a bench adds its own rule
// with SequencerOptions::extra_rules, without touching the sequencer.
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"  // kNaN
#include "cellbench/sequencer/instruments.hpp"

namespace cellbench::sequencer {

struct SafetyLimits {
    double max_temperature_c = 60.0;
    double min_voltage_v = 2.8, max_voltage_v = 4.2;  // the window, with a margin beyond the program's cut-offs
    double max_current_a = 60.0;
    double chamber_deviation_c = 5.0;
    double instrument_loss_grace_s = 10.0;
    // Per instrument (bench s without a reading before the run aborts); <= 0: instrument_loss_grace_s.
    double cycler_loss_grace_s = 0.0, daq_loss_grace_s = 0.0, chamber_loss_grace_s = 0.0;
    double chamber_safe_setpoint_c = 25.0;
};

// What the sequencer knows besides the reading itself (bench seconds; -1 = no reading yet).
struct SafetyContext {
    double run_start_s = 0.0;
    double chamber_target_c = kNaN;  // the program's chamber set point (NaN before one is set)
    double last_cycler_s = -1, last_daq_s = -1, last_chamber_s = -1;
};

using AbortReason = std::optional<std::string>;

class SafetyRule {
public:
    virtual ~SafetyRule() = default;
    [[nodiscard]] virtual const char* name() const = 0;
    virtual void reset() {}  // a run starts: forget what the last one left
    // record = a row the tester recorded itself (on_cycler_record); otherwise a live reading.
    virtual AbortReason on_cycler(const CyclerSample&, bool /*record*/, const SafetyContext&) { return {}; }
    virtual AbortReason on_daq(const DaqSample&, const SafetyContext&) { return {}; }
    virtual AbortReason on_chamber(const ChamberSample&, const SafetyContext&) { return {}; }
    virtual AbortReason on_tick(double /*t_s*/, const SafetyContext&) { return {}; }
};

using SafetyRules = std::vector<std::shared_ptr<SafetyRule>>;

// Voltage window and current limit (every cycler row), the tester's protect state (live readings), any cell
// thermocouple over the maximum, a chamber alarm, chamber air off its set point once it settled, and each
// instrument silent beyond its grace period.
SafetyRules default_safety_rules(const SafetyLimits& limits);

}  // namespace cellbench::sequencer
