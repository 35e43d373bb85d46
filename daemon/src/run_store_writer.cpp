// The run store's write side: the writer thread (batches, rollups, control records, fault episodes, the
// unsaved-record retry and sidecar), opening and closing the store, and the RunStore calls that queue writes.
// See run_store.hpp for the threading, durability and failure model.
#include "run_store_impl.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>

#include <spdlog/spdlog.h>

namespace cellbench::daemon {

using nlohmann::json;
using namespace store;

namespace {

// One second of one run and source, accumulated over a batch.
struct RollupAcc {
    RunId run = 0;
    std::int64_t second = 0;
    std::int64_t n = 0;
    double t_min = 0.0, t_max = 0.0;
    std::vector<double> min, max;  // NaN = no value yet
};

class RollupBatch {
public:
    explicit RollupBatch(std::size_t channels) : channels_(channels) {}

    void add(RunId run, double t, const double* values) {
        const auto second = static_cast<std::int64_t>(std::floor(t));
        RollupAcc* a = nullptr;
        for (auto it = accs_.rbegin(); it != accs_.rend() && it - accs_.rbegin() < 8; ++it)  // rows come in order
            if (it->run == run && it->second == second) {
                a = &*it;
                break;
            }
        if (!a) {
            accs_.push_back({run, second, 0, t, t, std::vector<double>(channels_, kNaN), std::vector<double>(channels_, kNaN)});
            a = &accs_.back();
        }
        ++a->n;
        a->t_min = std::min(a->t_min, t);
        a->t_max = std::max(a->t_max, t);
        for (std::size_t c = 0; c < channels_; ++c) {
            const double v = values[c];
            if (std::isnan(v)) continue;
            if (std::isnan(a->min[c]) || v < a->min[c]) a->min[c] = v;
            if (std::isnan(a->max[c]) || v > a->max[c]) a->max[c] = v;
        }
    }

    void write(Stmt& upsert) const {
        for (const auto& a : accs_) {
            upsert.integer(1, a.run).integer(2, a.second).integer(3, a.n).real(4, a.t_min).real(5, a.t_max);
            for (std::size_t c = 0; c < channels_; ++c)
                upsert.real(static_cast<int>(6 + 2 * c), a.min[c]).real(static_cast<int>(7 + 2 * c), a.max[c]);
            upsert.run();
        }
    }

private:
    std::size_t channels_;
    std::vector<RollupAcc> accs_;
};

std::array<double, 7> channel_values(const CyclerSample& s) {
    return {s.voltage_v, s.current_a, s.capacity_ah, s.energy_wh, s.soc, static_cast<double>(s.step_id),
            static_cast<double>(s.cycle)};
}
std::array<double, 5> channel_values(const DaqSample& s) {
    return {s.thermopile_v, s.surface_c, s.t1_c, s.t2_c, s.heat_flux_w_per_m2};
}

}  // namespace

namespace store {

WriterStatements::WriterStatements(sqlite3* db)
    : begin(db, "BEGIN IMMEDIATE", true),
      commit(db, "COMMIT", true),
      rollback(db, "ROLLBACK", true),
      cycler(db,
             "INSERT INTO cycler_samples(run_id, t_s, unix_s, voltage_v, current_a, capacity_ah, energy_wh, soc, "
             "step_id, step_type, cycle, status) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)",
             true),
      daq(db,
          "INSERT INTO daq_samples(run_id, t_s, unix_s, thermopile_v, surface_c, t1_c, t2_c, heat_flux_w_per_m2, "
          "sequence) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
          true),
      chamber(db,
              "INSERT INTO chamber_samples(run_id, t_s, unix_s, ambient_c, setpoint_c, running, alarm_bits) "
              "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
              true),
      counts(db,
             "UPDATE runs SET cycler_samples = cycler_samples + ?2, daq_samples = daq_samples + ?3, "
             "chamber_samples = chamber_samples + ?4 WHERE id = ?1",
             true),
      cycler_rollup(db, rollup_upsert(source_defs()[0]), true),
      daq_rollup(db, rollup_upsert(source_defs()[1]), true),
      create_run(db,
                 "INSERT INTO runs(program, cell, state, created_unix_s, started_unix_s, config_json) "
                 "VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                 true),
      set_state(db,
                std::string("UPDATE runs SET state = ?2, reason = COALESCE(?3, reason), "
                            "started_unix_s = CASE WHEN ?2 = 'running' AND started_unix_s IS NULL THEN ?4 "
                            "ELSE started_unix_s END, "
                            "ended_unix_s = CASE WHEN ?2 IN ") +
                    kTerminalStates + " THEN ?4 ELSE ended_unix_s END WHERE id = ?1 AND state NOT IN " +
                    kTerminalStates,
                true),
      step(db,
           "INSERT INTO steps(run_id, step_index, segment, step_id, cycle, type, started_t_s, started_unix_s, "
           "ended_t_s, ended_unix_s, capacity_ah, energy_wh, end_reason) "
           "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13) "
           "ON CONFLICT(run_id, step_index) DO UPDATE SET segment = excluded.segment, step_id = excluded.step_id, "
           "cycle = excluded.cycle, type = excluded.type, started_t_s = excluded.started_t_s, "
           "started_unix_s = excluded.started_unix_s, ended_t_s = excluded.ended_t_s, "
           "ended_unix_s = excluded.ended_unix_s, capacity_ah = excluded.capacity_ah, "
           "energy_wh = excluded.energy_wh, end_reason = excluded.end_reason",
           true),
      event(db,
            "INSERT INTO events(run_id, unix_s, t_s, level, kind, step, message, detail_json) "
            "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
            true),
      fit(db,
          "INSERT INTO pulse_fits(run_id, pulse_set, t_s, unix_s, soc, ocv_v, temperature_c, "
          "discharge_r0_ohm, discharge_r1_ohm, discharge_c1_f, discharge_r2_ohm, discharge_c2_f, "
          "charge_r0_ohm, charge_r1_ohm, charge_c1_f, charge_r2_ohm, charge_c2_f, method, rms_v, detail_json) "
          "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18, ?19, ?20) "
          "ON CONFLICT(run_id, pulse_set) DO UPDATE SET t_s = excluded.t_s, unix_s = excluded.unix_s, "
          "soc = excluded.soc, ocv_v = excluded.ocv_v, temperature_c = excluded.temperature_c, "
          "discharge_r0_ohm = excluded.discharge_r0_ohm, discharge_r1_ohm = excluded.discharge_r1_ohm, "
          "discharge_c1_f = excluded.discharge_c1_f, discharge_r2_ohm = excluded.discharge_r2_ohm, "
          "discharge_c2_f = excluded.discharge_c2_f, charge_r0_ohm = excluded.charge_r0_ohm, "
          "charge_r1_ohm = excluded.charge_r1_ohm, charge_c1_f = excluded.charge_c1_f, "
          "charge_r2_ohm = excluded.charge_r2_ohm, charge_c2_f = excluded.charge_c2_f, "
          "method = excluded.method, rms_v = excluded.rms_v, detail_json = excluded.detail_json",
          true),
      params(db, "INSERT INTO parameter_sets(run_id, created_unix_s, cell, params_json) VALUES (?1, ?2, ?3, ?4)", true),
      live_runs(db, "SELECT id, created_unix_s, started_unix_s FROM runs WHERE state IN ('starting','running','paused')", true),
      last_cycler(db, "SELECT unix_s FROM cycler_samples WHERE run_id = ?1 ORDER BY t_s DESC LIMIT 1", true),
      last_daq(db, "SELECT unix_s FROM daq_samples WHERE run_id = ?1 ORDER BY t_s DESC LIMIT 1", true),
      last_chamber(db, "SELECT unix_s FROM chamber_samples WHERE run_id = ?1 ORDER BY t_s DESC LIMIT 1", true),
      interrupt(db,
                "UPDATE runs SET state = 'interrupted', reason = ?2, ended_unix_s = ?3 WHERE id = ?1 AND "
                "state IN ('starting','running','paused')",
                true) {}

}  // namespace store

// ---------------------------------------------------------------------------------------------------------
// Writer thread

void RunStore::Impl::writer_main() {
    Batch writing;
    std::unique_lock lk(mu);
    for (;;) {
        if (unsaved.empty()) cv.wait(lk, [&] { return stop || !pending.empty(); });
        else cv.wait_for(lk, kUnsavedRetry, [&] { return stop || !pending.empty(); });
        if (!stop && !urgent && !pending.empty() && pending.samples() < opt.flush_rows)
            cv.wait_until(lk, first_pending + opt.flush_period,
                          [&] { return stop || urgent || pending.samples() >= opt.flush_rows; });
        if (pending.empty()) {
            if (!unsaved.empty()) {  // nothing new: retry what a fault left unsaved
                lk.unlock();
                retry_unsaved();
                lk.lock();
            }
            if (stop) break;
            continue;
        }
        std::swap(pending, writing);
        urgent = false;
        const std::uint64_t dropped = std::exchange(dropped_unreported, 0);
        lk.unlock();

        if (dropped > 0)
            report({StoreFaultKind::overflow, 0,
                    path.string() + ": writer queue full (" + std::to_string(opt.queue_capacity_samples) +
                        " samples waiting): " + std::to_string(dropped) + " new samples were dropped",
                    dropped});
        write_batch(writing);  // also releases the batch's samples from queued_samples
        // Freed, not cleared: a cleared vector keeps its capacity, so the largest batch ever written (a backlog
        // after a stalled disk, up to queue_capacity_samples at 128 bytes a cycler sample) stayed allocated for
        // the daemon's life. The soak found 548 KiB of one run's cycler samples still held six runs later.
        writing = Batch{};
        lk.lock();
    }
    lk.unlock();
    if (!unsaved.empty()) write_sidecar();
}

bool RunStore::Impl::transient(StoreFaultKind k) {
    return k == StoreFaultKind::disk_full || k == StoreFaultKind::busy || k == StoreFaultKind::io_error ||
           k == StoreFaultKind::readonly;
}

// Keeps the batch's records that matter after a failed retry (waiters are failed by the caller).
void RunStore::Impl::retain(std::vector<Control>& ops) {
    for (auto& op : ops) {
        const bool keep = std::holds_alternative<SetStateOp>(op) || std::holds_alternative<StepOp>(op) ||
                          std::holds_alternative<EventOp>(op) || std::holds_alternative<FitOp>(op) ||
                          std::holds_alternative<ParamsOp>(op);
        if (keep && unsaved.size() < kMaxUnsaved) unsaved.push_back(std::move(op));
    }
}

// One transaction with everything unsaved; true when it committed (or nothing was waiting).
bool RunStore::Impl::retry_unsaved() {
    if (unsaved.empty()) return true;
    try {
        ws->begin.run();
        for (auto& op : unsaved) run_control(op);
        ws->commit.run();
        commits.fetch_add(1, std::memory_order_release);
    } catch (const std::exception&) {
        rollback_if_open();
        return false;  // reported when it first failed
    }
    spdlog::warn("{}: database writable again: {} record(s) kept while it was not are now saved", path.string(),
                 unsaved.size());
    unsaved.clear();
    fault_episode.reset();
    return true;
}

// At close, with the database still refusing writes: the unsaved records as JSON lines beside it (best
// effort: on a full disk this may fail too, then the log is the only record).
void RunStore::Impl::write_sidecar() {
    const fs::path side = sidecar_path();
    std::FILE* f = std::fopen(side.c_str(), "a");
    std::size_t n = 0;
    for (const auto& op : unsaved) {
        json j;
        if (const auto* e = std::get_if<EventOp>(&op)) {
            j = to_json(e->event);
            j["record"] = "event";
            spdlog::error("unsaved event (run {}): {}: {}", e->event.run_id ? std::to_string(*e->event.run_id) : "-",
                          e->event.kind, e->event.message);
        } else if (const auto* st = std::get_if<SetStateOp>(&op)) {
            j = {{"record", "run_state"}, {"run_id", st->run}, {"state", to_string(st->state)},
                 {"reason", st->reason}, {"unix_s", st->unix_s}};
            spdlog::error("unsaved run state: run {} {} ({})", st->run, to_string(st->state), st->reason);
        } else {
            continue;  // steps, fits, parameter sets: derivable from the samples; not kept
        }
        if (f && std::fprintf(f, "%s\n", j.dump(-1, ' ', false, json::error_handler_t::replace).c_str()) > 0) ++n;
    }
    const bool ok = f && std::fflush(f) == 0;
    if (f) std::fclose(f);
    if (ok && n > 0) spdlog::error("{}: the database refused {} record(s) until close: written to {}", path.string(), n, side.string());
    else if (!ok) spdlog::error("{}: the database refused {} record(s) until close and {} cannot be written either: they are only in this log",
                                path.string(), unsaved.size(), side.string());
    unsaved.clear();
}

void RunStore::Impl::report(const StoreFault& f) {
    {
        std::lock_guard lk(mu);
        stats.last_fault = f;
    }
    if (f.kind != StoreFaultKind::overflow) {
        if (fault_episode == f.kind) return;  // already reported; nothing committed since
        fault_episode = f.kind;
    }
    if (opt.on_fault) {
        try {
            opt.on_fault(f);
        } catch (...) {
            // A throwing handler must not take the writer down.
        }
    }
}

void RunStore::Impl::rollback_if_open() {
    if (sqlite3_get_autocommit(wdb.get()) == 0) {
        try {
            ws->rollback.run();
        } catch (const SqlError&) {
            ws->rollback.reset();
        }
    }
}

void RunStore::Impl::write_samples(const Batch& b) {
    // Sample counts per run, added to runs.* at the end of the transaction.
    std::vector<std::pair<RunId, std::array<std::int64_t, 3>>> counts;
    auto count = [&](RunId run, int source) {
        if (counts.empty() || counts.back().first != run) {
            auto it = std::find_if(counts.begin(), counts.end(), [&](const auto& c) { return c.first == run; });
            if (it == counts.end()) counts.push_back({run, {0, 0, 0}});
            else std::iter_swap(it, counts.end() - 1);  // keep the current run at the back
        }
        ++counts.back().second[static_cast<std::size_t>(source)];
    };
    RollupBatch cycler_roll(source_defs()[0].channels.size()), daq_roll(source_defs()[1].channels.size());
    auto& c = ws->cycler;
    for (const auto& [run, s] : b.cycler) {
        cycler_roll.add(run, s.t_s, channel_values(s).data());
        c.integer(1, run).real(2, s.t_s).real(3, s.unix_s).real(4, s.voltage_v).real(5, s.current_a);
        c.real(6, s.capacity_ah).real(7, s.energy_wh).real(8, s.soc).integer(9, s.step_id);
        if (s.step_type.empty()) c.null(10); else c.text_static(10, s.step_type);
        c.integer(11, s.cycle);
        if (s.status.empty()) c.null(12); else c.text_static(12, s.status);
        c.step();
        c.reset();
        count(run, 0);
    }
    auto& d = ws->daq;
    for (const auto& [run, s] : b.daq) {
        daq_roll.add(run, s.t_s, channel_values(s).data());
        d.integer(1, run).real(2, s.t_s).real(3, s.unix_s).real(4, s.thermopile_v).real(5, s.surface_c);
        d.real(6, s.t1_c).real(7, s.t2_c).real(8, s.heat_flux_w_per_m2);
        if (s.sequence >= 0) d.integer(9, s.sequence); else d.null(9);
        d.step();
        d.reset();
        count(run, 1);
    }
    auto& h = ws->chamber;
    for (const auto& [run, s] : b.chamber) {
        h.integer(1, run).real(2, s.t_s).real(3, s.unix_s).real(4, s.ambient_c).real(5, s.setpoint_c);
        if (s.running) h.integer(6, *s.running ? 1 : 0); else h.null(6);
        h.integer(7, s.alarm_bits);
        h.step();
        h.reset();
        count(run, 2);
    }
    cycler_roll.write(ws->cycler_rollup);
    daq_roll.write(ws->daq_rollup);
    for (const auto& [run, n] : counts) {
        ws->counts.integer(1, run).integer(2, n[0]).integer(3, n[1]).integer(4, n[2]);
        ws->counts.run();
    }
}

void RunStore::Impl::run_control(Control& op) {
    std::visit(
        [&](auto& o) {
            using T = std::decay_t<decltype(o)>;
            if constexpr (std::is_same_v<T, CreateRunOp>) {
                auto& s = ws->create_run;
                const double created = o.run.created_unix_s.value_or(now_unix_s());
                s.text(1, o.run.program).text(2, o.run.cell).text(3, to_string(o.run.state)).real(4, created);
                if (o.run.state == RunState::running) s.real(5, created); else s.null(5);
                if (o.run.config.is_null()) s.null(6); else s.text(6, o.run.config.dump(-1, ' ', false, json::error_handler_t::replace));
                s.run();
                o.id = sqlite3_last_insert_rowid(wdb.get());
            } else if constexpr (std::is_same_v<T, SetStateOp>) {
                auto& s = ws->set_state;
                s.integer(1, o.run).text(2, to_string(o.state)).text_or_null(3, o.reason).real(4, o.unix_s);
                s.run();
            } else if constexpr (std::is_same_v<T, StepOp>) {
                auto& s = ws->step;
                const auto& st = o.step;
                s.integer(1, o.run).integer(2, st.index).integer(3, st.segment).integer(4, st.step_id);
                s.integer(5, st.cycle).text_or_null(6, st.type).real(7, st.started_t_s).real(8, st.started_unix_s);
                s.real(9, st.ended_t_s).real(10, st.ended_unix_s).real(11, st.capacity_ah).real(12, st.energy_wh);
                s.text_or_null(13, st.end_reason);
                s.run();
            } else if constexpr (std::is_same_v<T, EventOp>) {
                auto& s = ws->event;
                const auto& e = o.event;
                if (e.run_id) s.integer(1, *e.run_id); else s.null(1);
                s.real(2, e.unix_s).real(3, e.t_s).text(4, to_string(e.level)).text(5, e.kind);
                if (e.step) s.integer(6, *e.step); else s.null(6);
                s.text(7, e.message);
                if (e.detail.is_null()) s.null(8); else s.text(8, e.detail.dump(-1, ' ', false, json::error_handler_t::replace));
                s.run();
            } else if constexpr (std::is_same_v<T, FitOp>) {
                auto& s = ws->fit;
                const auto& f = o.fit;
                s.integer(1, f.run_id).integer(2, f.pulse_set).real(3, f.t_s).real(4, f.unix_s).real(5, f.soc);
                s.real(6, f.ocv_v).real(7, f.temperature_c);
                s.real(8, f.discharge.r0_ohm).real(9, f.discharge.r1_ohm).real(10, f.discharge.c1_f);
                s.real(11, f.discharge.r2_ohm).real(12, f.discharge.c2_f);
                s.real(13, f.charge.r0_ohm).real(14, f.charge.r1_ohm).real(15, f.charge.c1_f);
                s.real(16, f.charge.r2_ohm).real(17, f.charge.c2_f);
                s.text_or_null(18, f.method).real(19, f.rms_v);
                if (f.detail.is_null()) s.null(20); else s.text(20, f.detail.dump(-1, ' ', false, json::error_handler_t::replace));
                s.run();
            } else if constexpr (std::is_same_v<T, ParamsOp>) {
                auto& s = ws->params;
                const auto& p = o.params;
                if (p.run_id) s.integer(1, *p.run_id); else s.null(1);
                s.real(2, p.created_unix_s).text_or_null(3, p.cell).text(4, p.params.dump(-1, ' ', false, json::error_handler_t::replace));
                s.run();
            } else if constexpr (std::is_same_v<T, MarkInterruptedOp>) {
                o.ids.clear();
                std::vector<std::pair<RunId, double>> live;
                {
                    auto& s = ws->live_runs;
                    while (s.step()) {
                        const double started = s.col_real(2);
                        live.emplace_back(s.col_int(0), std::isfinite(started) ? started : s.col_real(1));
                    }
                    s.reset();
                }
                for (auto [id, ended] : live) {
                    // Ended at its last sample (index scans on (run_id, t_s)), else when it started.
                    for (Stmt* q : {&ws->last_cycler, &ws->last_daq, &ws->last_chamber}) {
                        q->integer(1, id);
                        if (q->step()) {
                            const double u = q->col_real(0);
                            if (std::isfinite(u)) ended = std::max(ended, u);
                        }
                        q->reset();
                    }
                    ws->interrupt.integer(1, id).text(2, o.reason).real(3, ended);
                    ws->interrupt.run();
                    o.ids.push_back(id);
                }
            } else if constexpr (std::is_same_v<T, FlushOp>) {
                // A barrier: nothing to write.
            }
        },
        op);
}

void RunStore::Impl::fulfil(std::vector<Control>& ops) {
    for (auto& op : ops) {
        if (auto* c = std::get_if<CreateRunOp>(&op)) c->done.set_value(c->id);
        else if (auto* m = std::get_if<MarkInterruptedOp>(&op)) m->done.set_value(m->ids);
        else if (auto* f = std::get_if<FlushOp>(&op)) f->done.set_value();
    }
}

void RunStore::Impl::fail(std::vector<Control>& ops, const StoreError& e) {
    for (auto& op : ops) {
        auto ex = std::make_exception_ptr(e);
        if (auto* c = std::get_if<CreateRunOp>(&op)) c->done.set_exception(ex);
        else if (auto* m = std::get_if<MarkInterruptedOp>(&op)) m->done.set_exception(ex);
        else if (auto* f = std::get_if<FlushOp>(&op)) f->done.set_value();  // flushed = nothing left to wait for
    }
}

StoreFault RunStore::Impl::fault_of(const SqlError& e, std::size_t samples_lost, const char* what) const {
    const auto kind = classify(e.code);
    return {kind, e.code,
            path.string() + ": " + plain_fault(kind) + " while " + what + " (" + e.what() + ")" +
                (samples_lost ? "; " + std::to_string(samples_lost) + " samples lost" : std::string()),
            samples_lost};
}

void RunStore::Impl::write_batch(Batch& b) {
    const auto t0 = std::chrono::steady_clock::now();
    const std::size_t n = b.samples();
    std::optional<StoreFault> fault, control_fault;
    bool controls_done = false;
    retry_unsaved();  // older records first
    try {
        ws->begin.run();
        write_samples(b);
        for (auto& op : b.control) run_control(op);
        ws->commit.run();
        commits.fetch_add(1, std::memory_order_release);
        controls_done = true;
    } catch (const SqlError& e) {
        rollback_if_open();
        fault = fault_of(e, n, "writing samples");
    } catch (const std::exception& e) {  // never let the writer thread die
        rollback_if_open();
        fault = fault_of(SqlError(0, e.what()), n, "writing samples");
    }
    if (fault && !b.control.empty()) {
        // Control records (run state, events) matter more than samples: retry them on their own.
        try {
            ws->begin.run();
            for (auto& op : b.control) run_control(op);
            ws->commit.run();
            commits.fetch_add(1, std::memory_order_release);
            controls_done = true;
        } catch (const std::exception& e) {
            rollback_if_open();
            const auto* sql = dynamic_cast<const SqlError*>(&e);
            control_fault = fault_of(sql ? *sql : SqlError(0, e.what()), 0, "writing run records");
        }
    }
    // Stats and fault reports first, then the waiters (flush, create_run): whoever waited sees the outcome.
    {
        std::lock_guard lk(mu);
        queued_samples -= n;
        stats.last_batch_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        if (fault) {
            ++stats.failed_batches;
            stats.samples_lost += n;
        } else {
            ++stats.batches;
            stats.samples_written += n;
        }
    }
    if (!fault) fault_episode.reset();
    if (fault) report(*fault);
    if (control_fault) report(*control_fault);
    if (std::any_of(b.control.begin(), b.control.end(), [](const Control& op) {
            const auto* f = std::get_if<FlushOp>(&op);
            return f && f->release_memory;
        }))
        sqlite3_db_release_memory(wdb.get());  // after the commit or rollback: no page is pinned
    if (controls_done) fulfil(b.control);
    else if (control_fault) {
        if (transient(control_fault->kind)) retain(b.control);
        fail(b.control, StoreError(control_fault->kind, control_fault->message));
    }
}

void RunStore::Impl::shutdown() {
    {
        std::lock_guard lk(mu);
        if (closed) return;
        closed = true;  // no new writes
        stop = true;
    }
    cv.notify_all();
    if (writer.joinable()) writer.join();  // drains the queue first
    ws.reset();
    {
        std::unique_lock lk(pool_mu);
        pool_closed = true;
        pool_cv.wait(lk, [&] { return idle.size() == readers_open; });  // reads in progress finish
        idle.clear();
        readers.clear();  // each connection's statements, then the connection
        readers_open = 0;
    }
    pool_cv.notify_all();
    wdb.reset();  // last connection: checkpoints the WAL into the database
}

// ---------------------------------------------------------------------------------------------------------
// RunStore: open, close, writes

namespace {
// Records a previous close could not save (Impl::write_sidecar): queued again, before anything else (restart
// recovery included), then the file is renamed *.imported so it is never applied twice.
void import_sidecar(RunStore& store, const fs::path& side) {
    std::error_code ec;
    if (!fs::exists(side, ec)) return;
    std::ifstream in(side);
    std::string line;
    std::size_t n = 0;
    while (std::getline(in, line)) {
        try {
            const json j = json::parse(line);
            const std::string record = j.value("record", "");
            if (record == "event") {
                EventRecord e;
                if (j.contains("run_id") && j["run_id"].is_number_integer()) e.run_id = j["run_id"].get<RunId>();
                e.unix_s = j.value("time_unix_s", 0.0);
                if (j.contains("test_time_s") && j["test_time_s"].is_number()) e.t_s = j["test_time_s"].get<double>();
                e.level = event_level_from_string(j.value("level", "error")).value_or(EventLevel::error);
                e.kind = j.value("kind", "event");
                if (j.contains("step") && j["step"].is_number_integer()) e.step = j["step"].get<int>();
                e.message = j.value("message", "");
                e.detail = j.contains("detail") ? j["detail"] : json(nullptr);
                store.record_event(e);
                ++n;
            } else if (record == "run_state" && j.contains("run_id") && j["run_id"].is_number_integer()) {
                if (const auto st = run_state_from_string(j.value("state", ""))) {
                    store.set_run_state(j["run_id"].get<RunId>(), *st, j.value("reason", ""), j.value("unix_s", 0.0));
                    ++n;
                }
            }
        } catch (const std::exception&) {
            // A line cut short by a crash while writing: skip it.
        }
    }
    if (!store.flush()) return;
    fs::rename(side, fs::path(side.string() + ".imported"), ec);
    spdlog::warn("{}: {} record(s) a previous run of the daemon could not save were imported from {}",
                 store.path().string(), n, side.string());
}
}  // namespace

RunStore::RunStore(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
RunStore::~RunStore() = default;

std::unique_ptr<RunStore> RunStore::open(const fs::path& path, RunStoreOptions options) {
    auto impl = std::make_unique<Impl>();
    impl->path = path;
    impl->opt = std::move(options);
    impl->opt.flush_rows = std::max<std::size_t>(1, impl->opt.flush_rows);
    impl->wdb = open_connection(path, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE, impl->opt.busy_timeout);
    sqlite3* db = impl->wdb.get();
    check_identity(db, path, true);
    try {
        // WAL: readers never block the writer; NORMAL: a commit survives a process crash (kill -9), and a power
        // loss can only lose the last commits, never corrupt the file.
        {
            Stmt s(db, "PRAGMA journal_mode = WAL");
            const std::string mode = s.step() ? s.col_text(0) : std::string();
            if (mode != "wal") open_fail(path, "the file system does not support SQLite's WAL mode (journal mode \"" + mode + "\")");
        }
        exec(db, "PRAGMA synchronous = NORMAL");
        exec(db, "PRAGMA journal_size_limit = 67108864");  // truncate a WAL grown past 64 MiB after checkpoints
        exec(db, "PRAGMA cache_size = -16384");            // 16 MiB for the writer
        if (impl->opt.max_page_count)  // PRAGMA takes no bound parameters; the text is a formatted integer
            exec(db, "PRAGMA max_page_count = " + std::to_string(std::max<std::int64_t>(1, *impl->opt.max_page_count)));
        create_schema(db);
        impl->ws = std::make_unique<WriterStatements>(db);
    } catch (const SqlError& e) {
        const auto kind = classify(e.code);
        std::string why = e.what();
        if (kind == StoreFaultKind::readonly) why = "read-only (" + why + ")";
        else if (kind == StoreFaultKind::corrupt) why = "not an SQLite database or damaged (" + why + ")";
        else if (kind == StoreFaultKind::busy) why = "locked by another process (" + why + ")";
        open_fail(path, why);
    }
    Impl* raw = impl.get();
    impl->writer = std::thread([raw] { raw->writer_main(); });
    const fs::path side = impl->sidecar_path();
    auto store = std::unique_ptr<RunStore>(new RunStore(std::move(impl)));
    import_sidecar(*store, side);
    return store;
}

std::unique_ptr<RunStore> RunStore::open_readonly(const fs::path& path) {
    auto impl = std::make_unique<Impl>();
    impl->path = path;
    impl->readonly = true;
    {
        Conn c = open_connection(path, SQLITE_OPEN_READONLY, impl->opt.busy_timeout);
        check_identity(c.get(), path, false);
    }
    {
        std::lock_guard lk(impl->mu);
        impl->stop = true;  // no writer thread
    }
    return std::unique_ptr<RunStore>(new RunStore(std::move(impl)));
}

void RunStore::close() { impl_->shutdown(); }
const fs::path& RunStore::path() const { return impl_->path; }
bool RunStore::read_only() const { return impl_->readonly; }

RunId RunStore::create_run(const NewRun& run) {
    impl_->check_writable();
    impl_->check_not_writer("create_run");
    std::future<RunId> fut;
    const bool queued = impl_->enqueue_control(
        [&] {
            CreateRunOp op{run, {}, 0};
            fut = op.done.get_future();
            return Control(std::move(op));
        },
        true);
    if (!queued) throw StoreError(StoreFaultKind::closed, impl_->path.string() + ": run store is closed");
    return fut.get();  // rethrows the StoreError of a failed commit
}

void RunStore::set_run_state(RunId run, RunState state, const std::string& reason, std::optional<double> unix_s) {
    impl_->check_writable();
    impl_->enqueue_control([&] { return Control(SetStateOp{run, state, reason, unix_s.value_or(now_unix_s())}); },
                           is_terminal(state));
}

bool RunStore::push(RunId run, const CyclerSample& s) { return push(run, std::span<const CyclerSample>(&s, 1)) == 1; }
bool RunStore::push(RunId run, const DaqSample& s) { return push(run, std::span<const DaqSample>(&s, 1)) == 1; }
bool RunStore::push(RunId run, const ChamberSample& s) { return push(run, std::span<const ChamberSample>(&s, 1)) == 1; }
std::size_t RunStore::push(RunId run, std::span<const CyclerSample> s) {
    return impl_->enqueue_samples(run, s, &Batch::cycler, 0, &StoreStats::cycler_samples_accepted);
}
std::size_t RunStore::push(RunId run, std::span<const DaqSample> s) {
    return impl_->enqueue_samples(run, s, &Batch::daq, 1, &StoreStats::daq_samples_accepted);
}
std::size_t RunStore::push(RunId run, std::span<const ChamberSample> s) {
    return impl_->enqueue_samples(run, s, &Batch::chamber, 2, &StoreStats::chamber_samples_accepted);
}

void RunStore::record_step(RunId run, const StepRecord& step) {
    impl_->check_writable();
    impl_->enqueue_control([&] { return Control(StepOp{run, step}); }, false);
}

void RunStore::record_event(const EventRecord& event) {
    impl_->check_writable();
    EventRecord e = event;
    if (!std::isfinite(e.unix_s) || e.unix_s <= 0.0) e.unix_s = now_unix_s();
    // Errors are written at once: they are what an operator reads after a crash.
    const bool urgent = e.level == EventLevel::error;
    impl_->enqueue_control([&] { return Control(EventOp{std::move(e)}); }, urgent);
}

void RunStore::record_pulse_fit(const PulseFitRecord& fit) {
    impl_->check_writable();
    impl_->enqueue_control([&] { return Control(FitOp{fit}); }, false);
}

void RunStore::record_parameter_set(const ParameterSetRecord& params) {
    impl_->check_writable();
    ParameterSetRecord p = params;
    if (!std::isfinite(p.created_unix_s) || p.created_unix_s <= 0.0) p.created_unix_s = now_unix_s();
    impl_->enqueue_control([&] { return Control(ParamsOp{std::move(p)}); }, false);
}

std::vector<RunId> RunStore::mark_interrupted_runs(const std::string& reason) {
    impl_->check_writable();
    impl_->check_not_writer("mark_interrupted_runs");
    std::future<std::vector<RunId>> fut;
    impl_->enqueue_control(
        [&] {
            MarkInterruptedOp op{reason, {}, {}};
            fut = op.done.get_future();
            return Control(std::move(op));
        },
        true);
    return fut.get();
}

bool RunStore::flush(std::chrono::milliseconds timeout) {
    if (impl_->readonly) return true;
    if (impl_->writer.joinable() && std::this_thread::get_id() == impl_->writer.get_id()) return false;
    std::future<void> fut;
    const bool queued = impl_->enqueue_control(
        [&] {
            FlushOp op;
            fut = op.done.get_future();
            return Control(std::move(op));
        },
        true);
    if (!queued) return true;  // closed: close() already drained everything
    return fut.wait_for(timeout) == std::future_status::ready;
}

std::future<void> RunStore::release_memory() {
    std::future<void> writer_done;
    if (!impl_->readonly)
        impl_->enqueue_control([&] {
            FlushOp op;
            op.release_memory = true;
            writer_done = op.done.get_future();
            return Control(std::move(op));
        }, false);
    {
        std::lock_guard lk(impl_->pool_mu);
        for (StmtCache* conn : impl_->idle) {
            conn->clear();  // the kept statements too: re-prepared by the next run's first reads
            sqlite3_db_release_memory(conn->db());
        }
    }
    if (!writer_done.valid()) {  // read-only or closed: no writer cache to wait for
        std::promise<void> now;
        now.set_value();
        writer_done = now.get_future();
    }
    return writer_done;
}

std::uint64_t RunStore::commit_count() const { return impl_->commits.load(std::memory_order_acquire); }

StoreStats RunStore::stats() const {
    std::lock_guard lk(impl_->mu);
    StoreStats s = impl_->stats;
    s.samples_queued = impl_->queued_samples;
    const double now = Impl::mono_s();
    s.cycler_samples_per_s = impl_->ingest_rates[0].rate(now, static_cast<double>(s.cycler_samples_accepted));
    s.daq_samples_per_s = impl_->ingest_rates[1].rate(now, static_cast<double>(s.daq_samples_accepted));
    s.chamber_samples_per_s = impl_->ingest_rates[2].rate(now, static_cast<double>(s.chamber_samples_accepted));
    return s;
}

}  // namespace cellbench::daemon
