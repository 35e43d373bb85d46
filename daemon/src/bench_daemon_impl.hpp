#pragma once
// BenchDaemon::Impl (internal to daemon/src): the daemon's state and its pieces, each defined where its
// responsibility lives:
//   bench_daemon.cpp           wiring: construction, start, the bench clock's pacer and tick, shutdown
//   bench_daemon_hosting.cpp   hosted simulated instruments and the drivers' connections
//   bench_daemon_feed.cpp      the feed: instrument readings into the sequencer and the run store
//   bench_daemon_commands.cpp  commands to the tester and the chamber, with retry
//   bench_daemon_faults.cpp    bench events and instrument fault episodes
//   bench_daemon_runs.cpp      starting, stopping, pausing runs; crash recovery; run answers
//   bench_daemon_api.cpp       the REST API's answers (ApiBackend)
//   bench_daemon_status.cpp    GET /status and GET /metrics
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <unistd.h>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/steady_timer.hpp>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/core/version.hpp"
#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/diagnose_jobs.hpp"
#include "cellbench/daemon/http_server.hpp"
#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/drivers/chamber_client.hpp"
#include "cellbench/drivers/dewe_driver.hpp"
#include "cellbench/drivers/neware_client.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/instruments/registry.hpp"
#include "cellbench/sequencer/sequencer.hpp"
#include "cellbench/sim/chamber_server.hpp"
#include "cellbench/sim/dewe_publisher.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/pace_gate.hpp"
#include "cellbench/sim/plant.hpp"
#include "bench_daemon_run_context.hpp"
#include "chamber/chamber_instrument.hpp"
#include "dewe/dewe_instrument.hpp"
#include "neware/neware_instrument.hpp"

namespace cellbench::daemon {

// Bodies of GET /runs/{id}/samples (serialized answers) for the last few distinct queries, each valid while the store has committed
// nothing since it was computed (RunStore::commit_count read before the query): then a fresh read would give
// the same answer, so fifty dashboards polling one run read the database once per commit, not fifty times.
class SampleAnswerCache {
public:
    struct Key {
        RunId run = 0;
        std::optional<double> from_s, to_s;
        std::size_t max_points = 0;
        bool operator==(const Key&) const = default;
    };
    std::shared_ptr<const std::string> find(const Key& k, std::uint64_t version) {
        std::lock_guard lock(m_);
        for (const auto& e : entries_)
            if (e.version == version && e.key == k) return e.answer;
        return nullptr;
    }
    void put(const Key& k, std::uint64_t version, std::shared_ptr<const std::string> answer) {
        std::lock_guard lock(m_);
        std::erase_if(entries_, [&](const Entry& e) { return e.key == k || e.version != version; });
        entries_.push_front({k, version, std::move(answer)});
        if (entries_.size() > kEntries) entries_.pop_back();
    }

private:
    static constexpr std::size_t kEntries = 4;  // a few dashboards' zoom levels; each answer is <= ~1 MB
    struct Entry {
        Key key;
        std::uint64_t version;
        std::shared_ptr<const std::string> answer;
    };
    std::mutex m_;
    std::deque<Entry> entries_;
};

struct BenchDaemon::Impl {
    BenchConfig cfg;
    BenchDaemonOptions opt;
    std::shared_ptr<sim::BenchClock> clock;
    double scale = 1.0;
    // Paced bench time (every instrument hosted): the pacer timer on the instruments' io_context is the only
    // thing that moves bench time on, by a bounded step per call, so a starved daemon slows the simulated
    // bench down instead of finding hundreds of bench seconds gone (and its instruments "silent").
    SteadyClock::time_point pace_report_at{};
    bool pace_slow_reported = false;
    // ... and never runs more than half an instrument's grace past its last reading (sim::PaceGate; the pacer's
    // own, on the io threads), fed the bench time of each instrument's last reading (Instrument::last_reading_t_s).
    std::optional<sim::PaceGate> pace_gate;
    std::string pace_waiting_for;  // the instrument the bench waits for while the gate is closed (under live_m)
    SteadyClock::time_point started_at = SteadyClock::now();

    asio::io_context io;
    std::optional<asio::executor_work_guard<asio::io_context::executor_type>> guard;
    std::vector<std::thread> threads;
    // The HTTP API on its own io_context and threads: a slow client, an expensive read (SQLite) or the accept
    // loop never occupies a thread the instrument drivers and the run engine's timers need.
    asio::io_context http_io;
    std::optional<asio::executor_work_guard<asio::io_context::executor_type>> http_guard;
    std::vector<std::thread> http_threads;
    std::unique_ptr<asio::steady_timer> tick_timer;
    std::unique_ptr<asio::steady_timer> pace_timer;  // paced bench time (see clock)

    // The sequencer is fed on its own thread, in arrival order. Its work at a step change (segmenting the run so
    // far, copying the window for a fit) takes tens of ms; on the drivers' strands that would delay the next
    // cycler poll, and at a high time scale the first reading after a current step would come late (R0 high).
    std::mutex feed_m;
    std::condition_variable feed_cv;
    std::deque<std::function<void()>> feed_q;
    bool feed_stop = false;
    std::thread feed_thread;
    std::thread refit_thread;  // final fits redone at start (runs whose fit did not land before a stop)

    void feed(std::function<void()> job) {
        {
            std::lock_guard l(feed_m);
            feed_q.push_back(std::move(job));
        }
        feed_cv.notify_one();
    }
    void feed_loop();

    std::unique_ptr<RunStore> store;
    SampleAnswerCache sample_answers;
    std::filesystem::path db_path;

    // Simulated instruments.
    std::optional<sim::BenchPlant> plant;
    std::unique_ptr<sim::NewareServer> neware_server;
    std::unique_ptr<sim::ChamberServer> chamber_server;
    std::unique_ptr<sim::DewePublisher> dewe_publisher;
    std::string daq_path;
    // The hosted DAQ's datagram socket: per process and per daemon (daq_endpoint).
    const std::string hosted_daq_path = [] {
        static std::atomic<int> serial{0};
        return (std::filesystem::temp_directory_path() /
                ("cellbench-dewe-can-" + std::to_string(::getpid()) + "-" + std::to_string(serial++) + ".sock"))
            .string();
    }();

    // Drivers.
    std::unique_ptr<drivers::NewareClient> neware;
    std::unique_ptr<drivers::ChamberClient> chamber;
    std::unique_ptr<drivers::DeweDriver> dewe;
    std::filesystem::path step_file_dir;  // real tester: where compiled step files are written

    // The drivers behind the Instrument interface (instruments/): state, address, data age, reconnects, faults
    // and lost frames of each, for GET /status, GET /metrics and /health. One line each in connect_drivers();
    // the typed pointers are for the readings' paths, which are instrument-specific anyway.
    instruments::InstrumentRegistry instruments;
    instruments::NewareInstrument* cycler_instrument = nullptr;
    instruments::ChamberInstrument* chamber_instrument = nullptr;
    instruments::DeweInstrument* daq_instrument = nullptr;

    std::unique_ptr<HttpServer> http;
    std::uint16_t bound_port = 0;

    // Diagnosis jobs (POST /runs/{id}/diagnose, POST /diagnose): their own worker thread.
    std::unique_ptr<DiagnoseJobs> diagnoses;

    // Instruments' state and live values (leaf lock).
    mutable std::mutex live_m;
    // The database's last write fault while it lasts (disk full, read-only, I/O error), for GET /health and
    // POST /runs (503 with the reason); cleared when a write commits again. Guarded by live_m.
    std::string db_fault;
    std::uint64_t db_fault_batches = 0;  // samples committed when the fault was seen
    std::optional<CyclerSample> live_cycler;
    std::optional<DaqSample> live_daq;
    std::optional<ChamberSample> live_chamber;
    double live_soc = kNaN;

    // Runs: run_m serialises the control operations (start/stop/pause/resume/shutdown); ctx_m guards the
    // pointer only (a leaf: sample handlers and sinks take it briefly).
    std::mutex run_m;
    mutable std::mutex ctx_m;
    std::shared_ptr<RunContext> ctx;  // the latest run (active or finished, until the next one starts)
    std::atomic<bool> stopping{false};
    bool shut = false;

    // Adapters from the sequencer's interfaces to the drivers.
    struct CyclerAdapter final : sequencer::Cycler {
        Impl& d;
        explicit CyclerAdapter(Impl& impl) : d(impl) {}
        void start(const protocol::StepProgram& program, const std::string& barcode) override { d.cycler_start(program, barcode); }
        void stop() override { d.cycler_stop("stop"); }
        void pause() override {
            d.neware->pause_program([&d = d](const drivers::NewareCommandResult& r) { d.command_result("pause", r); });
        }
        void resume() override {
            d.neware->continue_program([&d = d](const drivers::NewareCommandResult& r) { d.command_result("continue", r); });
        }
    } cycler_adapter{*this};

    struct ChamberAdapter final : sequencer::Chamber {
        Impl& d;
        explicit ChamberAdapter(Impl& impl) : d(impl) {}
        void set_setpoint(double c) override { d.chamber_setpoint(c, ++d.setpoint_generation, 0); }
        void set_running(bool running) override {
            d.chamber->set_running(running, [&d = d](const std::optional<drivers::ChamberFault>& f) {
                if (f) d.instrument_fault("chamber", "run/stop: " + f->message, false);
            });
        }
    } chamber_adapter{*this};

    Impl(BenchConfig c, BenchDaemonOptions o);

    double now_s() const { return clock->now_s(); }
    double bench_at(SteadyClock::time_point t) const { return clock->at(t); }

    std::shared_ptr<RunContext> current() const {
        std::lock_guard lock(ctx_m);
        return ctx;
    }
    std::shared_ptr<RunContext> active() const {
        auto c = current();
        return c && c->live ? c : nullptr;
    }

    // -- bench-level events (no run) and instrument faults (bench_daemon_faults.cpp) -------------------------
    void bench_event(EventLevel level, const std::string& kind, const std::string& message, json detail = nullptr,
                     std::optional<RunId> run = std::nullopt);

    static EventRecord event_record(std::optional<RunId> run, EventLevel level, const std::string& kind,
                                    const std::string& message, json detail);

    // An event the store refuses (full, locked) is logged, never thrown into the caller's path.
    void store_event(const EventRecord& e);

    // -- instrument faults (issue 6): episodes, policy, events (bench_daemon_faults.cpp) --------------------
    // A fault opens an episode of its key ("neware", "chamber", "chamber:alarm", "chamber:setpoint", "dewe",
    // "<instrument>:command"); its first occurrence is a "fault" event (later ones are counted), a valid
    // reading closes it with a "recovery" event. Recoverable faults leave the run going: the sequencer aborts
    // it when the instrument stays without readings past its grace (tick). Fatal ones abort it at once.
    struct FaultEpisode {
        bool open = false;
        double since_s = 0.0, last_s = 0.0;
        std::string fault, message;
        std::uint64_t occurrences = 0;
        std::optional<RunId> run;
    };
    std::mutex fault_m;  // leaf
    std::map<std::string, FaultEpisode> episodes;
    // (Fault occurrences and lost answers are counted on the instrument: Instrument::count_fault.)
    static std::string instrument_of(const std::string& key) { return key.substr(0, key.find(':')); }

    // Grace in bench time, never below what the host can promise in wall time (3 s; see limits_for).
    double grace_for(const std::string& instrument) const;
    // The shortest instrument-loss grace in bench seconds: what the host can promise in wall time. A real bench
    // (scale 1) keeps its configured grace down to 3 s; an accelerated simulated bench must ride out several
    // seconds of a starved host (make test beside a compiler measured more than 3 s), so 10 s of wall time.
    [[nodiscard]] double min_grace_s() const { return scale * (scale > 1.0 ? 10.0 : 3.0); }

    void record_run_event(std::optional<RunId> run, EventLevel level, const std::string& kind, const std::string& message,
                          json detail);

    void fault(const std::string& key, const std::string& kind, const std::string& message, bool fatal, json extra = nullptr);

    // A valid reading: closes the key's episode (after settle_s bench seconds without a new fault).
    void recovered(const std::string& key, double settle_s = 0.0);

    // Faults reported outside the drivers' own fault streams (commands not taken, set point writes).
    void instrument_fault(const std::string& instrument, const std::string& message, bool safety_data_lost);

    // The latest set point asked for is written until the chamber takes it (a newer one supersedes it): after
    // an abort, the safe set point must reach a chamber that was unreachable for a while.
    std::atomic<std::uint64_t> setpoint_generation{0};
    // Bumped when a run starts: a stop still being retried for an earlier run must not stop the new one.
    std::atomic<std::uint64_t> run_generation{0};
    std::atomic<std::uint64_t> stop_serial{0};  // cycler stops sent (cycler_start)

    // Between runs, the freed heap is given back to the system at most this often (see schedule_tick).
    static constexpr std::chrono::seconds kIdleTrimPeriod{2};
    std::chrono::steady_clock::time_point last_idle_trim{};
    std::future<void> idle_released;  // the store's caches released by the last idle trim
    void retry_later(int attempt, std::function<void()> fn, std::chrono::milliseconds cap = std::chrono::milliseconds(5000));

    void chamber_setpoint(double c, std::uint64_t gen, int attempt);

    void command_result(const std::string& what, const drivers::NewareCommandResult& r);

    // -- cycler: commands with retry (bench_daemon_commands.cpp), readings (bench_daemon_feed.cpp) ----------
    // A start that never left the daemon (tester unreachable) is sent again with backoff while the cycler's
    // loss grace lasts: the tester cannot have acted on it. Any other failure (refused, answer lost: the
    // tester may have started) is fatal to the run, as the sequencer cannot trust the program to run.
    void cycler_start(const protocol::StepProgram& program, const std::string& barcode, int attempt = 0,
                      std::optional<double> first_try_s = std::nullopt);

    // Stops the tester's program; a stop the tester did not acknowledge (unreachable, stalled) is sent again
    // with backoff until it is, unless a newer run started meanwhile: the cell is never left on a program.
    void cycler_stop(const std::string& why, int attempt = 0, std::optional<double> first_cmd = std::nullopt);

    // Bench time at which the tester's current test started (test time 0), per test id: maps the recorded
    // rows' test time onto the daemon's clock. Set from the first live reading of the test (answer time minus
    // the tester's total time), so rows keep the tester's exact spacing. Neware strand only.
    std::int64_t neware_test_id = 0;
    double neware_test_start_s = kNaN;

    void on_neware_sample(const drivers::NewareSample& s);

    void on_neware_event(const drivers::NewareEvent& e);

    // -- DAQ (bench_daemon_feed.cpp) ------------------------------------------------------------------------
    void on_dewe_sample(const drivers::DeweReading& r);

    void on_dewe_health(const drivers::DeweHealth& h);

    protocol::DeweStreamStats daq_loss_reported{};  // counts at the last loss event (fault_m)
    double daq_loss_event_s = -1e300;
    std::optional<RunId> daq_loss_run;  // the run of the last loss event: a new run gets its first one at once

    void daq_losses(const protocol::DeweStreamStats& st);

    // -- chamber (bench_daemon_feed.cpp) --------------------------------------------------------------------
    void on_chamber_status(const drivers::ChamberStatus& s);

    void on_chamber_fault(const drivers::ChamberFault& f);

    // -- start: wiring (bench_daemon.cpp), hosted simulators and drivers (bench_daemon_hosting.cpp) ---------
    void start();

    void note_db_fault(const std::string& what);
    // Under live_m: whether samples were committed since the fault was seen (then the fault is over).
    bool db_writable_again();

    ApiBackend* backend = nullptr;  // the BenchDaemon (set by it)
    ApiBackend& outer_backend() { return *backend; }

    std::string api_url() const;

    void host_simulation();

    drivers::CanEndpoint daq_endpoint() const;

    void connect_drivers();

    // Runs the daemon left live when it died (crash, kill -9, power loss): the bench is made safe before
    // anything else -- start() calls this before the tick and the API exist, so no run can start and nothing
    // else is commanded meanwhile. The cycler is told to stop and the chamber to go to its safe set point, both
    // at once, each retried until the instrument acknowledges it (at most kRecoveryAttempts, each bounded by
    // the driver's own timeouts); then every such run gets a recovery event saying what was acknowledged.
    // A completed run always gets a "fit" event from its final fit (the parameter set, or why there is none).
    // A run without one was stopped (kill -9, power loss) before the fit landed: visible as a fit_pending
    // event, and the fit is redone from the stored records on a worker thread (never on the run engine's).
    void redo_pending_fits();

    void recover();

    void schedule_pace();
    // The log says when the bench runs slower than asked (and when it is back), with the scale achieved.
    void report_pace();

    void schedule_tick();

    // -- runs (bench_daemon_runs.cpp) -----------------------------------------------------------------------
    sequencer::SafetyLimits limits_for(const CellConfig& cell) const;

    json start_run(const StartRequest& req);

    std::shared_ptr<RunContext> run_for_command(RunId id);

    json stop_run(RunId id);
    json pause_run(RunId id);
    json resume_run(RunId id);

    json run_json(const RunInfo& r) const;
    json run_json(RunId id) const;

    // -- shutdown (bench_daemon.cpp; wait_commands: bench_daemon_commands.cpp) ------------------------------
    void shutdown();

    // Waits until the stop request and the safe set point write sent just before have been answered: a probe
    // queued behind them on each instrument (the clients answer in order). Bounded by what the configured
    // timeouts allow: on the chamber a poll in progress, the write and the probe, each up to (retries + 1)
    // attempts of response_timeout_ms; on the cycler the stop and the probe. The probes' callbacks hold the
    // shared state, never this frame: one answering after the deadline finds nobody waiting, harmlessly.
    void wait_commands();
};

}  // namespace cellbench::daemon
