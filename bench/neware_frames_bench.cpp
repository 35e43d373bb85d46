// Neware BTS API frames split and parsed per second on one core: the client's whole receive path for
// inquire answers (FrameSplitter over 4 KiB reads + parse_response). At the default 100 ms poll the client
// needs 10 frames/s per connection; the figure says how much headroom that leaves.
#include <benchmark/benchmark.h>

#include <string>
#include <vector>

#include "cellbench/protocol/neware_bts.hpp"

using namespace cellbench::protocol::neware;

namespace {

// An inquire_resp for `channels` channels as the tester pretty-prints it.
std::string inquire_frame(int channels, int seq) {
    InquireResponse r;
    for (int c = 1; c <= channels; ++c) {
        InquireEntry e;
        e.channel = {"", 24, 1, 1, c};
        e.cycle_id = 3;
        e.step_id = 8;
        e.step_type = "dc";
        e.workstatus = ChannelStatus::working;
        e.barcode = "P45B-001";
        e.current_a = -20.0 + 0.0001 * seq;
        e.voltage_v = 3.7 - 0.0001 * c;
        e.capacity_ah = 0.0123 + 1e-6 * seq;
        e.energy_wh = 0.0456;
        e.total_time_s = 26005.3 + 0.1 * seq;
        e.relative_time_s = 12.5;
        e.log_code = 102000;
        r.channels.push_back(e);
    }
    return encode_response(r);
}

std::string stream_of(int channels, int frames) {
    std::string s;
    for (int i = 0; i < frames; ++i) s += inquire_frame(channels, i);
    return s;
}

void split_and_parse(benchmark::State& state, bool parse) {
    const int channels = static_cast<int>(state.range(0));
    constexpr int kFrames = 256;
    const std::string stream = stream_of(channels, kFrames);
    constexpr std::size_t kChunk = 4096;  // a typical async_read_some
    std::int64_t frames = 0;
    for (auto _ : state) {
        FrameSplitter splitter;
        for (std::size_t at = 0; at < stream.size(); at += kChunk) {
            splitter.feed(std::string_view(stream).substr(at, kChunk));
            while (auto f = splitter.next()) {
                if (parse) {
                    auto r = parse_response(*f);
                    benchmark::DoNotOptimize(r);
                } else {
                    benchmark::DoNotOptimize(f->data());
                }
                ++frames;
            }
        }
    }
    state.SetItemsProcessed(frames);
    state.SetBytesProcessed(static_cast<std::int64_t>(stream.size()) * state.iterations());
    state.counters["frame_bytes"] = static_cast<double>(stream.size()) / kFrames;
}

void BM_NewareSplitAndParseInquire(benchmark::State& state) { split_and_parse(state, true); }
void BM_NewareSplitOnly(benchmark::State& state) { split_and_parse(state, false); }

void BM_NewareEncodeInquireRequest(benchmark::State& state) {
    InquireRequest r;
    for (int c = 1; c <= 3; ++c) r.channels.push_back({"127.0.0.1", 24, 1, 1, c});
    for (auto _ : state) {
        auto s = encode_request(r);
        benchmark::DoNotOptimize(s);
    }
    state.SetItemsProcessed(state.iterations());
}

}  // namespace

// 3 = the thesis' parallel group, 8 = a whole BTS-4008.
BENCHMARK(BM_NewareSplitAndParseInquire)->Arg(3)->Arg(8);
BENCHMARK(BM_NewareSplitOnly)->Arg(3);
BENCHMARK(BM_NewareEncodeInquireRequest);

BENCHMARK_MAIN();
