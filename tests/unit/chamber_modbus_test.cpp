// Climatic chamber register map (protocol/chamber_modbus.hpp): scaling, 16/32-bit values and word order,
// the reads the client plans, decoding the state and alarms, checking writes, and the JSON form.
#include "cellbench/protocol/chamber_modbus.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"

namespace {

using namespace cellbench::protocol;
using nlohmann::json;
using Words = std::vector<std::uint16_t>;

TEST(ChamberRegisters, SetPointIsScaledAndRangeChecked) {
    const auto m = ChamberRegisterMap::bench_default();
    EXPECT_EQ(m.encode_setpoint(30.0), Words{300});
    EXPECT_EQ(m.encode_setpoint(-12.3), Words{0xFF85});  // -123 as int16
    EXPECT_EQ(m.encode_setpoint(180.0), Words{1800});
    EXPECT_FALSE(m.encode_setpoint(180.1)) << "above the chamber's range";
    EXPECT_FALSE(m.encode_setpoint(-60.0));
    EXPECT_FALSE(m.encode_setpoint(std::numeric_limits<double>::quiet_NaN()));
}

TEST(ChamberRegisters, ThirtyTwoBitValuesHonourTheWordOrder) {
    RegisterValueSpec f{RegisterTable::holding, 0, RegisterType::float32, WordOrder::high_word_first, 1.0, 0.0};
    EXPECT_EQ(encode_register_value(f, 25.5), (Words{0x41CC, 0x0000}));
    f.word_order = WordOrder::low_word_first;
    EXPECT_EQ(encode_register_value(f, 25.5), (Words{0x0000, 0x41CC}));
    const Words cdab{0x0000, 0x41CC};
    EXPECT_EQ(decode_register_value(f, cdab.data()), 25.5);

    RegisterValueSpec i{RegisterTable::input, 0, RegisterType::int32, WordOrder::high_word_first, 0.001, 0.0};
    const auto words = encode_register_value(i, -100.0);  // raw -100000 = 0xFFFE7960
    EXPECT_EQ(words, (Words{0xFFFE, 0x7960}));
    EXPECT_NEAR(*decode_register_value(i, words->data()), -100.0, 1e-12);

    RegisterValueSpec u{RegisterTable::holding, 0, RegisterType::uint16, WordOrder::high_word_first, 0.1, -50.0};
    const Words zero{0};
    EXPECT_EQ(decode_register_value(u, zero.data()), -50.0) << "offset applies after the scale";
    EXPECT_FALSE(encode_register_value(u, -60.0)) << "not representable in uint16";

    RegisterValueSpec u32{RegisterTable::holding, 0, RegisterType::uint32, WordOrder::low_word_first, 1.0, 0.0};
    const Words big{0x0001, 0x8000};  // low word 1, high word 0x8000
    EXPECT_EQ(decode_register_value(u32, big.data()), 2147483649.0);

    const Words nan{0x7FC0, 0x0000};
    RegisterValueSpec fh{RegisterTable::holding, 0, RegisterType::float32, WordOrder::high_word_first, 1.0, 0.0};
    EXPECT_FALSE(decode_register_value(fh, nan.data())) << "a NaN process value is not a temperature";
}

TEST(ChamberRegisters, ReadPlanUsesFewBlocksWithinTheModbusLimit) {
    const auto m = ChamberRegisterMap::bench_default();
    const auto plan = m.read_plan();
    ASSERT_EQ(plan.size(), 1u);
    EXPECT_EQ(plan[0].table, RegisterTable::holding);
    EXPECT_EQ(plan[0].start, 1);
    EXPECT_EQ(plan[0].count, 11);  // 1..11

    ChamberRegisterMap spread = m;
    spread.process_value = {RegisterTable::input, 0, RegisterType::float32, WordOrder::high_word_first, 1.0, 0.0};
    spread.setpoint.address = 300;
    spread.run.address = 2000;
    spread.alarms->address = 2001;
    spread.validate();
    const auto p = spread.read_plan();
    ASSERT_EQ(p.size(), 3u);
    EXPECT_EQ(p[0].table, RegisterTable::holding);
    EXPECT_EQ(p[0].start, 300);
    EXPECT_EQ(p[0].count, 1);
    EXPECT_EQ(p[1].start, 2000);
    EXPECT_EQ(p[1].count, 2);
    EXPECT_EQ(p[2].table, RegisterTable::input);
    EXPECT_EQ(p[2].count, 2);
}

TEST(ChamberRegisters, DecodesStateAndNamedAlarms) {
    const auto m = ChamberRegisterMap::bench_default();
    RegisterBlock block{RegisterTable::holding, 1, Words(11, 0)};
    block.values[0] = 312;                 // PV 31.2
    block.values[1] = 300;                 // SP 30.0
    block.values[9] = 1;                   // running
    block.values[10] = (1 << 2) | (1 << 4) | (1 << 9);  // heater_fault, door_open and an unnamed bit
    std::string error;
    const auto s = m.decode(std::span(&block, 1), &error);
    ASSERT_TRUE(s) << error;
    EXPECT_NEAR(s->process_value_c, 31.2, 1e-12);
    EXPECT_NEAR(s->setpoint_c, 30.0, 1e-12);
    EXPECT_EQ(s->running, true);
    EXPECT_EQ(s->alarm_word, (1 << 2) | (1 << 4) | (1 << 9));
    EXPECT_EQ(s->active_alarms, (std::vector<std::string>{"heater_fault", "door_open"}));

    block.values[9] = 7;
    EXPECT_FALSE(m.decode(std::span(&block, 1))->running.has_value()) << "neither run nor stop";

    RegisterBlock partial{RegisterTable::holding, 1, Words(5, 0)};
    EXPECT_FALSE(m.decode(std::span(&partial, 1), &error));
    EXPECT_NE(error.find("run/stop register 10"), std::string::npos) << error;
}

TEST(ChamberRegisters, WritesOnlyTheSetPointAndRunStopWithinRange) {
    const auto m = ChamberRegisterMap::bench_default();
    RegisterBlock image{RegisterTable::holding, 1, Words(11, 0)};
    image.values[1] = 300;

    auto r = m.apply_write(image, 2, Words{455});
    EXPECT_EQ(r.exception_code, 0);
    EXPECT_EQ(r.setpoint_c, 45.5);
    EXPECT_FALSE(r.running);
    EXPECT_EQ(image.values[1], 455);

    r = m.apply_write(image, 2, Words{2000});  // 200 degC
    EXPECT_EQ(r.exception_code, 3);
    EXPECT_EQ(image.values[1], 455) << "a refused write changes nothing";

    r = m.apply_write(image, 1, Words{999});  // the process value is read-only
    EXPECT_EQ(r.exception_code, 2);

    r = m.apply_write(image, 10, Words{0});
    EXPECT_EQ(r.exception_code, 0);
    EXPECT_EQ(r.running, false);
    r = m.apply_write(image, 10, Words{5});
    EXPECT_EQ(r.exception_code, 3);

    r = m.apply_write(image, 9, Words{0, 1});  // spans register 9, not writable
    EXPECT_EQ(r.exception_code, 2);

    // A 32-bit set point written in one request.
    ChamberRegisterMap wide = m;
    wide.setpoint = {RegisterTable::holding, 2, RegisterType::float32, WordOrder::low_word_first, 1.0, 0.0};
    wide.process_value.address = 5;
    wide.validate();
    RegisterBlock wide_image{RegisterTable::holding, 1, Words(11, 0)};
    const auto words = wide.encode_setpoint(-20.25);
    ASSERT_TRUE(words);
    r = wide.apply_write(wide_image, 2, *words);
    EXPECT_EQ(r.exception_code, 0);
    EXPECT_EQ(r.setpoint_c, -20.25);
}

TEST(ChamberRegistersJson, RoundTrips) {
    const auto m = ChamberRegisterMap::bench_default();
    const auto again = ChamberRegisterMap::from_json(m.to_json());
    EXPECT_EQ(again.to_json(), m.to_json());
    EXPECT_EQ(again.alarm_bit("door_open"), 4u);

    const auto j = json::parse(R"({
      "schema": "cellbench.chamber-modbus/1",
      "process_value": {"table": "input", "address": 100, "type": "float32", "word_order": "low_first", "scale": 1},
      "setpoint": {"address": 300, "type": "int32", "scale": 0.001},
      "run": {"address": 400, "run_value": 2, "stop_value": 1},
      "setpoint_range_c": [-40, 150]})");
    const auto custom = ChamberRegisterMap::from_json(j);
    EXPECT_EQ(custom.process_value.table, RegisterTable::input);
    EXPECT_EQ(custom.process_value.word_order, WordOrder::low_word_first);
    EXPECT_EQ(custom.setpoint.type, RegisterType::int32);
    EXPECT_EQ(custom.run.run_value, 2);
    EXPECT_FALSE(custom.alarms);
    EXPECT_EQ(custom.encode_setpoint(30.0), (Words{0x0000, 0x7530}));  // 30000, high word first
    EXPECT_EQ(ChamberRegisterMap::from_json(custom.to_json()).to_json(), custom.to_json());
}

std::string error_of(const json& j) {
    try {
        ChamberRegisterMap::from_json(j, "chamber.json");
    } catch (const cellbench::InputError& e) {
        return e.what();
    }
    return "no error";
}

TEST(ChamberRegistersJson, ErrorsNameTheJsonPath) {
    const json base = ChamberRegisterMap::bench_default().to_json();

    json j = base;
    j["setpoint"]["table"] = "input";
    EXPECT_NE(error_of(j).find("chamber.json: $.setpoint.table: expected \"holding\""), std::string::npos) << error_of(j);

    j = base;
    j["setpoint"]["address"] = 1;
    EXPECT_NE(error_of(j).find("$.setpoint.address: overlaps the registers of process_value"), std::string::npos) << error_of(j);

    j = base;
    j["process_value"]["type"] = "int64";
    EXPECT_NE(error_of(j).find("$.process_value.type: expected uint16"), std::string::npos) << error_of(j);

    j = base;
    j["alarms"]["bits"]["door_open"] = 16;
    EXPECT_NE(error_of(j).find("$.alarms.bits.door_open: expected an integer 0..15"), std::string::npos) << error_of(j);

    j = base;
    j["setpoint"]["scale"] = 0.01;  // 180 degC = 18000 fits; widen the range beyond int16
    j["setpoint_range_c"] = json::array({-50, 400});
    EXPECT_NE(error_of(j).find("$.setpoint_range_c: the set point register cannot represent"), std::string::npos) << error_of(j);

    j = base;
    j.erase("run");
    EXPECT_NE(error_of(j).find("$.run: missing"), std::string::npos) << error_of(j);

    j = base;
    j["process_value"]["address"] = 70000;
    EXPECT_NE(error_of(j).find("$.process_value.address: expected an integer 0..65535"), std::string::npos) << error_of(j);
}

}  // namespace
