// Foundation benchmarks (`make bench`): whole `cellbench fit` of the real 436 k-row HPPC (parse included),
// fit time per pulse set, simulation throughput, BDF CSV parse throughput. The scipy baseline of the thesis'
// per-segment method runs right after this program in `make bench` (bench/scipy_baseline.py).
#include <benchmark/benchmark.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "cellbench/estimator/fit.hpp"
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

void BM_SimulateHppc(benchmark::State& state) {
    std::ifstream in(std::filesystem::path(CELLBENCH_SOURCE_DIR) / "config/cells/p45b-thesis.json");
    std::stringstream ss;
    ss << in.rdbuf();
    const estimator::CellModel model(estimator::ParameterSet::from_json(nlohmann::json::parse(ss.str())));
    const auto& rec = hppc();
    for (auto _ : state) benchmark::DoNotOptimize(estimator::simulate(model, rec).voltage_v.back());
    state.SetItemsProcessed(static_cast<int64_t>(state.iterations() * rec.size()));
}
BENCHMARK(BM_SimulateHppc)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
