#pragma once
// Runs one program (config: cycler segments, chamber set points, waits for thermal equilibrium) against the
// instruments' interfaces, supervises the cell on every reading, and fits each HPPC pulse set online: when the
// SOC step and the long rest after it have ended (they give the OCV slope over the pulse set's SOC range), or as
// soon as it is clear that none follow (check_pulse_sets_locked).
//
// Threading: every on_* / tick / command call may come from any thread; they are serialised by one mutex.
// Fits run on a bounded worker pool (SequencerOptions::fit_threads) and report through the sink in the
// order their pulse sets completed.
//
// SOC has one owner, this class: the tester's step capacities (signed by the step's current), anchored at the
// run's first reading by the rested OCV (SequencerOptions::soc_from_ocv; 1.0 without it) and at the end of a
// full CC-CV charge (a CV step that ended below full_charge_current_a) at 1.0. soc() is the live value, every
// recorded row carries it, and each pulse-set fit gets the SOC of its rested start.
//
// States: run_states.hpp (the transition table; every change of state goes through it).
// Safety: rule objects (safety_rules.hpp), evaluated on every reading and on tick (silence): any temperature
// over the cell's maximum, voltage outside the window, current over the limit, chamber air off its set point
// once settled, an instrument silent beyond its grace period, or a bench's own rule -> the current is stopped,
// the chamber goes to its safe set point, the reason is recorded and the run ends `aborted`. A run never
// continues blind.
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/pulse_fit.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "cellbench/sequencer/instruments.hpp"
#include "cellbench/sequencer/run_states.hpp"
#include "cellbench/sequencer/safety_rules.hpp"
#include "cellbench/sequencer/worker_pool.hpp"

namespace cellbench::sequencer {

struct Segment {
    enum class Kind { Cycler, ChamberSetpoint, WaitEquilibrium } kind = Kind::Cycler;
    protocol::StepProgram program;  // Cycler
    double setpoint_c = 0.0;        // ChamberSetpoint
    double tolerance_c = 0.5, hold_s = 600.0, timeout_s = 4 * 3600.0;  // WaitEquilibrium
    std::string name;
    // WaitEquilibrium not reached within timeout_s: abort the run (true), or an alarm event and the program
    // goes on with the next segment (false).
    bool abort_on_timeout = true;
};

struct Program {
    std::string name;
    std::vector<Segment> segments;
};

// Where the sequencer reports (the daemon stores it; tests record it). Called with the sequencer's lock
// held (except on_pulse_fit / on_parameter_set, called from fit workers): keep them short, never call back.
class RunSink {
public:
    virtual ~RunSink() = default;
    virtual void on_state(RunState state, const std::string& reason) = 0;
    virtual void on_step(double t_mono_s, int segment, int step_id, int cycle_id, const std::string& step_type) = 0;
    // The step last reported by on_step has ended (called before the next on_step, and before the run's end
    // state): the tester's capacity and energy of that step (absolute values, from its last recorded row).
    virtual void on_step_end(double /*t_mono_s*/, double /*capacity_ah*/, double /*energy_wh*/) {}
    virtual void on_event(double t_mono_s, const std::string& severity, const std::string& kind,
                          const std::string& message) = 0;
    // fit.soc is the sequencer's SOC at the pulse set's rested start; t_mono_s the first pulse's start.
    virtual void on_pulse_fit(const estimator::PulseSetFit& fit, double t_mono_s) = 0;
    virtual void on_parameter_set(const estimator::ParameterSet& params, const nlohmann::json& summary) = 0;
};

struct SequencerOptions {
    SafetyLimits limits;      // the standard rules (default_safety_rules)
    SafetyRules extra_rules;  // a bench's own rules, evaluated after the standard ones
    double capacity_ah = 4.5;  // SOC = anchor + tester charge since the anchor / capacity_ah
    double area_m2 = 5.311e-3;  // the cell's surface (m^2) the end-of-run fit turns heat flux density into heat flow with
    bool fit_online = true;
    bool fit_at_end = true;
    // SOC of a rested cell from its voltage (the cell's OCV table); empty: the run starts at SOC 1.
    std::function<double(double ocv_v)> soc_from_ocv;
    double full_charge_current_a = 0.1;  // a CV charge step ending at or below this current leaves SOC 1
    std::size_t fit_threads = 2;         // worker threads of the fits (bounded; results delivered in order)
    // The run's recording stays readable (recording()) after the run ends; false: it is handed to the end fit
    // and released when the run ends (a daemon that stores every row keeps no second copy between runs).
    bool keep_recording_after_end = true;
};

class Sequencer {
public:
    Sequencer(Cycler& cycler, Chamber& chamber, RunSink& sink, SequencerOptions options);
    ~Sequencer();

    void start(const Program& program, double t_mono_s);
    void stop(const std::string& reason, double t_mono_s);  // operator stop: current off, chamber safe
    void pause(double t_mono_s);
    void resume(double t_mono_s);

    // The cycler's live reading (a poll): supervision (safety limits, protect, program end). Unless the tester
    // records the period itself (covered_by_records), the live readings are also the run's recording.
    void on_cycler(const CyclerSample& s);
    // A row the tester recorded itself (at its record interval, exact step edges): the run's recording, step
    // tracking and the pulse-set fits use these. All rows of a test arrive before the live reading that
    // reports the test finished.
    void on_cycler_record(const CyclerSample& s);
    void on_daq(const DaqSample& s);
    void on_chamber(const ChamberSample& s);
    // An instrument fault; safety_data_lost = the cell can no longer be watched (no voltage or temperature).
    void on_fault(const std::string& instrument, const std::string& message, bool safety_data_lost, double t_mono_s);
    // Ends an active run `aborted` now (current off, chamber to its safe set point), the reason as an event:
    // an immediately fatal fault the caller has already recorded in detail. No-op when no run is active.
    void abort(const std::string& reason, double t_mono_s);
    void tick(double t_mono_s);  // timeouts: instrument silence, equilibrium wait

    [[nodiscard]] RunState state() const;
    // Running, in a segment that waits for the cell and the chamber to reach equilibrium.
    [[nodiscard]] bool waiting_for_equilibrium() const;
    [[nodiscard]] double soc() const;  // live SOC (NaN before the first cycler row)
    [[nodiscard]] nlohmann::json status() const;  // segment, step, SOC, live values
    [[nodiscard]] Recording recording() const;    // the run so far (cycler time base, thermal values attached)
    void wait_for_fits();                         // every fit started so far computed and delivered
    [[nodiscard]] bool fits_idle() const;         // no fit waiting, computing or undelivered (never blocks)
    [[nodiscard]] bool fits_running() const;      // !fits_idle(), consistent with the run's state (takes its lock)

private:
    // Every safety rule in turn; the first reason aborts the run. True when it aborted.
    template <class Check>
    bool check_rules_locked(Check check, double t);
    [[nodiscard]] SafetyContext safety_context_locked() const;
    // The one place the state changes: the table's next state for this trigger, or false (refused).
    bool fire_locked(RunTrigger trigger);
    void record_locked(const CyclerSample& s);
    void abort_locked(const std::string& reason, double t);
    void finish_locked(RunState end_state, const std::string& reason, double t);
    void advance_locked(double t);
    void start_segment_locked(double t);
    void check_safety_locked(double t);
    // Online pulse-set fits. A complete pulse set waits (pending_fit_) for what follows it: a SOC step and a
    // long rest give the OCV slope over the pulse set's SOC range, so its fit is dispatched when that rest has
    // ended (see resolve_pending_fit_locked); otherwise as soon as that is clear. run_ending: the run ends now,
    // so what is there decides.
    void check_pulse_sets_locked(bool run_ending = false);
    void resolve_pending_fit_locked(bool run_ending);
    void dispatch_fit_locked(const Recording& window, const estimator::PulseSet& ps, double soc, double t_pulse,
                             const estimator::PulseFitOptions& po);
    void update_soc_locked(const CyclerSample& s);
    void end_step_locked(double t);
    [[nodiscard]] double soc_locked() const;
    // Runs compute() on the worker pool; the callable it returns (the delivery to the sink) runs only after
    // every earlier job's delivery, so fits reach the sink in the order the pulse sets completed.
    void spawn(std::function<std::function<void()>()> compute);

    Cycler& cycler_;
    Chamber& chamber_;
    RunSink& sink_;
    SequencerOptions opt_;
    mutable std::mutex mutex_;
    Program program_;
    RunState state_ = RunState::Idle;
    std::size_t segment_ = 0;
    bool cycler_seen_working_ = false;
    int last_step_id_ = -1, last_cycle_id_ = -1;
    double equilibrium_since_s_ = -1, segment_start_s_ = 0, run_start_s_ = 0;
    double last_cycler_s_ = -1, last_daq_s_ = -1, last_chamber_s_ = -1;
    std::optional<CyclerSample> last_cycler_;
    std::optional<DaqSample> last_daq_;
    std::optional<ChamberSample> last_chamber_;
    double chamber_target_c_ = kNaN;
    SafetyRules rules_;  // default_safety_rules(limits) + extra_rules
    Recording rec_;
    double elapsed_s_ = kNaN;  // time of the recording's last row (kept when the recording is released)
    double full_charge_row_ = 0;  // row where SOC = 1 (end of the last CCCV charge before the pulses)
    std::size_t fitted_pulse_sets_ = 0;
    std::map<int, double> step_capacity_ah_;  // |capacity| of each step's latest execution (capacity limits)
    std::size_t window_begin_ = 0;
    // A complete pulse set whose fit waits for the SOC step and the long rest after it.
    struct PendingFit {
        std::size_t begin = 0;          // recording row of the pulse set's window row 0
        estimator::PulseSet ps;         // rows relative to begin
        double soc = kNaN, t_pulse = kNaN;
    };
    std::optional<PendingFit> pending_fit_;
    // The open step's tester totals (on_step_end).
    double step_capacity_now_ah_ = kNaN, step_energy_now_wh_ = kNaN;
    bool step_open_ = false;  // on_step sent, on_step_end not yet
    // SOC (one owner): anchor SOC at tester charge q_anchor_ah_; q of closed steps plus the open one's.
    std::vector<double> rec_soc_;  // SOC of each row of rec_
    double soc_anchor_ = kNaN, q_anchor_ah_ = 0.0, q_closed_ah_ = 0.0, q_step_ah_ = 0.0;
    int soc_step_sign_ = 0;
    std::size_t soc_segment_ = 0;
    int soc_step_id_ = -1, soc_cycle_id_ = -1;
    std::string soc_step_type_;
    double soc_last_current_a_ = 0.0, soc_last_t_ = kNaN;
    // Last: destroyed (joined) first, while everything a delivery uses is still there.
    std::unique_ptr<OrderedWorkerPool> pool_;
};

}  // namespace cellbench::sequencer
