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

// One poll of the thesis' 3-member parallel group, both directions, as client and tester do it: the client
// serializes inquire (3 channels), the tester parses it and serializes inquire_resp, the client splits and
// parses that; then per member download (donwload_resp with `rows` rows, the real server's attribute layout
// and atime per row). Items = frames (each serialized once and parsed once): 8 per round.
void BM_NewareInquireDownloadRoundTrip(benchmark::State& state) {
    const int rows = static_cast<int>(state.range(0));
    std::vector<ChannelAddress> members;
    for (int c = 1; c <= 3; ++c) members.push_back({"127.0.0.1", 27, 21, 1, c});
    InquireResponse live;
    for (const auto& m : members) {
        InquireEntry e;
        e.channel = {"", m.devtype, m.devid, m.subdevid, m.chlid};
        e.cycle_id = 3;
        e.step_id = 8;
        e.step_type = "dc";
        e.workstatus = ChannelStatus::working;
        e.barcode = "P45B-001";
        e.current_a = -1.5;
        e.voltage_v = 3.7;
        e.capacity_ah = 0.0123;
        e.energy_wh = 0.0456;
        e.total_time_s = 26005.3;
        e.relative_time_s = 12.5;
        e.log_code = 102000;
        live.channels.push_back(e);
    }
    std::vector<DownloadResponse> downloads;
    for (const auto& m : members) {
        DownloadResponse d;
        d.channel = {"", m.devtype, m.devid, m.subdevid, m.chlid};
        d.testid = 143;
        d.startpos = 219576;
        for (int k = 0; k < rows; ++k) {
            DownloadRecord r;
            r.seqid = 219576 + k;
            r.step_id = 24;
            r.cycle_id = 29;
            r.step_type = "dc";
            r.test_time_s = 36070.0 + 0.1 * k;
            r.atime = "2025-12-28 22:29:05";
            r.voltage_v = 3.6780698299408;
            r.current_a = -1.500295051460852847;
            r.capacity_ah = 0.00295628436449786;
            r.energy_wh = 0.0135611368830335;
            d.records.push_back(r);
        }
        downloads.push_back(d);
    }
    std::int64_t frames = 0, bytes = 0;
    FrameSplitter splitter;
    auto through = [&](const std::string& wire, bool response) {
        splitter.feed(wire);
        auto f = splitter.next();
        bytes += static_cast<std::int64_t>(wire.size());
        ++frames;
        if (response) {
            auto r = parse_response(*f);
            benchmark::DoNotOptimize(r);
        } else {
            auto q = parse_request(*f);
            benchmark::DoNotOptimize(q);
        }
    };
    for (auto _ : state) {
        through(encode_request(InquireRequest{members}), false);
        through(encode_response(live), true);
        for (std::size_t m = 0; m < members.size(); ++m) {
            DownloadRequest q;
            q.channel = members[m];
            q.testid = 143;
            q.startpos = 219576;
            through(encode_request(q), false);
            through(encode_response(downloads[m]), true);
        }
    }
    state.SetItemsProcessed(frames);
    state.SetBytesProcessed(bytes);
    state.counters["frames_per_s"] = benchmark::Counter(static_cast<double>(frames), benchmark::Counter::kIsRate);
}

}  // namespace

BENCHMARK(BM_NewareInquireDownloadRoundTrip)->Arg(1)->Arg(10)->Arg(1000);

// 3 = the thesis' parallel group, 8 = a whole BTS-4008.
BENCHMARK(BM_NewareSplitAndParseInquire)->Arg(3)->Arg(8);
BENCHMARK(BM_NewareSplitOnly)->Arg(3);
BENCHMARK(BM_NewareEncodeInquireRequest);

BENCHMARK_MAIN();
