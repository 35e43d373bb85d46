// Runs: starting one (program, cell, limits, the sequencer), the operator's stop/pause/resume, crash
// recovery at start, the final fits redone, and a run's answer.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>
#include "cellbench/estimator/fit.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"

namespace cellbench::daemon {

// Runs the daemon left live when it died (crash, kill -9, power loss): the bench is made safe before
// anything else -- start() calls this before the tick and the API exist, so no run can start and nothing
// else is commanded meanwhile. The cycler is told to stop and the chamber to go to its safe set point, both
// at once, each retried until the instrument acknowledges it (at most kRecoveryAttempts, each bounded by
// the driver's own timeouts); then every such run gets a recovery event saying what was acknowledged.
// A completed run always gets a "fit" event from its final fit (the parameter set, or why there is none).
// A run without one was stopped (kill -9, power loss) before the fit landed: visible as a fit_pending
// event, and the fit is redone from the stored records on a worker thread (never on the run engine's).
void BenchDaemon::Impl::redo_pending_fits() {
    std::vector<RunId> pending;
    for (const auto& r : store->list_runs()) {
        if (r.state != RunState::completed || r.cycler_samples <= 10) continue;
        bool has_fit_event = false;
        for (const auto& e : store->events(r.id))
            if (e.kind == "fit" || e.kind == "fit_pending") has_fit_event = true;
        if (!has_fit_event && !store->latest_parameter_set(r.id)) pending.push_back(r.id);
    }
    if (pending.empty()) return;
    for (RunId id : pending)
        bench_event(EventLevel::warning, "fit_pending",
                    "the final fit of this run did not land before the daemon stopped; it is redone from the "
                    "stored records",
                    nullptr, id);
    refit_thread = std::thread([this, pending] {
        for (RunId id : pending) {
            try {
                const auto run = store->get_run(id);
                const auto rec = store->export_recording(id);
                const auto c = estimator::characterize({rec});
                ParameterSetRecord r;
                r.run_id = id;
                r.created_unix_s = unix_now_s();
                r.cell = run ? run->cell : std::string();
                r.params = c.params.to_json();
                store->record_parameter_set(r);
                bench_event(EventLevel::info, "fit", "parameter set fitted from the run (redone at restart)",
                            c.summary_json(), id);
                spdlog::info("run {}: final fit redone from the stored records", id);
            } catch (const std::exception& e) {
                bench_event(EventLevel::warning, "fit",
                            std::string("no parameter set for this run (redone at restart): ") + e.what(), nullptr, id);
            }
        }
    });
}

void BenchDaemon::Impl::recover() {
    const auto ids = store->mark_interrupted_runs();
    if (ids.empty()) return;
    spdlog::warn("{} run(s) were live when the daemon stopped: current off, chamber to {:.1f} degC",
                 ids.size(), cfg.chamber.safe_setpoint_c);
    constexpr int kRecoveryAttempts = 5;
    using Ack = std::shared_ptr<std::promise<std::string>>;  // "" = acknowledged, else why not
    auto wait = [](const Ack& p) {
        auto f = p->get_future();
        return f.wait_for(std::chrono::seconds(15)) == std::future_status::ready ? f.get() : std::string("no answer");
    };
    std::string cycler_error = "not tried", chamber_error = "not tried";
    int attempts = 0;
    while ((!cycler_error.empty() || !chamber_error.empty()) && attempts < kRecoveryAttempts) {
        ++attempts;
        Ack cyc, cham;
        if (!cycler_error.empty()) {
            cyc = std::make_shared<std::promise<std::string>>();
            neware->stop_program([cyc](const drivers::NewareCommandResult& r) { cyc->set_value(r.ok ? "" : r.error); });
        }
        if (!chamber_error.empty()) {
            cham = std::make_shared<std::promise<std::string>>();
            chamber->set_temperature(cfg.chamber.safe_setpoint_c, [cham](const std::optional<drivers::ChamberFault>& f) {
                cham->set_value(f ? f->message : std::string());
            });
        }
        if (cyc) cycler_error = wait(cyc);
        if (cham) chamber_error = wait(cham);
        if (!cycler_error.empty()) spdlog::warn("recovery: cycler stop not acknowledged (attempt {}): {}", attempts, cycler_error);
        if (!chamber_error.empty())
            spdlog::warn("recovery: chamber set point not acknowledged (attempt {}): {}", attempts, chamber_error);
    }
    const bool safe = cycler_error.empty() && chamber_error.empty();
    if (safe) spdlog::warn("recovery: the cycler stopped and the chamber is at its safe set point");
    else spdlog::error("recovery: the bench could NOT be confirmed safe: cycler: {}; chamber: {}",
                       cycler_error.empty() ? "stopped" : cycler_error, chamber_error.empty() ? "safe set point" : chamber_error);
    auto word = [](const std::string& err) { return err.empty() ? std::string("acknowledged") : "not acknowledged: " + err; };
    for (RunId id : ids)
        bench_event(safe ? EventLevel::warning : EventLevel::error, "recovery",
                    "the daemon restarted while this run was live; it is marked interrupted and does not "
                    "continue. Before anything else the cycler was commanded to stop (" + word(cycler_error) +
                        ") and the chamber to its safe set point " + fmt::format("{:.1f} degC", cfg.chamber.safe_setpoint_c) +
                        " (" + word(chamber_error) + ").",
                    {{"safe_setpoint_c", cfg.chamber.safe_setpoint_c}, {"cycler_stop", word(cycler_error)},
                     {"chamber_setpoint", word(chamber_error)}, {"attempts", attempts}},
                    id);
    store->flush();
}

sequencer::SafetyLimits BenchDaemon::Impl::limits_for(const CellConfig& cell) const {
    sequencer::SafetyLimits l;
    const auto& s = cfg.safety;
    l.max_temperature_c = std::min(s.max_temperature_c, cell.max_temperature_c > 0 ? cell.max_temperature_c : s.max_temperature_c);
    l.min_voltage_v = s.min_voltage_v;
    l.max_voltage_v = s.max_voltage_v;
    l.max_current_a = s.max_current_a;
    l.chamber_deviation_c = s.chamber_deviation_c;
    // Grace in bench time, but never below what the host can promise in wall time (min_grace_s): at 1000x a
    // 5 s grace would be 5 ms of wall time, which a loaded machine cannot guarantee.
    l.instrument_loss_grace_s = std::max(s.instrument_loss_grace_s, min_grace_s());
    l.cycler_loss_grace_s = grace_for("neware");
    l.daq_loss_grace_s = grace_for("dewe");
    l.chamber_loss_grace_s = grace_for("chamber");
    l.chamber_safe_setpoint_c = cfg.chamber.safe_setpoint_c;
    return l;
}

json BenchDaemon::Impl::start_run(const StartRequest& req) {
    std::lock_guard lock(run_m);
    if (stopping) throw Unavailable("the daemon is shutting down");
    if (active()) throw Conflict("run " + std::to_string(current()->id) + " is active; stop it first");
    CellConfig cell;
    Program program;
    try {
        cell = load_cell_config(cell_file(cfg.config_dir, req.cell));
        program = load_program(program_file(cfg.config_dir, req.program), cell, req.parameters, &cfg);
    } catch (const InputError& e) {
        throw BadRequest(std::string(e.what()) + " (programs and cells are looked up in " +
                         (cfg.config_dir / "programs").string() + " and " + (cfg.config_dir / "cells").string() + ")");
    }
    if (cycler_instrument->state() != instruments::InstrumentState::connected)
        throw Unavailable("the cycler is not connected (" + cycler_instrument->detail() + ")");
    sequencer::SequencerOptions so;
    so.limits = limits_for(cell);
    so.capacity_ah = cell.nominal_capacity_ah;
    so.keep_recording_after_end = false;  // the store has every row; no second copy kept between runs
    if (cell.params_path) {
        try {
            auto params = std::make_shared<const estimator::ParameterSet>(load_param_file(*cell.params_path));
            so.capacity_ah = params->capacity_ah;  // the characterised capacity
            // The run's starting SOC from the rested cell's voltage (the sequencer owns SOC).
            if (!params->ocv_v.empty()) so.soc_from_ocv = [params](double v) { return params->soc_from_ocv(v); };
        } catch (const std::exception& e) {
            spdlog::warn("cell {}: {}; SOC uses the nominal capacity", cell.id, e.what());
        }
    }
    so.area_m2 = cell.surface_or(cfg.daq.cell_area_m2);

    NewRun nr;
    nr.program = req.program;
    nr.cell = req.cell;
    nr.config = {{"program", program.to_json()}, {"cell", cell.to_json()}, {"bench", cfg.document},
                 {"time_scale", scale}};
    nr.state = RunState::running;
    // create_run is also the probe of a database that failed before: it commits (the fault is over) or
    // says why not.
    RunId id = 0;
    try {
        id = store->create_run(nr);
    } catch (const StoreError& e) {
        note_db_fault(std::string(to_string(e.kind())) + ": " + e.what());
        throw Unavailable(std::string("the database cannot record a run: ") + e.what());
    }
    {
        std::lock_guard l(live_m);
        db_fault.clear();
    }

    // The previous run's fits must have reported before its context goes.
    if (auto old = current()) old->seq->wait_for_fits();
    const double t0 = now_s();
    {
        std::lock_guard l(live_m);
        live_soc = kNaN;  // the new run's SOC comes with its first row
    }
    auto c = std::make_shared<RunContext>(*store, id, t0, cell.id);
    c->capacity_ah = so.capacity_ah;
    c->expected_s = estimate_duration(program, cell).total_s;
    const auto sp = to_sequencer_program(program);
    for (const auto& s : sp.segments) {  // the sequencer's segments: a cycler program may run as two step files
        if (s.kind != sequencer::Segment::Kind::Cycler) {
            c->steps_per_segment.push_back(static_cast<int>(s.program.steps.size()));
            continue;
        }
        for (const auto& part : protocol::tester_parts(s.program))
            c->steps_per_segment.push_back(static_cast<int>(part.steps.size()));
    }
    c->seq = std::make_unique<sequencer::Sequencer>(cycler_adapter, chamber_adapter, *c, so);
    {
        std::lock_guard l(ctx_m);
        ctx = c;
    }
    ++run_generation;  // a stop still being retried belongs to an earlier run
    bench_event(EventLevel::info, "operator", "run started: program " + req.program + ", cell " + req.cell,
                {{"max_temperature_c", so.limits.max_temperature_c}, {"capacity_ah", so.capacity_ah}}, id);
    try {
        c->seq->start(sp, t0);
    } catch (const std::exception& e) {
        c->live = false;
        store->set_run_state(id, RunState::aborted, e.what());
        throw BadRequest(e.what());
    }
    spdlog::info("run {} started: program {} on cell {}", id, req.program, req.cell);
    return run_json(id);
}

std::shared_ptr<RunContext> BenchDaemon::Impl::run_for_command(RunId id) {
    existing_run(*store, id);
    auto c = active();
    if (!c || c->id != id) throw Conflict("run " + std::to_string(id) + " is not active");
    return c;
}

json BenchDaemon::Impl::stop_run(RunId id) {
    std::lock_guard lock(run_m);
    auto c = run_for_command(id);
    c->seq->stop("stopped by the operator", now_s());
    return run_json(id);
}

json BenchDaemon::Impl::pause_run(RunId id) {
    std::lock_guard lock(run_m);
    auto c = run_for_command(id);
    try {
        c->seq->pause(now_s());
    } catch (const InputError& e) {
        throw Conflict(e.what());
    }
    return run_json(id);
}

json BenchDaemon::Impl::resume_run(RunId id) {
    std::lock_guard lock(run_m);
    auto c = run_for_command(id);
    try {
        c->seq->resume(now_s());
    } catch (const InputError& e) {
        throw Conflict(e.what());
    }
    return run_json(id);
}

json BenchDaemon::Impl::run_json(const RunInfo& r) const {
    json j = to_json(r);
    j.erase("config");
    // Commands land in the store's queue: a run we know is live is reported by its live state.
    auto c = current();
    RunState st = r.state;
    bool waiting = false;
    if (c && c->id == r.id) {
        const auto s = static_cast<sequencer::RunState>(c->seq_state.load());
        if (s != sequencer::RunState::Idle) st = store_state(s);
        waiting = st == RunState::running && c->seq->waiting_for_equilibrium();
    }
    j["state"] = api_state(st, waiting);
    // How it ended (the end state), null while live; `reason` says why in words.
    j["outcome"] = is_terminal(st) ? json(std::string(to_string(st))) : json(nullptr);
    std::string reason = r.reason;
    if (c && c->id == r.id && is_terminal(st)) {
        std::lock_guard l(c->m);
        if (!c->end_reason.empty()) reason = c->end_reason;
    }
    j["reason"] = is_terminal(st) && !reason.empty() ? json(reason) : json(nullptr);
    // `error`: the reason of a run that did not end as asked (aborted, interrupted), null otherwise.
    j["error"] = (st == RunState::aborted || st == RunState::interrupted) && !reason.empty() ? json(reason) : json(nullptr);
    j["step"] = nullptr;
    if (c && c->id == r.id && live_state(st)) {
        std::optional<CyclerSample> lc;
        {
            std::lock_guard l(live_m);
            lc = live_cycler;
        }
        j["step"] = c->step_json(lc ? c->rel(lc->t_s) : kNaN);
    }
    return j;
}

json BenchDaemon::Impl::run_json(RunId id) const {
    return run_json(existing_run(*store, id));
}

}  // namespace cellbench::daemon
