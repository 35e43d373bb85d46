// The run store's read queries: runs, steps, events, fits, parameter sets, sample windows and rows. Each call
// leases a reader connection and reads one committed snapshot (WAL: never blocks the writer).
#include "run_store_impl.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace cellbench::daemon {

using nlohmann::json;
using namespace store;

// The reader pool: a connection of its own per concurrent read, opened on demand, each with its statements.
RunStore::Impl::Lease RunStore::Impl::acquire() const {
    std::unique_lock lk(pool_mu);
    const std::size_t limit = std::max<std::size_t>(1, opt.read_connections);
    pool_cv.wait(lk, [&] { return pool_closed || !idle.empty() || readers_open < limit; });
    if (pool_closed) throw StoreError(StoreFaultKind::closed, path.string() + ": run store is closed");
    if (!idle.empty()) {
        StmtCache* conn = idle.back();
        idle.pop_back();
        return Lease(*this, *conn);
    }
    ++readers_open;
    lk.unlock();
    try {
        const int flags = readonly ? SQLITE_OPEN_READONLY : SQLITE_OPEN_READWRITE;
        Conn c = open_connection(path, flags, opt.busy_timeout);
        if (!readonly) exec(c.get(), "PRAGMA query_only = ON");
        auto cache = std::make_unique<StmtCache>(c.get());
        StmtCache& conn = *cache;
        {
            std::lock_guard relock(pool_mu);
            readers.emplace_back(std::move(c), std::move(cache));
        }
        return Lease(*this, conn);
    } catch (...) {
        std::lock_guard relock(pool_mu);
        --readers_open;
        pool_cv.notify_all();
        throw;
    }
}

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

RunInfo read_run_row(const Stmt& s, bool with_config) {
    RunInfo r;
    r.id = s.col_int(0);
    r.program = s.col_text(1);
    r.cell = s.col_text(2);
    r.state = run_state_from_string(s.col_text(3)).value_or(RunState::interrupted);
    r.created_unix_s = s.col_real(4);
    r.started_unix_s = s.col_opt_real(5);
    r.ended_unix_s = s.col_opt_real(6);
    r.reason = s.col_text(7);
    r.cycler_samples = s.col_int(8);
    r.daq_samples = s.col_int(9);
    r.chamber_samples = s.col_int(10);
    if (with_config) r.config = s.col_json(11);
    return r;
}

constexpr const char* kRunColumns =
    "id, program, cell, state, created_unix_s, started_unix_s, ended_unix_s, reason, cycler_samples, daq_samples, "
    "chamber_samples";

EventRecord read_event_row(const Stmt& s) {
    EventRecord e;
    e.id = s.col_int(0);
    if (!s.is_null(1)) e.run_id = s.col_int(1);
    e.unix_s = s.col_real(2);
    e.t_s = s.col_opt_real(3);
    e.level = event_level_from_string(s.col_text(4)).value_or(EventLevel::info);
    e.kind = s.col_text(5);
    if (!s.is_null(6)) e.step = static_cast<int>(s.col_int(6));
    e.message = s.col_text(7);
    e.detail = s.col_json(8);
    return e;
}

}  // namespace

// -- reads ------------------------------------------------------------------------------------------------

std::vector<RunInfo> RunStore::list_runs(std::size_t limit) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(), std::string("SELECT ") + kRunColumns + " FROM runs ORDER BY id DESC LIMIT ?1");
        s.integer(1, static_cast<std::int64_t>(std::min<std::size_t>(limit, INT64_MAX)));
        std::vector<RunInfo> out;
        while (s.step()) out.push_back(read_run_row(s, false));
        return out;
    });
}

std::optional<RunInfo> RunStore::get_run(RunId run, RunRead what) const {
    auto lease = impl_->acquire();
    const bool with_config = what == RunRead::with_config;
    return guarded_read(impl_->path, [&]() -> std::optional<RunInfo> {
        Stmt s(lease.stmts(), std::string("SELECT ") + kRunColumns + (with_config ? ", config_json" : "") +
                               " FROM runs WHERE id = ?1");
        s.integer(1, run);
        if (!s.step()) return std::nullopt;
        return read_run_row(s, with_config);
    });
}

std::vector<StepRecord> RunStore::steps(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT step_index, segment, step_id, cycle, type, started_t_s, started_unix_s, ended_t_s, ended_unix_s, "
               "capacity_ah, energy_wh, end_reason FROM steps WHERE run_id = ?1 ORDER BY step_index");
        s.integer(1, run);
        std::vector<StepRecord> out;
        while (s.step()) {
            StepRecord r;
            r.index = static_cast<int>(s.col_int(0));
            r.segment = static_cast<int>(s.col_int(1));
            r.step_id = static_cast<int>(s.col_int(2));
            r.cycle = static_cast<int>(s.col_int(3));
            r.type = s.col_text(4);
            r.started_t_s = s.col_real(5);
            r.started_unix_s = s.col_real(6);
            r.ended_t_s = s.col_opt_real(7);
            r.ended_unix_s = s.col_opt_real(8);
            r.capacity_ah = s.col_opt_real(9);
            r.energy_wh = s.col_opt_real(10);
            r.end_reason = s.col_text(11);
            out.push_back(std::move(r));
        }
        return out;
    });
}

std::vector<EventRecord> RunStore::events(RunId run, std::int64_t after_id, std::size_t limit) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT id, run_id, unix_s, t_s, level, kind, step, message, detail_json FROM events "
               "WHERE run_id = ?1 AND id > ?2 ORDER BY id LIMIT ?3");
        s.integer(1, run).integer(2, after_id).integer(3, static_cast<std::int64_t>(std::min<std::size_t>(limit, INT64_MAX)));
        std::vector<EventRecord> out;
        while (s.step()) out.push_back(read_event_row(s));
        return out;
    });
}

std::vector<EventRecord> RunStore::bench_events(std::int64_t after_id, std::size_t limit) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT id, run_id, unix_s, t_s, level, kind, step, message, detail_json FROM events "
               "WHERE run_id IS NULL AND id > ?1 ORDER BY id LIMIT ?2");
        s.integer(1, after_id).integer(2, static_cast<std::int64_t>(std::min<std::size_t>(limit, INT64_MAX)));
        std::vector<EventRecord> out;
        while (s.step()) out.push_back(read_event_row(s));
        return out;
    });
}

std::vector<PulseFitRecord> RunStore::pulse_fits(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT id, run_id, pulse_set, t_s, unix_s, soc, ocv_v, temperature_c, "
               "discharge_r0_ohm, discharge_r1_ohm, discharge_c1_f, discharge_r2_ohm, discharge_c2_f, "
               "charge_r0_ohm, charge_r1_ohm, charge_c1_f, charge_r2_ohm, charge_c2_f, method, rms_v, detail_json "
               "FROM pulse_fits WHERE run_id = ?1 ORDER BY pulse_set");
        s.integer(1, run);
        std::vector<PulseFitRecord> out;
        while (s.step()) {
            PulseFitRecord f;
            f.id = s.col_int(0);
            f.run_id = s.col_int(1);
            f.pulse_set = static_cast<int>(s.col_int(2));
            f.t_s = s.col_real(3);
            f.unix_s = s.col_real(4);
            f.soc = s.col_real(5);
            f.ocv_v = s.col_real(6);
            f.temperature_c = s.col_real(7);
            f.discharge = {s.col_real(8), s.col_real(9), s.col_real(10), s.col_real(11), s.col_real(12)};
            f.charge = {s.col_real(13), s.col_real(14), s.col_real(15), s.col_real(16), s.col_real(17)};
            f.method = s.col_text(18);
            f.rms_v = s.col_real(19);
            f.detail = s.col_json(20);
            f.restore_from_detail();
            out.push_back(std::move(f));
        }
        return out;
    });
}

std::optional<ParameterSetRecord> RunStore::latest_parameter_set(std::optional<RunId> run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&]() -> std::optional<ParameterSetRecord> {
        Stmt s(lease.stmts(),
               "SELECT id, run_id, created_unix_s, cell, params_json FROM parameter_sets "
               "WHERE ?1 IS NULL OR run_id = ?1 ORDER BY id DESC LIMIT 1");
        if (run) s.integer(1, *run); else s.null(1);
        if (!s.step()) return std::nullopt;
        ParameterSetRecord p;
        p.id = s.col_int(0);
        if (!s.is_null(1)) p.run_id = s.col_int(1);
        p.created_unix_s = s.col_real(2);
        p.cell = s.col_text(3);
        p.params = s.col_json(4);
        return p;
    });
}

SampleWindow RunStore::samples(RunId run, std::optional<double> from_s, std::optional<double> to_s,
                               std::size_t max_points) const {
    max_points = std::max<std::size_t>(2, max_points);
    auto lease = impl_->acquire();
    StmtCache& db = lease.stmts();
    return guarded_read(impl_->path, [&] {
        ReadTxn txn(db);
        SampleWindow w;
        w.run_id = run;
        w.max_points = max_points;
        const auto& defs = source_defs();

        // The window: as asked, else from the first to the last sample of any source (index look-ups).
        double first = kInf, last = -kInf;
        if (!from_s || !to_s) {
            for (const auto& d : defs) {
                Stmt a(db, std::string("SELECT t_s FROM ") + d.table + " WHERE run_id = ?1 ORDER BY t_s ASC LIMIT 1");
                a.integer(1, run);
                if (a.step()) first = std::min(first, a.col_real(0));
                Stmt b(db, std::string("SELECT t_s FROM ") + d.table + " WHERE run_id = ?1 ORDER BY t_s DESC LIMIT 1");
                b.integer(1, run);
                if (b.step()) last = std::max(last, b.col_real(0));
            }
        }
        w.from_s = from_s.value_or(first);
        w.to_s = to_s.value_or(last);
        if (!std::isfinite(w.from_s) || !std::isfinite(w.to_s) || w.to_s < w.from_s) return w;  // nothing

        std::vector<std::int64_t> counts;
        for (const auto& d : defs) {
            // Only "more than max_points?" matters: stop counting there (an index range scan of max_points + 1).
            Stmt c(db, std::string("SELECT count(*) FROM (SELECT 1 FROM ") + d.table +
                           " WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 LIMIT ?4)");
            c.integer(1, run).real(2, w.from_s).real(3, w.to_s).integer(4, static_cast<std::int64_t>(max_points) + 1);
            counts.push_back(c.step() ? c.col_int(0) : 0);
        }
        w.decimated = std::any_of(counts.begin(), counts.end(),
                                  [&](std::int64_t n) { return n > static_cast<std::int64_t>(max_points); });
        if (w.decimated) {
            w.bucket_count = std::max<std::size_t>(1, max_points / 2);
            w.bucket_s = (w.to_s - w.from_s) / static_cast<double>(w.bucket_count);
        }

        for (std::size_t k = 0; k < defs.size(); ++k) {
            if (counts[k] == 0) continue;
            const auto& d = defs[k];
            const std::size_t nc = d.channels.size();
            SourceWindow sw;
            sw.source = d.name;
            for (const char* ch : d.channels) sw.channels.emplace_back(ch);
            sw.min.resize(nc);
            sw.max.resize(nc);
            std::string columns = "t_s";
            for (const char* ch : d.channels) columns += std::string(", ") + ch;
            const std::string rows_sql = "SELECT " + columns + " FROM " + d.table +
                                         " WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s";

            if (!w.decimated) {
                Stmt s(db, rows_sql);
                s.integer(1, run).real(2, w.from_s).real(3, w.to_s);
                while (s.step()) {
                    sw.time_s.push_back(s.col_real(0));
                    sw.count.push_back(1);
                    for (std::size_t c = 0; c < nc; ++c) {
                        const double v = s.col_real(static_cast<int>(c + 1));
                        sw.min[c].push_back(v);
                        sw.max[c].push_back(v);
                    }
                }
                w.sources.push_back(std::move(sw));
                continue;
            }

            // Decimated: one pass in time order; a bucket is emitted when the next one starts. NaN never wins a
            // min/max. An item is a raw row (n = 1, min = max) or a rollup second (n rows, its min and max).
            std::int64_t current = -1;
            const auto last_bucket = static_cast<std::int64_t>(w.bucket_count) - 1;
            auto add = [&](double t, std::int64_t n, const Stmt& st, int first_col, bool pairs) {
                std::int64_t b = w.bucket_s > 0.0 ? static_cast<std::int64_t>(std::floor((t - w.from_s) / w.bucket_s)) : 0;
                b = std::clamp<std::int64_t>(b, 0, last_bucket);
                if (b != current) {
                    current = b;
                    sw.bucket.push_back(b);
                    sw.time_s.push_back(w.from_s + static_cast<double>(b) * w.bucket_s);
                    sw.count.push_back(0);
                    for (std::size_t c = 0; c < nc; ++c) {
                        sw.min[c].push_back(kNaN);
                        sw.max[c].push_back(kNaN);
                    }
                }
                sw.count.back() += static_cast<std::uint32_t>(n);
                for (std::size_t c = 0; c < nc; ++c) {
                    const int col = first_col + static_cast<int>(pairs ? 2 * c : c);
                    const double lo_v = st.col_real(col);
                    const double hi_v = pairs ? st.col_real(col + 1) : lo_v;
                    double& lo = sw.min[c].back();
                    double& hi = sw.max[c].back();
                    if (!std::isnan(lo_v) && (std::isnan(lo) || lo_v < lo)) lo = lo_v;
                    if (!std::isnan(hi_v) && (std::isnan(hi) || hi_v > hi)) hi = hi_v;
                }
            };
            auto add_rows = [&](double from, double to, bool to_inclusive) {
                Stmt s(db, "SELECT " + columns + " FROM " + d.table + " WHERE run_id = ?1 AND t_s >= ?2 AND t_s " +
                               (to_inclusive ? "<=" : "<") + " ?3 ORDER BY t_s");
                s.integer(1, run).real(2, from).real(3, to);
                while (s.step()) add(s.col_real(0), 1, s, 1, false);
            };
            // Whole seconds inside the window come from the rollup when a bucket spans several of them (a second
            // is placed by its first sample: at most 1 s off on a bucket of >= kRollupMinBucketS); the partial
            // seconds at the edges come from the rows.
            constexpr double kRollupMinBucketS = 5.0;
            const double first_second = std::ceil(w.from_s);
            const double end_second = std::floor(w.to_s);  // seconds [first_second, end_second) are inside
            if (d.rollup && w.bucket_s >= kRollupMinBucketS && end_second - first_second >= 1.0) {
                add_rows(w.from_s, first_second, false);
                std::string sql = "SELECT t_min, n";
                for (const char* ch : d.channels) sql += std::string(", ") + ch + "_min, " + ch + "_max";
                sql += std::string(" FROM ") + d.rollup + " WHERE run_id = ?1 AND second >= ?2 AND second < ?3 ORDER BY second";
                Stmt r(db, sql);
                r.integer(1, run)
                    .integer(2, static_cast<std::int64_t>(first_second))
                    .integer(3, static_cast<std::int64_t>(end_second));
                while (r.step()) add(r.col_real(0), r.col_int(1), r, 2, true);
                add_rows(end_second, w.to_s, true);
            } else {
                add_rows(w.from_s, w.to_s, true);
            }
            w.sources.push_back(std::move(sw));
        }
        return w;
    });
}

std::vector<CyclerSample> RunStore::cycler_rows(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT t_s, unix_s, voltage_v, current_a, capacity_ah, energy_wh, soc, step_id, cycle, step_type, status "
               "FROM cycler_samples WHERE run_id = ?1 ORDER BY rowid");
        s.integer(1, run);
        std::vector<CyclerSample> out;
        while (s.step()) {
            CyclerSample r;
            r.t_s = s.col_real(0);
            r.unix_s = s.col_real(1);
            r.voltage_v = s.col_real(2);
            r.current_a = s.col_real(3);
            r.capacity_ah = s.col_real(4);
            r.energy_wh = s.col_real(5);
            r.soc = s.col_real(6);
            r.step_id = s.is_null(7) ? 0 : static_cast<int>(s.col_int(7));
            r.cycle = s.is_null(8) ? 0 : static_cast<int>(s.col_int(8));
            r.step_type = s.col_text(9);
            r.status = s.col_text(10);
            out.push_back(std::move(r));
        }
        return out;
    });
}

std::vector<DaqSample> RunStore::daq_rows(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT t_s, unix_s, thermopile_v, surface_c, t1_c, t2_c, heat_flux_w_per_m2, sequence "
               "FROM daq_samples WHERE run_id = ?1 ORDER BY rowid");
        s.integer(1, run);
        std::vector<DaqSample> out;
        while (s.step()) {
            DaqSample r;
            r.t_s = s.col_real(0);
            r.unix_s = s.col_real(1);
            r.thermopile_v = s.col_real(2);
            r.surface_c = s.col_real(3);
            r.t1_c = s.col_real(4);
            r.t2_c = s.col_real(5);
            r.heat_flux_w_per_m2 = s.col_real(6);
            r.sequence = s.is_null(7) ? -1 : s.col_int(7);
            out.push_back(r);
        }
        return out;
    });
}

std::vector<ChamberSample> RunStore::chamber_rows(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(),
               "SELECT t_s, unix_s, ambient_c, setpoint_c, running, alarm_bits FROM chamber_samples "
               "WHERE run_id = ?1 ORDER BY rowid");
        s.integer(1, run);
        std::vector<ChamberSample> out;
        while (s.step()) {
            ChamberSample r;
            r.t_s = s.col_real(0);
            r.unix_s = s.col_real(1);
            r.ambient_c = s.col_real(2);
            r.setpoint_c = s.col_real(3);
            if (!s.is_null(4)) r.running = s.col_int(4) != 0;
            r.alarm_bits = s.is_null(5) ? 0u : static_cast<std::uint32_t>(s.col_int(5));
            out.push_back(r);
        }
        return out;
    });
}

std::string RunStore::integrity_check() const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.stmts(), "PRAGMA integrity_check");
        std::string out;
        while (s.step()) {
            if (!out.empty()) out += '\n';
            out += s.col_text(0);
        }
        return out;
    });
}

}  // namespace cellbench::daemon
