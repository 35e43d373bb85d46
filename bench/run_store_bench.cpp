// Sustained ingest into the SQLite run store (goal: >= 50 k samples/s with one core busy elsewhere).
//
// A producer pushes the bench's mix as fast as the store accepts it (cycler 10 Hz : DAQ 100 Hz : chamber 1 Hz,
// i.e. 10 : 100 : 1 rows), waiting whenever the bounded queue is full, and the clock stops only when everything
// is committed (flush), so the figure is what reaches the disk, not what fits in memory. A second thread spins
// for the whole run to take one core away, as the daemon's I/O and fitting threads would.
//
// Arg: samples per push() call (1 = the daemon pushing each sample as it arrives; 100 = a driver handing over
// a decoded burst).
#include <benchmark/benchmark.h>

#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <random>
#include <thread>
#include <vector>

#include "cellbench/daemon/run_store.hpp"

using namespace cellbench;
using namespace cellbench::daemon;
namespace fs = std::filesystem;

namespace {

class BusyCore {
public:
    BusyCore()
        : thread_([this] {
              volatile double x = 0.0;
              while (!stop_.load(std::memory_order_relaxed)) x = x + 1.0;
          }) {}
    ~BusyCore() {
        stop_ = true;
        thread_.join();
    }

private:
    std::atomic<bool> stop_{false};
    std::thread thread_;
};

// Pushes the next n rows in calls of per_call samples, waiting while the queue is full.
template <class Sample>
void push_some(RunStore& store, RunId run, const std::vector<Sample>& rows, std::size_t& next, std::size_t n,
               std::size_t per_call) {
    const std::size_t end = std::min(rows.size(), next + n);
    while (next < end) {
        const std::size_t k = std::min(per_call, end - next);
        const std::size_t got = store.push(run, std::span<const Sample>(rows.data() + next, k));
        next += got;
        if (got == 0) std::this_thread::yield();  // queue full: let the writer catch up
    }
}

void BM_RunStoreIngest(benchmark::State& state) {
    const std::size_t per_call = static_cast<std::size_t>(state.range(0));
    const fs::path dir = fs::temp_directory_path() / ("cellbench-bench-" + std::to_string(::getpid()) + "-" +
                                                      std::to_string(std::random_device{}()));
    fs::create_directories(dir);
    constexpr std::size_t kDaq = 200000, kCycler = kDaq / 10, kChamber = kDaq / 100;
    std::vector<CyclerSample> cy(kCycler);
    std::vector<DaqSample> dq(kDaq);
    std::vector<ChamberSample> ch(kChamber);
    for (std::size_t k = 0; k < kCycler; ++k) {
        auto& s = cy[k];
        s.t_s = k * 0.1;
        s.unix_s = 1.7e9 + s.t_s;
        s.voltage_v = 3.7;
        s.current_a = -4.5;
        s.capacity_ah = 0.00125 * s.t_s;
        s.energy_wh = 0.0046 * s.t_s;
        s.soc = 0.9;
        s.step_id = 8;
        s.cycle = 3;
        s.step_type = "cccv_dc";
        s.status = "working";
    }
    for (std::size_t k = 0; k < kDaq; ++k) {
        auto& s = dq[k];
        s.t_s = k * 0.01;
        s.unix_s = 1.7e9 + s.t_s;
        s.thermopile_v = 7e-4;
        s.surface_c = 30.5;
        s.t1_c = 31.0;
        s.t2_c = 30.8;
        s.heat_flux_w_per_m2 = 40.1;
        s.sequence = static_cast<std::int64_t>(k);
    }
    for (std::size_t k = 0; k < kChamber; ++k) {
        auto& s = ch[k];
        s.t_s = static_cast<double>(k);
        s.unix_s = 1.7e9 + s.t_s;
        s.ambient_c = 30.0;
        s.setpoint_c = 30.0;
        s.running = true;
    }

    std::uint64_t total = 0;
    {
        BusyCore busy;
        for (auto _ : state) {
            state.PauseTiming();
            fs::remove(dir / "bench.sqlite");
            fs::remove(dir / "bench.sqlite-wal");
            fs::remove(dir / "bench.sqlite-shm");
            auto store = RunStore::open(dir / "bench.sqlite");
            NewRun nr;
            nr.program = "bench";
            nr.cell = "p45b";
            const RunId run = store->create_run(nr);
            state.ResumeTiming();

            // Interleaved as the instruments deliver them: per 1 s of bench time, 100 DAQ, 10 cycler, 1 chamber.
            std::size_t ic = 0, id = 0, ih = 0;
            while (id < kDaq) {
                push_some(*store, run, dq, id, 100, per_call);
                push_some(*store, run, cy, ic, 10, per_call);
                push_some(*store, run, ch, ih, 1, per_call);
            }
            store->flush();
            total += kDaq + kCycler + kChamber;
            const auto st = store->stats();
            if (st.samples_written != kDaq + kCycler + kChamber) state.SkipWithError("samples were lost");

            state.PauseTiming();
            store.reset();
            state.ResumeTiming();
        }
    }
    state.counters["samples_per_s"] = benchmark::Counter(static_cast<double>(total), benchmark::Counter::kIsRate);
    std::error_code ec;
    fs::remove_all(dir, ec);
}

// The plot query of GET /runs/{id}/samples: a run with 1 M DAQ rows (2.8 h at 100 Hz) and 100 k cycler rows,
// the whole range decimated to 2000 points (min/max per bucket, one pass over the rows).
void BM_RunStoreWindow(benchmark::State& state) {
    const fs::path dir = fs::temp_directory_path() / ("cellbench-bench-" + std::to_string(::getpid()) + "-" +
                                                      std::to_string(std::random_device{}()));
    fs::create_directories(dir);
    auto store = RunStore::open(dir / "bench.sqlite");
    NewRun nr;
    nr.program = "bench";
    nr.cell = "p45b";
    const RunId run = store->create_run(nr);
    std::vector<DaqSample> dq(10000);
    for (std::size_t chunk = 0; chunk < 100; ++chunk) {
        for (std::size_t k = 0; k < dq.size(); ++k) {
            const double t = static_cast<double>(chunk * dq.size() + k) * 0.01;
            dq[k] = DaqSample{t, 1.7e9 + t, 7e-4, 30.0 + 0.001 * t, 31.0, 30.8, 40.0, static_cast<std::int64_t>(k)};
        }
        std::size_t next = 0;
        push_some(*store, run, dq, next, dq.size(), dq.size());
        std::vector<CyclerSample> cy(1000);
        for (std::size_t k = 0; k < cy.size(); ++k) {
            cy[k].t_s = static_cast<double>(chunk * cy.size() + k) * 0.1;
            cy[k].unix_s = 1.7e9 + cy[k].t_s;
            cy[k].voltage_v = 3.7;
            cy[k].current_a = -4.5;
        }
        next = 0;
        push_some(*store, run, cy, next, cy.size(), cy.size());
    }
    store->flush();
    for (auto _ : state) {
        const auto w = store->samples(run, std::nullopt, std::nullopt, 2000);
        benchmark::DoNotOptimize(w.sources.size());
    }
    state.counters["rows_per_s"] =
        benchmark::Counter(static_cast<double>(state.iterations()) * 1.1e6, benchmark::Counter::kIsRate);
    store.reset();
    std::error_code ec;
    fs::remove_all(dir, ec);
}

}  // namespace

BENCHMARK(BM_RunStoreWindow)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_RunStoreIngest)->Arg(1)->Arg(100)->Unit(benchmark::kMillisecond)->UseRealTime()->Iterations(3);

BENCHMARK_MAIN();
