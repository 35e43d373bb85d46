// API latency (`make bench`): GET /api/v1/status from 50 concurrent clients on loopback against the real
// HTTP server with a fake backend (so the figure is the HTTP layer's, not the bench's). Reported as
// counters p50_ms / p99_ms / max_ms (per request, measured by each client) and req_per_s.
// Goal (issue): p99 < 10 ms with 50 concurrent clients.
//  - KeepAlive: each client holds one connection (the dashboard's way).
//  - NewConnection: a fresh connection per request (the `cellbench` CLI's way).
#include <benchmark/benchmark.h>

#if __has_include("cellbench/daemon/http_server.hpp")  // built only once the daemon library exists

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "../tests/hil/hil_support.hpp"
#include "../tests/unit/api_test_support.hpp"

namespace {

using namespace cellbench::testing;
using Clock = std::chrono::steady_clock;

constexpr int kServerThreads = 2;  // cellbenchd runs a few threads on its io_context

void report(benchmark::State& state, std::vector<double>& ms, double wall_s, int failures) {
    std::sort(ms.begin(), ms.end());
    const auto at = [&](double q) { return ms.empty() ? 0.0 : ms[static_cast<std::size_t>(q * (ms.size() - 1))]; };
    state.counters["p50_ms"] = at(0.50);
    state.counters["p99_ms"] = at(0.99);
    state.counters["max_ms"] = ms.empty() ? 0.0 : ms.back();
    state.counters["req_per_s"] = wall_s > 0 ? static_cast<double>(ms.size()) / wall_s : 0.0;
    state.counters["requests"] = static_cast<double>(ms.size());
    state.counters["failures"] = failures;
}

// `clients` threads each send `per_client` requests; every latency is kept (bounded: clients*per_client).
template <class ClientLoop>
void run_clients(benchmark::State& state, int clients, int per_client, ClientLoop loop) {
    std::vector<double> all;
    int failures = 0;
    double wall_s = 0;
    for (auto _ : state) {
        std::vector<std::vector<double>> lat(static_cast<std::size_t>(clients));
        std::vector<int> failed(static_cast<std::size_t>(clients), 0);
        std::vector<std::thread> threads;
        const auto t0 = Clock::now();
        for (int c = 0; c < clients; ++c)
            threads.emplace_back([&, c] {
                lat[c].reserve(static_cast<std::size_t>(per_client));
                try {
                    loop(lat[c], per_client);
                } catch (const std::exception&) {
                    failed[c] = 1;
                }
            });
        for (auto& t : threads) t.join();
        wall_s += std::chrono::duration<double>(Clock::now() - t0).count();
        for (int c = 0; c < clients; ++c) {
            all.insert(all.end(), lat[c].begin(), lat[c].end());
            failures += failed[c];
        }
    }
    report(state, all, wall_s, failures);
}

void BM_StatusLatency_KeepAlive(benchmark::State& state) {
    spdlog::set_level(spdlog::level::warn);  // no "listening on" lines between the results
    FakeBackend backend;
    TestServer server(backend, {}, kServerThreads);
    const auto port = server.port();
    const std::string req = make_request(http::verb::get, "/api/v1/status");
    run_clients(state, static_cast<int>(state.range(0)), 200, [&](std::vector<double>& lat, int n) {
        Connection conn(port);
        for (int i = 0; i < n; ++i) {
            const auto t = Clock::now();
            conn.send(req);
            const auto r = conn.read();
            if (!r || r->result_int() != 200) throw std::runtime_error("bad answer");
            lat.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t).count());
        }
    });
}
BENCHMARK(BM_StatusLatency_KeepAlive)->Arg(50)->Iterations(3)->Unit(benchmark::kMillisecond)->UseRealTime();

void BM_StatusLatency_NewConnection(benchmark::State& state) {
    spdlog::set_level(spdlog::level::warn);
    FakeBackend backend;
    TestServer server(backend, {}, kServerThreads);
    const auto port = server.port();
    const std::string req = make_request(http::verb::get, "/api/v1/status", "", {{"Connection", "close"}});
    run_clients(state, static_cast<int>(state.range(0)), 40, [&](std::vector<double>& lat, int n) {
        for (int i = 0; i < n; ++i) {
            const auto t = Clock::now();
            Connection conn(port);
            conn.send(req);
            const auto r = conn.read();
            if (!r || r->result_int() != 200) throw std::runtime_error("bad answer");
            lat.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t).count());
        }
    });
}
BENCHMARK(BM_StatusLatency_NewConnection)->Arg(50)->Iterations(3)->Unit(benchmark::kMillisecond)->UseRealTime();

// The figure: 50 keep-alive clients on the real cellbenchd (simulated bench, every instrument hosted)
// while a short HPPC runs at 100x, each cycling through health, status, runs, the run's events and its samples
// at max_points=2000. All answers count (200, or 503/429 with Retry-After: the caps at the edge); p50/p99 are
// over every request, health_p99_ms over /health alone. Each iteration is 50 x 60 requests; the run goes on
// underneath (one run for all iterations; the figure is the API's under acquisition, not the run's end).
void BM_DaemonApiDuringRun(benchmark::State& state) {
    spdlog::set_level(spdlog::level::warn);
    cellbench::test::TempDir tmp("api-bench");
    auto cfg = cellbench::test::sim_bench_config(std::filesystem::path(CELLBENCH_SOURCE_DIR) / "config/bench.sim.json");
    cellbench::daemon::BenchDaemon d(cfg, cellbench::test::daemon_options_in(tmp, 100.0, "t"));
    d.start();
    if (!cellbench::test::eventually([&] { return cellbench::test::instruments_connected(d); }, std::chrono::seconds(30))) {
        state.SkipWithError("the simulated instruments did not connect");
        return;
    }
    const auto id = d.start_run({"hppc_short", "p45b", {}, {}})["id"].get<cellbench::daemon::RunId>();
    const auto port = d.http_port();
    const std::vector<std::string> targets = {"/api/v1/health", "/api/v1/status", "/api/v1/runs",
                                              "/api/v1/runs/" + std::to_string(id) + "/events",
                                              "/api/v1/runs/" + std::to_string(id) + "/samples?max_points=2000"};
    std::vector<double> health;
    std::mutex health_m;
    run_clients(state, static_cast<int>(state.range(0)), 60, [&](std::vector<double>& lat, int n) {
        Connection conn(port);
        std::vector<double> mine;
        for (int i = 0; i < n; ++i) {
            const std::string& target = targets[static_cast<std::size_t>(i) % targets.size()];
            const auto t = Clock::now();
            conn.send(make_request(http::verb::get, target));
            const auto r = conn.read();
            if (!r) throw std::runtime_error("no answer");
            const int code = r->result_int();
            if (code != 200 && code != 503 && code != 429) throw std::runtime_error("bad answer");
            const double ms = std::chrono::duration<double, std::milli>(Clock::now() - t).count();
            lat.push_back(ms);
            if (i % static_cast<int>(targets.size()) == 0) mine.push_back(ms);
        }
        std::lock_guard l(health_m);
        health.insert(health.end(), mine.begin(), mine.end());
    });
    std::sort(health.begin(), health.end());
    state.counters["health_p99_ms"] = health.empty() ? 0.0 : health[static_cast<std::size_t>(0.99 * (health.size() - 1))];
    d.stop_run(id);
    d.shutdown();
}
BENCHMARK(BM_DaemonApiDuringRun)->Arg(50)->Iterations(3)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace

#endif

BENCHMARK_MAIN();
