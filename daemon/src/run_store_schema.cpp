// The run store's schema: tables, indexes, rollups and the file's identity.
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
#include "run_store_sql.hpp"

namespace cellbench::daemon::store {

namespace {

constexpr std::int32_t kApplicationId = 0x43427273;  // 'CBrs'
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

std::int64_t pragma_int(sqlite3* db, const char* sql) {
    Stmt s(db, sql);
    return s.step() ? s.col_int(0) : 0;
}

}  // namespace

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

void create_schema(sqlite3* db) {
    exec(db, "BEGIN IMMEDIATE");
    exec_script(db, kSchema);
    for (const auto& d : source_defs())
        if (d.rollup) exec(db, rollup_ddl(d));
    exec(db, "PRAGMA application_id = 1128428147");  // kApplicationId ('CBrs')
    exec(db, "PRAGMA user_version = 1");             // kSchemaVersion
    exec(db, "COMMIT");
    static_assert(kApplicationId == 1128428147 && kSchemaVersion == 1, "keep the PRAGMA literals in step");
}

const char* const kTerminalStates = "('completed','stopped','aborted','interrupted')";

const std::vector<SourceDef>& source_defs() {
    static const std::vector<SourceDef> defs{
        {"cycler", "cycler_samples", "cycler_rollup",
         {"voltage_v", "current_a", "capacity_ah", "energy_wh", "soc", "step_id", "cycle"}},
        {"daq", "daq_samples", "daq_rollup", {"thermopile_v", "surface_c", "t1_c", "t2_c", "heat_flux_w_per_m2"}},
        {"chamber", "chamber_samples", nullptr, {"ambient_c", "setpoint_c", "running", "alarm_bits"}},
    };
    return defs;
}

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

}  // namespace cellbench::daemon::store
