#pragma once
// The run store: every run of the bench in one SQLite file (sqlite3 C API, WAL, synchronous=NORMAL, SQL only
// through prepared statements). Schema: see the top of run_store_schema.cpp.
//
// Writes never touch the disk on the caller's thread. push()/record_*() append to a bounded in-memory queue;
// one writer thread commits the queue in a transaction at least every flush_period (200 ms by default) or as
// soon as flush_rows samples are waiting. So `kill -9` loses at most what was queued since the last commit
// (about flush_period of samples), and WAL keeps the file sound at any instant. create_run(),
// mark_interrupted_runs() and flush() wait for their commit.
//
// Overflow policy: when queue_capacity_samples samples are waiting (the disk cannot keep up), new SAMPLES are
// refused (push returns false), counted in stats().samples_dropped and reported once per episode through
// on_fault (kind overflow). Control records (runs, steps, events, fits, parameter sets) are always queued:
// they are few, and losing an alarm would be worse than a little memory.
//
// Write failures (disk full, database locked by another process beyond busy_timeout, read-only file, I/O
// error, corruption) never throw on the caller's thread and never crash: the failed transaction is rolled back,
// its samples are counted as lost, its control records are retried once on their own, and on_fault is called
// (on the writer thread) with the kind and SQLite's message so the daemon can abort the run with a clear
// event. The store keeps accepting writes afterwards (a freed disk recovers).
//
// Reads run on their own connections (a small pool), each query in one read transaction: in WAL mode a
// reader sees the last committed snapshot and never blocks the writer, nor is blocked by it.
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <future>
#include <memory>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/pulse_fit.hpp"

namespace cellbench::daemon {

using RunId = std::int64_t;

// ---------------------------------------------------------------------------------------------------------
// Records

// starting/running/paused are live; the others are terminal (the first terminal state written wins).
// interrupted = the daemon died with the run live (set at restart by mark_interrupted_runs()).
enum class RunState { starting, running, paused, completed, stopped, aborted, interrupted };
std::string_view to_string(RunState state);
std::optional<RunState> run_state_from_string(std::string_view text);
bool is_terminal(RunState state);

struct NewRun {
    std::string program;                // program name ("hppc")
    std::string cell;                   // cell name ("p45b")
    nlohmann::json config;              // what the run was started with (expanded program, cell, bench)
    RunState state = RunState::running;
    std::optional<double> created_unix_s;  // default: now
};

struct RunInfo {
    RunId id = 0;
    std::string program, cell;
    RunState state = RunState::running;
    double created_unix_s = 0.0;
    std::optional<double> started_unix_s, ended_unix_s;
    std::string reason;                 // why it ended (abort reason, "stopped by operator", ...), may be empty
    std::int64_t cycler_samples = 0, daq_samples = 0, chamber_samples = 0;  // committed rows
    nlohmann::json config;              // as given to create_run (only filled by get_run with RunRead::with_config)
};

// Times: t_s = seconds on the daemon's monotonic clock since the run started (one clock for every source);
// unix_s = wall clock (UTC) when the sample was taken. NaN = not measured (stored as NULL).

// The parallel group as one channel (sums / mean of the members). Current + = charge (BDF).
struct CyclerSample {
    double t_s = 0.0, unix_s = 0.0;
    double voltage_v = kNaN, current_a = kNaN;
    double capacity_ah = kNaN, energy_wh = kNaN;  // as the tester counts them (step capacity)
    double soc = kNaN;                            // the daemon's Coulomb-counted estimate, 0..1
    int step_id = 0;                              // the tester's step number (1-based in its step list)
    int cycle = 0;
    std::string step_type;                        // the tester's word ("rest", "cc", "dc", "cv", ...)
    std::string status;                           // "working", "stop", "finish", "protect", "pause", ...
};

struct DaqSample {
    double t_s = 0.0, unix_s = 0.0;
    double thermopile_v = kNaN;        // raw heat flux sensor output
    double surface_c = kNaN;           // Type-T inside the heat flux sensor
    double t1_c = kNaN, t2_c = kNaN;   // Type-K at the positive / negative terminal
    double heat_flux_w_per_m2 = kNaN;  // + = leaving the cell (sensitivity-corrected)
    std::int64_t sequence = -1;        // DAQ sample counter (unwrapped); -1 = unknown
};

struct ChamberSample {
    double t_s = 0.0, unix_s = 0.0;
    double ambient_c = kNaN;           // process value: chamber air
    double setpoint_c = kNaN;
    std::optional<bool> running;       // run/stop register; nullopt = not readable
    std::uint32_t alarm_bits = 0;      // raw alarm word
};

// One execution of one tester step (a step inside a loop runs many times: one record each).
struct StepRecord {
    int index = 0;                     // 1-based running number within the run (key)
    int segment = 0;                   // program segment (0-based)
    int step_id = 0;                   // the tester's step number
    int cycle = 0;
    std::string type;                  // StepType word ("cc_discharge", ...)
    double started_t_s = 0.0, started_unix_s = 0.0;
    std::optional<double> ended_t_s, ended_unix_s;
    std::optional<double> capacity_ah, energy_wh;
    std::string end_reason;            // "time", "voltage", "current", "capacity", "stopped", ...
};

enum class EventLevel { info, warning, error };
std::string_view to_string(EventLevel level);
std::optional<EventLevel> event_level_from_string(std::string_view text);

struct EventRecord {
    std::int64_t id = 0;               // assigned by the store (increasing)
    std::optional<RunId> run_id;       // nullopt: bench-level (no run)
    double unix_s = 0.0;
    std::optional<double> t_s;         // test time, when in a run
    EventLevel level = EventLevel::info;
    std::string kind;                  // "operator", "alarm", "fault", "recovery", "instrument", "step", ...
    std::optional<int> step;           // step index (StepRecord::index) when it belongs to a step
    std::string message;               // plain words
    nlohmann::json detail;             // null or any JSON
};

// One completed HPPC pulse set.
struct PulseFitRecord {
    std::int64_t id = 0;
    RunId run_id = 0;
    int pulse_set = 0;                 // 1-based, in the order the run met them (key with run_id)
    double t_s = kNaN, unix_s = kNaN;  // start of the pulse set
    double soc = kNaN, ocv_v = kNaN, temperature_c = kNaN;
    estimator::RcValues discharge, charge;  // NaN when the fit could not tell
    estimator::RcValues discharge_sd, charge_sd;  // 1 sigma of the chosen result (NaN: the method gives none)
    bool tau_at_bound = false;         // the chosen result ended with a time constant on its search bound
    std::string method;                // "thesis" | "joint" (the chosen result)
    double rms_v = kNaN;               // RMS voltage error of the chosen result
    nlohmann::json detail;             // both methods, R0 steps, warnings, the chosen result's sigmas
    // Sets discharge_sd, charge_sd and tau_at_bound from detail (how the store keeps them).
    void restore_from_detail();
};
// From the online fitter's result (chosen method, C = tau / R).
PulseFitRecord pulse_fit_record(RunId run_id, int pulse_set, double t_s, double unix_s,
                                const estimator::PulseSetFit& fit);

struct ParameterSetRecord {
    std::int64_t id = 0;
    std::optional<RunId> run_id;
    double created_unix_s = 0.0;
    std::string cell;
    nlohmann::json params;             // cellbench.params/1
};

// ---------------------------------------------------------------------------------------------------------
// Samples of a time window, for plots: every sample, or min/max per bucket so that spikes survive.

struct SourceWindow {
    std::string source;                          // "cycler", "daq", "chamber"
    std::vector<std::string> channels;           // e.g. voltage_v, current_a, ...
    std::vector<double> time_s;                  // raw: sample time; decimated: bucket start
    std::vector<std::int64_t> bucket;            // decimated: bucket index (one grid for all sources)
    std::vector<std::uint32_t> count;            // samples behind each point (1 when raw)
    std::vector<std::vector<double>> min, max;   // [channel][point]; raw: min == max == value; NaN = none

    [[nodiscard]] std::size_t size() const { return time_s.size(); }
    // Index of a channel, or npos.
    [[nodiscard]] std::size_t channel(std::string_view name) const;
};

struct SampleWindow {
    RunId run_id = 0;
    double from_s = kNaN, to_s = kNaN;   // the window (defaults: first and last sample of the run)
    std::size_t max_points = 0;
    // Raw when every source has at most max_points samples in the window; otherwise the window is cut into
    // bucket_count = max_points / 2 equal buckets of bucket_s, each giving a min and a max (so at most
    // max_points numbers per channel). Empty buckets are omitted. Buckets of 5 s or more are filled from
    // per-second min/max rollups the writer keeps beside the rows (a second is placed by its first sample), so
    // a whole-run plot reads ~100x fewer rows at 100 Hz and still shows every spike.
    bool decimated = false;
    double bucket_s = 0.0;
    std::size_t bucket_count = 0;
    std::vector<SourceWindow> sources;   // sources with samples in the window

    [[nodiscard]] const SourceWindow* source(std::string_view name) const;
};

// ---------------------------------------------------------------------------------------------------------
// Faults

enum class StoreFaultKind { disk_full, busy, readonly, io_error, corrupt, overflow, closed, other };
std::string_view to_string(StoreFaultKind kind);

struct StoreFault {
    StoreFaultKind kind = StoreFaultKind::other;
    int sqlite_code = 0;               // extended result code (0 for overflow)
    std::string message;               // plain words with SQLite's message
    std::uint64_t samples_lost = 0;    // samples of the failed batch / dropped by the overflow
};

// A write that could not be done (create_run on a failing disk, a write on a read-only or closed store).
class StoreError : public std::runtime_error {
public:
    StoreError(StoreFaultKind kind, const std::string& message) : std::runtime_error(message), kind_(kind) {}
    [[nodiscard]] StoreFaultKind kind() const { return kind_; }

private:
    StoreFaultKind kind_;
};

struct StoreStats {
    std::uint64_t samples_queued = 0;    // waiting or being written now
    std::uint64_t samples_written = 0;   // committed
    std::uint64_t samples_dropped = 0;   // refused by the overflow policy
    std::uint64_t samples_lost = 0;      // in failed transactions
    std::uint64_t batches = 0, failed_batches = 0;
    double last_batch_ms = 0.0;          // duration of the last commit
    std::optional<StoreFault> last_fault;
    // Samples accepted by push() (queued for writing), by source, and their rate over the last ~10 s (GET /metrics).
    std::uint64_t cycler_samples_accepted = 0, daq_samples_accepted = 0, chamber_samples_accepted = 0;
    double cycler_samples_per_s = 0.0, daq_samples_per_s = 0.0, chamber_samples_per_s = 0.0;
};

struct RunStoreOptions {
    std::chrono::milliseconds flush_period{200};   // bound on what kill -9 loses
    std::size_t flush_rows = 20000;                // commit early when this many samples wait
    std::size_t queue_capacity_samples = 500000;   // overflow bound (~10 s at 50 k samples/s)
    std::chrono::milliseconds busy_timeout{2000};  // wait for a lock held by another process, then fail
    std::size_t read_connections = 4;              // reader pool size (queries beyond it wait)
    std::optional<std::int64_t> max_page_count;    // size limit in pages (a quota; tests use it for "disk full")
    // Called on the writer thread for every fault (keep it short: record an event, flag the run for abort).
    // It may queue records (record_event, set_run_state) but must not wait for the writer (flush, create_run,
    // mark_interrupted_runs): that would wait for itself.
    std::function<void(const StoreFault&)> on_fault;
};

// ---------------------------------------------------------------------------------------------------------

class RunStore {
public:
    // Opens or creates the database (schema created or checked). Throws InputError naming the path and the
    // reason when the file cannot be opened or written, is not an SQLite database, belongs to another
    // application, or was made by a newer cellbench.
    static std::unique_ptr<RunStore> open(const std::filesystem::path& path, RunStoreOptions options = {});
    // Reads only (export, `cellbench fit --db`): no writer thread; every write throws StoreError.
    static std::unique_ptr<RunStore> open_readonly(const std::filesystem::path& path);

    ~RunStore();  // close()
    RunStore(const RunStore&) = delete;
    RunStore& operator=(const RunStore&) = delete;

    // Commits what is queued, stops the writer, closes every connection. Later calls throw StoreError
    // (kind closed); push() returns false.
    void close();

    [[nodiscard]] const std::filesystem::path& path() const;
    [[nodiscard]] bool read_only() const;

    // -- writes (thread-safe) ------------------------------------------------------------------------------
    RunId create_run(const NewRun& run);  // waits for the commit; throws StoreError
    // Queued. Terminal states set ended_unix_s (default now), running sets started_unix_s once; a run that is
    // already in a terminal state keeps it. An empty reason keeps the stored one.
    void set_run_state(RunId run, RunState state, const std::string& reason = {},
                       std::optional<double> unix_s = std::nullopt);

    bool push(RunId run, const CyclerSample& sample);
    bool push(RunId run, const DaqSample& sample);
    bool push(RunId run, const ChamberSample& sample);
    // Batches: returns how many were accepted (all unless the queue is full).
    std::size_t push(RunId run, std::span<const CyclerSample> samples);
    std::size_t push(RunId run, std::span<const DaqSample> samples);
    std::size_t push(RunId run, std::span<const ChamberSample> samples);

    void record_step(RunId run, const StepRecord& step);  // insert or update by (run, index)
    void record_event(const EventRecord& event);          // id is assigned
    void record_pulse_fit(const PulseFitRecord& fit);     // insert or replace by (run, pulse_set)
    void record_parameter_set(const ParameterSetRecord& params);

    // Restart recovery: every run still starting/running/paused becomes interrupted (ended at its last sample,
    // reason given). Returns their ids so the daemon can record a recovery event for each. Waits for commit.
    std::vector<RunId> mark_interrupted_runs(
        const std::string& reason = "the daemon stopped while the run was live (found at restart)");

    // Waits until everything queued before the call is committed (or failed). False on timeout.
    bool flush(std::chrono::milliseconds timeout = std::chrono::seconds(30));
    // Between runs: the connections give back their page caches and the readers their prepared statements (the
    // idle readers now, the writer once it has committed what is queued). Never blocks on the writer; the caches
    // refill as they are used. The future is ready once the writer has freed its cache (up to cache_size,
    // 16 MiB): only then is that memory free heap a malloc_trim can return to the system (it may hold a
    // StoreError; nothing to do with it).
    [[nodiscard]] std::future<void> release_memory();

    [[nodiscard]] StoreStats stats() const;
    // Transactions the writer has committed so far. Unchanged between two reads = nothing new is visible to a
    // reader in between, so an answer computed after the first read is still exact (the API's read cache).
    [[nodiscard]] std::uint64_t commit_count() const;

    // -- reads (thread-safe; never block the writer) ------------------------------------------------------
    [[nodiscard]] std::vector<RunInfo> list_runs(std::size_t limit = 1000) const;  // newest first
    // What get_run reads: the run's summary, or with it the configuration the run was created with (program,
    // cell and bench as given). Parsing that JSON is most of a read's cost; status, events and existence checks
    // never need it (the API during a run: 60 % of /status CPU went to parsing a config it then dropped).
    enum class RunRead { summary, with_config };
    [[nodiscard]] std::optional<RunInfo> get_run(RunId run, RunRead what = RunRead::with_config) const;
    [[nodiscard]] std::vector<StepRecord> steps(RunId run) const;
    // Events of a run in order; after_id pages (events with id > after_id).
    [[nodiscard]] std::vector<EventRecord> events(RunId run, std::int64_t after_id = 0, std::size_t limit = 10000) const;
    // Bench-level events (no run) in order.
    [[nodiscard]] std::vector<EventRecord> bench_events(std::int64_t after_id = 0, std::size_t limit = 10000) const;
    [[nodiscard]] std::vector<PulseFitRecord> pulse_fits(RunId run) const;
    // The newest parameter set (of a run when given).
    [[nodiscard]] std::optional<ParameterSetRecord> latest_parameter_set(std::optional<RunId> run = std::nullopt) const;
    // Samples in [from_s, to_s] (test time, inclusive). max_points >= 2.
    [[nodiscard]] SampleWindow samples(RunId run, std::optional<double> from_s = std::nullopt,
                                       std::optional<double> to_s = std::nullopt, std::size_t max_points = 2000) const;
    // The run as one recording for write_bdf_csv: the cycler's samples are the rows (Test Time = t_s); DAQ and
    // chamber channels are interpolated linearly onto them, NaN where that source has no sample within
    // max_gap_s of the row (instrument lost) or outside its span. Optional test-time window for paging.
    [[nodiscard]] Recording export_recording(RunId run, std::optional<double> from_s = std::nullopt,
                                             std::optional<double> to_s = std::nullopt, double max_gap_s = 5.0) const;
    // Every stored sample of a run, source by source, in the order they were stored (rowid: the order the
    // daemon received them), in one read transaction each. For replays (`cellbench fit --db`): a long run's
    // DAQ is millions of rows, so these are for offline tools, never for the API.
    [[nodiscard]] std::vector<CyclerSample> cycler_rows(RunId run) const;
    [[nodiscard]] std::vector<DaqSample> daq_rows(RunId run) const;
    [[nodiscard]] std::vector<ChamberSample> chamber_rows(RunId run) const;
    // "ok", or SQLite's list of problems.
    [[nodiscard]] std::string integrity_check() const;

    struct Impl;  // run_store_impl.hpp

private:
    explicit RunStore(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
};

// JSON forms (field names as in the REST API of api.hpp).
nlohmann::json to_json(const RunInfo& run);  // config omitted when null
nlohmann::json to_json(const EventRecord& event);
nlohmann::json to_json(const PulseFitRecord& fit);
nlohmann::json to_json(const SampleWindow& window);

}  // namespace cellbench::daemon
