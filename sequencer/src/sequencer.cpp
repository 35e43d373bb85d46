#include "cellbench/sequencer/sequencer.hpp"

#include <algorithm>
#include <cmath>
#include <utility>

#include "cellbench/estimator/voltage_spikes.hpp"
#include "cellbench/estimator/segment.hpp"

namespace cellbench::sequencer {

const char* to_string(RunState s) {
    switch (s) {
        case RunState::Idle: return "idle";
        case RunState::Running: return "running";
        case RunState::Paused: return "paused";
        case RunState::Completed: return "completed";
        case RunState::Aborted: return "aborted";
        case RunState::Stopped: return "stopped";
    }
    return "?";
}

const char* to_string(RunTrigger t) {
    switch (t) {
        case RunTrigger::start: return "start";
        case RunTrigger::pause: return "pause";
        case RunTrigger::resume: return "resume";
        case RunTrigger::program_end: return "program end";
        case RunTrigger::operator_stop: return "stop";
        case RunTrigger::abort: return "abort";
    }
    return "?";
}

namespace {
bool active(RunState s) { return is_active(s); }
RunTrigger trigger_of_end(RunState end) {
    return end == RunState::Completed ? RunTrigger::program_end
           : end == RunState::Stopped ? RunTrigger::operator_stop
                                      : RunTrigger::abort;
}
std::string fmt(const char* f, double x) {
    char b[96];
    std::snprintf(b, sizeof b, f, x);
    return b;
}
}  // namespace

Sequencer::Sequencer(Cycler& cycler, Chamber& chamber, RunSink& sink, SequencerOptions options)
    : cycler_(cycler), chamber_(chamber), sink_(sink), opt_(std::move(options)),
      rules_(default_safety_rules(opt_.limits)), pool_(std::make_unique<OrderedWorkerPool>(opt_.fit_threads)) {
    for (auto& r : opt_.extra_rules)
        if (r) rules_.push_back(r);
}

bool Sequencer::fire_locked(RunTrigger trigger) {
    const auto next = next_state(state_, trigger);
    if (!next) return false;
    state_ = *next;
    return true;
}

SafetyContext Sequencer::safety_context_locked() const {
    return SafetyContext{run_start_s_, chamber_target_c_, last_cycler_s_, last_daq_s_, last_chamber_s_};
}

template <class Check>
bool Sequencer::check_rules_locked(Check check, double t) {
    const SafetyContext ctx = safety_context_locked();
    for (const auto& rule : rules_) {
        if (AbortReason why = check(*rule, ctx)) {
            abort_locked(*why, t);
            return true;
        }
    }
    return false;
}

Sequencer::~Sequencer() { wait_for_fits(); }

void Sequencer::spawn(std::function<std::function<void()>()> compute) { pool_->submit(std::move(compute)); }

void Sequencer::wait_for_fits() { pool_->wait_idle(); }

bool Sequencer::fits_idle() const { return pool_->idle(); }

bool Sequencer::fits_running() const {
    // Under the run's lock: the end of a run reports its state and submits its end fit in one step, so nobody
    // sees the run over with no fit pending before the end fit is under way.
    std::lock_guard<std::mutex> lock(mutex_);
    return !pool_->idle();
}

void Sequencer::start(const Program& program, double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (active(state_)) throw InputError("a run is already active");
    if (program.segments.empty()) throw InputError("program " + program.name + " has no segments");
    // A cycler program whose capacity limit needs a measured step (thesis eq. 2.4: C4) runs as two step files,
    // the second resolved from the first's rows when it starts (protocol::tester_parts; the real step-file
    // format has constant limits only).
    program_ = Program{program.name, {}};
    for (const Segment& s : program.segments) {
        if (s.kind != Segment::Kind::Cycler) {
            program_.segments.push_back(s);
            continue;
        }
        for (auto& part : protocol::tester_parts(s.program)) {
            Segment piece = s;
            piece.program = std::move(part);
            program_.segments.push_back(std::move(piece));
        }
    }
    if (!fire_locked(RunTrigger::start)) throw InputError(std::string("cannot start a run while one is ") + to_string(state_));
    for (auto& r : rules_) r->reset();
    segment_ = 0;
    rec_ = Recording{};
    elapsed_s_ = kNaN;
    rec_.source = program.name;
    rec_.surface_c.clear();
    fitted_pulse_sets_ = 0;
    window_begin_ = 0;
    pending_fit_.reset();
    full_charge_row_ = 0;
    rec_soc_.clear();
    soc_anchor_ = kNaN;
    q_anchor_ah_ = q_closed_ah_ = q_step_ah_ = 0.0;
    soc_step_sign_ = 0;
    soc_step_id_ = soc_cycle_id_ = -1;
    soc_step_type_.clear();
    soc_last_t_ = kNaN;
    step_capacity_now_ah_ = step_energy_now_wh_ = kNaN;
    step_open_ = false;
    run_start_s_ = t;
    last_cycler_s_ = last_daq_s_ = last_chamber_s_ = -1;
    last_step_id_ = last_cycle_id_ = -1;
    chamber_target_c_ = kNaN;
    sink_.on_state(RunState::Running, "started program " + program.name);
    start_segment_locked(t);
}

void Sequencer::start_segment_locked(double t) {
    while (state_ == RunState::Running) {
        if (segment_ >= program_.segments.size()) {
            finish_locked(RunState::Completed, "program finished", t);
            return;
        }
        const Segment& s = program_.segments[segment_];
        segment_start_s_ = t;
        if (s.kind == Segment::Kind::ChamberSetpoint) {
            chamber_.set_running(true);
            chamber_.set_setpoint(s.setpoint_c);
            chamber_target_c_ = s.setpoint_c;
            sink_.on_event(t, "info", "chamber", "chamber set point " + fmt("%.1f degC", s.setpoint_c));
            ++segment_;
            continue;
        }
        if (s.kind == Segment::Kind::WaitEquilibrium) {
            equilibrium_since_s_ = -1;
            sink_.on_event(t, "info", "equilibrium",
                           "waiting for cell and chamber within " + fmt("%.2f K", s.tolerance_c) + " for " +
                               fmt("%.0f s", s.hold_s));
            return;
        }
        cycler_seen_working_ = false;
        last_step_id_ = -1;
        if (s.program.first_step == 1) step_capacity_ah_.clear();
        protocol::StepProgram resolved;
        try {
            resolved = protocol::resolve_capacity_limits(s.program, [this](int id) -> std::optional<double> {
                const auto it = step_capacity_ah_.find(id);
                return it == step_capacity_ah_.end() ? std::nullopt : std::optional<double>(it->second);
            });
        } catch (const std::exception& e) {
            abort_locked(std::string("cannot write the step file: ") + e.what(), t);
            return;
        }
        for (const auto& [id, ah] : step_capacity_ah_)
            if (s.program.first_step > 1 && id < s.program.first_step)
                sink_.on_event(t, "info", "cycler", "measured C" + std::to_string(id) + " = " + fmt("%.4f Ah", ah) +
                                                        " for the capacity limits from step " +
                                                        std::to_string(s.program.first_step));
        cycler_.start(resolved, program_.name + "-" + std::to_string(segment_));
        sink_.on_event(t, "info", "cycler", "started step program " + s.program.name);
        return;
    }
}

void Sequencer::advance_locked(double t) {
    ++segment_;
    start_segment_locked(t);
}

void Sequencer::finish_locked(RunState end_state, const std::string& reason, double t) {
    if (!fire_locked(trigger_of_end(end_state))) return;
    end_step_locked(t);
    // A pulse set whose fit waited for what follows it is fitted with what there is.
    if (opt_.fit_online) resolve_pending_fit_locked(true);
    sink_.on_state(end_state, reason);
    const bool fit_now = end_state == RunState::Completed && opt_.fit_at_end && rec_.size() > 10;
    // Without keep_recording_after_end the recording goes to the end fit (or is dropped): the store holds every
    // row, and the pulse-set fits own copies of their windows.
    Recording rec;
    if (!opt_.keep_recording_after_end) {
        rec = std::exchange(rec_, Recording{});
        std::vector<double>().swap(rec_soc_);
    } else if (fit_now) {
        rec = rec_;
    }
    if (fit_now) {
        spawn([this, rec = std::move(rec), t]() -> std::function<void()> {
            try {
                // A run that does not discharge the cell from full to its cut-off does not measure the capacity:
                // the fit then takes the run's (the cell's characterised or nominal capacity).
                estimator::CharacterizationOptions co;
                co.fallback_capacity_ah = opt_.capacity_ah;
                co.fallback_capacity_source = "the run's cell capacity";
                co.area_m2 = opt_.area_m2;  // the cell's surface: heat flux density -> heat flow (C_th, R_th)
                auto c = std::make_shared<estimator::Characterization>(estimator::characterize({rec}, co));
                return [this, c] { sink_.on_parameter_set(c->params, c->summary_json()); };
            } catch (const std::exception& e) {
                return [this, t, what = std::string(e.what())] {
                    sink_.on_event(t, "warning", "fit", "no parameter set for this run: " + what);
                };
            }
        });
    }
}

void Sequencer::abort_locked(const std::string& reason, double t) {
    if (!active(state_)) return;
    cycler_.stop();
    chamber_.set_setpoint(opt_.limits.chamber_safe_setpoint_c);
    // The stop is sent, not yet confirmed: the tester acknowledges it in a "cycler" event ("current off"), or,
    // unreachable, keeps running its step file until the stop gets through (see the daemon's cycler_stop).
    sink_.on_event(t, "alarm", "abort", reason + "; stop sent to the cycler, chamber to its safe set point " +
                                             fmt("%.1f degC", opt_.limits.chamber_safe_setpoint_c));
    finish_locked(RunState::Aborted, reason, t);
}

void Sequencer::stop(const std::string& reason, double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!active(state_)) return;
    cycler_.stop();
    chamber_.set_setpoint(opt_.limits.chamber_safe_setpoint_c);
    sink_.on_event(t, "info", "operator", "stop: " + reason);
    finish_locked(RunState::Stopped, reason, t);
}

void Sequencer::pause(double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!next_state(state_, RunTrigger::pause))
        throw InputError(std::string("cannot pause a run that is ") + to_string(state_));
    cycler_.pause();
    fire_locked(RunTrigger::pause);
    sink_.on_event(t, "info", "operator", "pause");
    sink_.on_state(state_, "paused by the operator");
}

void Sequencer::resume(double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!next_state(state_, RunTrigger::resume))
        throw InputError(std::string("cannot resume a run that is ") + to_string(state_));
    cycler_.resume();
    fire_locked(RunTrigger::resume);
    sink_.on_event(t, "info", "operator", "resume");
    sink_.on_state(state_, "resumed by the operator");
}

void Sequencer::record_locked(const CyclerSample& s) {
    // The run's recording, on the cycler's time base with the latest thermal values.
    const double t_rel = s.t_mono_s - run_start_s_;
    update_soc_locked(s);
    if (rec_.time_s.empty() || t_rel > rec_.time_s.back()) {
        rec_soc_.push_back(soc_locked());
        rec_.time_s.push_back(t_rel);
        elapsed_s_ = t_rel;
        rec_.voltage_v.push_back(s.voltage_v);
        rec_.current_a.push_back(s.current_a);
        rec_.step_count.push_back(1000.0 * static_cast<double>(segment_) + s.step_id);
        rec_.step_type.push_back(s.step_type);
        const bool fresh = last_daq_ && std::abs(s.t_mono_s - last_daq_s_) < 5.0;
        rec_.surface_c.push_back(fresh ? last_daq_->surface_c : kNaN);
        rec_.heat_flux_w_per_m2.push_back(fresh ? last_daq_->heat_flux_w_per_m2 : kNaN);
        rec_.ambient_c.push_back(last_chamber_ ? last_chamber_->air_c : kNaN);
    }
    if (program_.segments[std::min(segment_, program_.segments.size() - 1)].kind != Segment::Kind::Cycler) return;
    // Step capacities of the latest execution (what a capacity limit refers to).
    if (s.step_id > 0 && std::isfinite(s.capacity_ah)) step_capacity_ah_[s.step_id] = std::abs(s.capacity_ah);
    // Step 0 is the idle tester (a live reading before its first row or after its test): no step of the program.
    if (s.step_id > 0 && (s.step_id != last_step_id_ || s.cycle_id != last_cycle_id_)) {
        end_step_locked(s.t_mono_s);
        step_capacity_now_ah_ = step_energy_now_wh_ = kNaN;
        sink_.on_step(s.t_mono_s, static_cast<int>(segment_), s.step_id, s.cycle_id, s.step_type);
        step_open_ = true;
        last_step_id_ = s.step_id;
        last_cycle_id_ = s.cycle_id;
        if (opt_.fit_online) check_pulse_sets_locked();
    }
    // The open step's totals: the tester's own counts of this step (its last row's).
    if (step_open_ && s.step_id == last_step_id_ && s.cycle_id == last_cycle_id_) {
        if (std::isfinite(s.capacity_ah)) step_capacity_now_ah_ = std::abs(s.capacity_ah);
        if (std::isfinite(s.energy_wh)) step_energy_now_wh_ = std::abs(s.energy_wh);
    }
}

void Sequencer::on_cycler_record(const CyclerSample& s) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!active(state_)) return;
    if (check_rules_locked([&](SafetyRule& r, const SafetyContext& c) { return r.on_cycler(s, true, c); }, s.t_mono_s))
        return;
    record_locked(s);
}

void Sequencer::on_cycler(const CyclerSample& s) {
    std::lock_guard<std::mutex> lock(mutex_);
    last_cycler_ = s;
    last_cycler_s_ = s.t_mono_s;
    if (!active(state_)) return;
    if (check_rules_locked([&](SafetyRule& r, const SafetyContext& c) { return r.on_cycler(s, false, c); }, s.t_mono_s))
        return;
    if (!s.covered_by_records) record_locked(s);
    if (program_.segments[std::min(segment_, program_.segments.size() - 1)].kind != Segment::Kind::Cycler) return;
    if (s.status == "working") cycler_seen_working_ = true;
    if (cycler_seen_working_ && state_ == RunState::Running && (s.status == "finish" || s.status == "stop")) {
        if (opt_.fit_online) check_pulse_sets_locked();
        end_step_locked(s.t_mono_s);  // the program's last step: its totals before the next segment
        sink_.on_event(s.t_mono_s, "info", "cycler", "step program finished (" + s.status + ")");
        advance_locked(s.t_mono_s);
    }
}

// SOC, one owner (see the header): the tester's charge of each step (its capacity, signed by the step's
// current; counted from the current when the tester gives no capacity), anchored at the first row (rested
// OCV) and at the end of a full CC-CV charge.
void Sequencer::update_soc_locked(const CyclerSample& s) {
    if (!std::isfinite(soc_anchor_)) {
        soc_anchor_ = 1.0;
        if (opt_.soc_from_ocv && std::abs(s.current_a) < 0.02 && std::isfinite(s.voltage_v)) {
            const double v = opt_.soc_from_ocv(s.voltage_v);
            if (std::isfinite(v)) soc_anchor_ = std::clamp(v, 0.0, 1.0);
        }
        q_anchor_ah_ = q_closed_ah_ = q_step_ah_ = 0.0;
    }
    if (segment_ != soc_segment_ || s.step_id != soc_step_id_ || s.cycle_id != soc_cycle_id_) {
        // The previous step closes: its charge joins the closed steps; a full charge re-anchors SOC at 1.
        q_closed_ah_ += q_step_ah_;
        if (soc_step_sign_ > 0 && soc_step_type_ == "cv" && soc_last_current_a_ <= opt_.full_charge_current_a &&
            q_step_ah_ > 0.0) {
            soc_anchor_ = 1.0;
            q_anchor_ah_ = q_closed_ah_;
        }
        q_step_ah_ = 0.0;
        soc_step_sign_ = 0;
        soc_segment_ = segment_;
        soc_step_id_ = s.step_id;
        soc_cycle_id_ = s.cycle_id;
    }
    if (s.current_a > 0.01) soc_step_sign_ = 1;
    else if (s.current_a < -0.01) soc_step_sign_ = -1;
    if (std::isfinite(s.capacity_ah) && s.step_id > 0) {
        q_step_ah_ = soc_step_sign_ * std::abs(s.capacity_ah);
    } else if (std::isfinite(soc_last_t_) && s.t_mono_s > soc_last_t_ && std::isfinite(s.current_a)) {
        q_step_ah_ += s.current_a * (s.t_mono_s - soc_last_t_) / 3600.0;
    }
    soc_step_type_ = s.step_type;
    soc_last_current_a_ = s.current_a;
    soc_last_t_ = s.t_mono_s;
}

// The step last reported by on_step ended: its tester totals, once.
void Sequencer::end_step_locked(double t) {
    if (!step_open_) return;
    step_open_ = false;
    sink_.on_step_end(t, step_capacity_now_ah_, step_energy_now_wh_);
}

double Sequencer::soc_locked() const {
    if (!std::isfinite(soc_anchor_)) return kNaN;
    return std::clamp(soc_anchor_ + (q_closed_ah_ + q_step_ah_ - q_anchor_ah_) / opt_.capacity_ah, 0.0, 1.0);
}

double Sequencer::soc() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return soc_locked();
}

void Sequencer::check_pulse_sets_locked(bool run_ending) {
    resolve_pending_fit_locked(run_ending);
    if (rec_.size() < 100) return;
    const Recording window = rec_.slice(window_begin_, rec_.size());
    const auto ps = estimator::last_complete_pulse_set(window);
    if (!ps) return;
    // One pending fit at a time: an earlier one still undecided is fitted now with what there is.
    if (pending_fit_) resolve_pending_fit_locked(true);
    const std::size_t begin = window_begin_;
    window_begin_ += ps->next_window_begin;  // after this pulse set (at its last rest when that is the next one's)
    ++fitted_pulse_sets_;
    // The SOC of the pulse set's rested start (the row before its first pulse; the SOC owner's value of that
    // row) and the start of its first pulse.
    const std::size_t rest_row = begin + ps->pulse_begin > 0 ? begin + ps->pulse_begin - 1 : 0;
    const double soc = rest_row < rec_soc_.size() ? rec_soc_[rest_row] : soc_locked();
    const std::size_t pulse_row = std::min(begin + ps->pulse_begin, rec_.size() - 1);
    const double t_pulse = run_start_s_ + rec_.time_s[pulse_row];
    pending_fit_ = PendingFit{begin, *ps, soc, t_pulse};
    resolve_pending_fit_locked(run_ending);
}

// The OCV slope a pulse set needs is the one over the SOC range it covers: from its rested start down by the
// discharge pulse's charge. A chord from the previous pulse set's rest (above this SOC) is wrong wherever the
// slope changes at this SOC (on the simulated cell, whose OCV table has its knots at the pulse sets' SOCs: the
// discharge R1 x1.4 and R2 +14 % at 90 %, R1 x1.5 at 20 %). The SOC step that follows the pulse set goes down
// through that range, and the long rest after it gives its OCV: the chord from the pulse set's rest to the end
// of that long rest. So the fit waits for that rest to end (what follows a pulse set is known only then); when
// no SOC step and long rest follow (or the run ends first), the fit estimates the slope from the pulse set
// itself (PulseFitOptions::estimate_unknown_ocv_slope).
void Sequencer::resolve_pending_fit_locked(bool run_ending) {
    if (!pending_fit_) return;
    const PendingFit p = *pending_fit_;
    const std::size_t after = p.begin + p.ps.end;  // first row after the charge relaxation
    // R0 of each direction is fitted with the pairs over every row, not held at its eq. 3.2 steps: a step
    // is the difference of two rows, so the tester's voltage noise goes into the held R0 (0.2 mV -> +-1 % of
    // R0, the size of R1's share of the first sample) and from there into the fast pair (C1 off by up to 22 %
    // on the noisy simulated tester); and after a charge pulse that turned CV the step at its end is taken at
    // the tapered current (at 100 % SOC: the charge C1 -78 %).
    estimator::PulseFitOptions po;
    po.r0_from_steps = false;
    const Recording window = rec_.slice(p.begin, std::min(after, rec_.size()));
    auto fit_now = [&] {
        pending_fit_.reset();
        dispatch_fit_locked(window, p.ps, p.soc, p.t_pulse, po);
    };
    // What followed the pulse set: a discharge (the SOC step), then a long rest, both ended?
    const auto phases = after < rec_.size() ? estimator::split_phases(rec_.slice(after, rec_.size()))
                                            : std::vector<estimator::Phase>{};
    const bool step_ended = !phases.empty() && !phases[0].open_end;
    if (!step_ended) {
        if (run_ending) fit_now();
        return;
    }
    if (phases[0].kind != estimator::PhaseKind::Discharge || phases.size() < 2 || !phases[1].is_rest())
        return fit_now();
    const estimator::Phase& rest = phases[1];
    if (rest.open_end && !run_ending) return;  // the rest goes on: its last row is the OCV
    if (rest.kind != estimator::PhaseKind::LongRest) return fit_now();
    // The rest's last row is its OCV. A rest the run ended in has no last row of its own: how many of its rows
    // a live daemon holds at the end depends on when the tester's last rows arrived, so the OCV is read where the
    // rest became long (the first row past the long-rest duration), which every replay of the run also has.
    std::size_t rest_last = after + rest.end - 1;
    if (rest.open_end) {
        const double long_rest_s = 0.99 * estimator::SegmentOptions{}.long_rest_s;
        const double t0 = rec_.time_s[after + rest.begin > 0 ? after + rest.begin - 1 : 0];
        for (std::size_t k = after + rest.begin; k <= rest_last; ++k)
            if (rec_.time_s[k] - t0 >= long_rest_s) {
                rest_last = k;
                break;
            }
    }
    const std::size_t a = p.begin + p.ps.pulse_begin - 1;
    double q = 0;
    for (std::size_t k = a + 1; k <= rest_last; ++k)
        if (std::isfinite(rec_.current_a[k])) q += rec_.current_a[k] * (rec_.time_s[k] - rec_.time_s[k - 1]) / 3600.0;
    const double slope = (rec_.voltage_v[rest_last] - rec_.voltage_v[a]) / q;
    if (std::isfinite(slope) && slope > 0.0) po.docv_dah_v_per_ah = slope;
    fit_now();
}

void Sequencer::dispatch_fit_locked(const Recording& window, const estimator::PulseSet& pset, double soc,
                                    double t_pulse, const estimator::PulseFitOptions& po) {
    spawn([this, rows = window, pset, soc, po, t = last_cycler_s_, t_pulse]() mutable -> std::function<void()> {
        try {
            // The rows as `cellbench fit` reads them: a tester's stale step rows and voltage spikes corrected.
            auto notes = estimator::correct_logging_artifacts(rows);
            auto fit = std::make_shared<estimator::PulseSetFit>(estimator::fit_pulse_set(rows, pset, po));
            for (auto& note : notes) fit->warnings.push_back(std::move(note));
            fit->soc = soc;
            return [this, fit, t_pulse] { sink_.on_pulse_fit(*fit, t_pulse); };
        } catch (const std::exception& e) {
            return [this, t, what = std::string(e.what())] {
                sink_.on_event(t, "warning", "fit", "pulse set not fitted: " + what);
            };
        }
    });
}

void Sequencer::on_daq(const DaqSample& s) {
    std::lock_guard<std::mutex> lock(mutex_);
    last_daq_ = s;
    last_daq_s_ = s.t_mono_s;
    if (!active(state_)) return;
    if (check_rules_locked([&](SafetyRule& r, const SafetyContext& c) { return r.on_daq(s, c); }, s.t_mono_s)) return;
    // Thermal equilibrium: cell surface and chamber air both at the target within tolerance, for the hold time.
    if (segment_ < program_.segments.size() && program_.segments[segment_].kind == Segment::Kind::WaitEquilibrium &&
        state_ == RunState::Running && last_chamber_ && std::isfinite(chamber_target_c_)) {
        const auto& seg = program_.segments[segment_];
        // The chamber air and every cell thermocouple (surface Type-T, terminals T1 and T2) that reads a value.
        bool stable = std::abs(last_chamber_->air_c - chamber_target_c_) < seg.tolerance_c;
        int sensors = 0;
        for (double temp : {s.surface_c, s.t1_c, s.t2_c}) {
            if (!std::isfinite(temp)) continue;
            ++sensors;
            stable = stable && std::abs(temp - chamber_target_c_) < seg.tolerance_c;
        }
        stable = stable && sensors > 0;
        if (!stable) {
            equilibrium_since_s_ = -1;
        } else if (equilibrium_since_s_ < 0) {
            equilibrium_since_s_ = s.t_mono_s;
        } else if (s.t_mono_s - equilibrium_since_s_ >= seg.hold_s) {
            sink_.on_event(s.t_mono_s, "info", "equilibrium", "cell and chamber at " + fmt("%.2f degC", chamber_target_c_));
            advance_locked(s.t_mono_s);
        }
    }
}

void Sequencer::on_chamber(const ChamberSample& s) {
    std::lock_guard<std::mutex> lock(mutex_);
    last_chamber_ = s;
    last_chamber_s_ = s.t_mono_s;
    if (!active(state_)) return;
    check_rules_locked([&](SafetyRule& r, const SafetyContext& c) { return r.on_chamber(s, c); }, s.t_mono_s);
}

void Sequencer::on_fault(const std::string& instrument, const std::string& message, bool safety_data_lost, double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    sink_.on_event(t, safety_data_lost ? "alarm" : "warning", "fault", instrument + ": " + message);
    if (safety_data_lost) abort_locked(instrument + " lost (" + message + "): the cell cannot be watched", t);
}

void Sequencer::abort(const std::string& reason, double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    abort_locked(reason, t);
}

void Sequencer::tick(double t) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!active(state_)) return;
    if (check_rules_locked([&](SafetyRule& r, const SafetyContext& c) { return r.on_tick(t, c); }, t)) return;
    if (segment_ < program_.segments.size() && program_.segments[segment_].kind == Segment::Kind::WaitEquilibrium &&
        state_ == RunState::Running && t - segment_start_s_ > program_.segments[segment_].timeout_s) {
        const auto& seg = program_.segments[segment_];
        const std::string what = "thermal equilibrium not reached within " + fmt("%.0f s", seg.timeout_s);
        if (seg.abort_on_timeout) return abort_locked(what, t);
        sink_.on_event(t, "alarm", "equilibrium", what + "; the program goes on (abort_on_timeout is false)");
        advance_locked(t);
    }
}

RunState Sequencer::state() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return state_;
}

bool Sequencer::waiting_for_equilibrium() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return state_ == RunState::Running && segment_ < program_.segments.size() &&
           program_.segments[segment_].kind == Segment::Kind::WaitEquilibrium;
}

nlohmann::json Sequencer::status() const {
    std::lock_guard<std::mutex> lock(mutex_);
    nlohmann::json j = {{"state", to_string(state_)}, {"program", program_.name}};
    if (segment_ < program_.segments.size()) {
        const auto& s = program_.segments[segment_];
        j["segment"] = {{"index", segment_},
                        {"kind", s.kind == Segment::Kind::Cycler ? "cycler"
                                 : s.kind == Segment::Kind::ChamberSetpoint ? "chamber_setpoint"
                                                                             : "wait_equilibrium"},
                        {"name", s.name}};
    }
    if (last_cycler_)
        j["cycler"] = {{"voltage_v", last_cycler_->voltage_v}, {"current_a", last_cycler_->current_a},
                       {"step_id", last_cycler_->step_id},     {"cycle_id", last_cycler_->cycle_id},
                       {"step_type", last_cycler_->step_type}, {"status", last_cycler_->status}};
    if (last_daq_)
        j["daq"] = {{"surface_c", last_daq_->surface_c}, {"t1_c", last_daq_->t1_c}, {"t2_c", last_daq_->t2_c},
                    {"heat_flux_w_per_m2", last_daq_->heat_flux_w_per_m2}};
    if (last_chamber_)
        j["chamber"] = {{"air_c", last_chamber_->air_c}, {"setpoint_c", last_chamber_->setpoint_c},
                        {"running", last_chamber_->running}, {"alarm_bits", last_chamber_->alarm_bits}};
    if (std::isfinite(elapsed_s_)) {
        j["soc_estimate"] = soc_locked();
        j["elapsed_s"] = elapsed_s_;
    }
    j["pulse_sets_fitted"] = fitted_pulse_sets_;
    return j;
}

Recording Sequencer::recording() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return rec_;
}

}  // namespace cellbench::sequencer
