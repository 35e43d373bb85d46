// libFuzzer target: the DEWE-43A CAN decoder and its layout parser must survive any bytes (never crash, never
// hang) and keep their counters consistent. Build: cmake -DCELLBENCH_FUZZ=ON -DCMAKE_CXX_COMPILER=clang++, or
//   clang++ -std=c++20 -g -O1 -fsanitize=fuzzer,address,undefined -Iprotocol/include -Icore/include \
//       tests/fuzz/can_decode_fuzz.cpp protocol/src/dewe_can.cpp -o can_decode_fuzz
#include <cstddef>
#include <cstdint>
#include <span>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/dewe_can.hpp"

using namespace cellbench::protocol;

namespace {

const DeweCanLayout& mixed_layout() {
    static const DeweCanLayout layout = DeweCanLayout::from_json(nlohmann::json::parse(R"({
      "frames": [{"can_id": "0x18FF0010", "counter": {"byte_offset": 7, "length": 1}},
                 {"can_id": "0x501", "counter": {"byte_offset": 0, "length": 1}}],
      "channels": {
        "thermopile_v": {"can_id": "0x18FF0010", "byte_offset": 0, "type": "float32", "byte_order": "big"},
        "type_t_c": {"can_id": "0x18FF0010", "byte_offset": 4, "length": 2, "type": "signed", "byte_order": "big", "scale": 0.1},
        "t1_c": {"can_id": "0x501", "byte_offset": 1, "length": 3, "type": "unsigned", "scale": 0.001},
        "t2_c": {"can_id": "0x501", "byte_offset": 4, "length": 4, "type": "signed", "byte_order": "big", "scale": 0.01}}})"));
    return layout;
}

void check(bool condition) {
    if (!condition) __builtin_trap();
}

void check_stats(const DeweStreamStats& s, std::uint64_t pushed) {
    check(s.records == pushed);
    check(s.garbage == s.wrong_size + s.bad_length + s.unknown_id + s.not_data + s.duplicates);
    check(s.frames + s.garbage == s.records);
    check(s.samples <= s.frames);
}

// A layout from JSON: parsing and validation either succeed or throw InputError; a valid layout round-trips
// and one encoded sample decodes back into exactly one sample.
void fuzz_layout(const std::uint8_t* data, std::size_t size) {
    const auto j = nlohmann::json::parse(data, data + size, nullptr, false);
    if (j.is_discarded()) return;
    try {
        const auto layout = DeweCanLayout::from_json(j);
        check(DeweCanLayout::from_json(layout.to_json()).to_json() == layout.to_json());
        DeweCanDecoder decoder(layout);
        const auto frames = encode_dewe_sample(layout, {1e-3, 25.0, 30.0, -5.0}, 3);
        std::size_t samples = 0;
        for (const auto& f : frames) samples += decoder.push(f, 0.0).has_value();
        check(samples == 1);
    } catch (const cellbench::InputError&) {
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0) return 0;
    const std::uint8_t mode = data[0];
    ++data;
    --size;
    if (mode % 3 == 2) {
        fuzz_layout(data, size);
        return 0;
    }
    static const DeweCanLayout bench = DeweCanLayout::bench_default();
    DeweCanDecoder decoder(mode % 3 == 0 ? bench : mixed_layout());
    // Mostly 16-byte records; a 0xFF byte at a record start makes that record's size the next byte (0..255).
    std::uint64_t pushed = 0;
    for (std::size_t i = 0; i < size;) {
        std::size_t n = 16;
        if (data[i] == 0xFF && i + 1 < size) {
            n = data[i + 1];
            i += 2;
        }
        n = std::min(n, size - i);
        (void)decoder.push_record(std::span<const std::uint8_t>(data + i, n), static_cast<double>(i));
        ++pushed;
        i += n;
        if (n == 0) ++i;
    }
    check_stats(decoder.stats(), pushed);
    return 0;
}
