// cellbenchd: runs the battery-cell test bench unattended (INTERFACES.md, "Daemon").
//   cellbenchd --config FILE [--listen HOST:PORT] [--db PATH] [--token TOKEN] [--time-scale X] [--web-root DIR]
// Exit status: 0 after a clean shutdown (SIGTERM/SIGINT), 1 bad configuration or failure to start, 2 usage.
#include <csignal>
#if defined(__GLIBC__)
#include <malloc.h>
#endif
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <optional>
#include <string>

#include <CLI/CLI.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/signal_set.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/core/version.hpp"
#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/daemon/http_server.hpp"
#include "cellbench/daemon/systemd.hpp"

using namespace cellbench;

int main(int argc, char** argv) {
#if defined(__GLIBC__)
    // Two malloc arenas instead of glibc's default of eight per core: the daemon's threads (instruments, store,
    // fit workers, HTTP) allocate briefly and free, and with an arena each their freed heap stays spread over
    // arenas malloc_trim cannot fully return (soak, seed 6: RSS after the last run +75 % over the first with the
    // default, +21.5 % with two arenas). MALLOC_ARENA_MAX in the environment still decides when it is set.
    if (!std::getenv("MALLOC_ARENA_MAX")) mallopt(M_ARENA_MAX, 2);
    // A fixed trim threshold (glibc's initial 128 KiB). glibc raises it each time a large mapped block is freed (up
    // to 64 MiB), and malloc_trim returns the free chunks of every arena but the top of the main arena's heap only:
    // the fit workers' arena kept its heap's top resident after a run's end fit (soak, seed 6: anonymous memory
    // 3.7 MiB after the first run, 9.5 after the 40 degC HPPC with the dynamic threshold; 5.0 fixed). With the
    // threshold fixed, free() gives such a top back once it exceeds 128 KiB. MALLOC_TRIM_THRESHOLD_ still decides.
    if (!std::getenv("MALLOC_TRIM_THRESHOLD_")) mallopt(M_TRIM_THRESHOLD, 128 * 1024);
#endif
    CLI::App app{"cellbenchd: the battery-cell test bench daemon (REST/JSON API under /api/v1)"};
    std::string config = "config/bench.sim.json";
    std::string listen, db, token;
    std::optional<double> time_scale;
    bool verbose = false, quiet = false;
    app.add_option("--config", config, "Bench configuration (cellbench.bench/1)")->capture_default_str();
    app.add_option("--listen", listen, "API address HOST:PORT (default: the config's listen, 127.0.0.1:8750)");
    app.add_option("--db", db, "SQLite database of the runs (default: the config's database.path)");
    app.add_option("--token", token, "API bearer token for POST endpoints (default: $CELLBENCH_TOKEN)");
    app.add_option("--time-scale", time_scale, "Bench seconds per wall second of the simulated instruments")
        ->check(CLI::PositiveNumber);
    std::string web_root;
    app.add_option("--web-root", web_root,
                   "Serve the dashboard from this folder (e.g. build/web/dist) instead of the one built in")
        ->check(CLI::ExistingDirectory);
    app.set_version_flag("--version", cellbench::version_string(), "Print the version and exit");
    app.add_flag("-v,--verbose", verbose, "Debug logging");
    app.add_flag("-q,--quiet", quiet, "Warnings and errors only");
    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        const int code = app.exit(e);
        return code == 0 ? 0 : 2;
    }
    spdlog::set_level(quiet ? spdlog::level::warn : verbose ? spdlog::level::debug : spdlog::level::info);
    // Under systemd: "<N>" priorities instead of time stamps when logging to the journal; sd_notify.
    daemon::systemd::use_journal_format_if_connected();
    const auto notifier = daemon::systemd::Notifier::from_environment();

    daemon::BenchConfig cfg;
    daemon::BenchDaemonOptions opt;
    try {
        cfg = daemon::load_bench_config(config);
        if (!listen.empty()) {
            const auto ep = daemon::parse_endpoint(listen);
            if (!ep) {
                std::fprintf(stderr, "cellbenchd: --listen: expected HOST:PORT, got \"%s\"\n", listen.c_str());
                return 2;
            }
            opt.listen = *ep;
        }
    } catch (const InputError& e) {  // ConfigError lists every problem, one per line
        std::fprintf(stderr, "cellbenchd: bad configuration:\n%s\n", e.what());
        return 1;
    }
    if (!db.empty()) opt.db_path = db;
    opt.time_scale = time_scale;
    // The HTTP server reads it when it starts (HttpServerOptions::static_dir); set before any thread runs.
    opt.web_root = web_root;
    opt.token = token;
    if (opt.token.empty()) {
        const char* env = std::getenv(cfg.token_env.empty() ? "CELLBENCH_TOKEN" : cfg.token_env.c_str());
        if (env) opt.token = env;
    }
    if (opt.token.empty())
        spdlog::warn("no API token (--token or ${}): POST endpoints are refused", cfg.token_env);

    try {
        daemon::BenchDaemon bench(cfg, opt);
        bench.start();
        std::printf("cellbenchd: API %s\ncellbenchd: database %s\n", bench.api_url().c_str(),
                    bench.database_path().string().c_str());
        std::fflush(stdout);
        notifier.notify("READY=1\nSTATUS=API " + bench.api_url());
        // WATCHDOG=1 at half the timeout, only while the daemon's io_context runs what is posted to it.
        std::optional<daemon::systemd::Watchdog> watchdog;
        if (const auto timeout = daemon::systemd::watchdog_timeout(); timeout && notifier.active())
            watchdog.emplace(notifier, *timeout / 2, [&bench](std::function<void()> done) { bench.post(std::move(done)); });

        // Signals on their own io_context in the main thread: the daemon's threads never block on them.
        boost::asio::io_context signals_io;
        boost::asio::signal_set signals(signals_io, SIGINT, SIGTERM);
        signals.async_wait([&](const boost::system::error_code& ec, int sig) {
            if (!ec) spdlog::info("signal {}: shutting down", sig);
            notifier.notify("STOPPING=1\nSTATUS=shutting down");
        });
        signals_io.run();
        if (watchdog) watchdog->stop();
        bench.shutdown();
    } catch (const InputError& e) {
        std::fprintf(stderr, "cellbenchd: %s\n", e.what());
        return 1;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "cellbenchd: cannot start: %s\n", e.what());
        return 1;
    }
    return 0;
}
