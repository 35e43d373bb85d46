#include "cellbench/daemon/bench_daemon.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <functional>
#include <fstream>
#include <future>
#include <map>
#include <set>
#include <mutex>
#include <sstream>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

#include <unistd.h>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/core/version.hpp"
#include "cellbench/daemon/diagnose_jobs.hpp"
#include "cellbench/daemon/http_server.hpp"
#include "cellbench/daemon/metrics.hpp"
#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/drivers/chamber_client.hpp"
#include "cellbench/drivers/dewe_driver.hpp"
#include "cellbench/drivers/neware_client.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/json_input.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "cellbench/sequencer/sequencer.hpp"
#include "cellbench/sim/chamber_server.hpp"
#include "cellbench/sim/dewe_publisher.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/plant.hpp"

namespace cellbench::daemon {

namespace asio = boost::asio;
using nlohmann::json;
using SteadyClock = std::chrono::steady_clock;

namespace {

const char* const kVersion = cellbench::version();  // CMake project version (core/version.hpp)

double unix_now_s() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}
// Wall (UTC) time of a steady_clock instant in the recent past.
double unix_at(SteadyClock::time_point t) {
    return unix_now_s() - std::chrono::duration<double>(SteadyClock::now() - t).count();
}
json nullable(double x) { return std::isfinite(x) ? json(x) : json(nullptr); }

// Paced bench time: the pacer runs every kPacePeriod; a call more than kPaceMaxStepWallS after the previous
// one (the host starved the daemon) adds only kPaceMaxStepWallS x scale bench seconds.
constexpr auto kPacePeriod = std::chrono::milliseconds(10);
constexpr double kPaceMaxStepWallS = 0.1;

// A bench-time period as a wall timer period (the simulation runs time_scale bench s per wall s), >= 1 ms.
std::chrono::milliseconds wall_period(double bench_ms, double scale, double min_ms = 1.0) {
    return std::chrono::milliseconds(static_cast<std::int64_t>(std::max(min_ms, std::round(bench_ms / scale))));
}

estimator::ParameterSet load_param_file(const std::filesystem::path& path) {
    std::ifstream in(path);
    if (!in) throw InputError(path.string() + ": cannot read the parameter set");
    std::stringstream text;
    text << in.rdbuf();
    return estimator::ParameterSet::from_json(protocol::parse_json_input(text.str(), path.string()), path.string());
}

sequencer::Program to_sequencer_program(const Program& p) {
    sequencer::Program out;
    out.name = p.name;
    for (const auto& seg : p.segments) {
        sequencer::Segment s;
        if (const auto* c = std::get_if<CyclerSegment>(&seg)) {
            s.kind = sequencer::Segment::Kind::Cycler;
            s.program = c->program;
            s.name = c->program.name;
        } else if (const auto* sp = std::get_if<ChamberSetpointSegment>(&seg)) {
            s.kind = sequencer::Segment::Kind::ChamberSetpoint;
            s.setpoint_c = sp->setpoint_c;
            s.name = "chamber set point";
        } else if (const auto* w = std::get_if<WaitEquilibriumSegment>(&seg)) {
            s.kind = sequencer::Segment::Kind::WaitEquilibrium;
            s.tolerance_c = w->tolerance_c;
            s.hold_s = w->hold_s;
            s.timeout_s = w->timeout_s;
            s.abort_on_timeout = w->abort_on_timeout;
            s.name = "wait for thermal equilibrium";
        }
        out.segments.push_back(std::move(s));
    }
    return out;
}

RunState store_state(sequencer::RunState s) {
    switch (s) {
        case sequencer::RunState::Running: return RunState::running;
        case sequencer::RunState::Paused: return RunState::paused;
        case sequencer::RunState::Completed: return RunState::completed;
        case sequencer::RunState::Aborted: return RunState::aborted;
        case sequencer::RunState::Stopped: return RunState::stopped;
        case sequencer::RunState::Idle: break;
    }
    return RunState::starting;
}

EventLevel event_level(const std::string& severity) {
    if (severity == "info") return EventLevel::info;
    if (severity == "warning") return EventLevel::warning;
    return EventLevel::error;  // "alarm", "error"
}

// The API's run state (INTERFACES.md): the store's word, except that a live run waiting for the cell and
// chamber to reach equilibrium says so.
std::string api_state(RunState s, bool waiting_equilibrium) {
    if (s == RunState::running && waiting_equilibrium) return "waiting_equilibrium";
    return std::string(to_string(s));
}

bool live_state(RunState s) { return s == RunState::starting || s == RunState::running || s == RunState::paused; }

std::string safe_name(std::string s) {
    for (char& c : s)
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') c = '_';
    return s;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// One run: the sequencer, the sink that writes what it reports to the store, and the step bookkeeping.

struct RunContext final : sequencer::RunSink {
    RunStore& store;
    RunId id;
    double start_bench_s;            // bench time at which the run started (t_s = bench - this)
    std::string cell_name;
    std::vector<int> steps_per_segment;
    std::unique_ptr<sequencer::Sequencer> seq;

    std::atomic<bool> live{true};
    std::atomic<int> seq_state{static_cast<int>(sequencer::RunState::Running)};

    // Leaf lock: sink callbacks (under the sequencer's lock) and sample handlers.
    mutable std::mutex m;
    int step_index = 0;
    std::string end_reason;  // why the run ended (terminal state), as the sequencer said
    std::optional<StepRecord> open_step;
    int pulse_sets = 0;
    double last_cycler_t_s = kNaN;  // run time of the latest stored cycler row
    double capacity_ah = 4.5;
    // The open step's totals as the sequencer reported them at its end (on_step_end); else the live reading's.
    std::optional<std::pair<double, double>> step_totals;
    double last_capacity_ah = kNaN, last_energy_wh = kNaN;
    double expected_s = kNaN;  // the program's expected duration (estimate_duration), for progress by time

    RunContext(RunStore& s, RunId run, double start, std::string cell)
        : store(s), id(run), start_bench_s(start), cell_name(std::move(cell)) {}

    double rel(double t_bench) const { return t_bench - start_bench_s; }

    void on_state(sequencer::RunState state, const std::string& reason) override {
        seq_state = static_cast<int>(state);
        const RunState st = store_state(state);
        if (is_terminal(st)) {
            live = false;
            std::lock_guard lock(m);
            end_reason = reason;  // the API shows it even while the store cannot commit it (disk full, locked)
            close_step_locked(unix_now_s(), last_cycler_t_s, state == sequencer::RunState::Completed ? "end" : "stopped");
        }
        store.set_run_state(id, st, reason);
        spdlog::info("run {}: {} ({})", id, sequencer::to_string(state), reason);
    }

    void close_step_locked(double unix_s, double t_s, const std::string& why) {
        if (!open_step) return;
        open_step->ended_t_s = std::isfinite(t_s) ? t_s : open_step->started_t_s;
        open_step->ended_unix_s = unix_s;
        if (std::isfinite(last_capacity_ah)) open_step->capacity_ah = std::abs(last_capacity_ah);
        if (std::isfinite(last_energy_wh)) open_step->energy_wh = std::abs(last_energy_wh);
        open_step->end_reason = why;
        if (step_totals) {
            open_step->capacity_ah = step_totals->first;
            open_step->energy_wh = step_totals->second;
        }
        store.record_step(id, *open_step);
        open_step.reset();
        step_totals.reset();
    }

    void on_step_end(double, double capacity_ah, double energy_wh) override {
        std::lock_guard lock(m);
        step_totals = std::make_pair(capacity_ah, energy_wh);
    }

    void on_step(double t_mono_s, int segment, int step_id, int cycle_id, const std::string& step_type) override {
        std::lock_guard lock(m);
        const double t = rel(t_mono_s), u = unix_now_s();
        close_step_locked(u, t, "next step");
        StepRecord r;
        r.index = ++step_index;
        r.segment = segment;
        r.step_id = step_id;
        r.cycle = cycle_id;
        r.type = step_type;
        r.started_t_s = t;
        r.started_unix_s = u;
        store.record_step(id, r);
        open_step = r;
    }

    void on_event(double t_mono_s, const std::string& severity, const std::string& kind,
                  const std::string& message) override {
        EventRecord e;
        e.run_id = id;
        e.unix_s = unix_now_s();
        e.t_s = rel(t_mono_s);
        e.level = event_level(severity);
        e.kind = kind;
        {
            std::lock_guard lock(m);
            if (open_step) e.step = open_step->index;
        }
        e.message = message;
        store.record_event(e);
        if (e.level == EventLevel::error) spdlog::warn("run {}: {}: {}", id, kind, message);
    }

    void on_pulse_fit(const estimator::PulseSetFit& fit, double t_mono_s) override {
        // SOC and start time as the sequencer (SOC's one owner) gave them.
        int n = 0;
        {
            std::lock_guard lock(m);
            n = ++pulse_sets;
        }
        store.record_pulse_fit(pulse_fit_record(id, n, rel(t_mono_s), kNaN, fit));
        const auto d = fit.chosen_discharge();
        spdlog::info("run {}: pulse set {} fitted: SOC {:.3f}, R0 discharge {:.3f} mOhm", id, n, fit.soc,
                     d.r0_ohm * 1e3);
    }

    void on_parameter_set(const estimator::ParameterSet& params, const json& summary) override {
        ParameterSetRecord r;
        r.run_id = id;
        r.created_unix_s = unix_now_s();
        r.cell = cell_name;
        r.params = params.to_json();
        store.record_parameter_set(r);
        EventRecord e;
        e.run_id = id;
        e.unix_s = r.created_unix_s;
        e.kind = "fit";
        e.message = "parameter set fitted from the run";
        e.detail = summary;
        store.record_event(e);
    }

    json step_json(double t_s) const {
        std::lock_guard lock(m);
        if (!open_step) return nullptr;
        const auto seg = static_cast<std::size_t>(open_step->segment);
        return {{"index", open_step->step_id},
                {"count", seg < steps_per_segment.size() ? steps_per_segment[seg] : 0},
                {"type", open_step->type},
                {"run_step", open_step->index},
                {"elapsed_s", std::isfinite(t_s) ? std::max(0.0, t_s - open_step->started_t_s) : 0.0}};
    }
};

// ---------------------------------------------------------------------------------------------------------

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
    void feed_loop() {
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

    std::unique_ptr<RunStore> store;
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
    std::string neware_address, chamber_address, daq_address;
    std::filesystem::path step_file_dir;  // real tester: where compiled step files are written

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
    std::string neware_state = "connecting", chamber_state = "connecting", daq_state = "connecting";
    std::string neware_detail, chamber_detail, daq_detail;
    // /metrics: returns to "connected" after having been connected, per instrument (live_m).
    std::map<std::string, std::uint64_t> reconnects;
    std::set<std::string> was_connected;
    void note_state(const std::string& instrument, const std::string& old_state, const std::string& new_state) {
        if (new_state != "connected" || old_state == "connected") return;
        if (!was_connected.insert(instrument).second) ++reconnects[instrument];
    }
    std::optional<CyclerSample> live_cycler;
    std::vector<protocol::neware::InquireEntry> live_members;  // the group's channels, newest poll
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

    Impl(BenchConfig c, BenchDaemonOptions o) : cfg(std::move(c)), opt(std::move(o)) {
        // --time-scale also applies without a simulation section: a daemon driving `cellbench sim --time-scale X`
        // from config/bench.hil.json must run its clock, polls and grace periods at the same scale.
        scale = opt.time_scale.value_or(cfg.simulation ? cfg.simulation->time_scale : 1.0);
        if (!(scale > 0) || !std::isfinite(scale)) throw InputError("time scale: expected a positive number");
        const bool all_hosted = cfg.cycler.mode == CyclerConfig::Mode::simulated &&
                                cfg.chamber.mode == ChamberConfig::Mode::simulated &&
                                cfg.daq.mode == DaqConfig::Mode::simulated;
        // A daemon driving instruments in another process (`cellbench sim`, real ones) keeps wall x scale: both
        // sides must agree on durations. A daemon hosting the whole bench paces it.
        clock = all_hosted ? std::make_shared<sim::BenchClock>(scale, 0.0, sim::BenchClock::Paced{kPaceMaxStepWallS})
                           : std::make_shared<sim::BenchClock>(scale, 0.0);
        db_path = opt.db_path.value_or(cfg.database.path);
        if (opt.listen) cfg.listen = *opt.listen;
    }

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

    // -- bench-level events (no run) and instrument faults ---------------------------------------------------
    void bench_event(EventLevel level, const std::string& kind, const std::string& message, json detail = nullptr,
                     std::optional<RunId> run = std::nullopt) {
        if (!store) return;
        store_event(event_record(run, level, kind, message, std::move(detail)));
    }

    static EventRecord event_record(std::optional<RunId> run, EventLevel level, const std::string& kind,
                                    const std::string& message, json detail) {
        EventRecord e;
        e.run_id = run;
        e.unix_s = unix_now_s();
        e.level = level;
        e.kind = kind;
        e.message = message;
        e.detail = std::move(detail);
        return e;
    }

    // An event the store refuses (full, locked) is logged, never thrown into the caller's path.
    void store_event(const EventRecord& e) {
        try {
            store->record_event(e);
        } catch (const std::exception& ex) {
            spdlog::warn("cannot record event: {}", ex.what());
        }
    }

    // -- instrument faults (issue 6): episodes, policy, events ----------------------------------------------
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
    // /metrics: every fault occurrence per instrument, and the cycler's lost or malformed answers (fault_m).
    std::map<std::string, std::uint64_t> fault_count, lost_answers;

    static std::string instrument_of(const std::string& key) { return key.substr(0, key.find(':')); }

    // Grace in bench time, never below what the host can promise in wall time (3 s; see limits_for).
    double grace_for(const std::string& instrument) const {
        const auto& f = cfg.faults;
        const double g = instrument == "neware" ? f.cycler.grace_s : instrument == "dewe" ? f.daq.grace_s : f.chamber.grace_s;
        return std::max(g, scale * 3.0);
    }

    void record_run_event(std::optional<RunId> run, EventLevel level, const std::string& kind, const std::string& message,
                          json detail) {
        if (!store) return;
        EventRecord e = event_record(run, level, kind, message, std::move(detail));
        if (run) {
            if (auto c = current(); c && c->id == *run) {
                e.t_s = c->rel(now_s());
                std::lock_guard l(c->m);
                if (c->open_step) e.step = c->open_step->index;
            }
        }
        store_event(e);
    }

    void fault(const std::string& key, const std::string& kind, const std::string& message, bool fatal, json extra = nullptr) {
        const double now = now_s();
        const std::string instrument = instrument_of(key);
        auto c = active();
        bool first = false;
        std::optional<RunId> run;
        {
            std::lock_guard l(fault_m);
            auto& ep = episodes[key];
            if (!ep.open) {
                ep = FaultEpisode{};
                ep.open = first = true;
                ep.since_s = now;
                ep.fault = kind;
                if (c) ep.run = c->id;
            } else if (c && ep.run != c->id) {
                ep.run = c->id;  // a fault still going on when a run started: that run records it too
                first = true;
            }
            ++ep.occurrences;
            ++fault_count[instrument];
            if (kind == "timeout" || kind == "protocol_error") ++lost_answers[instrument];
            ep.last_s = now;
            ep.message = message;
            run = c ? std::optional<RunId>(c->id) : ep.run;
        }
        if (first || fatal) {
            json detail = {{"instrument", instrument}, {"fault", kind}, {"message", message},
                           {"action", fatal ? "abort" : "reconnect"}};
            if (!fatal) detail["grace_s"] = grace_for(instrument);
            if (extra.is_object())
                for (const auto& [k, v] : extra.items()) detail[k] = v;
            spdlog::warn("{}: {} fault: {}{}", instrument, kind, message, fatal ? " (fatal: the run aborts)" : "");
            record_run_event(run, fatal ? EventLevel::error : EventLevel::warning, "fault", instrument + ": " + message,
                             std::move(detail));
        }
        if (fatal && c) c->seq->abort(instrument + ": " + message + " (" + kind + ", immediately fatal)", now);
    }

    // A valid reading: closes the key's episode (after settle_s bench seconds without a new fault).
    void recovered(const std::string& key, double settle_s = 0.0) {
        const double now = now_s();
        FaultEpisode ep;
        {
            std::lock_guard l(fault_m);
            const auto it = episodes.find(key);
            if (it == episodes.end() || !it->second.open || now - it->second.last_s < settle_s) return;
            ep = it->second;
            it->second.open = false;
        }
        const std::string instrument = instrument_of(key);
        const double down_s = std::max(0.0, now - ep.since_s);
        spdlog::info("{}: recovered from {} after {:.1f} s ({} occurrences)", instrument, ep.fault, down_s, ep.occurrences);
        auto c = active();
        const auto run = ep.run ? ep.run : (c ? std::optional<RunId>(c->id) : std::nullopt);
        char text[64];
        std::snprintf(text, sizeof text, " cleared after %.1f s", down_s);
        record_run_event(run, EventLevel::info, "recovery", instrument + ": " + ep.fault + text,
                         {{"instrument", instrument}, {"fault", ep.fault}, {"down_s", down_s},
                          {"occurrences", ep.occurrences}, {"last_message", ep.message}});
    }

    // Faults reported outside the drivers' own fault streams (commands not taken, set point writes).
    void instrument_fault(const std::string& instrument, const std::string& message, bool safety_data_lost) {
        fault(instrument + ":command", "command", message, safety_data_lost);
    }

    // The latest set point asked for is written until the chamber takes it (a newer one supersedes it): after
    // an abort, the safe set point must reach a chamber that was unreachable for a while.
    std::atomic<std::uint64_t> setpoint_generation{0};
    // Bumped when a run starts: a stop still being retried for an earlier run must not stop the new one.
    std::atomic<std::uint64_t> run_generation{0};
    std::atomic<std::uint64_t> stop_serial{0};  // cycler stops sent (cycler_start)

    void retry_later(int attempt, std::function<void()> fn) {
        auto timer = std::make_shared<asio::steady_timer>(io);
        timer->expires_after(std::chrono::milliseconds(std::min<std::int64_t>(5000, 250LL << std::min(attempt, 5))));
        timer->async_wait([this, timer, fn = std::move(fn)](const boost::system::error_code& ec) {
            if (!ec && !stopping) fn();
        });
    }

    void chamber_setpoint(double c, std::uint64_t gen, int attempt) {
        chamber->set_temperature(c, [this, c, gen, attempt](const std::optional<drivers::ChamberFault>& f) {
            if (!f) {
                if (attempt > 0) spdlog::info("chamber: set point {:.1f} degC taken after {} attempts", c, attempt + 1);
                return recovered("chamber:command");
            }
            if (attempt == 0) instrument_fault("chamber", "set point " + std::to_string(c) + " degC: " + f->message, false);
            if (f->kind == drivers::ChamberFaultKind::rejected || stopping || gen != setpoint_generation) return;
            retry_later(attempt, [this, c, gen, attempt] {
                if (gen == setpoint_generation) chamber_setpoint(c, gen, attempt + 1);
            });
        });
    }

    void command_result(const std::string& what, const drivers::NewareCommandResult& r) {
        if (r.ok) {
            spdlog::debug("neware {}: ok", what);
            recovered("neware:command");
            return;
        }
        spdlog::warn("neware {} failed: {}", what, r.error);
        // A cycler that did not take a command: the run cannot be trusted to follow its program.
        instrument_fault("neware", what + " not acknowledged: " + r.error, what == "start" || what == "stop");
    }

    // -- cycler ---------------------------------------------------------------------------------------------
    // A start that never left the daemon (tester unreachable) is sent again with backoff while the cycler's
    // loss grace lasts: the tester cannot have acted on it. Any other failure (refused, answer lost: the
    // tester may have started) is fatal to the run, as the sequencer cannot trust the program to run.
    void cycler_start(const protocol::StepProgram& program, const std::string& barcode, int attempt = 0,
                      std::optional<double> first_try_s = std::nullopt) {
        const std::string xml = protocol::compile_step_file(program);
        std::string path;
        if (neware_server) {
            path = "C:\\cellbench\\" + safe_name(barcode) + ".xml";
            neware_server->add_step_file(path, xml);
        } else {
            // A real BTS PC reads the step file by path: write it where that PC can see it.
            std::filesystem::create_directories(step_file_dir);
            const auto p = step_file_dir / (safe_name(barcode) + ".xml");
            std::ofstream(p) << xml;
            path = p.string();
        }
        spdlog::info("neware: starting step program '{}' ({} steps) from {}", program.name, program.steps.size(), path);
        const double t_first = first_try_s.value_or(now_s());
        const std::uint64_t gen = run_generation, stops = stop_serial;
        // Still wanted: the same run, running (not paused, not ended), and no stop sent since.
        auto wanted = [this, gen, stops] {
            if (stopping || gen != run_generation || stops != stop_serial) return false;
            const auto c = active();
            return c && c->seq->state() == sequencer::RunState::Running;
        };
        neware->start_program(path, barcode, [this, program, barcode, attempt, t_first, wanted](const drivers::NewareCommandResult& r) {
            if (r.ok || !r.never_sent) return command_result("start", r);
            if (!wanted()) return;
            if (now_s() - t_first >= grace_for("neware")) return command_result("start", r);
            if (attempt == 0) instrument_fault("neware", "start not sent: " + r.error + "; sending it again", false);
            retry_later(attempt, [this, program, barcode, attempt, t_first, wanted] {
                if (wanted()) cycler_start(program, barcode, attempt + 1, t_first);
            });
        });
    }

    // Stops the tester's program; a stop the tester did not acknowledge (unreachable, stalled) is sent again
    // with backoff until it is, unless a newer run started meanwhile: the cell is never left on a program.
    void cycler_stop(const std::string& why, int attempt = 0, std::optional<double> first_cmd = std::nullopt) {
        if (attempt == 0) ++stop_serial;  // a start still being retried is no longer wanted
        const double t_cmd = first_cmd.value_or(now_s());
        const std::uint64_t gen = run_generation;
        neware->stop_program([this, t_cmd, why, attempt, gen](const drivers::NewareCommandResult& r) {
            if (!r.ok) {
                if (attempt == 0) command_result("stop", r);
                if (stopping || gen != run_generation) return;
                spdlog::warn("neware: stop not acknowledged ({}); sending it again", r.error);
                return retry_later(attempt, [this, why, attempt, t_cmd, gen] {
                    if (gen == run_generation) cycler_stop(why, attempt + 1, t_cmd);
                });
            }
            // When the tester confirmed: recorded so the reaction time of a safety stop is visible.
            const double t_ack = now_s();
            if (auto c = current()) {
                EventRecord e;
                e.run_id = c->id;
                e.unix_s = unix_now_s();
                e.t_s = c->rel(t_ack);
                e.kind = "cycler";
                e.message = "current off: the tester acknowledged the stop";
                e.detail = {{"commanded_t_s", c->rel(t_cmd)}, {"acknowledged_t_s", c->rel(t_ack)}, {"why", why},
                            {"attempts", attempt + 1}};
                store->record_event(e);
            }
        });
    }

    // Bench time at which the tester's current test started (test time 0), per test id: maps the recorded
    // rows' test time onto the daemon's clock. Set from the first live reading of the test (answer time minus
    // the tester's total time), so rows keep the tester's exact spacing. Neware strand only.
    std::int64_t neware_test_id = 0;
    double neware_test_start_s = kNaN;

    void on_neware_sample(const drivers::NewareSample& s) {
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
        live_members = s.members;
    }

    void on_neware_event(const drivers::NewareEvent& e) {
        {
            std::lock_guard lock(live_m);
            switch (e.kind) {
                case drivers::NewareEventKind::connected:
                    note_state("neware", neware_state, "connected");
                    neware_state = "connected";
                    neware_detail.clear();
                    break;
                case drivers::NewareEventKind::disconnected:
                case drivers::NewareEventKind::connect_failed: neware_state = "offline"; neware_detail = e.message; break;
                case drivers::NewareEventKind::group_fault: neware_state = "error"; neware_detail = e.message; break;
                default: neware_detail = e.message; break;
            }
        }
        spdlog::log(e.kind == drivers::NewareEventKind::connect_failed ? spdlog::level::debug : spdlog::level::info,
                    "neware: {}: {}", drivers::to_string(e.kind), e.message);
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

    // -- DAQ --------------------------------------------------------------------------------------------------
    void on_dewe_sample(const drivers::DeweReading& r) {
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
    }

    void on_dewe_health(const drivers::DeweHealth& h) {
        std::string state;
        switch (h.state) {
            case drivers::DeweStreamState::streaming: state = "connected"; break;
            case drivers::DeweStreamState::waiting: state = "connecting"; break;
            case drivers::DeweStreamState::silent: state = "offline"; break;
            case drivers::DeweStreamState::stopped: state = "offline"; break;
        }
        bool changed = false;
        {
            std::lock_guard lock(live_m);
            changed = state != daq_state;
            note_state("dewe", daq_state, state);
            daq_state = state;
            daq_detail = h.message;
        }
        if (changed) spdlog::info("dewe: {} ({})", drivers::to_string(h.state), h.message);
        // Silence: a fault episode (the next sample closes it); the sequencer aborts past the DAQ's grace (tick:
        // no cell temperature). Lost frames (counter gaps) and garbage: counted, and an event at most every
        // loss_event_interval_s with what was lost since the previous one.
        if (changed && h.state == drivers::DeweStreamState::silent) fault("dewe", "silence", h.message, false);
        daq_losses(h.stats);
    }

    protocol::DeweStreamStats daq_loss_reported{};  // counts at the last loss event (fault_m)
    double daq_loss_event_s = -1e300;
    std::optional<RunId> daq_loss_run;  // the run of the last loss event: a new run gets its first one at once

    void daq_losses(const protocol::DeweStreamStats& st) {
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

    // -- chamber ----------------------------------------------------------------------------------------------
    void on_chamber_status(const drivers::ChamberStatus& s) {
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
        note_state("chamber", chamber_state, "connected");
        chamber_state = "connected";
        chamber_detail.clear();
    }

    void on_chamber_fault(const drivers::ChamberFault& f) {
        {
            std::lock_guard lock(live_m);
            chamber_state = f.kind == drivers::ChamberFaultKind::unreachable ? "offline" : "error";
            chamber_detail = f.operation + ": " + f.message;
        }
        spdlog::warn("chamber: {} ({}): {}", drivers::to_string(f.kind), f.operation, f.message);
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

    // -- start ------------------------------------------------------------------------------------------------
    void start() {
        // Store first: nothing runs without somewhere to record it.
        RunStoreOptions so;
        so.flush_period = std::chrono::milliseconds(cfg.database.flush_period_ms);
        so.queue_capacity_samples = cfg.database.queue_capacity_samples;
        so.max_page_count = opt.db_max_page_count;
        if (opt.db_busy_timeout) so.busy_timeout = *opt.db_busy_timeout;
        so.on_fault = [this](const StoreFault& f) {
            spdlog::error("database: {}: {}", to_string(f.kind), f.message);
            if (f.kind == StoreFaultKind::overflow) return;
            note_db_fault(std::string(to_string(f.kind)) + ": " + f.message);
            // Never on the writer thread: aborting records events, which the writer must commit.
            asio::post(io, [this, msg = f.message] { instrument_fault("database", msg, true); });
        };
        if (!db_path.parent_path().empty()) {
            std::error_code ec;
            std::filesystem::create_directories(db_path.parent_path(), ec);
            if (ec)
                throw InputError(db_path.string() + ": cannot create the database folder " +
                                 db_path.parent_path().string() + ": " + ec.message() +
                                 " (choose a writable folder with --db)");
        }
        store = RunStore::open(db_path, so);
        step_file_dir = std::filesystem::absolute(db_path).parent_path() / "stepfiles";
        diagnoses = std::make_unique<DiagnoseJobs>();

        feed_thread = std::thread([this] { feed_loop(); });
        guard.emplace(io.get_executor());
        for (int k = 0; k < std::max(1, opt.io_threads); ++k) threads.emplace_back([this] { io.run(); });
        if (clock->paced()) {  // before the simulated instruments start: their time stands still without it
            pace_timer = std::make_unique<asio::steady_timer>(io);
            pace_report_at = SteadyClock::now() + std::chrono::seconds(10);
            schedule_pace();
        }

        host_simulation();
        connect_drivers();
        recover();
        redo_pending_fits();

        // Tick: silence and equilibrium timeouts; once per bench second, at most every 200 ms wall.
        tick_timer = std::make_unique<asio::steady_timer>(io);
        schedule_tick();

        HttpServerOptions ho;
        ho.host = cfg.listen.host;
        ho.port = static_cast<std::uint16_t>(cfg.listen.port);
        ho.token = opt.token;
        if (!opt.web_root.empty()) ho.static_dir = opt.web_root;
        http = std::make_unique<HttpServer>(http_io, outer_backend(), ho);
        http->start();
        http_guard.emplace(http_io.get_executor());
        for (int k = 0; k < std::max(1, opt.io_threads); ++k) http_threads.emplace_back([this] { http_io.run(); });
        bound_port = http->local_endpoint().port();
        spdlog::info("cellbenchd: API {} (bench time x{}{})", api_url(), scale,
                     clock->paced() ? ", paced: slows down when the host is starved" : "");
    }

    void note_db_fault(const std::string& what) {
        const auto written = store ? store->stats().samples_written : 0;
        std::lock_guard l(live_m);
        db_fault = what;
        db_fault_batches = written;
    }
    // Under live_m: whether samples were committed since the fault was seen (then the fault is over).
    bool db_writable_again() {
        if (db_fault.empty()) return true;
        if (store && store->stats().samples_written > db_fault_batches) {
            db_fault.clear();
            return true;
        }
        return false;
    }

    ApiBackend* backend = nullptr;  // the BenchDaemon (set by it)
    ApiBackend& outer_backend() { return *backend; }

    std::string api_url() const {
        return "http://" + cfg.listen.host + ":" + std::to_string(bound_port ? bound_port : cfg.listen.port) + "/api/v1";
    }

    void host_simulation() {
        if (!cfg.any_simulated()) return;
        if (!cfg.simulation) throw InputError(cfg.source.string() + ": $.simulation: missing (simulated instruments need a cell)");
        const auto& simc = *cfg.simulation;
        const sim::PlantOptions po = simulated_plant_options(cfg, load_param_file(simc.params_path));
        plant.emplace(po);

        if (cfg.cycler.mode == CyclerConfig::Mode::simulated) {
            sim::NewareServerOptions no;
            // Hosted: an ephemeral port (the configured one is for a tester outside the daemon), so two
            // daemons, or a daemon beside `cellbench sim`, never collide.
            no.host = cfg.cycler.endpoint.host;
            no.port = 0;
            no.max_channel_current_a = cfg.cycler.channel_max_current_a;
            no.cell_channels.clear();
            for (const auto& ch : cfg.cycler.channels) no.cell_channels.push_back(ch.chlid);
            if (!cfg.cycler.channels.empty()) {
                const auto& a = cfg.cycler.channels.front();
                no.ip = a.ip;
                no.devtype = a.devtype;
                no.devid = a.devid;
                no.subdevid = a.subdevid;
            }
            // The tester's execution bursts (time_scale x timer period of bench time) bound how close to a
            // current step the first reading after it can be: keep them near the poll period.
            no.timer_period_ms = static_cast<int>(std::clamp<std::int64_t>(
                wall_period(cfg.cycler.poll_period_ms, scale).count(), 1, 5));
            neware_server = std::make_unique<sim::NewareServer>(*plant, clock, no);
            neware_server->start();
            spdlog::info("simulated neware (hosted) listening on {}", neware_server->description());
        }
        if (cfg.chamber.mode == ChamberConfig::Mode::simulated) {
            sim::ChamberServerOptions co;
            co.host = cfg.chamber.endpoint.host;
            co.port = 0;  // hosted: an ephemeral port (see the cycler)
            if (!cfg.chamber.register_map.is_null() && !cfg.chamber.register_map.empty())
                co.map = protocol::ChamberRegisterMap::from_json(cfg.chamber.register_map,
                                                                 cfg.source.string() + " $.instruments.chamber.register_map");
            chamber_server = std::make_unique<sim::ChamberServer>(*plant, clock, co);
            chamber_server->start();
            spdlog::info("simulated chamber (hosted) listening on {}", chamber_server->description());
        }
        if (cfg.daq.mode == DaqConfig::Mode::simulated) {
            drivers::CanEndpoint ep = daq_endpoint();
            sim::DewePublisherOptions dopt;
            if (!cfg.daq.layout.is_null() && !cfg.daq.layout.empty())
                dopt.layout = protocol::DeweCanLayout::from_json(cfg.daq.layout, cfg.source.string() + " $.instruments.daq.layout");
            if (opt.daq_sample_rate_hz) dopt.sample_rate_hz = *opt.daq_sample_rate_hz;
            dewe_publisher = std::make_unique<sim::DewePublisher>(io, *plant, clock, drivers::open_can_publisher(io, ep), dopt);
            dewe_publisher->start();
            spdlog::info("simulated dewe (hosted) sending to {}", dewe_publisher->description());
        }
    }

    drivers::CanEndpoint daq_endpoint() const {
        drivers::CanEndpoint ep;
        ep.kind = cfg.daq.transport == DaqConfig::Transport::socketcan ? drivers::CanEndpoint::Kind::socketcan
                                                                       : drivers::CanEndpoint::Kind::can_dgram;
        ep.name = ep.kind == drivers::CanEndpoint::Kind::socketcan ? cfg.daq.interface
                                                                   : opt.daq_socket_path.value_or(cfg.daq.socket_path);
        // A hosted simulated DAQ on a datagram socket: a path of this process (the configured one is for a
        // publisher outside the daemon), so two daemons never take each other's socket.
        if (ep.kind == drivers::CanEndpoint::Kind::can_dgram && cfg.daq.mode == DaqConfig::Mode::simulated &&
            !opt.daq_socket_path)
            ep.name = hosted_daq_path;
        return ep;
    }

    void connect_drivers() {
        // Cycler.
        drivers::NewareClientOptions no;
        no.host = cfg.cycler.endpoint.host;
        no.port = neware_server ? neware_server->port() : cfg.cycler.endpoint.port;
        no.members = cfg.cycler.channels;
        no.poll_period = wall_period(cfg.cycler.poll_period_ms, scale);  // poll periods are bench time
        no.request_timeout = std::chrono::milliseconds(cfg.cycler.response_timeout_ms);
        no.reconnect_initial = std::chrono::milliseconds(cfg.faults.cycler.reconnect_initial_ms);
        no.reconnect_max = std::chrono::milliseconds(cfg.faults.cycler.reconnect_max_ms);
        no.group = cfg.cycler.group;
        neware_address = no.host + ":" + std::to_string(no.port);
        neware = std::make_unique<drivers::NewareClient>(io, no);
        neware->on_sample([this](const drivers::NewareSample& s) { on_neware_sample(s); });
        neware->on_event([this](const drivers::NewareEvent& e) { on_neware_event(e); });
        neware->start();

        // Chamber.
        drivers::ChamberClientOptions co;
        co.host = cfg.chamber.endpoint.host;
        co.port = chamber_server ? chamber_server->port() : cfg.chamber.endpoint.port;
        co.unit_id = cfg.chamber.unit_id;
        if (!cfg.chamber.register_map.is_null() && !cfg.chamber.register_map.empty())
            co.map = protocol::ChamberRegisterMap::from_json(cfg.chamber.register_map,
                                                             cfg.source.string() + " $.instruments.chamber.register_map");
        co.poll_interval = wall_period(cfg.chamber.poll_period_ms, scale);
        // Modbus answer timeout and retries are wall time (the link's, not the bench's); the set point watch is
        // bench time.
        co.response_timeout = std::chrono::milliseconds(cfg.faults.chamber.response_timeout_ms);
        co.retries = cfg.faults.chamber.retries;
        co.setpoint_tolerance_c = cfg.faults.chamber.setpoint_tolerance_c;
        co.setpoint_timeout = std::chrono::milliseconds(static_cast<std::int64_t>(
            std::max(1.0, cfg.faults.chamber.setpoint_timeout_s * 1e3 / scale)));
        chamber_address = co.host + ":" + std::to_string(co.port);
        chamber = std::make_unique<drivers::ChamberClient>(io, co);
        chamber->on_status([this](const drivers::ChamberStatus& s) { on_chamber_status(s); });
        chamber->on_fault([this](const drivers::ChamberFault& f) { on_chamber_fault(f); });
        chamber->start();

        // DAQ.
        const auto ep = daq_endpoint();
        daq_address = (ep.kind == drivers::CanEndpoint::Kind::socketcan ? "can " : "can-dgram ") + ep.name;
        drivers::DeweDriverOptions dopt;
        if (!cfg.daq.layout.is_null() && !cfg.daq.layout.empty())
            dopt.layout = protocol::DeweCanLayout::from_json(cfg.daq.layout, cfg.source.string() + " $.instruments.daq.layout");
        dopt.sensitivity_v_per_w_per_m2 = cfg.daq.sensitivity_v_per_w_per_m2;
        dopt.area_m2 = cfg.daq.cell_area_m2;
        // At least 1 s of wall time: a loaded host (or the simulated DAQ's timer at a high time scale) can hold a
        // healthy stream back for a few hundred ms, which must not read as silence (faults' grace floors at 3 s).
        dopt.silence_timeout = std::chrono::milliseconds(static_cast<std::int64_t>(
            std::max(1000.0, 1000.0 * cfg.daq.stale_after_s / scale)));
        std::shared_ptr<drivers::CanTransport> transport =
            ep.kind == drivers::CanEndpoint::Kind::can_dgram
                ? drivers::open_can_dgram_listener(io, ep.name, std::chrono::milliseconds(200))
                : drivers::open_can_listener(io, ep);
        dewe = std::make_unique<drivers::DeweDriver>(io, transport, dopt);
        dewe->on_sample([this](const drivers::DeweReading& r) { on_dewe_sample(r); });
        dewe->on_health([this](const drivers::DeweHealth& h) { on_dewe_health(h); });
        dewe->start();
    }

    // Runs the daemon left live when it died (crash, kill -9, power loss): the bench is made safe before
    // anything else -- start() calls this before the tick and the API exist, so no run can start and nothing
    // else is commanded meanwhile. The cycler is told to stop and the chamber to go to its safe set point, both
    // at once, each retried until the instrument acknowledges it (at most kRecoveryAttempts, each bounded by
    // the driver's own timeouts); then every such run gets a recovery event saying what was acknowledged.
    // A completed run always gets a "fit" event from its final fit (the parameter set, or why there is none).
    // A run without one was stopped (kill -9, power loss) before the fit landed: visible as a fit_pending
    // event, and the fit is redone from the stored records on a worker thread (never on the run engine's).
    void redo_pending_fits() {
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

    void recover() {
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

    void schedule_pace() {
        pace_timer->expires_after(kPacePeriod);
        pace_timer->async_wait([this](const boost::system::error_code& ec) {
            if (ec || stopping) return;
            const auto now = SteadyClock::now();
            clock->pace(now);
            if (now >= pace_report_at) {
                pace_report_at = now + std::chrono::seconds(10);
                report_pace();
            }
            schedule_pace();
        });
    }
    // The log says when the bench runs slower than asked (and when it is back), with the scale achieved.
    void report_pace() {
        const double achieved = clock->achieved_scale();
        if (achieved < 0.9 * scale) {
            spdlog::warn("bench time: x{:.1f} achieved of x{} asked over the last 10 s (the host is busy; the simulated "
                         "bench slows down with the daemon, {:.1f} s of wall time not simulated so far)",
                         achieved, scale, clock->lost_wall_s());
            pace_slow_reported = true;
        } else if (pace_slow_reported) {
            spdlog::info("bench time: back at x{:.1f} of x{}", achieved, scale);
            pace_slow_reported = false;
        }
    }

    void schedule_tick() {
        const auto period = std::chrono::milliseconds(std::clamp<std::int64_t>(
            static_cast<std::int64_t>(1000.0 / scale), 1, 200));
        tick_timer->expires_after(period);
        tick_timer->async_wait([this](const boost::system::error_code& ec) {
            if (ec || stopping) return;
            // The tick's time is taken now, not when the feed thread gets to it: readings queued before it carry
            // their arrival times, so a feed thread behind by a second never reads as instrument silence.
            if (auto c = active()) feed([c, t = now_s()] { c->seq->tick(t); });
            schedule_tick();
        });
    }

    // -- runs -------------------------------------------------------------------------------------------------
    sequencer::SafetyLimits limits_for(const CellConfig& cell) const {
        sequencer::SafetyLimits l;
        const auto& s = cfg.safety;
        l.max_temperature_c = std::min(s.max_temperature_c, cell.max_temperature_c > 0 ? cell.max_temperature_c : s.max_temperature_c);
        l.min_voltage_v = s.min_voltage_v;
        l.max_voltage_v = s.max_voltage_v;
        l.max_current_a = s.max_current_a;
        l.chamber_deviation_c = s.chamber_deviation_c;
        // Grace in bench time, but never below what the host can promise in wall time (3 s): at 1000x a 5 s
        // grace would be 5 ms of wall time, which a loaded machine cannot guarantee.
        l.instrument_loss_grace_s = std::max(s.instrument_loss_grace_s, scale * 3.0);
        l.cycler_loss_grace_s = grace_for("neware");
        l.daq_loss_grace_s = grace_for("dewe");
        l.chamber_loss_grace_s = grace_for("chamber");
        l.chamber_safe_setpoint_c = cfg.chamber.safe_setpoint_c;
        return l;
    }

    json start_run(const StartRequest& req) {
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
        {
            std::lock_guard l(live_m);
            if (neware_state != "connected") throw Unavailable("the cycler is not connected (" + neware_detail + ")");
        }
        sequencer::SequencerOptions so;
        so.limits = limits_for(cell);
        so.capacity_ah = cell.nominal_capacity_ah;
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
        so.area_m2 = cell.surface_area_m2 > 0 ? cell.surface_area_m2 : cfg.daq.cell_area_m2;

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

    std::shared_ptr<RunContext> run_for_command(RunId id) {
        if (!store->get_run(id)) throw NotFound("no run " + std::to_string(id));
        auto c = active();
        if (!c || c->id != id) throw Conflict("run " + std::to_string(id) + " is not active");
        return c;
    }

    json stop_run(RunId id) {
        std::lock_guard lock(run_m);
        auto c = run_for_command(id);
        c->seq->stop("stopped by the operator", now_s());
        return run_json(id);
    }
    json pause_run(RunId id) {
        std::lock_guard lock(run_m);
        auto c = run_for_command(id);
        try {
            c->seq->pause(now_s());
        } catch (const InputError& e) {
            throw Conflict(e.what());
        }
        return run_json(id);
    }
    json resume_run(RunId id) {
        std::lock_guard lock(run_m);
        auto c = run_for_command(id);
        try {
            c->seq->resume(now_s());
        } catch (const InputError& e) {
            throw Conflict(e.what());
        }
        return run_json(id);
    }

    json run_json(const RunInfo& r) const {
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
    json run_json(RunId id) const {
        const auto r = store->get_run(id);
        if (!r) throw NotFound("no run " + std::to_string(id));
        return run_json(*r);
    }

    // -- shutdown ---------------------------------------------------------------------------------------------
    void shutdown() {
        std::lock_guard lock(run_m);
        if (shut) return;
        shut = true;
        stopping = true;
        if (http) http->stop();
        http_guard.reset();
        http_io.stop();
        for (auto& t : http_threads)
            if (t.joinable()) t.join();
        http_threads.clear();
        if (auto c = active()) {
            spdlog::info("shutdown: stopping run {} (current off, chamber to {:.1f} degC)", c->id, cfg.chamber.safe_setpoint_c);
            c->seq->stop("the daemon is shutting down", now_s());
            // Give the tester and the chamber time to take the commands before the connections close.
            wait_commands();
        }
        if (auto c = current()) c->seq->wait_for_fits();
        if (diagnoses) diagnoses->stop();  // before the store closes: a job may be reading a run
        if (tick_timer) tick_timer->cancel();
        if (pace_timer) pace_timer->cancel();
        if (neware) neware->stop();
        if (chamber) chamber->stop();
        if (dewe) dewe->stop();
        if (dewe_publisher) dewe_publisher->stop();
        if (chamber_server) chamber_server->stop();
        if (neware_server) neware_server->stop();
        guard.reset();
        io.stop();
        for (auto& t : threads)
            if (t.joinable()) t.join();
        threads.clear();
        {
            std::lock_guard l(feed_m);
            feed_stop = true;
        }
        feed_cv.notify_all();
        if (feed_thread.joinable()) feed_thread.join();
        if (refit_thread.joinable()) refit_thread.join();
        if (store) {
            store->flush();
            store->close();
        }
        spdlog::info("cellbenchd stopped");
    }

    // Waits until the stop request and the safe set point write sent just before have been answered: a probe
    // queued behind them on each instrument (the clients answer in order). Bounded by what the configured
    // timeouts allow: on the chamber a poll in progress, the write and the probe, each up to (retries + 1)
    // attempts of response_timeout_ms; on the cycler the stop and the probe. The probes' callbacks hold the
    // shared state, never this frame: one answering after the deadline finds nobody waiting, harmlessly.
    void wait_commands() {
        struct Pending {
            std::mutex m;
            std::condition_variable cv;
            int left = 2;
        };
        auto p = std::make_shared<Pending>();
        auto done = [p] {
            std::lock_guard l(p->m);
            --p->left;
            p->cv.notify_all();
        };
        const auto& ch = cfg.faults.chamber;
        const double chamber_s = 3.0 * (ch.retries + 1) * ch.response_timeout_ms / 1e3;
        const double cycler_s = 2.0 * cfg.cycler.response_timeout_ms / 1e3;
        const auto limit = std::chrono::duration<double>(std::max(chamber_s, cycler_s) + 1.0);
        neware->request(protocol::neware::ChannelListRequest{protocol::neware::Command::getchlstatus, cfg.cycler.channels},
                        [done](const auto&, const std::string&) { done(); });
        chamber->read_status([done](const auto&, const auto&) { done(); });
        std::unique_lock l(p->m);
        if (!p->cv.wait_for(l, limit, [&] { return p->left <= 0; }))
            spdlog::warn("shutdown: the instruments did not answer within {:.1f} s; closing the connections", limit.count());
    }
};

// ---------------------------------------------------------------------------------------------------------

BenchDaemon::BenchDaemon(BenchConfig config, BenchDaemonOptions options)
    : impl_(std::make_unique<Impl>(std::move(config), std::move(options))) {
    impl_->backend = this;
}

BenchDaemon::~BenchDaemon() {
    try {
        shutdown();
    } catch (const std::exception& e) {
        spdlog::error("shutdown: {}", e.what());
    }
}

void BenchDaemon::start() {
    try {
        impl_->start();
    } catch (...) {
        impl_->shutdown();
        throw;
    }
}
void BenchDaemon::shutdown() { impl_->shutdown(); }
std::string BenchDaemon::api_url() const { return impl_->api_url(); }
std::uint16_t BenchDaemon::http_port() const { return impl_->bound_port; }
std::filesystem::path BenchDaemon::database_path() const { return std::filesystem::absolute(impl_->db_path); }
double BenchDaemon::bench_now_s() const { return impl_->now_s(); }
double BenchDaemon::time_scale() const { return impl_->scale; }
double BenchDaemon::achieved_time_scale() const { return impl_->clock->achieved_scale(); }
RunStore& BenchDaemon::store() { return *impl_->store; }
sim::BenchPlant* BenchDaemon::plant() { return impl_->plant ? &*impl_->plant : nullptr; }
sim::NewareServer* BenchDaemon::neware_server() { return impl_->neware_server.get(); }
sim::ChamberServer* BenchDaemon::chamber_server() { return impl_->chamber_server.get(); }
sim::DewePublisher* BenchDaemon::dewe_publisher() { return impl_->dewe_publisher.get(); }
std::optional<RunId> BenchDaemon::active_run() const {
    if (auto c = impl_->active()) return c->id;
    return std::nullopt;
}

json BenchDaemon::health() {
    std::lock_guard l(impl_->live_m);
    const bool db_ok = impl_->db_writable_again();
    const bool ok = impl_->neware_state == "connected" && impl_->chamber_state == "connected" &&
                    impl_->daq_state == "connected" && db_ok;
    json j = {{"status", ok ? "ok" : "degraded"},
              {"version", kVersion},
              {"uptime_s", std::chrono::duration<double>(SteadyClock::now() - impl_->started_at).count()},
              {"database", {{"writable", db_ok}}}};
    if (!db_ok) j["database"]["detail"] = impl_->db_fault;
    return j;
}

json BenchDaemon::status() {
    auto& d = *impl_;
    json j = {{"version", kVersion},
              {"uptime_s", std::chrono::duration<double>(SteadyClock::now() - d.started_at).count()},
              {"bench_time_s", d.now_s()},
              {"time_scale", d.scale},
              {"time_scale_achieved", d.clock->achieved_scale()},
              {"bench_time_paced", d.clock->paced()}};
    auto c = d.active();
    double t_rel = kNaN;
    {
        std::lock_guard l(d.live_m);
        auto mode = [](bool simulated) { return simulated ? "simulated" : "real"; };
        j["instruments"] = json::array({
            {{"name", "neware"}, {"kind", "cycler"}, {"state", d.neware_state}, {"address", d.neware_address},
             {"detail", d.neware_detail}, {"mode", mode(d.neware_server != nullptr)}},
            {{"name", "chamber"}, {"kind", "chamber"}, {"state", d.chamber_state}, {"address", d.chamber_address},
             {"detail", d.chamber_detail}, {"mode", mode(d.chamber_server != nullptr)}},
            {{"name", "dewe"}, {"kind", "daq"}, {"state", d.daq_state}, {"address", d.daq_address},
             {"detail", d.daq_detail}, {"mode", mode(d.dewe_publisher != nullptr)}},
        });
        // Data age: wall seconds since the instrument's newest reading (null before the first).
        const double now_unix = unix_now_s();
        auto age = [&](const auto& row) { return row ? json(std::max(0.0, now_unix - row->unix_s)) : json(nullptr); };
        j["instruments"][0]["data_age_s"] = age(d.live_cycler);
        j["instruments"][1]["data_age_s"] = age(d.live_chamber);
        j["instruments"][2]["data_age_s"] = age(d.live_daq);
        // The tester channels wired in parallel as the cycler, each as it reports itself (newest poll).
        json members = json::array();
        for (const auto& m : d.live_members)
            members.push_back({{"channel", m.channel.key()}, {"voltage_v", nullable(m.voltage_v)},
                               {"current_a", nullable(m.current_a)},
                               {"status", std::string(protocol::neware::to_string(m.workstatus))}});
        j["instruments"][0]["members"] = std::move(members);
        json live = {{"time_unix_s", unix_now_s()}, {"test_time_s", nullptr}, {"voltage_v", nullptr},
                     {"current_a", nullptr}, {"soc", nullptr}, {"surface_c", nullptr}, {"ambient_c", nullptr},
                     {"t1_c", nullptr}, {"t2_c", nullptr}, {"heat_flux_w_per_m2", nullptr}};
        if (d.live_cycler) {
            live["voltage_v"] = nullable(d.live_cycler->voltage_v);
            live["current_a"] = nullable(d.live_cycler->current_a);
            live["time_unix_s"] = d.live_cycler->unix_s;
            if (c) {
                t_rel = c->rel(d.live_cycler->t_s);
                live["test_time_s"] = t_rel;
                live["soc"] = nullable(d.live_soc);
            }
        }
        if (d.live_daq) {
            live["surface_c"] = nullable(d.live_daq->surface_c);
            live["t1_c"] = nullable(d.live_daq->t1_c);
            live["t2_c"] = nullable(d.live_daq->t2_c);
            live["heat_flux_w_per_m2"] = nullable(d.live_daq->heat_flux_w_per_m2);
        }
        if (d.live_chamber) {
            live["ambient_c"] = nullable(d.live_chamber->ambient_c);
            live["setpoint_c"] = nullable(d.live_chamber->setpoint_c);
        }
        j["live"] = std::move(live);
    }
    j["run"] = c ? d.run_json(c->id) : json(nullptr);
    // Progress by expected time: test time over the program's expected duration (an estimate: the fraction
    // stays below 1 until the run ends).
    if (c && std::isfinite(c->expected_s) && c->expected_s > 0 && std::isfinite(t_rel))
        j["progress"] = {{"elapsed_s", t_rel},
                         {"expected_duration_s", c->expected_s},
                         {"fraction", std::clamp(t_rel / c->expected_s, 0.0, 0.99)}};
    else
        j["progress"] = nullptr;
    if (c) j["sequencer"] = c->seq->status();
    return j;
}

json BenchDaemon::list_runs() {
    json runs = json::array();
    for (const auto& r : impl_->store->list_runs()) runs.push_back(impl_->run_json(r));
    return {{"runs", std::move(runs)}};
}

json BenchDaemon::get_run(RunId id) { return impl_->run_json(id); }

json BenchDaemon::samples(RunId id, const SampleQuery& q) {
    if (!impl_->store->get_run(id)) throw NotFound("no run " + std::to_string(id));
    if (q.from_s && q.to_s && *q.from_s > *q.to_s) throw BadRequest("from must not be after to");
    const std::size_t max_points = std::clamp<std::size_t>(q.max_points, 2, kMaxSamplePoints);
    const auto w = impl_->store->samples(id, q.from_s, q.to_s, max_points);
    // The API's shape: one time base (the cycler's, or the bucket grid) with every series on it; DAQ and
    // chamber values are the latest at or before each point (raw), or the bucket's min/max (decimated).
    json j = {{"run_id", id}, {"from_s", nullable(w.from_s)}, {"to_s", nullable(w.to_s)},
              {"max_points", max_points}, {"decimated", w.decimated}};
    const SourceWindow* base = w.source("cycler");
    if (!base && !w.sources.empty()) base = &w.sources.front();
    json series = json::object();
    std::vector<double> time_s = base ? base->time_s : std::vector<double>{};
    struct Map {
        const char* source;
        const char* channel;
        const char* api;
    };
    static const Map maps[] = {{"cycler", "voltage_v", "voltage_v"}, {"cycler", "current_a", "current_a"},
                               {"cycler", "soc", "soc"},             {"daq", "surface_c", "surface_c"},
                               {"chamber", "ambient_c", "ambient_c"}, {"daq", "t1_c", "t1_c"},
                               {"daq", "t2_c", "t2_c"},              {"daq", "heat_flux_w_per_m2", "heat_flux_w_per_m2"}};
    if (w.decimated) {
        j["bucket_s"] = w.bucket_s;
        // Buckets of the base source; other sources looked up by bucket index.
        for (const auto& m : maps) {
            const SourceWindow* s = w.source(m.source);
            if (!s || !base) continue;
            const std::size_t ch = s->channel(m.channel);
            if (ch == std::string::npos) continue;
            std::map<std::int64_t, std::size_t> at;
            for (std::size_t k = 0; k < s->bucket.size(); ++k) at[s->bucket[k]] = k;
            json mn = json::array(), mx = json::array();
            for (std::size_t k = 0; k < base->bucket.size(); ++k) {
                const auto it = at.find(base->bucket[k]);
                mn.push_back(it == at.end() ? json(nullptr) : nullable(s->min[ch][it->second]));
                mx.push_back(it == at.end() ? json(nullptr) : nullable(s->max[ch][it->second]));
            }
            series[m.api] = {{"min", std::move(mn)}, {"max", std::move(mx)}};
        }
    } else {
        // Each point carries the source's sample in (previous point, this point] that departs most from the
        // value shown before, so a DAQ spike between two cycler rows survives (the DAQ may sample faster).
        for (const auto& m : maps) {
            const SourceWindow* s = w.source(m.source);
            if (!s || !base) continue;
            const std::size_t ch = s->channel(m.channel);
            if (ch == std::string::npos) continue;
            const auto& values = s->min[ch];
            json v = json::array();
            std::size_t k = 0;  // next source sample not yet consumed
            double shown = kNaN;
            for (double t : time_s) {
                std::optional<std::size_t> pick;
                for (; k < s->time_s.size() && s->time_s[k] <= t + 1e-9; ++k) {
                    if (!std::isfinite(values[k])) continue;
                    if (!pick || !std::isfinite(shown) ||
                        std::abs(values[k] - shown) > std::abs(values[*pick] - shown))
                        pick = k;
                }
                if (!pick && k > 0 && std::isfinite(values[k - 1])) pick = k - 1;  // slower source: latest sample
                if (pick) shown = values[*pick];
                v.push_back(pick ? nullable(values[*pick]) : json(nullptr));
            }
            series[m.api] = std::move(v);
        }
    }
    j["time_s"] = time_s;
    j["series"] = std::move(series);
    return j;
}

json BenchDaemon::events(RunId id) {
    if (!impl_->store->get_run(id)) throw NotFound("no run " + std::to_string(id));
    json ev = json::array();
    for (const auto& e : impl_->store->events(id)) {
        json x = to_json(e);
        // The API's levels are info/warning/error.
        ev.push_back(std::move(x));
    }
    return {{"run_id", id}, {"events", std::move(ev)}};
}

json BenchDaemon::steps(RunId id) {
    if (!impl_->store->get_run(id)) throw NotFound("no run " + std::to_string(id));
    json out = json::array();
    for (const auto& s : impl_->store->steps(id)) {
        auto opt = [](const std::optional<double>& v) { return v && std::isfinite(*v) ? json(*v) : json(nullptr); };
        out.push_back({{"index", s.index}, {"segment", s.segment}, {"step_id", s.step_id}, {"cycle", s.cycle},
                       {"type", s.type}, {"started_s", s.started_t_s}, {"ended_s", opt(s.ended_t_s)},
                       {"capacity_ah", opt(s.capacity_ah)}, {"energy_wh", opt(s.energy_wh)},
                       {"end_reason", s.end_reason}});
    }
    return {{"run_id", id}, {"steps", std::move(out)}};
}

json BenchDaemon::fits(RunId id) {
    if (!impl_->store->get_run(id)) throw NotFound("no run " + std::to_string(id));
    json f = json::array();
    for (const auto& r : impl_->store->pulse_fits(id)) f.push_back(to_json(r));
    return {{"run_id", id}, {"fits", std::move(f)}};
}

std::unique_ptr<ExportCursor> BenchDaemon::export_bdf_csv(RunId id) {
    if (!impl_->store->get_run(id)) throw NotFound("no run " + std::to_string(id));
    const Recording rec = impl_->store->export_recording(id);
    std::ostringstream out;
    protocol::write_bdf_csv(out, rec);
    return std::make_unique<StringExportCursor>(out.str());
}

// ---- diagnosis jobs (api.hpp "Diagnosis jobs"; the work is in diagnose_jobs.cpp and the estimator).
namespace {

json read_json(const std::filesystem::path& path) {
    std::ifstream in(path);
    if (!in) throw InputError(path.string() + ": cannot read");
    std::stringstream text;
    text << in.rdbuf();
    return protocol::parse_json_input(text.str(), path.string());
}

// A parameter set as the diagnosis requests name it: config/cells/NAME.json, a cellbench.params/1 file, or a
// cell (cellbench.cell/1) standing for the parameter set its "params" names. Returns it and the file's stem.
std::pair<estimator::ParameterSet, std::string> load_named_params(const std::filesystem::path& config_dir,
                                                                  const std::string& name) {
    const auto where = (config_dir / "cells").string();
    try {
        const auto file = cell_file(config_dir, name);
        std::error_code ec;
        if (!std::filesystem::is_regular_file(file, ec))
            throw BadRequest("\"params\": no parameter set \"" + name + "\" in " + where +
                             " (GET /api/v1/cells lists them)");
        const json j = read_json(file);
        if (j.is_object() && j.contains("schema") && j["schema"] == "cellbench.cell/1") {
            const CellConfig cell = load_cell_config(file);
            if (!cell.params_path)
                throw BadRequest("\"params\": cell \"" + name + "\" names no parameter set (its \"params\"); name one in " +
                                 where);
            return {load_param_file(*cell.params_path), cell.params_path->stem().string()};
        }
        return {estimator::ParameterSet::from_json(j, file.string()), file.stem().string()};
    } catch (const InputError& e) {
        throw BadRequest(std::string("\"params\": ") + e.what());
    }
}

void check_effects(const std::vector<std::string>& effects) {
    const auto& cat = estimator::effect_catalogue();
    for (const auto& e : effects)
        if (std::find(cat.begin(), cat.end(), e) == cat.end()) {
            std::string list;
            for (const auto& c : cat) list += (list.empty() ? "" : ", ") + c;
            throw BadRequest("\"effects\": unknown effect id \"" + e + "\" (known: " + list + ")");
        }
}

}  // namespace

json BenchDaemon::diagnose_run(RunId id, const DiagnoseRequest& request) {
    auto& d = *impl_;
    const json run = d.run_json(id);  // NotFound
    if (run["outcome"].is_null())  // not ended: any live state
        throw Conflict("run " + std::to_string(id) + " is still " + run.value("state", "live") +
                       "; diagnose it once it has ended");
    check_effects(request.effects);
    estimator::ParameterSet params;
    std::string used;
    if (request.params == "run") {
        const auto fitted = d.store->latest_parameter_set(id);
        if (!fitted)
            throw BadRequest("\"params\": \"run\": run " + std::to_string(id) +
                             " has no fitted parameter set (the daemon fits one when an HPPC with enough pulse sets "
                             "ends); name a parameter set under " + (d.cfg.config_dir / "cells").string() + " instead");
        try {
            params = estimator::ParameterSet::from_json(fitted->params, "run " + std::to_string(id) + " parameter set");
        } catch (const InputError& e) {
            throw BadRequest(std::string("\"params\": \"run\": ") + e.what());
        }
        used = "run " + std::to_string(id);
    } else {
        std::tie(params, used) = load_named_params(d.cfg.config_dir, request.params);
    }
    json info = {{"source", {{"kind", "run"}, {"run_id", id}, {"program", run.value("program", "")},
                             {"cell", run.value("cell", "")}}},
                 {"params", request.params},
                 {"params_used", used}};
    RunStore* store = d.store.get();
    return d.diagnoses->submit(std::move(info), request.effects,
                               [store, id, params = std::move(params)](const std::function<void(std::string_view)>& stage) {
                                   stage("reading run " + std::to_string(id) + " from the database");
                                   DiagnoseInput in{params, store->export_recording(id)};
                                   in.recording.source = "run " + std::to_string(id);
                                   return in;
                               });
}

json BenchDaemon::diagnose_recording(const DiagnoseRequest& request, std::string csv) {
    auto& d = *impl_;
    if (request.params == "run")
        throw BadRequest("\"params\": \"run\" names a run's fitted parameter set; name a parameter set under " +
                         (d.cfg.config_dir / "cells").string());
    check_effects(request.effects);
    auto [params, used] = load_named_params(d.cfg.config_dir, request.params);
    std::string name = request.body.is_object() ? request.body.value("name", std::string{}) : std::string{};
    const std::string source = name.empty() ? std::string("uploaded recording") : name;
    // The header and the first rows now, for a clear 400; the whole file on the worker (it may be large).
    {
        std::size_t end = 0;
        for (int lines = 0; lines < 200 && end != std::string::npos; ++lines) {
            end = csv.find('\n', end);
            if (end != std::string::npos) ++end;
        }
        const std::string_view head = end == std::string::npos ? std::string_view(csv) : std::string_view(csv).substr(0, end);
        try {
            (void)protocol::parse_bdf_csv(head, source);
        } catch (const InputError& e) {
            throw BadRequest(std::string("not a BDF CSV recording: ") + e.what());
        }
    }
    json info = {{"source", {{"kind", "upload"}, {"bytes", csv.size()}, {"name", name}}},
                 {"params", request.params},
                 {"params_used", used}};
    return d.diagnoses->submit(
        std::move(info), request.effects,
        [csv = std::move(csv), params = std::move(params), source](const std::function<void(std::string_view)>& stage) {
            stage("parsing the recording");
            protocol::BdfReadReport report;
            DiagnoseInput in{params, protocol::parse_bdf_csv(csv, source, &report)};
            if (report.repaired_timestamps > 0)
                spdlog::info("diagnosis: {}: repaired {} repeated or slightly backward timestamps", source,
                             report.repaired_timestamps);
            return in;
        });
}

json BenchDaemon::diagnosis(std::int64_t job) { return impl_->diagnoses->get(job); }
json BenchDaemon::list_diagnoses() { return impl_->diagnoses->list(); }

json BenchDaemon::cells() {
    const auto& dir = impl_->cfg.config_dir;
    json cells = json::array(), sets = json::array();
    for (const auto& name : list_cells(dir)) {
        json c = {{"name", name}, {"params", nullptr}};
        try {
            const CellConfig cell = load_cell_config(cell_file(dir, name));
            c["description"] = cell.name;
            if (cell.params_path) c["params"] = cell.params_path->stem().string();
        } catch (const std::exception& e) {
            c["error"] = e.what();
        }
        cells.push_back(std::move(c));
    }
    std::error_code ec;
    std::vector<std::filesystem::path> files;
    if (std::filesystem::is_directory(dir / "cells", ec))
        for (const auto& e : std::filesystem::directory_iterator(dir / "cells", ec))
            if (e.is_regular_file() && e.path().extension() == ".json") files.push_back(e.path());
    std::sort(files.begin(), files.end());
    for (const auto& f : files) {
        try {
            const json j = read_json(f);
            if (!j.is_object() || j.value("schema", "") != "cellbench.params/1") continue;
            sets.push_back({{"name", f.stem().string()}, {"cell", j.value("cell", "")},
                            {"capacity_ah", j.contains("capacity_ah") ? j["capacity_ah"] : json(nullptr)}});
        } catch (const std::exception&) {
        }
    }
    return {{"cells", std::move(cells)}, {"parameter_sets", std::move(sets)}, {"programs", list_programs(dir)}};
}

json BenchDaemon::start_run(const StartRequest& request) { return impl_->start_run(request); }
json BenchDaemon::stop_run(RunId id) { return impl_->stop_run(id); }
json BenchDaemon::pause_run(RunId id) { return impl_->pause_run(id); }
json BenchDaemon::resume_run(RunId id) { return impl_->resume_run(id); }

// ---- lab integration (issue 7): GET /metrics gathers a snapshot here, metrics.cpp formats it; post() is the
// ---- watchdog's liveness probe of the io_context (cellbenchd's sd_notify WATCHDOG=1 pings).
std::string BenchDaemon::metrics_text() {
    auto& d = *impl_;
    metrics::BenchSnapshot s;
    s.uptime_s = std::chrono::duration<double>(SteadyClock::now() - d.started_at).count();
    s.version = cellbench::version();
    s.git = cellbench::git_describe();
    const bool run_active = d.active() != nullptr;
    {
        std::lock_guard l(d.live_m);
        s.instruments = {{"neware", "cycler", d.neware_state, d.neware_server != nullptr, std::nullopt, 0, 0, std::nullopt},
                         {"chamber", "chamber", d.chamber_state, d.chamber_server != nullptr, std::nullopt, 0, 0, std::nullopt},
                         {"dewe", "daq", d.daq_state, d.dewe_publisher != nullptr, std::nullopt, 0, 0, std::nullopt}};
        if (d.live_cycler) s.voltage_v = d.live_cycler->voltage_v, s.current_a = d.live_cycler->current_a;
        if (d.live_daq) s.surface_c = d.live_daq->surface_c;
        if (d.live_chamber) s.ambient_c = d.live_chamber->ambient_c;
        if (run_active) s.soc = d.live_soc;
        for (auto& i : s.instruments) i.reconnects = d.reconnects.contains(i.name) ? d.reconnects.at(i.name) : 0;
    }
    {
        std::lock_guard l(d.fault_m);
        for (auto& i : s.instruments) {
            if (const auto it = d.fault_count.find(i.name); it != d.fault_count.end()) i.faults = it->second;
            if (i.name == "neware") i.lost_frames = d.lost_answers.contains("neware") ? d.lost_answers.at("neware") : 0;
        }
    }
    if (d.neware_server) s.instruments[0].sim_requests = d.neware_server->stats().requests;
    if (d.chamber_server) s.instruments[1].sim_requests = d.chamber_server->stats().requests;
    if (d.dewe) {
        s.daq_stream = d.dewe->health().stats;
        s.instruments[2].lost_frames = s.daq_stream->lost_frames;
    }
    if (d.store) s.store = d.store->stats();
    if (auto c = d.current()) {
        metrics::RunSnapshot r;
        r.id = c->id;
        r.active = c->live;
        try {
            const json j = d.run_json(c->id);
            r.state = j.value("state", "");
            if (j.contains("step") && j["step"].is_object()) {
                if (j["step"].contains("index") && j["step"]["index"].is_number_integer()) r.step_index = j["step"]["index"].get<int>();
                if (j["step"].contains("count") && j["step"]["count"].is_number_integer()) r.step_count = j["step"]["count"].get<int>();
            }
        } catch (const std::exception& e) {
            spdlog::debug("metrics: run {}: {}", c->id, e.what());
        }
        s.run = std::move(r);
    }
    return metrics::format_bench_metrics(s);
}

void BenchDaemon::post(std::function<void()> fn) { asio::post(impl_->io, std::move(fn)); }
// ---- end of lab integration


sim::PlantOptions simulated_plant_options(const BenchConfig& cfg, estimator::ParameterSet params) {
    if (!cfg.simulation) throw InputError(cfg.source.string() + ": $.simulation: missing (simulated instruments need a cell)");
    const auto& simc = *cfg.simulation;
    if (!simc.hidden.empty()) {
        // Hidden physics the simulated cell has and the model may not (same ids as `diagnose`).
        auto ext = params.extensions.to_json();
        for (const auto& [k, v] : simc.hidden.items()) ext[k] = v;
        params.extensions = estimator::ModelExtensions::from_json(ext, cfg.source.string() + " $.simulation.hidden");
    }
    sim::PlantOptions po;
    po.cell = std::move(params);
    po.initial_soc = simc.initial_soc;
    po.initial_temperature_c = simc.initial_temperature_c;
    po.chamber_setpoint_c = simc.initial_temperature_c;
    po.seed = simc.seed;
    po.heat_flux_sensitivity_v_per_w_per_m2 = cfg.daq.sensitivity_v_per_w_per_m2;
    // The plant's default air ripple is the chamber's worst-case constancy (+-0.5 K, a sine). The
    // sequencer judges equilibrium on the instantaneous air, and the programs' tolerance is 0.5 K: a
    // +-0.5 K sine never stays inside it for the 30 min hold. Simulate a chamber well within its spec.
    po.chamber_ripple_c = std::min(po.chamber_ripple_c, 0.3);
    return po;
}

}  // namespace cellbench::daemon
