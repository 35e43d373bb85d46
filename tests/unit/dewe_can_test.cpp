// DEWE-43A CAN stream (protocol/dewe_can.hpp): the 16-byte struct can_frame records, the channel layout
// (signed/unsigned/float32, byte order, scale), counter gaps, garbage, and the layout's JSON form.
#include "cellbench/protocol/dewe_can.hpp"

#include <gtest/gtest.h>
#include <linux/can.h>

#include <cmath>
#include <cstring>
#include <random>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"

namespace {

using namespace cellbench::protocol;
using nlohmann::json;

std::vector<std::uint8_t> bytes_of(const CanRecord& r) { return {r.begin(), r.end()}; }

TEST(CanRecord, IsByteForByteTheKernelsStructCanFrame) {
    static_assert(sizeof(struct can_frame) == kCanRecordBytes);
    const std::array<std::uint8_t, 3> payload{0x01, 0x02, 0x03};
    const CanFrame standard = CanFrame::data_frame(0x123, false, payload);
    EXPECT_EQ(bytes_of(encode_can_record(standard)),
              (std::vector<std::uint8_t>{0x23, 0x01, 0x00, 0x00, 0x03, 0x00, 0x00, 0x00,  //
                                         0x01, 0x02, 0x03, 0x00, 0x00, 0x00, 0x00, 0x00}));

    const std::array<std::uint8_t, 8> full{0xA0, 0xA1, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7};
    const CanFrame extended = CanFrame::data_frame(0x1ABCDEF0, true, full);
    EXPECT_TRUE(extended.extended());
    EXPECT_EQ(extended.id(), 0x1ABCDEF0u);
    const auto record = encode_can_record(extended);
    EXPECT_EQ(bytes_of(record),
              (std::vector<std::uint8_t>{0xF0, 0xDE, 0xBC, 0x9A, 0x08, 0x00, 0x00, 0x00,  //
                                         0xA0, 0xA1, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7}));

    // The same bytes as the kernel's own struct on this (little-endian) host.
    struct can_frame kernel {};
    kernel.can_id = 0x1ABCDEF0 | CAN_EFF_FLAG;
    kernel.len = 8;
    std::memcpy(kernel.data, full.data(), 8);
    EXPECT_EQ(std::memcmp(&kernel, record.data(), kCanRecordBytes), 0);
    static_assert(kCanEffFlag == CAN_EFF_FLAG && kCanRtrFlag == CAN_RTR_FLAG && kCanErrFlag == CAN_ERR_FLAG);

    const auto back = decode_can_record(record);
    ASSERT_TRUE(back);
    EXPECT_EQ(*back, extended);
}

TEST(CanRecord, RejectsWrongSizesAndLengthsAboveEight) {
    CanRecordError why{};
    const std::vector<std::uint8_t> short_record(10, 0);
    EXPECT_FALSE(decode_can_record(short_record, &why));
    EXPECT_EQ(why, CanRecordError::wrong_size);
    const std::vector<std::uint8_t> fd_record(72, 0);
    EXPECT_FALSE(decode_can_record(fd_record, &why));
    auto record = encode_can_record(CanFrame::data_frame(0x10, false, {}));
    record[4] = 9;
    EXPECT_FALSE(decode_can_record(record, &why));
    EXPECT_EQ(why, CanRecordError::bad_length);
}

TEST(CanField, ReadsSignedUnsignedFloatInBothByteOrders) {
    const std::uint8_t p[8] = {0x12, 0x34, 0xFF, 0xFE, 0x3F, 0xC0, 0x00, 0x00};
    EXPECT_EQ(read_field({0, 2, CanValueType::unsigned_int, ByteOrder::little_endian}, p), 0x3412);
    EXPECT_EQ(read_field({0, 2, CanValueType::unsigned_int, ByteOrder::big_endian}, p), 0x1234);
    EXPECT_EQ(read_field({2, 2, CanValueType::signed_int, ByteOrder::little_endian}, p), -257);  // 0xFEFF
    EXPECT_EQ(read_field({2, 2, CanValueType::signed_int, ByteOrder::big_endian}, p), -2);       // 0xFFFE
    EXPECT_EQ(read_field({0, 3, CanValueType::unsigned_int, ByteOrder::big_endian}, p), 0x1234FF);
    EXPECT_EQ(read_field({2, 3, CanValueType::signed_int, ByteOrder::little_endian}, p), 0x3FFEFF);
    EXPECT_EQ(read_field({4, 4, CanValueType::float32, ByteOrder::big_endian}, p), 1.5);  // 0x3FC00000
    EXPECT_EQ(read_field({0, 1, CanValueType::signed_int, ByteOrder::little_endian}, p + 2), -1);

    // Writing rounds and saturates.
    std::uint8_t out[8] = {};
    write_field({0, 2, CanValueType::signed_int, ByteOrder::big_endian}, -2.4, out);
    EXPECT_EQ(out[0], 0xFF);
    EXPECT_EQ(out[1], 0xFE);
    write_field({2, 1, CanValueType::unsigned_int, ByteOrder::little_endian}, 300.0, out);
    EXPECT_EQ(out[2], 0xFF);
    write_field({3, 1, CanValueType::signed_int, ByteOrder::little_endian}, -1000.0, out);
    EXPECT_EQ(out[3], 0x80);
    write_field({4, 4, CanValueType::float32, ByteOrder::little_endian}, -0.25, out);
    EXPECT_EQ(read_field({4, 4, CanValueType::float32, ByteOrder::little_endian}, out), -0.25);
}

// A layout unlike the default: one extended frame, big-endian fields, a 1-byte counter at the end.
json mixed_layout_json() {
    return json::parse(R"({
      "schema": "cellbench.dewe-can/1",
      "frames": [{"can_id": "0x18FF0010", "counter": {"byte_offset": 7, "length": 1}},
                 {"can_id": 1281, "counter": {"byte_offset": 0, "length": 1}}],
      "channels": {
        "thermopile_v": {"can_id": "0x18FF0010", "byte_offset": 0, "type": "float32", "byte_order": "big", "scale": 1e-3},
        "type_t_c":     {"can_id": "0x18FF0010", "byte_offset": 4, "length": 2, "type": "signed", "byte_order": "big",
                         "scale": 0.1, "offset": -40},
        "t1_c":         {"can_id": "0x501", "byte_offset": 1, "length": 3, "type": "unsigned", "byte_order": "little",
                         "scale": 0.001, "offset": -100},
        "t2_c":         {"can_id": "0x501", "byte_offset": 4, "length": 2, "type": "unsigned", "byte_order": "big",
                         "scale": 0.01}
      }})");
}

TEST(DeweLayout, DecodesScaledFieldsOfEveryKind) {
    const auto layout = DeweCanLayout::from_json(mixed_layout_json());
    EXPECT_TRUE(layout.frames[0].extended) << "29-bit identifiers are extended by default";
    DeweCanDecoder decoder(layout);

    // thermopile: float32 BE 12.5 -> 12.5e-3 V; Type-T: int16 BE 0x02BC = 700 -> 700*0.1-40 = 30 degC.
    const std::array<std::uint8_t, 8> a{0x41, 0x48, 0x00, 0x00, 0x02, 0xBC, 0x00, 0x07};
    // t1: u24 LE 0x01ADB0 = 110000 -> 110000*0.001-100 = 10 degC; t2: u16 BE 0x0BB8 = 3000 -> 30 degC.
    const std::array<std::uint8_t, 6> b{0x07, 0xB0, 0xAD, 0x01, 0x0B, 0xB8};
    EXPECT_FALSE(decoder.push(CanFrame::data_frame(0x18FF0010, true, a), 1.0)) << "half a sample";
    const auto s = decoder.push(CanFrame::data_frame(0x501, false, b), 1.5);
    ASSERT_TRUE(s);
    EXPECT_DOUBLE_EQ(s->thermopile_v(), 12.5e-3);
    EXPECT_NEAR(s->type_t_c(), 30.0, 1e-12);
    EXPECT_NEAR(s->t1_c(), 10.0, 1e-9);
    EXPECT_NEAR(s->t2_c(), 30.0, 1e-12);
    EXPECT_EQ(s->time_s, 1.5) << "stamped with the frame that completed it";
    EXPECT_EQ(s->sequence, 7u);
    EXPECT_EQ(decoder.stats().samples, 1u);
    EXPECT_EQ(decoder.stats().garbage, 0u);
}

TEST(DeweLayout, EncoderAndDecoderRoundTrip) {
    const auto layout = DeweCanLayout::bench_default();
    DeweCanDecoder decoder(layout);
    const std::array<double, 4> values{1.234567e-3, 31.27, 30.5, -12.34};
    for (std::uint64_t k = 65530; k < 65545; ++k) {  // across the 16-bit wrap
        std::optional<DeweSample> s;
        const auto frames = encode_dewe_sample(layout, values, k);
        ASSERT_EQ(frames.size(), 2u);
        for (const auto& f : frames) {
            const auto record = encode_can_record(f);
            s = decoder.push_record(record, static_cast<double>(k));
        }
        ASSERT_TRUE(s);
        EXPECT_EQ(s->sequence, k) << "the sequence unwraps the counter";
        EXPECT_NEAR(s->thermopile_v(), values[0], 1e-10);  // float32
        EXPECT_NEAR(s->type_t_c(), values[1], 0.005);      // 0.01 degC steps
        EXPECT_NEAR(s->t1_c(), values[2], 0.005);
        EXPECT_NEAR(s->t2_c(), values[3], 0.005);
    }
    EXPECT_EQ(decoder.stats().lost_samples, 0u);
    EXPECT_EQ(decoder.stats().samples, 15u);
}

TEST(DeweDecoder, CountsCounterGapsAsLostSamples) {
    const auto layout = DeweCanLayout::bench_default();
    DeweCanDecoder decoder(layout);
    const std::array<double, 4> v{1e-4, 30, 30, 30};
    auto send = [&](std::uint64_t k) {
        std::optional<DeweSample> s;
        for (const auto& f : encode_dewe_sample(layout, v, k)) s = decoder.push(f, 0.0);
        return s;
    };
    EXPECT_TRUE(send(10));
    EXPECT_TRUE(send(11));
    const auto after_gap = send(15);
    ASSERT_TRUE(after_gap);
    EXPECT_EQ(after_gap->sequence, 15u);
    EXPECT_EQ(decoder.stats().lost_samples, 3u);
    EXPECT_EQ(decoder.stats().lost_frames, 6u);  // both frames of 12, 13, 14

    // Half a sample (only its first frame) is a lost sample too.
    const auto frames16 = encode_dewe_sample(layout, v, 16);
    EXPECT_FALSE(decoder.push(frames16[0], 0.0));
    EXPECT_TRUE(send(17));
    EXPECT_EQ(decoder.stats().lost_samples, 4u);
    EXPECT_EQ(decoder.stats().lost_frames, 7u);

    // A counter going back (the DAQ restarted) is a resync, not 65 000 lost samples.
    const auto restarted = send(0);
    ASSERT_TRUE(restarted);
    EXPECT_EQ(restarted->sequence, 18u) << "the sequence stays monotonic";
    EXPECT_EQ(decoder.stats().resyncs, 1u);
    EXPECT_EQ(decoder.stats().lost_samples, 4u);
    EXPECT_EQ(decoder.stats().samples, 5u);
}

TEST(DeweDecoder, OneByteCounterWrapsWithoutLoss) {
    auto j = mixed_layout_json();
    DeweCanDecoder decoder(DeweCanLayout::from_json(j));
    const std::array<double, 4> v{0.0, 20.0, 20.0, 20.0};
    std::uint64_t samples = 0;
    for (std::uint64_t k = 250; k < 262; ++k)
        for (const auto& f : encode_dewe_sample(decoder.layout(), v, k))
            if (decoder.push(f, 0.0)) ++samples;
    EXPECT_EQ(samples, 12u);
    EXPECT_EQ(decoder.stats().lost_samples, 0u);
    EXPECT_EQ(decoder.stats().resyncs, 0u);
}

TEST(DeweDecoder, CountsAndDropsGarbageWithoutLosingTheStream) {
    const auto layout = DeweCanLayout::bench_default();
    DeweCanDecoder decoder(layout);
    const std::array<double, 4> v{2e-4, 30, 30, 30};
    auto frames = encode_dewe_sample(layout, v, 1);
    for (const auto& f : frames) decoder.push(f, 0.0);

    const std::array<std::uint8_t, 8> junk{1, 2, 3, 4, 5, 6, 7, 8};
    EXPECT_FALSE(decoder.push(CanFrame::data_frame(0x7FF, false, junk), 0.0));         // unknown id
    EXPECT_FALSE(decoder.push(CanFrame::data_frame(0x310, true, junk), 0.0));          // same number, extended
    CanFrame short_frame = frames[1];
    short_frame.len = 5;                                                                // 0x311 needs 8
    EXPECT_FALSE(decoder.push(short_frame, 0.0));
    CanFrame remote = frames[0];
    remote.can_id |= kCanRtrFlag;
    EXPECT_FALSE(decoder.push(remote, 0.0));
    CanFrame error = frames[0];
    error.can_id |= kCanErrFlag;
    EXPECT_FALSE(decoder.push(error, 0.0));
    EXPECT_FALSE(decoder.push(frames[1], 0.0));                                         // duplicate
    const std::vector<std::uint8_t> ten(10, 0xAB);
    EXPECT_FALSE(decoder.push_record(ten, 0.0));                                        // wrong size
    auto bad_len = encode_can_record(frames[0]);
    bad_len[4] = 12;
    EXPECT_FALSE(decoder.push_record(bad_len, 0.0));                                    // len > 8

    const auto& s = decoder.stats();
    EXPECT_EQ(s.unknown_id, 2u);
    EXPECT_EQ(s.bad_length, 2u);
    EXPECT_EQ(s.not_data, 2u);
    EXPECT_EQ(s.duplicates, 1u);
    EXPECT_EQ(s.wrong_size, 1u);
    EXPECT_EQ(s.garbage, 8u);
    EXPECT_EQ(s.lost_samples, 0u);

    std::optional<DeweSample> next;
    for (const auto& f : encode_dewe_sample(layout, v, 2)) next = decoder.push(f, 0.0);
    ASSERT_TRUE(next) << "the stream goes on after garbage";
    EXPECT_EQ(next->sequence, 2u);
    EXPECT_EQ(decoder.stats().lost_samples, 0u);
}

TEST(DeweDecoder, SurvivesRandomBytes) {
    DeweCanDecoder decoder(DeweCanLayout::bench_default());
    std::mt19937 rng(7);
    std::vector<std::uint8_t> record(16);
    for (int i = 0; i < 200000; ++i) {
        const std::size_t n = rng() % 4 == 0 ? rng() % 40 : 16;
        record.resize(n);
        for (auto& b : record) b = static_cast<std::uint8_t>(rng());
        if (n >= 4 && rng() % 2) record[1] = 0x03, record[0] = 0x10 + (rng() % 2), record[2] = record[3] = 0;
        (void)decoder.push_record(record, i);
    }
    EXPECT_EQ(decoder.stats().records, 200000u);
    EXPECT_GT(decoder.stats().garbage, 0u);
}

TEST(DeweLayoutJson, RoundTripsAndKeepsTheDefault) {
    const auto layout = DeweCanLayout::bench_default();
    const auto again = DeweCanLayout::from_json(layout.to_json());
    EXPECT_EQ(again.to_json(), layout.to_json());
    const auto mixed = DeweCanLayout::from_json(mixed_layout_json());
    EXPECT_EQ(DeweCanLayout::from_json(mixed.to_json()).to_json(), mixed.to_json());
}

std::string error_of(const json& j) {
    try {
        DeweCanLayout::from_json(j, "layout.json");
    } catch (const cellbench::InputError& e) {
        return e.what();
    }
    return "no error";
}

TEST(DeweLayoutJson, ErrorsNameTheJsonPath) {
    auto j = mixed_layout_json();
    j["channels"].erase("type_t_c");
    EXPECT_NE(error_of(j).find("layout.json: $.channels.type_t_c: missing"), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["channels"]["thermopile_v"]["length"] = 3;
    EXPECT_NE(error_of(j).find("$.channels.thermopile_v.length"), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["channels"]["t2_c"]["byte_offset"] = 2;  // onto t1_c
    EXPECT_NE(error_of(j).find("$.channels.t2_c: overlaps"), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["channels"]["t1_c"]["can_id"] = "0x502";
    EXPECT_NE(error_of(j).find("$.channels.t1_c.can_id: frame 0x502 is not declared"), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["frames"][1]["can_id"] = "0xZZ";
    EXPECT_NE(error_of(j).find("$.frames[1].can_id"), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["frames"][1]["counter"]["byte_offset"] = 6;  // 6 + 4 > 8 data bytes
    j["frames"][1]["counter"]["length"] = 4;
    EXPECT_NE(error_of(j).find("$.frames[1].counter"), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["channels"]["t1_c"]["byte_order"] = "middle";
    EXPECT_NE(error_of(j).find("$.channels.t1_c.byte_order: expected \"little\""), std::string::npos) << error_of(j);

    j = mixed_layout_json();
    j["frames"][1]["can_id"] = 0x900;  // more than 11 bits on a frame declared standard
    j["frames"][1]["extended"] = false;
    EXPECT_NE(error_of(j).find("$.frames[1].can_id: expected an 11-bit identifier"), std::string::npos) << error_of(j);

    EXPECT_NE(error_of(json::array()).find("$: expected a JSON object"), std::string::npos);
}

}  // namespace
