// Recording reader throughput (issue 16): MB/s of the checked readers on the real files -- the CLI's streamed
// file read (NUL, line-length and size checks as the bytes come), the BDF CSV parser (std::from_chars, one
// pass, physical-range checks) and the DewesoftX export parser. BM_ParseBdfCsv in estimator_bench is the same
// BDF parse on the 18 MB HPPC; this adds the steps around it.
#include <benchmark/benchmark.h>

#include <filesystem>

#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/dewesoft_export.hpp"
#include "cli/files.hpp"

using namespace cellbench;

namespace {

const std::filesystem::path kData = std::filesystem::path(CELLBENCH_SHARED_DIR) / "data" / "p45b";

void BM_ReadFileChecked(benchmark::State& state) {
    const auto path = kData / "hppc_1c_30degC.bdf.csv";
    std::size_t bytes = 0;
    for (auto _ : state) {
        const auto text = cli::read_file(path);
        bytes = text.size();
        benchmark::DoNotOptimize(text.data());
    }
    state.SetBytesProcessed(static_cast<int64_t>(state.iterations() * bytes));
}
BENCHMARK(BM_ReadFileChecked)->Unit(benchmark::kMillisecond);

void BM_ReadAndParseBdf(benchmark::State& state) {
    const auto path = kData / "hppc_1c_30degC.bdf.csv";
    std::size_t bytes = 0;
    for (auto _ : state) {
        const auto text = cli::read_file(path);
        bytes = text.size();
        benchmark::DoNotOptimize(protocol::parse_bdf_csv(text, path.string()));
    }
    state.SetBytesProcessed(static_cast<int64_t>(state.iterations() * bytes));
}
BENCHMARK(BM_ReadAndParseBdf)->Unit(benchmark::kMillisecond);

void BM_ParseDewesoftExport(benchmark::State& state) {
    const auto text = cli::read_file(kData / "rw_30degC_dewesoft.csv");
    for (auto _ : state) benchmark::DoNotOptimize(protocol::parse_dewesoft_export(text, "rw_30degC_dewesoft.csv"));
    state.SetBytesProcessed(static_cast<int64_t>(state.iterations() * text.size()));
}
BENCHMARK(BM_ParseDewesoftExport)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
