// The dashboard's live update (`make bench`): server time of GET /api/v1/runs/{id}/samples for the last
// 10 minutes of a run, answered by the real cellbenchd (BenchDaemon on config/bench.sim.json, the real HTTP
// server, a SQLite store) over a keep-alive loopback connection, measured from the request's first byte to
// the response's last.
// Goal (issue 7): < 100 ms for a 10-minute window at full resolution.
//
// The run: 20 minutes with the cycler at 10 Hz, the DAQ at 100 Hz (the DEWE-43A's rate on the real bench; the
// simulated one defaults to 10 Hz) and the chamber at 1 Hz, written through RunStore before the daemon opens
// the database. The window is the last 10 minutes (from = end - 600 s, no `to`, as the live page asks):
//  - FullResolution: max_points=100000, so nothing is decimated: 6 000 cycler rows with every series on
//    them (60 000 DAQ rows and 600 chamber rows read to fill them in).
//  - DashboardRequest: max_points=2800, what the live page asks for at a 1400 px wide chart (min/max buckets).
//  - BackendOnly: BenchDaemon::samples() and the JSON text, no HTTP; StoreOnly: RunStore::samples() (where the
//    time goes).
#include <benchmark/benchmark.h>

#include <unistd.h>

#include <utility>  // before Boost.Asio (Boost 1.74, g++ 12, C++20)

#include <cmath>
#include <filesystem>
#include <memory>
#include <random>

#include <spdlog/spdlog.h>

#include "../tests/unit/api_test_support.hpp"
#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/daemon/run_store.hpp"

using namespace cellbench;
namespace fs = std::filesystem;

namespace {

constexpr double kRunS = 1200.0, kWindowS = 600.0;

struct Fixture {
    fs::path dir;
    std::unique_ptr<daemon::BenchDaemon> d;
    daemon::RunId run = 0;

    Fixture() {
        dir = fs::temp_directory_path() /
              ("cellbench-dashboard-bench-" + std::to_string(::getpid()) + "-" + std::to_string(std::random_device{}()));
        fs::create_directories(dir);
        {
            auto store = daemon::RunStore::open(dir / "bench.sqlite");
            daemon::NewRun nr;
            nr.program = "hppc_short";
            nr.cell = "p45b";
            run = store->create_run(nr);
            std::vector<daemon::CyclerSample> cy;
            for (int k = 0; k < static_cast<int>(kRunS * 10); ++k) {
                daemon::CyclerSample s;
                s.t_s = k * 0.1;
                s.unix_s = 1.7e9 + s.t_s;
                s.voltage_v = 3.7 + 0.05 * std::sin(k * 0.01);
                s.current_a = (k / 300) % 2 ? -3.8 : 0.0;
                s.capacity_ah = 0.0;
                s.energy_wh = 0.0;
                s.soc = 0.9 - k * 1e-6;
                s.step_id = 1 + k / 300;
                s.cycle = 1;
                s.step_type = "dc";
                s.status = "working";
                cy.push_back(s);
            }
            std::vector<daemon::DaqSample> dq;
            for (int k = 0; k < static_cast<int>(kRunS * 100); ++k) {
                const double t = k * 0.01;
                dq.push_back({t, 1.7e9 + t, 7e-4, 30.0 + 1e-3 * t, 31.0, 30.8, 40.0 + std::sin(t), k});
            }
            std::vector<daemon::ChamberSample> ch;
            for (int k = 0; k < static_cast<int>(kRunS); ++k) {
                daemon::ChamberSample s;
                s.t_s = k + 0.5;
                s.unix_s = 1.7e9 + s.t_s;
                s.ambient_c = 30.0;
                s.setpoint_c = 30.0;
                ch.push_back(s);
            }
            // Pushed in pieces the bounded queue accepts.
            const auto push_all = [&](const auto& rows) {
                for (std::size_t at = 0; at < rows.size();) {
                    const std::size_t n = std::min<std::size_t>(20000, rows.size() - at);
                    at += store->push(run, std::span(rows.data() + at, n));
                    store->flush();
                }
            };
            push_all(cy);
            push_all(dq);
            push_all(ch);
            store->flush();
        }
        auto cfg = daemon::load_bench_config(fs::path(CELLBENCH_SOURCE_DIR) / "config/bench.sim.json");
        cfg.cycler.endpoint.port = 0;
        cfg.chamber.endpoint.port = 0;
        daemon::BenchDaemonOptions o;
        o.listen = daemon::Endpoint{"127.0.0.1", 0};
        o.db_path = dir / "bench.sqlite";
        o.daq_socket_path = (dir / "dewe.sock").string();
        d = std::make_unique<daemon::BenchDaemon>(cfg, o);
        d->start();
    }
    ~Fixture() {
        d.reset();
        std::error_code ec;
        fs::remove_all(dir, ec);
    }
};

Fixture* fx = nullptr;

void over_http(benchmark::State& state, std::size_t max_points) {
    cellbench::testing::Connection conn(fx->d->http_port());
    const std::string req = cellbench::testing::make_request(
        cellbench::testing::http::verb::get, "/api/v1/runs/" + std::to_string(fx->run) + "/samples?from=" + std::to_string(kRunS - kWindowS) +
                             "&max_points=" + std::to_string(max_points));
    std::size_t bytes = 0, points = 0;
    bool decimated = true;
    for (auto _ : state) {
        conn.send(req);
        const auto r = conn.read();
        if (!r || r->result_int() != 200) {
            state.SkipWithError("bad answer");
            return;
        }
        bytes = r->body().size();
        state.PauseTiming();
        const auto j = cellbench::testing::json::parse(r->body());
        points = j["time_s"].size();
        decimated = j["decimated"].get<bool>();
        state.ResumeTiming();
    }
    state.counters["points"] = static_cast<double>(points);
    state.counters["decimated"] = decimated ? 1 : 0;
    state.counters["kB"] = static_cast<double>(bytes) / 1024.0;
}

void BM_LiveWindow10min_FullResolution(benchmark::State& state) { over_http(state, daemon::kMaxSamplePoints); }
void BM_LiveWindow10min_DashboardRequest(benchmark::State& state) { over_http(state, 2800); }

void BM_LiveWindow10min_BackendOnly(benchmark::State& state) {
    daemon::SampleQuery q;
    q.from_s = kRunS - kWindowS;
    q.max_points = daemon::kMaxSamplePoints;
    std::size_t bytes = 0;
    for (auto _ : state) {
        const auto j = fx->d->samples(fx->run, q);
        bytes = j.dump().size();
    }
    state.counters["kB"] = static_cast<double>(bytes) / 1024.0;
}

// The store query alone (RunStore::samples: the SQLite reads), for the breakdown.
void BM_LiveWindow10min_StoreOnly(benchmark::State& state) {
    std::size_t rows = 0;
    for (auto _ : state) {
        const auto w = fx->d->store().samples(fx->run, kRunS - kWindowS, std::nullopt, daemon::kMaxSamplePoints);
        rows = 0;
        for (const auto& s : w.sources) rows += s.size();
    }
    state.counters["rows"] = static_cast<double>(rows);
}

}  // namespace

BENCHMARK(BM_LiveWindow10min_StoreOnly)->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(2.0);
BENCHMARK(BM_LiveWindow10min_FullResolution)->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(2.0);
BENCHMARK(BM_LiveWindow10min_DashboardRequest)->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(2.0);
BENCHMARK(BM_LiveWindow10min_BackendOnly)->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(2.0);

int main(int argc, char** argv) {
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    spdlog::set_level(spdlog::level::warn);
    Fixture f;
    fx = &f;
    benchmark::RunSpecifiedBenchmarks();
    fx = nullptr;
    benchmark::Shutdown();
    return 0;
}
