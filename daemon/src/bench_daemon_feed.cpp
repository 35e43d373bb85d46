// The feed: each instrument's readings, stamped on the bench clock, into the live values, the sequencer (on
// the feed thread, in arrival order) and the run store; the instruments' state changes and data losses.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>

namespace cellbench::daemon {

void BenchDaemon::Impl::feed_loop() {
    std::unique_lock l(feed_m);
    while (true) {
        feed_cv.wait(l, [&] { return feed_stop || !feed_q.empty(); });
        if (feed_q.empty()) return;  // stopping and drained
        auto job = std::move(feed_q.front());
        feed_q.pop_front();
        l.unlock();
        try {
            job();
        } catch (const std::exception& e) {
            spdlog::error("sequencer: {}", e.what());
        }
        l.lock();
    }
}

void BenchDaemon::Impl::on_neware_sample(const drivers::NewareSample& s) {
    const double t = bench_at(s.time);
    const auto& g = s.group;
    const auto status = std::string(protocol::neware::to_string(g.status));
    // A valid answer, with no new fault for a few polls, ends a fault episode (a flapping link stays one).
    recovered("neware", 3e-3 * cfg.cycler.poll_period_ms);
    auto c = active();

    // The store's row of a reading (t_s and soc are the run's; set when stored).
    static constexpr auto row_of = [](const sequencer::CyclerSample& cs) {
        CyclerSample row;
        row.unix_s = cs.t_wall_s;
        row.voltage_v = cs.voltage_v;
        row.current_a = cs.current_a;
        row.capacity_ah = cs.capacity_ah;
        row.energy_wh = cs.energy_wh;
        row.step_id = cs.step_id;
        row.cycle = cs.cycle_id;
        row.step_type = cs.step_type;
        row.status = cs.status;
        return row;
    };
    // Stored on the feed thread once the sequencer (SOC's one owner) has taken the row: it carries that SOC.
    auto store_row = [this, c](const sequencer::CyclerSample& cs) {
        CyclerSample row = row_of(cs);
        row.t_s = c->rel(cs.t_mono_s);
        row.soc = c->seq->soc();
        {
            std::lock_guard lock(c->m);
            c->last_cycler_t_s = row.t_s;
        }
        store->push(c->id, row);
        std::lock_guard lock(live_m);
        live_soc = row.soc;
    };

    // Recorded rows first (they precede the live reading), on the tester's own time base.
    if (s.test_id != 0 && s.test_id != neware_test_id && std::isfinite(g.total_time_s)) {
        neware_test_id = s.test_id;
        neware_test_start_s = t - g.total_time_s;
    }
    if (!s.records.empty() && std::isfinite(neware_test_start_s)) {
        std::vector<sequencer::CyclerSample> rows;
        rows.reserve(s.records.size());
        for (const auto& r : s.records) {
            sequencer::CyclerSample cs;
            cs.t_mono_s = neware_test_start_s + r.test_time_s;
            cs.t_wall_s = unix_at(s.time) - (t - cs.t_mono_s);
            cs.voltage_v = r.voltage_v;
            cs.current_a = r.current_a;
            cs.capacity_ah = r.capacity_ah;
            cs.energy_wh = r.energy_wh;
            cs.step_id = r.step_id;
            cs.cycle_id = r.cycle_id;
            cs.step_type = r.step_type;
            cs.status = "working";
            rows.push_back(std::move(cs));
        }
        if (c) feed([c, store_row, rows = std::move(rows)] {
            for (const auto& cs : rows) {
                c->seq->on_cycler_record(cs);
                store_row(cs);
            }
        });
    }

    sequencer::CyclerSample cs;
    cs.t_mono_s = t;
    cs.t_wall_s = unix_at(s.time);
    cs.voltage_v = g.voltage_v;
    cs.current_a = g.current_a;
    cs.capacity_ah = g.capacity_ah;
    cs.energy_wh = g.energy_wh;
    cs.step_id = g.step_id;
    cs.cycle_id = g.cycle_id;
    cs.step_type = g.step_type;
    cs.status = status;
    cs.covered_by_records = s.recording;
    // Without recorded rows (a tester that does not record, or before the first download) the live
    // readings are the samples stored.
    CyclerSample row = row_of(cs);
    if (c) {
        {
            std::lock_guard lock(c->m);
            c->last_capacity_ah = g.capacity_ah;
            c->last_energy_wh = g.energy_wh;
        }
        feed([c, cs, store_row, stored = !s.recording] {
            c->seq->on_cycler(cs);
            if (stored) store_row(cs);
        });
    }
    std::lock_guard lock(live_m);
    row.t_s = t;  // live: bench time
    row.soc = live_soc;
    live_cycler = row;
    cycler_instrument->note_reading(row.unix_s, t);
    std::vector<instruments::MemberReading> members;
    members.reserve(s.members.size());
    for (const auto& m : s.members)
        members.push_back({m.channel.key(), m.voltage_v, m.current_a, std::string(protocol::neware::to_string(m.workstatus))});
    cycler_instrument->set_members(std::move(members));
}

void BenchDaemon::Impl::on_neware_event(const drivers::NewareEvent& e) {
    using instruments::InstrumentState;
    auto& cyc = *cycler_instrument;
    switch (e.kind) {
        case drivers::NewareEventKind::connected: cyc.set_state(InstrumentState::connected, ""); break;
        case drivers::NewareEventKind::disconnected:
        case drivers::NewareEventKind::connect_failed: cyc.set_state(InstrumentState::offline, e.message); break;
        case drivers::NewareEventKind::group_fault: cyc.set_state(InstrumentState::error, e.message); break;
        default: cyc.set_detail(e.message); break;
    }
    // The driver has logged it (once per kind of fault in an episode: drivers/episode_log.hpp).
    spdlog::debug("neware: {}: {}", drivers::to_string(e.kind), e.message);
    // A misbehaving parallel group (a member in protect, sharing off; the client has stopped every member):
    // immediately fatal. Lost connections, lost or malformed answers: the client reconnects with backoff and
    // the run goes on while readings come back within the grace (a valid poll answer closes the episode).
    switch (e.kind) {
        case drivers::NewareEventKind::group_fault: {
            json extra = json::object();
            if (e.fault) extra["member"] = e.fault->member_key;
            fault("neware:group", "group_fault", e.message, true, std::move(extra));
            break;
        }
        case drivers::NewareEventKind::disconnected:
        case drivers::NewareEventKind::connect_failed:
        case drivers::NewareEventKind::timeout:
        case drivers::NewareEventKind::protocol_error:
            fault("neware", drivers::to_string(e.kind), e.message, false);
            break;
        default: break;  // connected (a reading closes the episode), command_failed (command_result)
    }
}

void BenchDaemon::Impl::on_dewe_sample(const drivers::DeweReading& r) {
    const double t = bench_at(r.time);
    sequencer::DaqSample ds{t, unix_at(r.time), r.thermopile_v, r.type_t_c, r.t1_c, r.t2_c, r.heat_flux_w_per_m2};
    DaqSample row;
    row.unix_s = ds.t_wall_s;
    row.thermopile_v = r.thermopile_v;
    row.surface_c = r.type_t_c;
    row.t1_c = r.t1_c;
    row.t2_c = r.t2_c;
    row.heat_flux_w_per_m2 = r.heat_flux_w_per_m2;
    row.sequence = static_cast<std::int64_t>(r.sequence);
    recovered("dewe");
    if (auto c = active()) {
        row.t_s = c->rel(t);
        feed([c, ds] { c->seq->on_daq(ds); });
        store->push(c->id, row);
    }
    std::lock_guard lock(live_m);
    row.t_s = t;
    live_daq = row;
    daq_instrument->note_reading(row.unix_s, t);
}

void BenchDaemon::Impl::on_dewe_health(const drivers::DeweHealth& h) {
    using instruments::InstrumentState;
    InstrumentState state = InstrumentState::offline;
    switch (h.state) {
        case drivers::DeweStreamState::streaming: state = InstrumentState::connected; break;
        case drivers::DeweStreamState::waiting: state = InstrumentState::connecting; break;
        case drivers::DeweStreamState::silent: state = InstrumentState::offline; break;
        case drivers::DeweStreamState::stopped: state = InstrumentState::offline; break;
    }
    const bool changed = daq_instrument->set_state(state, h.message);
    if (changed) spdlog::info("dewe: {} ({})", drivers::to_string(h.state), h.message);
    // Silence: a fault episode (the next sample closes it); the sequencer aborts past the DAQ's grace (tick:
    // no cell temperature). Lost frames (counter gaps) and garbage: counted, and an event at most every
    // loss_event_interval_s with what was lost since the previous one.
    if (changed && h.state == drivers::DeweStreamState::silent) fault("dewe", "silence", h.message, false);
    daq_losses(h.stats);
}

void BenchDaemon::Impl::daq_losses(const protocol::DeweStreamStats& st) {
    const double now = now_s();
    auto c = active();
    const auto run = c ? std::optional<RunId>(c->id) : std::nullopt;
    json detail;
    std::string message;
    {
        std::lock_guard l(fault_m);
        const auto& r = daq_loss_reported;
        const std::uint64_t samples = st.lost_samples - r.lost_samples, frames = st.lost_frames - r.lost_frames,
                            garbage = st.garbage - r.garbage, resyncs = st.resyncs - r.resyncs;
        if (samples + frames + garbage + resyncs == 0) return;
        if (run == daq_loss_run && now - daq_loss_event_s < cfg.faults.daq.loss_event_interval_s) return;
        daq_loss_event_s = now;
        daq_loss_run = run;
        daq_loss_reported = st;
        message = "dewe: " + std::to_string(samples) + " samples lost (" + std::to_string(frames) +
                  " frames missing from the counters), " + std::to_string(garbage) + " garbage frames ignored" +
                  (resyncs ? ", " + std::to_string(resyncs) + " counter restarts" : std::string());
        detail = {{"instrument", "dewe"}, {"fault", "data_loss"}, {"action", "count"},
                  {"lost_samples", samples}, {"lost_frames", frames}, {"garbage_frames", garbage},
                  {"resyncs", resyncs}, {"total_lost_samples", st.lost_samples},
                  {"total_lost_frames", st.lost_frames}, {"total_garbage_frames", st.garbage},
                  {"total_samples", st.samples}};
    }
    spdlog::warn("{}", message);
    record_run_event(run, EventLevel::warning, "fault", message, std::move(detail));
}

void BenchDaemon::Impl::on_chamber_status(const drivers::ChamberStatus& s) {
    const double t = bench_at(s.time);
    sequencer::ChamberSample cs{t, unix_at(s.time), s.process_value_c, s.setpoint_c, s.running.value_or(true),
                                s.alarm_word};
    ChamberSample row;
    row.unix_s = cs.t_wall_s;
    row.ambient_c = s.process_value_c;
    row.setpoint_c = s.setpoint_c;
    row.running = s.running;
    row.alarm_bits = s.alarm_word;
    recovered("chamber");
    if (s.alarm_word == 0) recovered("chamber:alarm");
    if (std::abs(s.process_value_c - s.setpoint_c) <= cfg.faults.chamber.setpoint_tolerance_c) recovered("chamber:setpoint");
    if (auto c = active()) {
        row.t_s = c->rel(t);
        feed([c, cs] { c->seq->on_chamber(cs); });
        store->push(c->id, row);
    }
    std::lock_guard lock(live_m);
    row.t_s = t;
    live_chamber = row;
    chamber_instrument->note_reading(row.unix_s, t);
    chamber_instrument->set_state(instruments::InstrumentState::connected, "");
}

void BenchDaemon::Impl::on_chamber_fault(const drivers::ChamberFault& f) {
    chamber_instrument->set_state(f.kind == drivers::ChamberFaultKind::unreachable ? instruments::InstrumentState::offline
                                                                                   : instruments::InstrumentState::error,
                                  f.operation + ": " + f.message);
    spdlog::debug("chamber: {} ({}): {}", drivers::to_string(f.kind), f.operation, f.message);  // the driver logged it
    // Policy (config: fault_policy.chamber). An alarm bit is immediately fatal; a set point not reached and
    // an exception answer are fatal when the policy says "abort"; the rest (no answer, lost connection,
    // garbled answer) is retried on a fresh connection while readings come back within the grace.
    const auto& p = cfg.faults.chamber;
    const std::string kind = drivers::to_string(f.kind);
    const json extra = {{"operation", f.operation}, {"attempts", f.attempts}};
    switch (f.kind) {
        case drivers::ChamberFaultKind::alarm: fault("chamber:alarm", kind, f.message, true, extra); break;
        case drivers::ChamberFaultKind::setpoint_not_reached:
            fault("chamber:setpoint", kind, f.message, p.setpoint_not_reached == SetpointAction::abort, extra);
            break;
        case drivers::ChamberFaultKind::exception_response: {
            json x = extra;
            x["exception_code"] = f.exception_code;
            fault("chamber", kind, f.message, p.exception_response == FaultAction::abort, std::move(x));
            break;
        }
        case drivers::ChamberFaultKind::rejected: fault("chamber:command", kind, f.message, false, extra); break;
        default: fault("chamber", kind, f.message, false, extra); break;
    }
}

}  // namespace cellbench::daemon
