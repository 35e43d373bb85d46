// cellbenchd's bench: see bench_daemon.hpp. This file is the wiring: the daemon's construction, start
// (store, hosted instruments, drivers, recovery, timers, HTTP), the bench clock's pacer and tick, and shutdown.
// The pieces of BenchDaemon::Impl: bench_daemon_impl.hpp.
#include "bench_daemon_impl.hpp"

#include <algorithm>

#include <boost/asio/post.hpp>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace cellbench::daemon {

namespace {
// A run's recording, fits and samples in flight are freed when it ends, but glibc keeps freed heap (and the
// fit workers' arenas) mapped; an unattended daemon gives it back between runs so its RSS does not ratchet up
// to the largest run it ever did (soak: RSS at the end within 10 % of RSS after the first run).
// What the heap holds after the trim (all arenas): in use is live data (a leak grows it), free is fragmentation
// the trim could not return (pages pinned by live blocks), mmapped the large blocks outside the arenas. Logged at
// debug, so a soak's log tells retention from fragmentation when RSS ratchets.
void return_free_memory() {
#if defined(__GLIBC__)
    malloc_trim(0);
#if __GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 33)
    if (!spdlog::should_log(spdlog::level::debug)) return;  // mallinfo2 walks every arena under its lock
    const struct mallinfo2 m = mallinfo2();
    constexpr double kMiB = 1024.0 * 1024.0;
    spdlog::debug("heap after trim: {:.2f} MiB in use, {:.2f} MiB free in the arenas ({:.2f} MiB of arena), "
                  "{:.2f} MiB in {} mmapped blocks",
                  static_cast<double>(m.uordblks) / kMiB, static_cast<double>(m.fordblks) / kMiB,
                  static_cast<double>(m.arena) / kMiB, static_cast<double>(m.hblkhd) / kMiB, m.hblks);
#endif
#endif
}
}  // namespace

BenchDaemon::Impl::Impl(BenchConfig c, BenchDaemonOptions o) : cfg(std::move(c)), opt(std::move(o)) {
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

void BenchDaemon::Impl::start() {
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
        pace_gate.emplace(scale, std::min(scale, kPaceGatedScale));
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

void BenchDaemon::Impl::note_db_fault(const std::string& what) {
    const auto written = store ? store->stats().samples_written : 0;
    std::lock_guard l(live_m);
    db_fault = what;
    db_fault_batches = written;
}

// Under live_m: whether samples were committed since the fault was seen (then the fault is over).
bool BenchDaemon::Impl::db_writable_again() {
    if (db_fault.empty()) return true;
    if (store && store->stats().samples_written > db_fault_batches) {
        db_fault.clear();
        return true;
    }
    return false;
}

std::string BenchDaemon::Impl::api_url() const {
    return "http://" + cfg.listen.host + ":" + std::to_string(bound_port ? bound_port : cfg.listen.port) + "/api/v1";
}

void BenchDaemon::Impl::schedule_pace() {
    pace_timer->expires_after(kPacePeriod);
    pace_timer->async_wait([this](const boost::system::error_code& ec) {
        if (ec || stopping) return;
        const auto now = SteadyClock::now();
        // Not past half an instrument's grace beyond its last reading: a daemon that gets some CPU but whose
        // drivers fall behind (or whose hosted tester does) slows the bench down instead of aborting the run.
        std::vector<sim::PaceGate::Source> sources;
        sources.reserve(instruments.size());
        for (const auto& inst : instruments)  // the bench time of each one's last reading: the instrument keeps it
            sources.push_back({inst->name(), inst->last_reading_t_s().value_or(-1.0), grace_for(inst->name())});
        const auto gate = pace_gate->decide(clock->now_s(), sources, now);
        using Change = sim::PaceGate::Change;
        if (gate.change != Change::none) {
            {
                std::lock_guard l(live_m);
                pace_waiting_for = gate.gated ? gate.waiting_for : std::string();
            }
            if (gate.change == Change::closed)
                spdlog::warn("bench time: slowed to x{} while waiting for {} (its last reading {:.0f} s of bench time "
                             "ago, grace {:.0f} s; the daemon or the simulated instrument is behind)",
                             gate.scale, gate.waiting_for, gate.lag_bench_s, grace_for(gate.waiting_for));
            else if (gate.change == Change::gave_up)
                spdlog::warn("bench time: back at x{} with {} still silent after a whole grace of wall time: its "
                             "silence is taken as real", scale, gate.waiting_for);
            else
                spdlog::info("bench time: readings caught up, back at x{}", scale);
        }
        clock->pace(now, gate.scale);
        if (now >= pace_report_at) {
            pace_report_at = now + std::chrono::seconds(10);
            report_pace();
        }
        schedule_pace();
    });
}

// The log says when the bench runs slower than asked (and when it is back), with the scale achieved.
void BenchDaemon::Impl::report_pace() {
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

void BenchDaemon::Impl::schedule_tick() {
    const auto period = std::chrono::milliseconds(std::clamp<std::int64_t>(
        static_cast<std::int64_t>(1000.0 / scale), 1, 200));
    tick_timer->expires_after(period);
    tick_timer->async_wait([this](const boost::system::error_code& ec) {
        if (ec || stopping) return;
        // The tick's time is taken now, not when the feed thread gets to it: readings queued before it carry
        // their arrival times, so a feed thread behind by a second never reads as instrument silence.
        if (auto c = active()) feed([c, t = now_s()] { c->seq->tick(t); });
        else if (auto last = current(); last && last->memory_returned < 2 && last->seq->fits_idle()) {
            // Once per run, after its end fit was delivered: the store's caches, then (a later tick, once the
            // writer has released its cache: it does so at its next commit) the freed heap.
            if (last->memory_returned == 0) {
                last->store_released = store->release_memory();
                last->memory_returned = 1;
            } else if (last->store_released.wait_for(std::chrono::seconds(0)) == std::future_status::ready) {
                return_free_memory();
                last->memory_returned = 2;
                last_idle_trim = std::chrono::steady_clock::now();
            }
        } else if (!active() && std::chrono::steady_clock::now() - last_idle_trim > kIdleTrimPeriod) {
            // Idle between runs, the API still answers (run records, samples, exports): the page caches those
            // queries filled are released, and (once the writer has done so, the next period) the freed heap goes
            // back to the system, so an idle daemon's RSS is its live data, not the high-water mark of the last
            // query. Cheap: the heap is small when no run is active.
            if (!idle_released.valid() || idle_released.wait_for(std::chrono::seconds(0)) == std::future_status::ready) {
                return_free_memory();
                idle_released = store->release_memory();
            }
            last_idle_trim = std::chrono::steady_clock::now();
        }
        schedule_tick();
    });
}

void BenchDaemon::Impl::shutdown() {
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
    instruments.stop_all();
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
