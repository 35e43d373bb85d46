// Foundation benchmarks (`make bench`): whole `cellbench fit` of the real 436 k-row HPPC (parse included),
// fit time per pulse set, simulation throughput, BDF CSV parse throughput. The scipy baseline of the thesis'
// per-segment method runs right after this program in `make bench` (bench/scipy_baseline.py).
#include <benchmark/benchmark.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/generate.hpp"
#include "cellbench/estimator/model.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

using namespace cellbench;

namespace {

const std::filesystem::path kData = std::filesystem::path(CELLBENCH_SHARED_DIR) / "data" / "p45b";

const std::string& hppc_text() {
    static const std::string text = [] {
        std::ifstream in(kData / "hppc_1c_30degC.bdf.csv", std::ios::binary);
        std::stringstream ss;
        ss << in.rdbuf();
        return ss.str();
    }();
    return text;
}

const Recording& hppc() {
    static const Recording rec = protocol::parse_bdf_csv(hppc_text(), "hppc_1c_30degC.bdf.csv");
    return rec;
}

void BM_ParseBdfCsv(benchmark::State& state) {
    const auto& text = hppc_text();
    for (auto _ : state) benchmark::DoNotOptimize(protocol::parse_bdf_csv(text, "hppc"));
    state.SetBytesProcessed(static_cast<int64_t>(state.iterations() * text.size()));
    state.counters["MB_per_s"] = benchmark::Counter(static_cast<double>(state.iterations() * text.size()) / 1e6,
                                                    benchmark::Counter::kIsRate);
    state.counters["rows"] = static_cast<double>(hppc().size());
}
BENCHMARK(BM_ParseBdfCsv)->Unit(benchmark::kMillisecond);

// The whole fit of the HPPC recording: parse + segmentation + every pulse set (both methods) + thermal.
void BM_WholeFitHppc(benchmark::State& state) {
    const auto& text = hppc_text();
    std::size_t sets = 0;
    for (auto _ : state) {
        const auto rec = protocol::parse_bdf_csv(text, "hppc");
        const auto c = estimator::characterize({rec});
        sets = c.pulse_fits.size();
        benchmark::DoNotOptimize(c.params.capacity_ah);
    }
    state.counters["pulse_sets"] = static_cast<double>(sets);
}
BENCHMARK(BM_WholeFitHppc)->Unit(benchmark::kMillisecond)->Iterations(3);

// Like for like with bench/scipy_baseline.py: parse + find the pulse sets + the thesis' per-segment fits.
void BM_ThesisMethodOnlyHppc(benchmark::State& state) {
    const auto& text = hppc_text();
    estimator::PulseFitOptions po;
    po.joint_method = false;
    for (auto _ : state) {
        const auto rec = protocol::parse_bdf_csv(text, "hppc");
        const auto seg = estimator::segment_recording(rec);
        for (const auto& ps : seg.pulse_sets) benchmark::DoNotOptimize(estimator::fit_pulse_set(rec, ps, po).r0);
    }
}
BENCHMARK(BM_ThesisMethodOnlyHppc)->Unit(benchmark::kMillisecond)->Iterations(3);

void BM_FitOnePulseSet(benchmark::State& state) {
    const auto& rec = hppc();
    const auto seg = estimator::segment_recording(rec);
    const auto& ps = seg.pulse_sets.at(static_cast<std::size_t>(state.range(0)));
    estimator::PulseFitOptions po;
    po.docv_dah_v_per_ah = 0.9 / 3.8;
    for (auto _ : state) benchmark::DoNotOptimize(estimator::fit_pulse_set(rec, ps, po).joint_rms_v);
}
BENCHMARK(BM_FitOnePulseSet)->Arg(4)->Arg(8)->Unit(benchmark::kMillisecond);

const estimator::CellModel& thesis_model() {
    static const estimator::CellModel model = [] {
        std::ifstream in(std::filesystem::path(CELLBENCH_SOURCE_DIR) / "config/cells/p45b-thesis.json");
        std::stringstream ss;
        ss << in.rdbuf();
        return estimator::CellModel(estimator::ParameterSet::from_json(nlohmann::json::parse(ss.str())));
    }();
    return model;
}

// A drive profile under current on every row (the case diagnose simulates over and over): the generator's
// one-hour randomized validation profile of the thesis cell, with sensor noise.
const Recording& drive_cycle() {
    static const Recording rec = [] {
        estimator::GeneratorOptions g;
        g.seed = 1;
        return estimator::generate_case(thesis_model().params(), g).validation;
    }();
    return rec;
}

// The loop simulate() ran before its fast path: CellModel::step row by row (the reference the fast path is
// pinned to in tests/unit/model_fast_test.cpp). For the speed-up ratio only.
double simulate_reference(const estimator::CellModel& model, const Recording& rec) {
    estimator::CellState s;
    s.soc = 0.9;
    s.temperature_c = 30.0;
    std::vector<double> v(rec.size()), t(rec.size());
    for (std::size_t k = 0; k < rec.size(); ++k) {
        const double dt = k == 0 ? 0.0 : rec.time_s[k] - rec.time_s[k - 1];
        v[k] = model.step(s, rec.current_a[k], 30.0, dt).voltage_v;
        t[k] = s.temperature_c;
    }
    return v.back() + t.back();
}

// Simulation throughput on one core (issue 11's goal: >= 10 M samples/s), the whole simulate() call: trace
// allocation, every output column.
void simulate_bench(benchmark::State& state, const Recording& rec, bool reference) {
    const auto& model = thesis_model();
    for (auto _ : state) {
        if (reference)
            benchmark::DoNotOptimize(simulate_reference(model, rec));
        else
            benchmark::DoNotOptimize(estimator::simulate(model, rec).voltage_v.back());
    }
    state.counters["samples_per_s"] = benchmark::Counter(static_cast<double>(state.iterations() * rec.size()),
                                                         benchmark::Counter::kIsRate);
    state.counters["rows"] = static_cast<double>(rec.size());
}
void BM_SimulateHppc(benchmark::State& state) { simulate_bench(state, hppc(), false); }
void BM_SimulateHppcReferenceStep(benchmark::State& state) { simulate_bench(state, hppc(), true); }
void BM_SimulateDriveCycle(benchmark::State& state) { simulate_bench(state, drive_cycle(), false); }
void BM_SimulateDriveCycleReferenceStep(benchmark::State& state) { simulate_bench(state, drive_cycle(), true); }
BENCHMARK(BM_SimulateHppc)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_SimulateHppcReferenceStep)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_SimulateDriveCycle)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_SimulateDriveCycleReferenceStep)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
