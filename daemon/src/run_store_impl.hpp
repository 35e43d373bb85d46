#pragma once
// RunStore::Impl (internal to daemon/src): the writer queue and thread, the unsaved-record retry, and the
// reader pool. The writer side is defined in run_store_writer.cpp, the pool and the reads in run_store_queries.cpp and
// run_store_export.cpp. See run_store.hpp for the threading, durability and failure model.
#include <array>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <future>
#include <mutex>
#include <optional>
#include <span>
#include <thread>
#include <utility>
#include <variant>
#include <vector>

#include "cellbench/daemon/metrics.hpp"
#include "cellbench/daemon/run_store.hpp"
#include "run_store_sql.hpp"

namespace cellbench::daemon {

namespace fs = std::filesystem;

namespace store {

// Control records: everything the writer commits besides samples. Those with a promise are waited for.
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
    bool release_memory = false;  // the writer then frees its connection's page cache, before `done` (RunStore::release_memory)
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

// Prepared statements of the writer connection (prepared once, reused for every row; run_store_writer.cpp).
struct WriterStatements {
    Stmt begin, commit, rollback;
    Stmt cycler, daq, chamber, counts, cycler_rollup, daq_rollup;
    Stmt create_run, set_state, step, event, fit, params;
    Stmt live_runs, last_cycler, last_daq, last_chamber, interrupt;

    explicit WriterStatements(sqlite3* db);
};

}  // namespace store

struct RunStore::Impl {
    using Conn = store::Conn;
    using StmtCache = store::StmtCache;
    using Batch = store::Batch;
    using Control = store::Control;
    using WriterStatements = store::WriterStatements;

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
    std::atomic<std::uint64_t> commits{0};  // transactions committed by the writer (RunStore::commit_count)
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
    // Reader connections: each open one has its statement cache in `readers` (destroyed before its
    // connection is closed); `idle` holds the ones not leased.
    mutable std::vector<std::pair<Conn, std::unique_ptr<StmtCache>>> readers;
    mutable std::vector<StmtCache*> idle;
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

    // -- writer thread (run_store_writer.cpp) ---------------------------------------------------------------
    void writer_main();
    [[nodiscard]] fs::path sidecar_path() const { return fs::path(path.string() + ".unsaved.jsonl"); }
    static bool transient(StoreFaultKind k);
    // Keeps the batch's records that matter after a failed retry (waiters are failed by the caller).
    void retain(std::vector<Control>& ops);
    // One transaction with everything unsaved; true when it committed (or nothing was waiting).
    bool retry_unsaved();
    // At close, with the database still refusing writes: the unsaved records as JSON lines beside it.
    void write_sidecar();
    void report(const StoreFault& f);
    void rollback_if_open();
    void write_samples(const Batch& b);
    void run_control(Control& op);
    static void fulfil(std::vector<Control>& ops);
    static void fail(std::vector<Control>& ops, const StoreError& e);
    StoreFault fault_of(const store::SqlError& e, std::size_t samples_lost, const char* what) const;
    void write_batch(Batch& b);

    // -- lifecycle ------------------------------------------------------------------------------------------
    // Stops new writes, drains the queue, waits for reads in progress, closes every connection.
    void shutdown();

    // -- reader pool ----------------------------------------------------------------------------------------
    class Lease {
    public:
        Lease(const Impl& impl, StmtCache& conn) : impl_(impl), conn_(conn) {}
        ~Lease() { impl_.release(conn_); }
        Lease(const Lease&) = delete;
        Lease& operator=(const Lease&) = delete;
        // The connection and its prepared statements (Stmt(lease.stmts(), sql)).
        [[nodiscard]] StmtCache& stmts() const { return conn_; }

    private:
        const Impl& impl_;
        StmtCache& conn_;
    };

    // A reader connection from the pool (opened on demand up to opt.read_connections); blocks while all are
    // leased. Throws StoreError when the store is closed.
    [[nodiscard]] Lease acquire() const;

    void release(StmtCache& conn) const {
        {
            std::lock_guard lk(pool_mu);
            idle.push_back(&conn);
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

}  // namespace cellbench::daemon
