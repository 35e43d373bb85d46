// libFuzzer target: the chamber register map must decode any register contents a (broken) controller may
// answer, check any write request, and parse or refuse any JSON map, without crashing. Build: cmake
// -DCELLBENCH_FUZZ=ON -DCMAKE_CXX_COMPILER=clang++, or
//   clang++ -std=c++20 -g -O1 -fsanitize=fuzzer,address,undefined -Iprotocol/include -Icore/include \
//       tests/fuzz/chamber_response_fuzz.cpp protocol/src/chamber_modbus.cpp -o chamber_response_fuzz
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/chamber_modbus.hpp"

using namespace cellbench::protocol;

namespace {

void check(bool condition) {
    if (!condition) __builtin_trap();
}

// Maps with every value kind: the default (int16), and 32-bit float/int in both word orders in two tables.
const std::vector<ChamberRegisterMap>& maps() {
    static const std::vector<ChamberRegisterMap> all = [] {
        std::vector<ChamberRegisterMap> v{ChamberRegisterMap::bench_default()};
        ChamberRegisterMap wide = ChamberRegisterMap::bench_default();
        wide.process_value = {RegisterTable::input, 0, RegisterType::float32, WordOrder::low_word_first, 1.0, 0.0};
        wide.setpoint = {RegisterTable::holding, 2, RegisterType::int32, WordOrder::high_word_first, 0.001, 0.0};
        wide.run.address = 4;
        wide.alarms->address = 5;
        wide.alarms->table = RegisterTable::input;
        wide.validate();
        v.push_back(wide);
        return v;
    }();
    return all;
}

std::uint16_t word(const std::uint8_t* p) { return static_cast<std::uint16_t>(p[0] << 8 | p[1]); }

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size < 1) return 0;
    const std::uint8_t mode = data[0];
    ++data;
    --size;
    const auto& map = maps()[(mode >> 2) % maps().size()];
    switch (mode % 4) {
        case 0: {  // register contents as read: fill the read plan from the bytes (short answers included)
            std::vector<RegisterBlock> blocks;
            std::size_t at = 0;
            for (const auto& range : map.read_plan()) {
                RegisterBlock b{range.table, range.start, {}};
                for (std::size_t i = 0; i < range.count && at + 1 < size; ++i, at += 2) b.values.push_back(word(data + at));
                blocks.push_back(std::move(b));
            }
            std::string error;
            const auto state = map.decode(blocks, &error);
            if (state) {
                check(std::isfinite(state->process_value_c) && std::isfinite(state->setpoint_c));
                check(state->active_alarms.size() <= 16);
            } else {
                check(!error.empty());
            }
            break;
        }
        case 1: {  // a write request against a holding image
            if (size < 2) return 0;
            RegisterBlock image{RegisterTable::holding, 0, std::vector<std::uint16_t>(16, 0)};
            const std::uint16_t address = word(data);
            std::vector<std::uint16_t> values;
            for (std::size_t at = 2; at + 1 < size && values.size() < 123; at += 2) values.push_back(word(data + at));
            const RegisterBlock before = image;
            const auto result = map.apply_write(image, address, values);
            if (result.exception_code != 0) check(image.values == before.values);
            if (result.setpoint_c) check(*result.setpoint_c >= map.setpoint_min_c && *result.setpoint_c <= map.setpoint_max_c);
            break;
        }
        case 2: {  // a map from JSON
            const auto j = nlohmann::json::parse(data, data + size, nullptr, false);
            if (j.is_discarded()) return 0;
            try {
                const auto m = ChamberRegisterMap::from_json(j);
                check(ChamberRegisterMap::from_json(m.to_json()).to_json() == m.to_json());
                for (const auto& r : m.read_plan()) check(r.count >= 1 && r.count <= 125);
            } catch (const cellbench::InputError&) {
            }
            break;
        }
        default: {  // value conversions round-trip where representable
            if (size < 8) return 0;
            double value = 0;
            std::memcpy(&value, data, sizeof value);
            for (const auto* spec : {&map.process_value, &map.setpoint}) {
                const auto words = encode_register_value(*spec, value);
                if (!words) continue;
                const auto back = decode_register_value(*spec, words->data());
                check(back.has_value());
            }
            break;
        }
    }
    return 0;
}
