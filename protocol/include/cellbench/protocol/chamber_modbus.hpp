#pragma once
// Register map of the climatic chamber's Modbus TCP controller (MSL EC 300CA in the thesis, 2.1.5): where the
// process value (air temperature), the set point, run/stop and the alarm bits live, and how the numbers are
// scaled. Pure: registers in, values out. The Modbus framing itself is libmodbus' job (drivers/).
//
// Values: value = raw * scale + offset; raw is a 16-bit (uint16/int16) or 32-bit (uint32/int32/float32)
// quantity, 32-bit ones over two consecutive registers with a configurable word order (high word first =
// "ABCD", the Modbus convention; low word first = "CDAB", common in controllers).
//
// JSON form ("cellbench.chamber-modbus/1"):
//   {"schema": "cellbench.chamber-modbus/1",
//    "process_value": {"table": "holding", "address": 1, "type": "int16", "scale": 0.1},
//    "setpoint":      {"address": 2, "type": "int16", "scale": 0.1},
//    "run":           {"address": 10, "run_value": 1, "stop_value": 0},
//    "alarms":        {"table": "holding", "address": 11, "bits": {"high_temperature": 0, "heater_fault": 2}},
//    "setpoint_range_c": [-50, 180]}
// "table" is "holding" (function 3) or "input" (function 4), default holding; the set point and run/stop
// are holding registers (written with function 6 or 16). "word_order": "high_first" (default) | "low_first".
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace cellbench::protocol {

enum class RegisterTable { holding, input };
enum class RegisterType { uint16, int16, uint32, int32, float32 };
enum class WordOrder { high_word_first, low_word_first };

struct RegisterValueSpec {
    RegisterTable table = RegisterTable::holding;
    std::uint16_t address = 0;
    RegisterType type = RegisterType::int16;
    WordOrder word_order = WordOrder::high_word_first;
    double scale = 0.1;
    double offset = 0.0;

    [[nodiscard]] std::size_t width_registers() const;  // 1 or 2
};

struct RunControlSpec {
    std::uint16_t address = 10;  // holding register
    std::uint16_t run_value = 1;
    std::uint16_t stop_value = 0;
};

struct AlarmSpec {
    RegisterTable table = RegisterTable::holding;
    std::uint16_t address = 11;
    std::vector<std::pair<std::string, unsigned>> bits;  // name, bit 0..15
};

// Registers as read: a contiguous block of one table.
struct RegisterBlock {
    RegisterTable table = RegisterTable::holding;
    std::uint16_t start = 0;
    std::vector<std::uint16_t> values;

    // Pointer to `count` registers from `address`, or nullptr when the block does not hold them all.
    [[nodiscard]] const std::uint16_t* find(RegisterTable t, std::uint16_t address, std::size_t count) const;
    [[nodiscard]] std::uint16_t* find(RegisterTable t, std::uint16_t address, std::size_t count);
};

// A read the client issues: `count` registers of `table` from `start` (count <= 125, the Modbus limit).
struct RegisterRange {
    RegisterTable table = RegisterTable::holding;
    std::uint16_t start = 0;
    std::uint16_t count = 0;
};

// The chamber as the registers describe it.
struct ChamberRegisterState {
    double process_value_c = 0.0;
    double setpoint_c = 0.0;
    std::optional<bool> running;     // nullopt when the register holds neither the run nor the stop value
    std::uint16_t alarm_word = 0;    // raw alarm register (0 without an alarm register)
    std::vector<std::string> active_alarms;  // names of the configured bits that are set
};

// Outcome of a write request checked against the map (used by the simulated chamber).
struct ChamberWriteResult {
    std::uint8_t exception_code = 0;    // 0 = accepted; else a Modbus exception (2 address, 3 value)
    std::string reason;                 // for an exception
    std::optional<double> setpoint_c;   // the set point after the write, if the write touched it
    std::optional<bool> running;        // run/stop after the write, if the write touched it
};

struct ChamberRegisterMap {
    RegisterValueSpec process_value{RegisterTable::holding, 1, RegisterType::int16, WordOrder::high_word_first, 0.1, 0.0};
    RegisterValueSpec setpoint{RegisterTable::holding, 2, RegisterType::int16, WordOrder::high_word_first, 0.1, 0.0};
    RunControlSpec run;
    std::optional<AlarmSpec> alarms;
    double setpoint_min_c = -50.0;  // EC 300CA range (thesis table 2.9)
    double setpoint_max_c = 180.0;

    // The simulated chamber's map: PV 1, SP 2 (int16, 0.1 degC), run/stop 10, alarm word 11 with
    // high_temperature 0, low_temperature 1, heater_fault 2, cooling_fault 3, door_open 4.
    static ChamberRegisterMap bench_default();

    // Throws InputError naming the JSON path and what was expected.
    static ChamberRegisterMap from_json(const nlohmann::json& j, const std::string& source = "chamber register map");
    [[nodiscard]] nlohmann::json to_json() const;
    // Throws InputError on overlapping registers, a set point outside the holding table, bad bits, ranges the
    // set point encoding cannot represent, or scale 0.
    void validate(const std::string& source = "chamber register map") const;

    // Registers that carry a set point (nullopt if NaN, outside setpoint_min/max_c or not representable).
    [[nodiscard]] std::optional<std::vector<std::uint16_t>> encode_setpoint(double setpoint_c) const;
    // The reads that fetch every mapped register (fewest blocks, each <= 125 registers).
    [[nodiscard]] std::vector<RegisterRange> read_plan() const;
    // Decodes the state from blocks that cover the map; nullopt (with *error) when a register is missing.
    [[nodiscard]] std::optional<ChamberRegisterState> decode(std::span<const RegisterBlock> blocks,
                                                             std::string* error = nullptr) const;
    // Names of the alarm bits set in a raw alarm word.
    [[nodiscard]] std::vector<std::string> alarm_names(std::uint16_t alarm_word) const;
    // Bit of a named alarm.
    [[nodiscard]] std::optional<unsigned> alarm_bit(const std::string& name) const;

    // Checks a write of `values` at holding `address` (function 6: one value; 16: several) and applies it to
    // `holding` (an image of the holding registers) when accepted: only the set point and run/stop registers
    // are writable, a set point must decode inside the range, run/stop must be the run or the stop value.
    ChamberWriteResult apply_write(RegisterBlock& holding, std::uint16_t address,
                                   std::span<const std::uint16_t> values) const;
};

inline constexpr const char* kChamberModbusSchema = "cellbench.chamber-modbus/1";

// Raw value conversion: decode from 1 or 2 registers (nullopt if the raw value is not finite, e.g. a NaN
// float); encode returns nullopt when the value cannot be represented.
std::optional<double> decode_register_value(const RegisterValueSpec& spec, const std::uint16_t* registers);
std::optional<std::vector<std::uint16_t>> encode_register_value(const RegisterValueSpec& spec, double value);

}  // namespace cellbench::protocol
