// SQLite run store: see run_store.hpp for the threading, durability and failure model.
//
// Schema (PRAGMA application_id = 'CBrs', user_version = 1):
//
//   runs(id, program, cell, state, created/started/ended_unix_s, reason, config_json,
//        cycler_samples, daq_samples, chamber_samples)      -- counters kept up to date by each commit
//   steps(run_id, step_index, segment, step_id, cycle, type, started/ended t_s and unix_s, capacity_ah,
//         energy_wh, end_reason)                              -- PRIMARY KEY (run_id, step_index)
//   cycler_samples(run_id, t_s, unix_s, voltage_v, current_a, capacity_ah, energy_wh, soc, step_id, step_type,
//                  cycle, status)
//   daq_samples(run_id, t_s, unix_s, thermopile_v, surface_c, t1_c, t2_c, heat_flux_w_per_m2, sequence)
//   chamber_samples(run_id, t_s, unix_s, ambient_c, setpoint_c, running, alarm_bits)
//   events(id, run_id NULL = bench, unix_s, t_s, level, kind, step, message, detail_json)
//   pulse_fits(id, run_id, pulse_set, t_s, unix_s, soc, ocv_v, temperature_c, discharge_* and charge_*
//              (r0_ohm, r1_ohm, c1_f, r2_ohm, c2_f), method, rms_v, detail_json) -- UNIQUE (run_id, pulse_set)
//   parameter_sets(id, run_id, created_unix_s, cell, params_json)
//   cycler_rollup, daq_rollup(run_id, second, n, t_min, t_max, <channel>_min, <channel>_max ...)
//                                                         -- per whole second of t_s; PRIMARY KEY (run_id, second)
//
// Why one wide table per source: the instruments sample all their channels together, at their own rates
// (cycler ~10 Hz, DAQ 10-100 Hz, chamber ~1 Hz). A row per source sample keeps each sample's channels together
// at their native rate with no resampling and no NULL-padding between sources; a narrow (run, channel, t,
// value) layout would store the keys 5-10 times per sample and turn every plot query into a pivot. Rows are
// appended in time order, so the rowid B-tree and the (run_id, t_s) index both grow at their right edge
// (cheap inserts), and a time-window query is one index range scan per source. Text columns (step_type,
// status) repeat a few bytes per row; cheaper than a join for every read. NULL = not measured.
//
// Times: t_s is the daemon's monotonic clock in seconds since the run started (all sources share it, so they
// line up exactly); unix_s is the wall clock, kept per sample because it can be stepped (NTP) and an export
// must still say when each row was taken.
#include "cellbench/daemon/run_store.hpp"
#include "cellbench/daemon/metrics.hpp"

#include <fcntl.h>
#include <sqlite3.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include <algorithm>
#include <array>
#include <limits>
#include <cmath>
#include <condition_variable>
#include <fstream>
#include <future>
#include <mutex>
#include <system_error>
#include <thread>
#include <unordered_map>
#include <variant>

#include <spdlog/spdlog.h>

namespace cellbench::daemon {

using nlohmann::json;
namespace fs = std::filesystem;

namespace {

constexpr std::int32_t kApplicationId = 0x43427273;  // 'CBrs'
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr int kSchemaVersion = 1;

constexpr const char* kSchema = R"SQL(
CREATE TABLE IF NOT EXISTS runs(
  id INTEGER PRIMARY KEY,
  program TEXT NOT NULL,
  cell TEXT NOT NULL,
  state TEXT NOT NULL CHECK (state IN ('starting','running','paused','completed','stopped','aborted','interrupted')),
  created_unix_s REAL NOT NULL,
  started_unix_s REAL,
  ended_unix_s REAL,
  reason TEXT,
  config_json TEXT,
  cycler_samples INTEGER NOT NULL DEFAULT 0,
  daq_samples INTEGER NOT NULL DEFAULT 0,
  chamber_samples INTEGER NOT NULL DEFAULT 0);
CREATE INDEX IF NOT EXISTS runs_state ON runs(state);

CREATE TABLE IF NOT EXISTS steps(
  run_id INTEGER NOT NULL REFERENCES runs(id),
  step_index INTEGER NOT NULL,
  segment INTEGER NOT NULL,
  step_id INTEGER,
  cycle INTEGER,
  type TEXT,
  started_t_s REAL,
  started_unix_s REAL,
  ended_t_s REAL,
  ended_unix_s REAL,
  capacity_ah REAL,
  energy_wh REAL,
  end_reason TEXT,
  PRIMARY KEY (run_id, step_index));

CREATE TABLE IF NOT EXISTS cycler_samples(
  run_id INTEGER NOT NULL REFERENCES runs(id),
  t_s REAL NOT NULL,
  unix_s REAL NOT NULL,
  voltage_v REAL,
  current_a REAL,
  capacity_ah REAL,
  energy_wh REAL,
  soc REAL,
  step_id INTEGER,
  step_type TEXT,
  cycle INTEGER,
  status TEXT);
CREATE INDEX IF NOT EXISTS cycler_samples_run_t ON cycler_samples(run_id, t_s);

CREATE TABLE IF NOT EXISTS daq_samples(
  run_id INTEGER NOT NULL REFERENCES runs(id),
  t_s REAL NOT NULL,
  unix_s REAL NOT NULL,
  thermopile_v REAL,
  surface_c REAL,
  t1_c REAL,
  t2_c REAL,
  heat_flux_w_per_m2 REAL,
  sequence INTEGER);
CREATE INDEX IF NOT EXISTS daq_samples_run_t ON daq_samples(run_id, t_s);

CREATE TABLE IF NOT EXISTS chamber_samples(
  run_id INTEGER NOT NULL REFERENCES runs(id),
  t_s REAL NOT NULL,
  unix_s REAL NOT NULL,
  ambient_c REAL,
  setpoint_c REAL,
  running INTEGER,
  alarm_bits INTEGER);
CREATE INDEX IF NOT EXISTS chamber_samples_run_t ON chamber_samples(run_id, t_s);

CREATE TABLE IF NOT EXISTS events(
  id INTEGER PRIMARY KEY,
  run_id INTEGER REFERENCES runs(id),
  unix_s REAL NOT NULL,
  t_s REAL,
  level TEXT NOT NULL CHECK (level IN ('info','warning','error')),
  kind TEXT NOT NULL,
  step INTEGER,
  message TEXT NOT NULL,
  detail_json TEXT);
CREATE INDEX IF NOT EXISTS events_run ON events(run_id, id);

CREATE TABLE IF NOT EXISTS pulse_fits(
  id INTEGER PRIMARY KEY,
  run_id INTEGER NOT NULL REFERENCES runs(id),
  pulse_set INTEGER NOT NULL,
  t_s REAL,
  unix_s REAL,
  soc REAL,
  ocv_v REAL,
  temperature_c REAL,
  discharge_r0_ohm REAL, discharge_r1_ohm REAL, discharge_c1_f REAL, discharge_r2_ohm REAL, discharge_c2_f REAL,
  charge_r0_ohm REAL, charge_r1_ohm REAL, charge_c1_f REAL, charge_r2_ohm REAL, charge_c2_f REAL,
  method TEXT,
  rms_v REAL,
  detail_json TEXT,
  UNIQUE (run_id, pulse_set));

CREATE TABLE IF NOT EXISTS parameter_sets(
  id INTEGER PRIMARY KEY,
  run_id INTEGER REFERENCES runs(id),
  created_unix_s REAL NOT NULL,
  cell TEXT,
  params_json TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS parameter_sets_run ON parameter_sets(run_id, id);
)SQL";

double now_unix_s() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

// ---------------------------------------------------------------------------------------------------------
// Thin sqlite3 wrappers

struct SqlError : std::runtime_error {
    int code;
    SqlError(int c, const std::string& m) : std::runtime_error(m), code(c) {}
};

// SQLite's message plus the operating system's words when a system call failed ("... (Permission denied)").
std::string sqlite_message(sqlite3* db, int code) {
    std::string msg = db ? sqlite3_errmsg(db) : sqlite3_errstr(code);
    if (db) {
        if (const int err = sqlite3_system_errno(db); err != 0) msg += " (" + std::generic_category().message(err) + ")";
    }
    return msg;
}

[[noreturn]] void throw_sql(sqlite3* db, int code, std::string_view /*what*/) {
    const int ext = db ? sqlite3_extended_errcode(db) : code;
    throw SqlError(ext ? ext : code, sqlite_message(db, code));
}

class Stmt {
public:
    Stmt(sqlite3* db, std::string_view sql, bool persistent = false) : db_(db) {
        const int rc = sqlite3_prepare_v3(db, sql.data(), static_cast<int>(sql.size()),
                                          persistent ? SQLITE_PREPARE_PERSISTENT : 0, &s_, nullptr);
        if (rc != SQLITE_OK) throw_sql(db, rc, "prepare");
    }
    ~Stmt() { sqlite3_finalize(s_); }
    Stmt(const Stmt&) = delete;
    Stmt& operator=(const Stmt&) = delete;

    Stmt& real(int i, double v) {
        check(std::isfinite(v) ? sqlite3_bind_double(s_, i, v) : sqlite3_bind_null(s_, i));
        return *this;
    }
    Stmt& real(int i, const std::optional<double>& v) { return v ? real(i, *v) : null(i); }
    Stmt& integer(int i, std::int64_t v) {
        check(sqlite3_bind_int64(s_, i, v));
        return *this;
    }
    Stmt& integer(int i, const std::optional<std::int64_t>& v) { return v ? integer(i, *v) : null(i); }
    // The text must stay alive until the next bind of this parameter or reset (batches outlive their steps).
    Stmt& text_static(int i, std::string_view v) {
        check(sqlite3_bind_text(s_, i, v.data(), static_cast<int>(v.size()), SQLITE_STATIC));
        return *this;
    }
    Stmt& text(int i, std::string_view v) {
        check(sqlite3_bind_text(s_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT));
        return *this;
    }
    Stmt& text_or_null(int i, std::string_view v) { return v.empty() ? null(i) : text(i, v); }
    Stmt& null(int i) {
        check(sqlite3_bind_null(s_, i));
        return *this;
    }

    // True for a row, false when done; throws SqlError otherwise.
    bool step() {
        const int rc = sqlite3_step(s_);
        if (rc == SQLITE_ROW) return true;
        if (rc == SQLITE_DONE) return false;
        throw_sql(db_, rc, "step");
    }
    void run() {
        while (step()) {
        }
        reset();
    }
    void reset() { sqlite3_reset(s_); }

    [[nodiscard]] bool is_null(int c) const { return sqlite3_column_type(s_, c) == SQLITE_NULL; }
    [[nodiscard]] double col_real(int c) const { return is_null(c) ? kNaN : sqlite3_column_double(s_, c); }
    [[nodiscard]] std::optional<double> col_opt_real(int c) const {
        return is_null(c) ? std::nullopt : std::optional<double>(sqlite3_column_double(s_, c));
    }
    [[nodiscard]] std::int64_t col_int(int c) const { return sqlite3_column_int64(s_, c); }
    [[nodiscard]] std::string col_text(int c) const {
        const auto* p = sqlite3_column_text(s_, c);
        return p ? std::string(reinterpret_cast<const char*>(p), static_cast<std::size_t>(sqlite3_column_bytes(s_, c))) : std::string();
    }
    [[nodiscard]] json col_json(int c) const {
        if (is_null(c)) return nullptr;
        return json::parse(col_text(c), nullptr, false);  // a damaged cell reads as "discarded", never throws
    }

private:
    void check(int rc) {
        if (rc != SQLITE_OK) throw_sql(db_, rc, "bind");
    }
    sqlite3* db_;
    sqlite3_stmt* s_ = nullptr;
};

// Runs a fixed script (schema) statement by statement, each prepared.
void exec_script(sqlite3* db, const char* sql) {
    const char* tail = sql;
    while (tail && *tail) {
        sqlite3_stmt* s = nullptr;
        const int rc = sqlite3_prepare_v2(db, tail, -1, &s, &tail);
        if (rc != SQLITE_OK) throw_sql(db, rc, "prepare");
        if (!s) continue;  // whitespace / comment
        int st;
        while ((st = sqlite3_step(s)) == SQLITE_ROW) {
        }
        sqlite3_finalize(s);
        if (st != SQLITE_DONE) throw_sql(db, st, "exec");
    }
}

void exec(sqlite3* db, std::string_view sql) { Stmt(db, sql).run(); }

StoreFaultKind classify(int code) {
    switch (code & 0xff) {
        case SQLITE_FULL: return StoreFaultKind::disk_full;
        case SQLITE_BUSY:
        case SQLITE_LOCKED: return StoreFaultKind::busy;
        case SQLITE_READONLY: return StoreFaultKind::readonly;
        case SQLITE_IOERR: return StoreFaultKind::io_error;
        case SQLITE_CORRUPT:
        case SQLITE_NOTADB: return StoreFaultKind::corrupt;
        case SQLITE_CANTOPEN: return StoreFaultKind::io_error;
        default: return StoreFaultKind::other;
    }
}

std::string plain_fault(StoreFaultKind kind) {
    switch (kind) {
        case StoreFaultKind::disk_full: return "disk full (or the database size limit reached)";
        case StoreFaultKind::busy: return "database locked by another process";
        case StoreFaultKind::readonly: return "database is read-only";
        case StoreFaultKind::io_error: return "disk I/O error";
        case StoreFaultKind::corrupt: return "database file is damaged";
        case StoreFaultKind::overflow: return "writer queue full";
        case StoreFaultKind::closed: return "run store is closed";
        default: return "database error";
    }
}

// Open-time problems are the user's to fix (a bad --db path): InputError naming the path.
[[noreturn]] void open_fail(const fs::path& path, const std::string& why) {
    throw InputError(path.string() + ": cannot use as the run database: " + why);
}

struct ConnCloser {
    void operator()(sqlite3* db) const { sqlite3_close_v2(db); }
};
using Conn = std::unique_ptr<sqlite3, ConnCloser>;

// SQLite in WAL mode creates PATH-wal and PATH-shm beside the database, so a database opened for writing needs a
// folder it can create files in. Checked by creating (and removing) a probe file, so the message says which
// folder and why (an immutable or read-only folder used to read "No such file or directory").
void check_folder_writable(const fs::path& path) {
    const fs::path parent = path.parent_path().empty() ? fs::path(".") : path.parent_path();
    std::error_code ec;
    if (!fs::is_directory(parent, ec)) return;  // reported by the open with its own message
    const fs::path probe = parent / (".cellbench-write-probe-" + std::to_string(::getpid()));
    const int fd = ::open(probe.c_str(), O_CREAT | O_EXCL | O_WRONLY | O_CLOEXEC, 0600);
    if (fd < 0) {
        const int err = errno;
        if (err == EEXIST) return;  // a leftover probe: the folder took files before
        open_fail(path, "cannot create files in the folder " + parent.string() + " (" + std::strerror(err) +
                            "): SQLite keeps " + path.filename().string() + "-wal and " + path.filename().string() +
                            "-shm beside the database, so its folder must be writable (choose another --db or "
                            "fix the folder's permissions)");
    }
    ::close(fd);
    fs::remove(probe, ec);
}

Conn open_connection(const fs::path& path, int flags, std::chrono::milliseconds busy_timeout) {
    if (flags & SQLITE_OPEN_CREATE) check_folder_writable(path);
    sqlite3* raw = nullptr;
    const int rc = sqlite3_open_v2(path.c_str(), &raw, flags | SQLITE_OPEN_NOMUTEX, nullptr);
    Conn db(raw);
    if (rc != SQLITE_OK) {
        std::string why = sqlite_message(raw, rc);
        std::error_code ec;
        const fs::path parent = path.parent_path().empty() ? fs::path(".") : path.parent_path();
        if (!fs::is_directory(parent, ec)) why = "the folder " + parent.string() + " does not exist";
        else if (fs::is_directory(path, ec)) why += " (it is a folder)";
        else if ((flags & SQLITE_OPEN_CREATE) == 0 && !fs::exists(path, ec)) why += " (no such file)";
        open_fail(path, why);
    }
    sqlite3_extended_result_codes(db.get(), 1);
    sqlite3_busy_timeout(db.get(), static_cast<int>(busy_timeout.count()));
    return db;
}

std::int64_t pragma_int(sqlite3* db, const char* sql) {
    Stmt s(db, sql);
    return s.step() ? s.col_int(0) : 0;
}

// Checks that the file is ours (or empty). Throws InputError.
void check_identity(sqlite3* db, const fs::path& path, bool may_create) {
    try {
        const auto app = pragma_int(db, "PRAGMA application_id");
        const auto version = pragma_int(db, "PRAGMA user_version");
        if (app == 0) {
            const auto objects = pragma_int(db, "SELECT count(*) FROM sqlite_schema");
            if (objects > 0) open_fail(path, "an SQLite database of another application (no cellbench run tables)");
            if (!may_create) open_fail(path, "an empty database (no runs recorded)");
        } else if (app != kApplicationId) {
            open_fail(path, "an SQLite database of another application (application_id " + std::to_string(app) + ")");
        } else if (version > kSchemaVersion) {
            open_fail(path, "written by a newer cellbench (schema " + std::to_string(version) + ", this build reads " +
                                std::to_string(kSchemaVersion) + ")");
        }
    } catch (const SqlError& e) {
        const auto kind = classify(e.code);
        if (kind == StoreFaultKind::corrupt) open_fail(path, "not an SQLite database or damaged (" + std::string(e.what()) + ")");
        open_fail(path, std::string(e.what()));
    }
}

const char* const kTerminalStates = "('completed','stopped','aborted','interrupted')";

// ---------------------------------------------------------------------------------------------------------
// Sources (for the window query and the export)

struct SourceDef {
    const char* name;
    const char* table;
    const char* rollup;                 // 1-second min/max table, or nullptr (chamber: ~1 Hz already)
    std::vector<const char*> channels;  // numeric columns
};

const std::vector<SourceDef>& source_defs() {
    static const std::vector<SourceDef> defs{
        {"cycler", "cycler_samples", "cycler_rollup",
         {"voltage_v", "current_a", "capacity_ah", "energy_wh", "soc", "step_id", "cycle"}},
        {"daq", "daq_samples", "daq_rollup", {"thermopile_v", "surface_c", "t1_c", "t2_c", "heat_flux_w_per_m2"}},
        {"chamber", "chamber_samples", nullptr, {"ambient_c", "setpoint_c", "running", "alarm_bits"}},
    };
    return defs;
}

// Rollups: per run and whole second of t_s, the number of samples, their first/last time and each channel's
// min and max. The writer updates them in the same transaction as the rows they summarise, so they always agree.
// A plot of a long run reads these (100x fewer rows at 100 Hz) and still shows every spike.
std::string rollup_ddl(const SourceDef& d) {
    std::string sql = std::string("CREATE TABLE IF NOT EXISTS ") + d.rollup +
                      "(run_id INTEGER NOT NULL, second INTEGER NOT NULL, n INTEGER NOT NULL, t_min REAL NOT NULL, "
                      "t_max REAL NOT NULL";
    for (const char* c : d.channels) sql += std::string(", ") + c + "_min REAL, " + c + "_max REAL";
    return sql + ", PRIMARY KEY (run_id, second)) WITHOUT ROWID";
}

std::string rollup_upsert(const SourceDef& d) {
    std::string cols = "run_id, second, n, t_min, t_max", vals = "?1, ?2, ?3, ?4, ?5", set;
    int k = 6;
    for (const char* c : d.channels) {
        cols += std::string(", ") + c + "_min, " + c + "_max";
        vals += ", ?" + std::to_string(k) + ", ?" + std::to_string(k + 1);
        k += 2;
        // min()/max() of two values is NULL when either is: fall back to the one that is not.
        for (const char* f : {"min", "max"}) {
            const std::string col = std::string(c) + "_" + f;
            set += ", " + col + " = coalesce(" + f + "(" + col + ", excluded." + col + "), " + col + ", excluded." + col + ")";
        }
    }
    return std::string("INSERT INTO ") + d.rollup + "(" + cols + ") VALUES (" + vals +
           ") ON CONFLICT(run_id, second) DO UPDATE SET n = n + excluded.n, t_min = min(t_min, excluded.t_min), "
           "t_max = max(t_max, excluded.t_max)" + set;
}

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

// Linear interpolation of (t, y) at ascending query times; NaN outside [t.front(), t.back()] and where the
// two bracketing samples are more than max_gap_s apart (the instrument was silent: do not invent data).
std::vector<double> interpolate_with_gaps(const std::vector<double>& t, const std::vector<double>& y,
                                          const std::vector<double>& q, double max_gap_s) {
    std::vector<double> out(q.size(), kNaN);
    if (t.empty()) return out;
    std::size_t j = 0;
    for (std::size_t k = 0; k < q.size(); ++k) {
        const double x = q[k];
        if (!(x >= t.front()) || !(x <= t.back())) continue;
        while (j + 1 < t.size() && t[j + 1] <= x) ++j;
        if (t[j] == x) {
            out[k] = y[j];
            continue;
        }
        if (j + 1 >= t.size()) continue;
        const double dt = t[j + 1] - t[j];
        if (!(dt > 0.0) || dt > max_gap_s) continue;
        const double w = (x - t[j]) / dt;
        out[k] = y[j] + w * (y[j + 1] - y[j]);
    }
    return out;
}

json rc_json(const estimator::RcValues& v) {
    if (!std::isfinite(v.r0_ohm) && !std::isfinite(v.r1_ohm) && !std::isfinite(v.r2_ohm)) return nullptr;
    return {{"r0_ohm", v.r0_ohm}, {"r1_ohm", v.r1_ohm}, {"c1_f", v.c1_f}, {"r2_ohm", v.r2_ohm}, {"c2_f", v.c2_f}};
}

json nullable(double v) { return std::isfinite(v) ? json(v) : json(nullptr); }

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Enumerations

std::string_view to_string(RunState state) {
    switch (state) {
        case RunState::starting: return "starting";
        case RunState::running: return "running";
        case RunState::paused: return "paused";
        case RunState::completed: return "completed";
        case RunState::stopped: return "stopped";
        case RunState::aborted: return "aborted";
        case RunState::interrupted: return "interrupted";
    }
    return "running";
}

std::optional<RunState> run_state_from_string(std::string_view text) {
    for (auto s : {RunState::starting, RunState::running, RunState::paused, RunState::completed, RunState::stopped,
                   RunState::aborted, RunState::interrupted})
        if (text == to_string(s)) return s;
    return std::nullopt;
}

bool is_terminal(RunState state) {
    return state == RunState::completed || state == RunState::stopped || state == RunState::aborted ||
           state == RunState::interrupted;
}

std::string_view to_string(EventLevel level) {
    switch (level) {
        case EventLevel::info: return "info";
        case EventLevel::warning: return "warning";
        case EventLevel::error: return "error";
    }
    return "info";
}

std::optional<EventLevel> event_level_from_string(std::string_view text) {
    for (auto l : {EventLevel::info, EventLevel::warning, EventLevel::error})
        if (text == to_string(l)) return l;
    return std::nullopt;
}

std::string_view to_string(StoreFaultKind kind) {
    switch (kind) {
        case StoreFaultKind::disk_full: return "disk_full";
        case StoreFaultKind::busy: return "busy";
        case StoreFaultKind::readonly: return "readonly";
        case StoreFaultKind::io_error: return "io_error";
        case StoreFaultKind::corrupt: return "corrupt";
        case StoreFaultKind::overflow: return "overflow";
        case StoreFaultKind::closed: return "closed";
        case StoreFaultKind::other: return "other";
    }
    return "other";
}

std::size_t SourceWindow::channel(std::string_view name) const {
    for (std::size_t i = 0; i < channels.size(); ++i)
        if (channels[i] == name) return i;
    return static_cast<std::size_t>(-1);
}

const SourceWindow* SampleWindow::source(std::string_view name) const {
    for (const auto& s : sources)
        if (s.source == name) return &s;
    return nullptr;
}

PulseFitRecord pulse_fit_record(RunId run_id, int pulse_set, double t_s, double unix_s, const estimator::PulseSetFit& fit) {
    PulseFitRecord r;
    r.run_id = run_id;
    r.pulse_set = pulse_set;
    r.t_s = t_s;
    r.unix_s = unix_s;
    r.soc = fit.soc;
    r.ocv_v = fit.ocv_v;
    r.temperature_c = fit.temperature_c;
    r.discharge = estimator::to_rc_values(fit.chosen_discharge());
    r.charge = estimator::to_rc_values(fit.chosen_charge());
    r.method = estimator::to_string(fit.chosen);
    r.rms_v = fit.chosen == estimator::PulseSetFit::Method::Joint ? fit.joint_rms_v : fit.thesis_rms_v;
    auto method_json = [](const estimator::Rc2Params<double>& d, const estimator::Rc2Params<double>& c, double rms, bool at_bound) {
        return json{{"discharge", rc_json(estimator::to_rc_values(d))},
                    {"charge", rc_json(estimator::to_rc_values(c))},
                    {"rms_v", nullable(rms)},
                    {"at_bound", at_bound}};
    };
    r.detail = {
        {"thesis", method_json(fit.thesis_discharge, fit.thesis_charge, fit.thesis_rms_v, fit.thesis_at_bound)},
        {"joint", method_json(fit.joint_discharge, fit.joint_charge, fit.joint_rms_v, fit.joint_at_bound)},
        {"joint_fit_rms_v", nullable(fit.joint_fit_rms_v)},
        {"joint_converged", fit.joint_converged},
        {"joint_ocv_offset_v", nullable(fit.joint_ocv_offset_v)},
        {"r0_steps", {{"ab_ohm", nullable(fit.r0.ab_ohm)}, {"cd_ohm", nullable(fit.r0.cd_ohm)},
                      {"ef_ohm", nullable(fit.r0.ef_ohm)}, {"gh_ohm", nullable(fit.r0.gh_ohm)},
                      {"discharge_sampling_corrected_ohm", nullable(fit.r0.discharge_corrected_ohm)},
                      {"charge_sampling_corrected_ohm", nullable(fit.r0.charge_corrected_ohm)}}},
        {"rows", {fit.begin, fit.end}},
        {"warnings", fit.warnings},
    };
    return r;
}

// ---------------------------------------------------------------------------------------------------------
// Implementation

namespace {

struct CreateRunOp {
    NewRun run;
    std::promise<RunId> done;
    RunId id = 0;
};
struct SetStateOp {
    RunId run;
    RunState state;
    std::string reason;
    double unix_s;
};
struct StepOp {
    RunId run;
    StepRecord step;
};
struct EventOp {
    EventRecord event;
};
struct FitOp {
    PulseFitRecord fit;
};
struct ParamsOp {
    ParameterSetRecord params;
};
struct MarkInterruptedOp {
    std::string reason;
    std::promise<std::vector<RunId>> done;
    std::vector<RunId> ids;
};
struct FlushOp {
    std::promise<void> done;
};
using Control = std::variant<CreateRunOp, SetStateOp, StepOp, EventOp, FitOp, ParamsOp, MarkInterruptedOp, FlushOp>;

struct Batch {
    std::vector<std::pair<RunId, CyclerSample>> cycler;
    std::vector<std::pair<RunId, DaqSample>> daq;
    std::vector<std::pair<RunId, ChamberSample>> chamber;
    std::vector<Control> control;

    [[nodiscard]] std::size_t samples() const { return cycler.size() + daq.size() + chamber.size(); }
    [[nodiscard]] bool empty() const { return samples() == 0 && control.empty(); }
    void clear() {
        cycler.clear();
        daq.clear();
        chamber.clear();
        control.clear();
    }
};

// Prepared statements of the writer connection (prepared once, reused for every row).
struct WriterStatements {
    Stmt begin, commit, rollback;
    Stmt cycler, daq, chamber, counts, cycler_rollup, daq_rollup;
    Stmt create_run, set_state, step, event, fit, params;
    Stmt live_runs, last_cycler, last_daq, last_chamber, interrupt;

    explicit WriterStatements(sqlite3* db)
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
};

}  // namespace

struct RunStore::Impl {
    fs::path path;
    RunStoreOptions opt;
    bool readonly = false;

    // Writer connection: used by the constructor, then only by the writer thread.
    Conn wdb;
    std::unique_ptr<WriterStatements> ws;
    std::thread writer;

    // Queue (guarded by mu).
    mutable std::mutex mu;
    std::condition_variable cv;
    Batch pending;
    std::size_t queued_samples = 0;  // pending + being written
    std::chrono::steady_clock::time_point first_pending{};
    bool urgent = false;
    bool stop = false;
    bool closed = false;
    std::uint64_t dropped_unreported = 0;
    StoreStats stats;
    // Control records (run states, steps, events, fits, parameter sets) whose transaction failed on a
    // transient fault (disk full, locked, I/O error): kept and retried before every batch and every
    // kUnsavedRetry, so the abort event written while the disk was full lands once the database is writable
    // again. What is still unsaved at close goes to the sidecar DB.unsaved.jsonl (imported by the next open).
    // Writer thread only. The kind of the fault last reported: a fault of the same kind is reported once per
    // episode (until a commit succeeds), so a full disk does not turn every retry into another event.
    static constexpr std::chrono::milliseconds kUnsavedRetry{1000};
    static constexpr std::size_t kMaxUnsaved = 100000;
    std::vector<Control> unsaved;
    std::optional<StoreFaultKind> fault_episode;
    // Ingestion rate per source (cycler, daq, chamber) for GET /metrics; guarded by mu.
    std::array<metrics::RateMeter, 3> ingest_rates{};
    static double mono_s() {
        return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
    }

    // Reader pool.
    mutable std::mutex pool_mu;
    mutable std::condition_variable pool_cv;
    mutable std::vector<sqlite3*> idle;
    mutable std::size_t readers_open = 0;
    mutable bool pool_closed = false;

    ~Impl() { shutdown(); }

    // -- queue --------------------------------------------------------------------------------------------
    // Appends under the lock; wakes the writer when the batch becomes due.
    template <class F>
    bool enqueue_control(F&& make_op, bool wake) {
        std::lock_guard lk(mu);
        if (closed) return false;
        if (pending.empty()) first_pending = std::chrono::steady_clock::now();
        pending.control.emplace_back(make_op());
        if (wake) urgent = true;
        cv.notify_one();
        return true;
    }

    template <class Sample>
    std::size_t enqueue_samples(RunId run, std::span<const Sample> samples,
                                std::vector<std::pair<RunId, Sample>> Batch::*queue, std::size_t source,
                                std::uint64_t StoreStats::*accepted_count) {
        std::lock_guard lk(mu);
        if (closed || readonly) return 0;
        ingest_rates[source].observe(mono_s(), static_cast<double>(stats.*accepted_count));
        const bool was_empty = pending.empty();
        std::size_t accepted = 0;
        for (const auto& s : samples) {
            // t_s and unix_s are NOT NULL: a sample without a time would fail its whole batch.
            if (!std::isfinite(s.t_s) || !std::isfinite(s.unix_s)) {
                ++stats.samples_dropped;
                continue;
            }
            if (queued_samples >= opt.queue_capacity_samples) {
                ++stats.samples_dropped;
                ++dropped_unreported;
                continue;
            }
            (pending.*queue).emplace_back(run, s);
            ++queued_samples;
            ++accepted;
        }
        stats.*accepted_count += accepted;
        if (was_empty && !pending.empty()) {
            first_pending = std::chrono::steady_clock::now();
            cv.notify_one();
        } else if (pending.samples() >= opt.flush_rows) {
            cv.notify_one();
        }
        return accepted;
    }

    // -- writer thread --------------------------------------------------------------------------------------
    void writer_main() {
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
            writing.clear();
            lk.lock();
        }
        lk.unlock();
        if (!unsaved.empty()) write_sidecar();
    }

    [[nodiscard]] fs::path sidecar_path() const { return fs::path(path.string() + ".unsaved.jsonl"); }

    static bool transient(StoreFaultKind k) {
        return k == StoreFaultKind::disk_full || k == StoreFaultKind::busy || k == StoreFaultKind::io_error ||
               k == StoreFaultKind::readonly;
    }
    // Keeps the batch's records that matter after a failed retry (waiters are failed by the caller).
    void retain(std::vector<Control>& ops) {
        for (auto& op : ops) {
            const bool keep = std::holds_alternative<SetStateOp>(op) || std::holds_alternative<StepOp>(op) ||
                              std::holds_alternative<EventOp>(op) || std::holds_alternative<FitOp>(op) ||
                              std::holds_alternative<ParamsOp>(op);
            if (keep && unsaved.size() < kMaxUnsaved) unsaved.push_back(std::move(op));
        }
    }
    // One transaction with everything unsaved; true when it committed (or nothing was waiting).
    bool retry_unsaved() {
        if (unsaved.empty()) return true;
        try {
            ws->begin.run();
            for (auto& op : unsaved) run_control(op);
            ws->commit.run();
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
    void write_sidecar() {
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

    void report(const StoreFault& f) {
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

    void rollback_if_open() {
        if (sqlite3_get_autocommit(wdb.get()) == 0) {
            try {
                ws->rollback.run();
            } catch (const SqlError&) {
                ws->rollback.reset();
            }
        }
    }

    void write_samples(const Batch& b) {
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

    void run_control(Control& op) {
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

    static void fulfil(std::vector<Control>& ops) {
        for (auto& op : ops) {
            if (auto* c = std::get_if<CreateRunOp>(&op)) c->done.set_value(c->id);
            else if (auto* m = std::get_if<MarkInterruptedOp>(&op)) m->done.set_value(m->ids);
            else if (auto* f = std::get_if<FlushOp>(&op)) f->done.set_value();
        }
    }

    static void fail(std::vector<Control>& ops, const StoreError& e) {
        for (auto& op : ops) {
            auto ex = std::make_exception_ptr(e);
            if (auto* c = std::get_if<CreateRunOp>(&op)) c->done.set_exception(ex);
            else if (auto* m = std::get_if<MarkInterruptedOp>(&op)) m->done.set_exception(ex);
            else if (auto* f = std::get_if<FlushOp>(&op)) f->done.set_value();  // flushed = nothing left to wait for
        }
    }

    StoreFault fault_of(const SqlError& e, std::size_t samples_lost, const char* what) const {
        const auto kind = classify(e.code);
        return {kind, e.code,
                path.string() + ": " + plain_fault(kind) + " while " + what + " (" + e.what() + ")" +
                    (samples_lost ? "; " + std::to_string(samples_lost) + " samples lost" : std::string()),
                samples_lost};
    }

    void write_batch(Batch& b) {
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
        if (controls_done) fulfil(b.control);
        else if (control_fault) {
            if (transient(control_fault->kind)) retain(b.control);
            fail(b.control, StoreError(control_fault->kind, control_fault->message));
        }
    }

    // -- lifecycle ------------------------------------------------------------------------------------------
    void shutdown() {
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
            for (sqlite3* db : idle) sqlite3_close_v2(db);
            idle.clear();
            readers_open = 0;
        }
        pool_cv.notify_all();
        wdb.reset();  // last connection: checkpoints the WAL into the database
    }

    // -- reader pool ----------------------------------------------------------------------------------------
    class Lease {
    public:
        Lease(const Impl& impl, sqlite3* db) : impl_(impl), db_(db) {}
        ~Lease() { impl_.release(db_); }
        Lease(const Lease&) = delete;
        Lease& operator=(const Lease&) = delete;
        [[nodiscard]] sqlite3* db() const { return db_; }

    private:
        const Impl& impl_;
        sqlite3* db_;
    };

    [[nodiscard]] Lease acquire() const {
        std::unique_lock lk(pool_mu);
        const std::size_t limit = std::max<std::size_t>(1, opt.read_connections);
        pool_cv.wait(lk, [&] { return pool_closed || !idle.empty() || readers_open < limit; });
        if (pool_closed) throw StoreError(StoreFaultKind::closed, path.string() + ": run store is closed");
        if (!idle.empty()) {
            sqlite3* db = idle.back();
            idle.pop_back();
            return Lease(*this, db);
        }
        ++readers_open;
        lk.unlock();
        try {
            const int flags = readonly ? SQLITE_OPEN_READONLY : SQLITE_OPEN_READWRITE;
            Conn c = open_connection(path, flags, opt.busy_timeout);
            if (!readonly) exec(c.get(), "PRAGMA query_only = ON");
            return Lease(*this, c.release());
        } catch (...) {
            std::lock_guard relock(pool_mu);
            --readers_open;
            pool_cv.notify_all();
            throw;
        }
    }

    void release(sqlite3* db) const {
        {
            std::lock_guard lk(pool_mu);
            idle.push_back(db);
        }
        pool_cv.notify_all();
    }

    // The synchronous calls wait for the writer; from the writer itself (an on_fault handler) they never return.
    void check_not_writer(const char* what) const {
        if (writer.joinable() && std::this_thread::get_id() == writer.get_id())
            throw StoreError(StoreFaultKind::other, std::string(what) + " called from the run store's writer thread");
    }

    void check_writable() const {
        if (readonly) throw StoreError(StoreFaultKind::readonly, path.string() + ": run store opened read-only");
        std::lock_guard lk(mu);
        if (closed) throw StoreError(StoreFaultKind::closed, path.string() + ": run store is closed");
    }
};

namespace {

// One read transaction: every statement inside sees the same committed snapshot.
class ReadTxn {
public:
    explicit ReadTxn(sqlite3* db) : db_(db) { exec(db_, "BEGIN"); }
    ~ReadTxn() {
        try {
            exec(db_, "COMMIT");
        } catch (...) {
        }
    }

private:
    sqlite3* db_;
};

// Read errors are not the caller's input: surface them as StoreError with SQLite's words.
template <class F>
auto guarded_read(const fs::path& path, F&& f) {
    try {
        return f();
    } catch (const SqlError& e) {
        const auto kind = classify(e.code);
        throw StoreError(kind, path.string() + ": " + plain_fault(kind) + " while reading (" + e.what() + ")");
    }
}

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

// ---------------------------------------------------------------------------------------------------------
// RunStore

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
        exec(db, "BEGIN IMMEDIATE");
        exec_script(db, kSchema);
        for (const auto& d : source_defs())
            if (d.rollup) exec(db, rollup_ddl(d));
        exec(db, "PRAGMA application_id = 1128428147");  // kApplicationId ('CBrs')
        exec(db, "PRAGMA user_version = 1");             // kSchemaVersion
        exec(db, "COMMIT");
        impl->ws = std::make_unique<WriterStatements>(db);
    } catch (const SqlError& e) {
        const auto kind = classify(e.code);
        std::string why = e.what();
        if (kind == StoreFaultKind::readonly) why = "read-only (" + why + ")";
        else if (kind == StoreFaultKind::corrupt) why = "not an SQLite database or damaged (" + why + ")";
        else if (kind == StoreFaultKind::busy) why = "locked by another process (" + why + ")";
        open_fail(path, why);
    }
    static_assert(kApplicationId == 1128428147 && kSchemaVersion == 1, "keep the PRAGMA literals in step");
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

// -- reads ------------------------------------------------------------------------------------------------

std::vector<RunInfo> RunStore::list_runs(std::size_t limit) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.db(), std::string("SELECT ") + kRunColumns + " FROM runs ORDER BY id DESC LIMIT ?1");
        s.integer(1, static_cast<std::int64_t>(std::min<std::size_t>(limit, INT64_MAX)));
        std::vector<RunInfo> out;
        while (s.step()) out.push_back(read_run_row(s, false));
        return out;
    });
}

std::optional<RunInfo> RunStore::get_run(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&]() -> std::optional<RunInfo> {
        Stmt s(lease.db(), std::string("SELECT ") + kRunColumns + ", config_json FROM runs WHERE id = ?1");
        s.integer(1, run);
        if (!s.step()) return std::nullopt;
        return read_run_row(s, true);
    });
}

std::vector<StepRecord> RunStore::steps(RunId run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.db(),
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
        Stmt s(lease.db(),
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
        Stmt s(lease.db(),
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
        Stmt s(lease.db(),
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
            out.push_back(std::move(f));
        }
        return out;
    });
}

std::optional<ParameterSetRecord> RunStore::latest_parameter_set(std::optional<RunId> run) const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&]() -> std::optional<ParameterSetRecord> {
        Stmt s(lease.db(),
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
    sqlite3* db = lease.db();
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
        Stmt s(lease.db(),
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
        Stmt s(lease.db(),
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
        Stmt s(lease.db(),
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

Recording RunStore::export_recording(RunId run, std::optional<double> from_s, std::optional<double> to_s,
                                     double max_gap_s) const {
    auto lease = impl_->acquire();
    sqlite3* db = lease.db();
    return guarded_read(impl_->path, [&] {
        ReadTxn txn(db);
        Recording rec;
        rec.source = impl_->path.filename().string() + " run " + std::to_string(run);
        // (Infinite bounds would bind as NULL; use finite sentinels.)
        const double lo = from_s && std::isfinite(*from_s) ? *from_s : -1e300;
        const double hi = to_s && std::isfinite(*to_s) ? *to_s : 1e300;

        Stmt c(db,
               "SELECT t_s, unix_s, voltage_v, current_a, step_id, cycle, step_type FROM cycler_samples "
               "WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s");
        c.integer(1, run).real(2, lo).real(3, hi);
        bool any_type = false;
        while (c.step()) {
            rec.time_s.push_back(c.col_real(0));
            rec.unix_time_s.push_back(c.col_real(1));
            rec.voltage_v.push_back(c.col_real(2));
            rec.current_a.push_back(c.col_real(3));
            rec.step_count.push_back(c.is_null(4) ? kNaN : static_cast<double>(c.col_int(4)));
            rec.cycle_count.push_back(c.is_null(5) ? kNaN : static_cast<double>(c.col_int(5)));
            rec.step_type.push_back(c.col_text(6));
            any_type = any_type || !rec.step_type.back().empty();
        }
        if (!any_type) rec.step_type.clear();
        if (rec.empty()) {
            rec.unix_time_s.clear();
            rec.step_count.clear();
            rec.cycle_count.clear();
            return rec;
        }

        // DAQ / chamber rows around the cycler's span (a margin so the edge rows can interpolate).
        const double a = rec.time_s.front() - max_gap_s;
        const double b = rec.time_s.back() + max_gap_s;
        auto read_source = [&](const char* sql, std::size_t channels, std::vector<double>& t,
                               std::vector<std::vector<double>>& ys) {
            Stmt s(db, sql);
            s.integer(1, run).real(2, a).real(3, b);
            ys.assign(channels, {});
            while (s.step()) {
                t.push_back(s.col_real(0));
                for (std::size_t k = 0; k < channels; ++k) ys[k].push_back(s.col_real(static_cast<int>(k + 1)));
            }
        };
        std::vector<double> td;
        std::vector<std::vector<double>> yd;
        read_source("SELECT t_s, surface_c, t1_c, t2_c, heat_flux_w_per_m2 FROM daq_samples "
                    "WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s",
                    4, td, yd);
        if (!td.empty()) {
            rec.surface_c = interpolate_with_gaps(td, yd[0], rec.time_s, max_gap_s);
            rec.t1_c = interpolate_with_gaps(td, yd[1], rec.time_s, max_gap_s);
            rec.t2_c = interpolate_with_gaps(td, yd[2], rec.time_s, max_gap_s);
            rec.heat_flux_w_per_m2 = interpolate_with_gaps(td, yd[3], rec.time_s, max_gap_s);
            // A channel the layout does not carry (all NULL) is "not measured", not a column of NaN.
            for (auto* ch : {&rec.surface_c, &rec.t1_c, &rec.t2_c, &rec.heat_flux_w_per_m2})
                if (!Recording::has_values(*ch)) ch->clear();
        }
        std::vector<double> tc;
        std::vector<std::vector<double>> yc;
        read_source("SELECT t_s, ambient_c FROM chamber_samples WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s",
                    1, tc, yc);
        if (!tc.empty()) {
            rec.ambient_c = interpolate_with_gaps(tc, yc[0], rec.time_s, max_gap_s);
            if (!Recording::has_values(rec.ambient_c)) rec.ambient_c.clear();
        }
        return rec;
    });
}

std::string RunStore::integrity_check() const {
    auto lease = impl_->acquire();
    return guarded_read(impl_->path, [&] {
        Stmt s(lease.db(), "PRAGMA integrity_check");
        std::string out;
        while (s.step()) {
            if (!out.empty()) out += '\n';
            out += s.col_text(0);
        }
        return out;
    });
}

// ---------------------------------------------------------------------------------------------------------
// JSON

json to_json(const RunInfo& r) {
    json j = {{"id", r.id},
              {"program", r.program},
              {"cell", r.cell},
              {"state", std::string(to_string(r.state))},
              {"created_unix_s", r.created_unix_s},
              {"started_unix_s", r.started_unix_s ? json(*r.started_unix_s) : json(nullptr)},
              {"ended_unix_s", r.ended_unix_s ? json(*r.ended_unix_s) : json(nullptr)},
              {"reason", r.reason.empty() ? json(nullptr) : json(r.reason)},
              {"samples", r.cycler_samples + r.daq_samples + r.chamber_samples},
              {"samples_by_source", {{"cycler", r.cycler_samples}, {"daq", r.daq_samples}, {"chamber", r.chamber_samples}}}};
    if (!r.config.is_null()) j["config"] = r.config;
    return j;
}

json to_json(const EventRecord& e) {
    return {{"id", e.id},
            {"run_id", e.run_id ? json(*e.run_id) : json(nullptr)},
            {"time_unix_s", e.unix_s},
            {"test_time_s", e.t_s ? json(*e.t_s) : json(nullptr)},
            {"level", std::string(to_string(e.level))},
            {"kind", e.kind},
            {"step", e.step ? json(*e.step) : json(nullptr)},
            {"message", e.message},
            {"detail", e.detail}};
}

json to_json(const PulseFitRecord& f) {
    return {{"pulse_set", f.pulse_set},
            {"test_time_s", nullable(f.t_s)},
            {"time_unix_s", nullable(f.unix_s)},
            {"soc", nullable(f.soc)},
            {"ocv_v", nullable(f.ocv_v)},
            {"temperature_c", nullable(f.temperature_c)},
            {"discharge", rc_json(f.discharge)},
            {"charge", rc_json(f.charge)},
            {"method", f.method},
            {"rms_v", nullable(f.rms_v)}};
}

json to_json(const SampleWindow& w) {
    json sources = json::object();
    for (const auto& s : w.sources) {
        json series = json::object();
        for (std::size_t c = 0; c < s.channels.size(); ++c) {
            auto arr = [](const std::vector<double>& v) {
                json a = json::array();
                for (double x : v) a.push_back(nullable(x));
                return a;
            };
            if (w.decimated) series[s.channels[c]] = {{"min", arr(s.min[c])}, {"max", arr(s.max[c])}};
            else series[s.channels[c]] = arr(s.min[c]);
        }
        json o = {{"time_s", s.time_s}, {"series", std::move(series)}};
        if (w.decimated) {
            o["bucket"] = s.bucket;
            o["count"] = s.count;
        }
        sources[s.source] = std::move(o);
    }
    return {{"run_id", w.run_id},
            {"from_s", nullable(w.from_s)},
            {"to_s", nullable(w.to_s)},
            {"max_points", w.max_points},
            {"decimated", w.decimated},
            {"bucket_s", w.decimated ? json(w.bucket_s) : json(nullptr)},
            {"sources", std::move(sources)}};
}

}  // namespace cellbench::daemon
