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
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

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

}  // namespace

#endif

BENCHMARK_MAIN();
