#pragma once
// cellbenchd's bench: from a BenchConfig it hosts the simulated instruments (when the config says
// "simulated"), connects the real drivers to them (or to real instruments), adapts the drivers to the
// sequencer's interfaces, feeds every reading into the sequencer and the run store on one clock, and serves
// the REST API (ApiBackend) through the HTTP server.
//
// Clock: every reading is stamped in bench seconds of one BenchClock (the simulated instruments' clock, so a
// time-scaled simulation and the daemon agree on "now"; scale 1 for real instruments), converted from the
// driver's steady_clock receive instant. Store rows carry t_s = bench time - run start, plus wall time.
//
// Threading: one io_context run by a few threads (drivers, HTTP, tick timer). The sequencer serialises its own
// calls; the daemon's own locks are leaves (never held while calling the sequencer from a sink callback).
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/daemon/run_store.hpp"
#include "cellbench/sim/plant.hpp"

namespace cellbench::sim {
class BenchPlant;
class NewareServer;
class ChamberServer;
class DewePublisher;
}

namespace cellbench::daemon {

struct BenchDaemonOptions {
    std::optional<Endpoint> listen;               // overrides BenchConfig::listen (port 0 = any free port)
    std::optional<std::filesystem::path> db_path; // overrides BenchConfig::database.path
    std::string token;                            // API bearer token; empty = mutating endpoints refused
    std::optional<double> time_scale;             // overrides simulation.time_scale
    std::optional<std::string> daq_socket_path;   // overrides the can-dgram socket path (tests: a temp path)
    std::optional<double> daq_sample_rate_hz;     // simulated DEWE rate in bench Hz (default 10)
    std::optional<std::int64_t> db_max_page_count; // database size limit in pages (tests: a "full disk")
    std::optional<std::chrono::milliseconds> db_busy_timeout;  // wait for another process's lock (default 2 s)
    std::filesystem::path web_root;               // serve the dashboard from this folder (empty: built in)
    int io_threads = 2;
};

class BenchDaemon final : public ApiBackend {
public:
    BenchDaemon(BenchConfig config, BenchDaemonOptions options = {});
    ~BenchDaemon() override;  // shutdown()
    BenchDaemon(const BenchDaemon&) = delete;
    BenchDaemon& operator=(const BenchDaemon&) = delete;

    // Opens the store, hosts the simulated instruments, connects the drivers, recovers interrupted runs
    // (instruments commanded safe, one recovery event per run), starts the tick timer and the HTTP server.
    // Throws (InputError / std::runtime_error) when any of that cannot be done.
    void start();
    // Stops the active run (current off, chamber to its safe set point), flushes and closes the store, stops
    // drivers, servers and the HTTP listener. Idempotent.
    void shutdown();

    [[nodiscard]] std::string api_url() const;              // "http://127.0.0.1:8750/api/v1"
    [[nodiscard]] std::uint16_t http_port() const;          // bound port (after start)
    [[nodiscard]] std::filesystem::path database_path() const;
    [[nodiscard]] double bench_now_s() const;               // the daemon's clock
    [[nodiscard]] double time_scale() const;                // asked for (bench s per wall s)
    // Achieved over about the last 10 s: below time_scale() when the host starves a daemon that hosts the whole
    // simulated bench (its bench time is paced, sim::BenchClock::Paced).
    [[nodiscard]] double achieved_time_scale() const;
    [[nodiscard]] RunStore& store();
    // The simulated plant (nullptr when no instrument is simulated): tests inject faults through it.
    [[nodiscard]] sim::BenchPlant* plant();
    // The simulated instruments the daemon hosts (nullptr when that instrument is real): their fault switches.
    [[nodiscard]] sim::NewareServer* neware_server();
    [[nodiscard]] sim::ChamberServer* chamber_server();
    [[nodiscard]] sim::DewePublisher* dewe_publisher();
    // The active (running or paused) run, if any.
    [[nodiscard]] std::optional<RunId> active_run() const;

    // ApiBackend (thread-safe).
    nlohmann::json health() override;
    nlohmann::json status() override;
    nlohmann::json list_runs() override;
    nlohmann::json get_run(RunId id) override;
    nlohmann::json samples(RunId id, const SampleQuery& query) override;
    std::shared_ptr<const std::string> samples_body(RunId id, const SampleQuery& query) override;
    nlohmann::json events(RunId id) override;
    nlohmann::json fits(RunId id) override;
    nlohmann::json steps(RunId id) override;
    std::unique_ptr<ExportCursor> export_bdf_csv(RunId id) override;
    nlohmann::json start_run(const StartRequest& request) override;
    nlohmann::json stop_run(RunId id) override;
    nlohmann::json pause_run(RunId id) override;
    nlohmann::json resume_run(RunId id) override;
    // Diagnosis jobs (diagnose_jobs.hpp: one worker thread, one job at a time, a short queue, the last 8 kept).
    nlohmann::json diagnose_run(RunId id, const DiagnoseRequest& request) override;
    nlohmann::json diagnose_recording(const DiagnoseRequest& request, std::string csv) override;
    nlohmann::json diagnosis(std::int64_t job) override;
    nlohmann::json list_diagnoses() override;
    nlohmann::json cells() override;
    std::string metrics_text() override;

    // Runs fn on the daemon's io_context (cellbenchd's watchdog: a probe that runs proves the loop is alive).
    void post(std::function<void()> fn);

    struct Impl;

private:
    std::unique_ptr<Impl> impl_;
};

// The simulated plant of a bench config: its cell (the parameter set plus the config's hidden physics),
// initial state, seed and sensor. Shared by cellbenchd (hosting the simulation) and `cellbench sim`.
sim::PlantOptions simulated_plant_options(const BenchConfig& cfg, estimator::ParameterSet params);

}  // namespace cellbench::daemon
