// DEWE-43A CAN decoding throughput on one core. Goal: keep up with two saturated CAN 2.0B buses (~16 k
// frames/s) with under 5 % of a core. `core_pct_at_16k` is the percentage of one core that 16 000 frames/s
// take at the measured speed (goal: < 5; Google Benchmark prints it with an "s" because it is an inverted rate).
#include <benchmark/benchmark.h>

#include <sys/socket.h>
#include <unistd.h>

#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/protocol/dewe_can.hpp"
#include "cellbench/protocol/heat_flux.hpp"

namespace {

using namespace cellbench::protocol;

constexpr double kTwoSaturatedBusesFramesPerS = 16000.0;

// One full cycle of the 16-bit counter: looping over it never shows a gap.
std::vector<CanRecord> records_of(const DeweCanLayout& layout, std::uint64_t samples) {
    std::vector<CanRecord> records;
    for (std::uint64_t k = 0; k < samples; ++k)
        for (const auto& f : encode_dewe_sample(layout, {1e-3 + 1e-9 * k, 30.0, 30.5, 29.5}, k))
            records.push_back(encode_can_record(f));
    return records;
}

void add_counters(benchmark::State& state, std::int64_t frames) {
    state.SetItemsProcessed(frames);
    state.counters["frames_per_s"] = benchmark::Counter(static_cast<double>(frames), benchmark::Counter::kIsRate);
    // Inverted rate of (frames / 16 000 / 100): percent of a core busy per second of two saturated buses.
    state.counters["core_pct_at_16k"] = benchmark::Counter(static_cast<double>(frames) / (kTwoSaturatedBusesFramesPerS * 100.0),
                                                           benchmark::Counter::kIsRate | benchmark::Counter::kInvert);
}

// Record bytes -> frame -> layout decode -> sample, and the heat flux conversion the driver adds.
void BM_DecodeRecordsToHeatFlux(benchmark::State& state) {
    const auto layout = DeweCanLayout::bench_default();
    const auto records = records_of(layout, 65536);
    DeweCanDecoder decoder(layout);
    std::size_t i = 0;
    double sum = 0.0;
    for (auto _ : state) {
        const auto s = decoder.push_record(records[i], static_cast<double>(i));
        if (s) sum += heat_flux_density_w_per_m2(s->thermopile_v(), s->type_t_c(), kFhf05ThesisSensitivityVPerWPerM2);
        if (++i == records.size()) i = 0;
    }
    benchmark::DoNotOptimize(sum);
    if (decoder.stats().lost_samples != 0 || decoder.stats().garbage != 0) state.SkipWithError("unexpected loss");
    add_counters(state, static_cast<std::int64_t>(state.iterations()));
}
BENCHMARK(BM_DecodeRecordsToHeatFlux);

// A heavier layout: big-endian fields, a 24-bit value, an extended identifier, 1-byte counters.
void BM_DecodeMixedLayout(benchmark::State& state) {
    const auto layout = DeweCanLayout::from_json(nlohmann::json::parse(R"({
      "frames": [{"can_id": "0x18FF0010", "counter": {"byte_offset": 7, "length": 1}},
                 {"can_id": "0x501", "counter": {"byte_offset": 0, "length": 1}}],
      "channels": {
        "thermopile_v": {"can_id": "0x18FF0010", "byte_offset": 0, "type": "float32", "byte_order": "big"},
        "type_t_c": {"can_id": "0x18FF0010", "byte_offset": 4, "length": 2, "type": "signed", "byte_order": "big", "scale": 0.1},
        "t1_c": {"can_id": "0x501", "byte_offset": 1, "length": 3, "type": "unsigned", "scale": 0.001, "offset": -100},
        "t2_c": {"can_id": "0x501", "byte_offset": 4, "length": 2, "type": "unsigned", "byte_order": "big", "scale": 0.01}}})"));
    const auto records = records_of(layout, 256);
    DeweCanDecoder decoder(layout);
    std::size_t i = 0;
    for (auto _ : state) {
        benchmark::DoNotOptimize(decoder.push_record(records[i], 0.0));
        if (++i == records.size()) i = 0;
    }
    add_counters(state, static_cast<std::int64_t>(state.iterations()));
}
BENCHMARK(BM_DecodeMixedLayout);

// The can-dgram path as the driver sees it: one datagram per frame through a Unix datagram socket (send and
// receive syscalls both counted, so this overstates the receiving side), then decoded.
void BM_UnixDatagramSendReceiveDecode(benchmark::State& state) {
    int fds[2];
    if (::socketpair(AF_UNIX, SOCK_DGRAM, 0, fds) != 0) {
        state.SkipWithError("socketpair failed");
        return;
    }
    const auto layout = DeweCanLayout::bench_default();
    const auto records = records_of(layout, 65536);
    DeweCanDecoder decoder(layout);
    constexpr std::size_t kBatch = 8;  // below the default datagram queue length
    std::size_t i = 0;
    std::int64_t frames = 0;
    std::uint8_t buffer[64];
    for (auto _ : state) {
        for (std::size_t b = 0; b < kBatch; ++b)
            (void)::send(fds[0], records[(i + b) % records.size()].data(), kCanRecordBytes, 0);
        for (std::size_t b = 0; b < kBatch; ++b) {
            const auto n = ::recv(fds[1], buffer, sizeof buffer, 0);
            if (n > 0) benchmark::DoNotOptimize(decoder.push_record({buffer, static_cast<std::size_t>(n)}, 0.0));
        }
        i = (i + kBatch) % records.size();
        frames += kBatch;
    }
    ::close(fds[0]);
    ::close(fds[1]);
    if (decoder.stats().lost_samples != 0) state.SkipWithError("unexpected loss");
    add_counters(state, frames);
}
BENCHMARK(BM_UnixDatagramSendReceiveDecode);

}  // namespace

BENCHMARK_MAIN();
