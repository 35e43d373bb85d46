#include "cellbench/protocol/dewe_can.hpp"

#include <algorithm>
#include <bit>
#include <cstdio>
#include <cmath>
#include <cstring>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/core/json_fields.hpp"

namespace cellbench::protocol {

// ---------------------------------------------------------------------------------------------------------
// CAN records.

CanFrame CanFrame::data_frame(std::uint32_t id, bool extended, std::span<const std::uint8_t> payload) {
    CanFrame f;
    f.can_id = extended ? ((id & kCanEffMask) | kCanEffFlag) : (id & kCanSffMask);
    f.len = static_cast<std::uint8_t>(std::min(payload.size(), kCanMaxDlen));
    std::copy_n(payload.begin(), f.len, f.data.begin());
    return f;
}

void encode_can_record(const CanFrame& frame, std::uint8_t* out) {
    // struct can_frame on a little-endian Linux host: can_id, len, __pad, __res0, len8_dlc, data[8] at 8.
    out[0] = static_cast<std::uint8_t>(frame.can_id);
    out[1] = static_cast<std::uint8_t>(frame.can_id >> 8);
    out[2] = static_cast<std::uint8_t>(frame.can_id >> 16);
    out[3] = static_cast<std::uint8_t>(frame.can_id >> 24);
    out[4] = frame.len;
    out[5] = 0;
    out[6] = 0;
    out[7] = frame.len8_dlc;
    const std::size_t n = std::min<std::size_t>(frame.len, kCanMaxDlen);
    for (std::size_t i = 0; i < kCanMaxDlen; ++i) out[8 + i] = i < n ? frame.data[i] : 0;
}

CanRecord encode_can_record(const CanFrame& frame) {
    CanRecord r{};
    encode_can_record(frame, r.data());
    return r;
}

std::optional<CanFrame> decode_can_record(std::span<const std::uint8_t> b, CanRecordError* error) {
    if (b.size() != kCanRecordBytes) {
        if (error) *error = CanRecordError::wrong_size;
        return std::nullopt;
    }
    if (b[4] > kCanMaxDlen) {
        if (error) *error = CanRecordError::bad_length;
        return std::nullopt;
    }
    CanFrame f;
    f.can_id = static_cast<std::uint32_t>(b[0]) | static_cast<std::uint32_t>(b[1]) << 8 |
               static_cast<std::uint32_t>(b[2]) << 16 | static_cast<std::uint32_t>(b[3]) << 24;
    f.len = b[4];
    f.len8_dlc = b[7];
    std::memcpy(f.data.data(), b.data() + 8, kCanMaxDlen);
    return f;
}

// ---------------------------------------------------------------------------------------------------------
// Fields.

namespace {

std::uint64_t read_raw(const CanField& field, const std::uint8_t* payload) {
    std::uint64_t raw = 0;
    const std::uint8_t* p = payload + field.byte_offset;
    if (field.byte_order == ByteOrder::little_endian) {
        for (std::size_t i = field.length_bytes; i-- > 0;) raw = (raw << 8) | p[i];
    } else {
        for (std::size_t i = 0; i < field.length_bytes; ++i) raw = (raw << 8) | p[i];
    }
    return raw;
}

void write_raw(const CanField& field, std::uint64_t raw, std::uint8_t* payload) {
    std::uint8_t* p = payload + field.byte_offset;
    for (std::size_t i = 0; i < field.length_bytes; ++i) {
        const auto byte = static_cast<std::uint8_t>(raw >> (8 * i));
        if (field.byte_order == ByteOrder::little_endian)
            p[i] = byte;
        else
            p[field.length_bytes - 1 - i] = byte;
    }
}

std::uint64_t modulus_of(std::size_t length_bytes) {
    return length_bytes >= 8 ? 0 : (std::uint64_t{1} << (8 * length_bytes));  // 0 = 2^64
}

}  // namespace

double read_field(const CanField& field, const std::uint8_t* payload) {
    const std::uint64_t raw = read_raw(field, payload);
    switch (field.type) {
        case CanValueType::float32:
            return static_cast<double>(std::bit_cast<float>(static_cast<std::uint32_t>(raw)));
        case CanValueType::signed_int: {
            const unsigned bits = static_cast<unsigned>(8 * field.length_bytes);
            if (bits >= 64) return static_cast<double>(static_cast<std::int64_t>(raw));
            const std::uint64_t sign = std::uint64_t{1} << (bits - 1);
            // Sign extension: (x ^ sign) - sign maps [2^(b-1), 2^b) to the negative range.
            return static_cast<double>(static_cast<std::int64_t>((raw ^ sign) - sign));
        }
        case CanValueType::unsigned_int:
        default:
            return static_cast<double>(raw);
    }
}

void write_field(const CanField& field, double value, std::uint8_t* payload) {
    const unsigned bits = static_cast<unsigned>(8 * field.length_bytes);
    std::uint64_t raw = 0;
    switch (field.type) {
        case CanValueType::float32:
            raw = std::bit_cast<std::uint32_t>(static_cast<float>(value));
            break;
        case CanValueType::signed_int: {
            const double max = std::ldexp(1.0, static_cast<int>(bits) - 1);  // 2^(b-1): first value out of range
            const double r = std::nearbyint(value);
            std::int64_t v = 0;
            if (std::isnan(r)) v = 0;
            else if (r >= max) v = bits >= 64 ? INT64_MAX : static_cast<std::int64_t>(max) - 1;
            else if (r < -max) v = bits >= 64 ? INT64_MIN : -static_cast<std::int64_t>(max);
            else v = static_cast<std::int64_t>(r);
            raw = static_cast<std::uint64_t>(v);
            break;
        }
        case CanValueType::unsigned_int: {
            const double max = std::ldexp(1.0, static_cast<int>(bits));  // 2^b
            const double r = std::nearbyint(value);
            if (std::isnan(r) || r <= 0) raw = 0;
            else if (r >= max) raw = bits >= 64 ? UINT64_MAX : (std::uint64_t{1} << bits) - 1;
            else raw = static_cast<std::uint64_t>(r);
            break;
        }
    }
    write_raw(field, raw, payload);
}

// ---------------------------------------------------------------------------------------------------------
// Layout.

const char* dewe_channel_name(DeweChannel channel) {
    switch (channel) {
        case DeweChannel::thermopile_v: return "thermopile_v";
        case DeweChannel::type_t_c: return "type_t_c";
        case DeweChannel::t1_c: return "t1_c";
        case DeweChannel::t2_c: return "t2_c";
    }
    return "?";
}

DeweCanLayout DeweCanLayout::bench_default() {
    DeweCanLayout l;
    const CanField counter{0, 2, CanValueType::unsigned_int, ByteOrder::little_endian};
    l.frames.push_back({0x310, false, counter});
    l.frames.push_back({0x311, false, counter});
    l.channels.push_back({DeweChannel::thermopile_v, 0x310, false,
                          {2, 4, CanValueType::float32, ByteOrder::little_endian}, 1.0, 0.0});
    // 0.01 degC in int16: -327.68 .. 327.67 degC covers the chamber's -50..180 degC.
    for (const auto& [channel, offset] : {std::pair{DeweChannel::type_t_c, 2}, {DeweChannel::t1_c, 4},
                                          {DeweChannel::t2_c, 6}})
        l.channels.push_back({channel, 0x311, false,
                              {static_cast<std::size_t>(offset), 2, CanValueType::signed_int,
                               ByteOrder::little_endian},
                              0.01, 0.0});
    return l;
}

const DeweChannelSpec* DeweCanLayout::channel(DeweChannel c) const {
    for (const auto& spec : channels)
        if (spec.channel == c) return &spec;
    return nullptr;
}

namespace {

using nlohmann::json;

// The shared JSON field readers (json_fields.hpp): errors read "SOURCE: JSON.PATH: what was expected".
using json_fields::bool_value;
using json_fields::fail;
using json_fields::finite_number;
using json_fields::member;
using json_fields::string_value;

// Every integer of the layout may also be a string: CAN identifiers are written "0x310" in every data sheet.
std::uint64_t layout_unsigned(const json& j, std::uint64_t max, const std::string& source, const std::string& path) {
    return json_fields::unsigned_value(j, max, source, path, json_fields::IntegerText::accepted);
}

std::string hex_id(std::uint32_t id) {
    char buf[16];
    std::snprintf(buf, sizeof buf, "0x%X", static_cast<unsigned>(id));
    return buf;
}

void check_field(const CanField& f, const std::string& source, const std::string& path) {
    if (f.type == CanValueType::float32 && f.length_bytes != 4)
        fail(source, path + ".length", "expected 4 for a float32 field (got " + std::to_string(f.length_bytes) + ")");
    if (f.length_bytes < 1 || f.length_bytes > 8)
        fail(source, path + ".length", "expected 1..8 bytes (got " + std::to_string(f.length_bytes) + ")");
    if (f.byte_offset + f.length_bytes > kCanMaxDlen)
        fail(source, path, "field at byte " + std::to_string(f.byte_offset) + " with " +
                               std::to_string(f.length_bytes) + " bytes does not fit in 8 data bytes");
}

void check_id(std::uint32_t id, bool extended, const std::string& source, const std::string& path) {
    if (id > (extended ? kCanEffMask : kCanSffMask))
        fail(source, path + ".can_id",
             extended ? "expected a 29-bit identifier" : "expected an 11-bit identifier (set \"extended\": true for 29 bits)");
}

ByteOrder byte_order_of(const json& j, const std::string& source, const std::string& path) {
    const std::string s = string_value(j, source, path);
    if (s == "little" || s == "intel") return ByteOrder::little_endian;
    if (s == "big" || s == "motorola") return ByteOrder::big_endian;
    fail(source, path, "expected \"little\" (Intel) or \"big\" (Motorola), got \"" + s + "\"");
}

CanValueType type_of(const json& j, const std::string& source, const std::string& path) {
    const std::string s = string_value(j, source, path);
    if (s == "unsigned") return CanValueType::unsigned_int;
    if (s == "signed") return CanValueType::signed_int;
    if (s == "float32") return CanValueType::float32;
    fail(source, path, "expected \"unsigned\", \"signed\" or \"float32\", got \"" + s + "\"");
}

// A field object: byte_offset, length, optional byte_order (little) and type (default_type).
CanField field_of(const json& j, CanValueType default_type, bool allow_type, const std::string& source,
                  const std::string& path) {
    CanField f;
    f.byte_offset = static_cast<std::size_t>(layout_unsigned(member(j, "byte_offset", source, path), 7, source, path + ".byte_offset"));
    f.type = default_type;
    if (allow_type && j.contains("type")) f.type = type_of(j["type"], source, path + ".type");
    if (j.contains("length"))
        f.length_bytes = static_cast<std::size_t>(layout_unsigned(j["length"], 8, source, path + ".length"));
    else if (f.type == CanValueType::float32)
        f.length_bytes = 4;
    else
        fail(source, path + ".length", "missing (required)");
    if (j.contains("byte_order")) f.byte_order = byte_order_of(j["byte_order"], source, path + ".byte_order");
    check_field(f, source, path);
    return f;
}

bool extended_of(const json& j, std::uint64_t id, const std::string& source, const std::string& path) {
    if (j.contains("extended")) return bool_value(j["extended"], source, path + ".extended");
    return id > kCanSffMask;
}

json field_json(const CanField& f, bool with_type) {
    json j = {{"byte_offset", f.byte_offset}, {"length", f.length_bytes},
              {"byte_order", f.byte_order == ByteOrder::little_endian ? "little" : "big"}};
    if (with_type)
        j["type"] = f.type == CanValueType::float32 ? "float32" : f.type == CanValueType::signed_int ? "signed" : "unsigned";
    return j;
}

}  // namespace

DeweCanLayout DeweCanLayout::from_json(const json& j, const std::string& source) {
    if (!j.is_object()) fail(source, "$", "expected a JSON object");
    if (j.contains("schema") && j["schema"] != kDeweCanLayoutSchema)
        fail(source, "$.schema", std::string("expected \"") + kDeweCanLayoutSchema + "\"");
    DeweCanLayout l;

    const json& frames = member(j, "frames", source, "$");
    if (!frames.is_array() || frames.empty()) fail(source, "$.frames", "expected a non-empty array of frames");
    for (std::size_t i = 0; i < frames.size(); ++i) {
        const std::string path = "$.frames[" + std::to_string(i) + "]";
        const json& fj = frames[i];
        DeweFrameSpec f;
        const auto id = layout_unsigned(member(fj, "can_id", source, path), kCanEffMask, source, path + ".can_id");
        f.can_id = static_cast<std::uint32_t>(id);
        f.extended = extended_of(fj, id, source, path);
        check_id(f.can_id, f.extended, source, path);
        f.counter = field_of(member(fj, "counter", source, path), CanValueType::unsigned_int, false, source,
                             path + ".counter");
        l.frames.push_back(f);
    }

    const json& channels = member(j, "channels", source, "$");
    if (!channels.is_object()) fail(source, "$.channels", "expected an object keyed by channel name");
    for (const auto& [name, cj] : channels.items()) {
        const std::string path = "$.channels." + name;
        DeweChannelSpec c;
        bool known = false;
        for (std::size_t k = 0; k < kDeweChannelCount; ++k)
            if (name == dewe_channel_name(static_cast<DeweChannel>(k))) {
                c.channel = static_cast<DeweChannel>(k);
                known = true;
            }
        if (!known) fail(source, path, "unknown channel (expected thermopile_v, type_t_c, t1_c or t2_c)");
        const auto id = layout_unsigned(member(cj, "can_id", source, path), kCanEffMask, source, path + ".can_id");
        c.can_id = static_cast<std::uint32_t>(id);
        c.extended = extended_of(cj, id, source, path);
        c.field = field_of(cj, CanValueType::unsigned_int, true, source, path);
        if (!cj.contains("type")) fail(source, path + ".type", "missing (required: \"unsigned\", \"signed\" or \"float32\")");
        if (cj.contains("scale")) c.scale = finite_number(cj["scale"], source, path + ".scale");
        if (cj.contains("offset")) c.offset = finite_number(cj["offset"], source, path + ".offset");
        l.channels.push_back(c);
    }
    // Keep the canonical channel order whatever the JSON order.
    std::sort(l.channels.begin(), l.channels.end(),
              [](const auto& a, const auto& b) { return a.channel < b.channel; });
    l.validate(source);
    return l;
}

json DeweCanLayout::to_json() const {
    json j;
    j["schema"] = kDeweCanLayoutSchema;
    j["frames"] = json::array();
    for (const auto& f : frames)
        j["frames"].push_back({{"can_id", hex_id(f.can_id)}, {"extended", f.extended}, {"counter", field_json(f.counter, false)}});
    j["channels"] = json::object();
    for (const auto& c : channels) {
        json cj = field_json(c.field, true);
        cj["can_id"] = hex_id(c.can_id);
        cj["extended"] = c.extended;
        cj["scale"] = c.scale;
        cj["offset"] = c.offset;
        j["channels"][dewe_channel_name(c.channel)] = cj;
    }
    return j;
}

void DeweCanLayout::validate(const std::string& source) const {
    if (frames.empty()) fail(source, "$.frames", "expected at least one frame");
    if (frames.size() > 32) fail(source, "$.frames", "expected at most 32 frames");
    std::vector<std::uint8_t> used(frames.size() * kCanMaxDlen, 0);  // byte occupancy per frame
    auto occupy = [&](std::size_t frame, const CanField& f, const std::string& path) {
        for (std::size_t b = f.byte_offset; b < f.byte_offset + f.length_bytes; ++b) {
            if (used[frame * kCanMaxDlen + b]) fail(source, path, "overlaps another field at byte " + std::to_string(b));
            used[frame * kCanMaxDlen + b] = 1;
        }
    };
    for (std::size_t i = 0; i < frames.size(); ++i) {
        const std::string path = "$.frames[" + std::to_string(i) + "]";
        const auto& f = frames[i];
        check_id(f.can_id, f.extended, source, path);
        check_field(f.counter, source, path + ".counter");
        if (f.counter.type != CanValueType::unsigned_int) fail(source, path + ".counter", "expected an unsigned counter");
        for (std::size_t k = 0; k < i; ++k)
            if (frames[k].can_id == f.can_id && frames[k].extended == f.extended)
                fail(source, path + ".can_id", "duplicate frame " + hex_id(f.can_id));
        occupy(i, f.counter, path + ".counter");
    }
    for (std::size_t i = 0; i < channels.size(); ++i) {
        const auto& c = channels[i];
        const std::string path = std::string("$.channels.") + dewe_channel_name(c.channel);
        for (std::size_t k = 0; k < i; ++k)
            if (channels[k].channel == c.channel) fail(source, path, "channel given twice");
        check_id(c.can_id, c.extended, source, path);
        check_field(c.field, source, path);
        if (!std::isfinite(c.scale) || c.scale == 0.0) fail(source, path + ".scale", "expected a finite non-zero number");
        if (!std::isfinite(c.offset)) fail(source, path + ".offset", "expected a finite number");
        const auto it = std::find_if(frames.begin(), frames.end(),
                                     [&](const auto& f) { return f.can_id == c.can_id && f.extended == c.extended; });
        if (it == frames.end())
            fail(source, path + ".can_id", "frame " + hex_id(c.can_id) + " is not declared in $.frames");
        occupy(static_cast<std::size_t>(it - frames.begin()), c.field, path);
    }
    for (const auto required : {DeweChannel::thermopile_v, DeweChannel::type_t_c})
        if (!channel(required))
            fail(source, std::string("$.channels.") + dewe_channel_name(required),
                 "missing (required: the heat flux needs the thermopile voltage and the sensor's Type-T)");
}

// ---------------------------------------------------------------------------------------------------------
// Decoder.

DeweCanDecoder::DeweCanDecoder(DeweCanLayout layout) : layout_(std::move(layout)) {
    layout_.validate();
    for (const auto& spec : layout_.frames) {
        FrameState fs;
        fs.spec = spec;
        fs.can_id_with_flags = spec.extended ? (spec.can_id | kCanEffFlag) : spec.can_id;
        fs.min_length = spec.counter.byte_offset + spec.counter.length_bytes;
        fs.counter_modulus = modulus_of(spec.counter.length_bytes);
        frames_.push_back(fs);
    }
    for (std::size_t c = 0; c < layout_.channels.size(); ++c) {
        const auto& ch = layout_.channels[c];
        for (auto& fs : frames_)
            if (fs.spec.can_id == ch.can_id && fs.spec.extended == ch.extended) {
                fs.channels.push_back(c);
                fs.min_length = std::max(fs.min_length, ch.field.byte_offset + ch.field.length_bytes);
            }
    }
    sample_modulus_ = 0;
    for (const auto& fs : frames_)
        if (fs.counter_modulus != 0 && (sample_modulus_ == 0 || fs.counter_modulus < sample_modulus_))
            sample_modulus_ = fs.counter_modulus;
    full_mask_ = frames_.size() >= 32 ? 0xFFFFFFFFu : ((1u << frames_.size()) - 1u);
}

void DeweCanDecoder::resync() {
    for (auto& fs : frames_) fs.last_counter.reset();
    pending_ = false;
    last_counter_.reset();
}

std::optional<DeweSample> DeweCanDecoder::push_record(std::span<const std::uint8_t> record, double time_s) {
    CanRecordError error{};
    const auto frame = decode_can_record(record, &error);
    if (!frame) {
        ++stats_.records;
        ++stats_.garbage;
        ++(error == CanRecordError::wrong_size ? stats_.wrong_size : stats_.bad_length);
        return std::nullopt;
    }
    return push(*frame, time_s);
}

namespace {
// (now - previous) modulo m, with m == 0 meaning 2^64.
std::uint64_t forward_distance(std::uint64_t previous, std::uint64_t now, std::uint64_t m) {
    return m == 0 ? now - previous : (now + m - previous) % m;
}
bool is_backward_jump(std::uint64_t distance, std::uint64_t m) {
    return m == 0 ? distance > (std::uint64_t{1} << 63) : distance > m / 2;
}
}  // namespace

std::optional<DeweSample> DeweCanDecoder::push(const CanFrame& frame, double time_s) {
    ++stats_.records;
    auto garbage = [&](std::uint64_t& kind) -> std::optional<DeweSample> {
        ++kind;
        ++stats_.garbage;
        return std::nullopt;
    };
    if (frame.error() || frame.remote()) return garbage(stats_.not_data);
    if (frame.len > kCanMaxDlen) return garbage(stats_.bad_length);

    std::size_t index = 0;
    const std::uint32_t key = frame.can_id & (kCanEffFlag | kCanEffMask);
    while (index < frames_.size() && frames_[index].can_id_with_flags != key) ++index;
    if (index == frames_.size()) return garbage(stats_.unknown_id);
    FrameState& fs = frames_[index];
    if (frame.len < fs.min_length) return garbage(stats_.bad_length);

    const auto counter = static_cast<std::uint64_t>(read_raw(fs.spec.counter, frame.data.data()));
    if (fs.last_counter) {
        if (counter == *fs.last_counter) return garbage(stats_.duplicates);
        const std::uint64_t d = forward_distance(*fs.last_counter, counter, fs.counter_modulus);
        if (!is_backward_jump(d, fs.counter_modulus)) stats_.lost_frames += d - 1;
    }
    fs.last_counter = counter;
    ++stats_.frames;

    const std::uint64_t c = sample_modulus_ == 0 ? counter : counter % sample_modulus_;
    if (pending_ && c != pending_counter_) {
        // The pending sample never got all its frames: it is lost, and the stream moves on.
        ++stats_.lost_samples;
        last_counter_ = pending_counter_;
        sequence_ = pending_sequence_;
        pending_ = false;
    }
    if (!pending_) {
        std::uint64_t sequence = c;
        if (last_counter_) {
            const std::uint64_t d = forward_distance(*last_counter_, c, sample_modulus_);
            if (d == 0) {  // repeats a sample already delivered (frame counters of different widths)
                --stats_.frames;
                return garbage(stats_.duplicates);
            }
            if (is_backward_jump(d, sample_modulus_)) {
                ++stats_.resyncs;  // the DAQ restarted its counter: keep the sequence monotonic
                sequence = sequence_ + 1;
            } else {
                stats_.lost_samples += d - 1;
                sequence = sequence_ + d;
            }
        }
        pending_ = true;
        pending_counter_ = c;
        pending_sequence_ = sequence;
        pending_mask_ = 0;
        pending_values_.fill(std::numeric_limits<double>::quiet_NaN());
    }
    for (const std::size_t ci : fs.channels) {
        const auto& ch = layout_.channels[ci];
        pending_values_[static_cast<std::size_t>(ch.channel)] = read_field(ch.field, frame.data.data()) * ch.scale + ch.offset;
    }
    pending_mask_ |= 1u << index;
    if (pending_mask_ != full_mask_) return std::nullopt;

    pending_ = false;
    last_counter_ = pending_counter_;
    sequence_ = pending_sequence_;
    ++stats_.samples;
    DeweSample s;
    s.time_s = time_s;
    s.sequence = pending_sequence_;
    s.values = pending_values_;
    return s;
}

std::vector<CanFrame> encode_dewe_sample(const DeweCanLayout& layout, const std::array<double, kDeweChannelCount>& values,
                                         std::uint64_t counter) {
    std::vector<CanFrame> out;
    out.reserve(layout.frames.size());
    for (const auto& spec : layout.frames) {
        CanFrame f;
        f.can_id = spec.extended ? (spec.can_id | kCanEffFlag) : spec.can_id;
        std::size_t len = spec.counter.byte_offset + spec.counter.length_bytes;
        const std::uint64_t m = modulus_of(spec.counter.length_bytes);
        write_raw(spec.counter, m == 0 ? counter : counter % m, f.data.data());
        for (const auto& ch : layout.channels) {
            if (ch.can_id != spec.can_id || ch.extended != spec.extended) continue;
            const double v = values[static_cast<std::size_t>(ch.channel)];
            write_field(ch.field, (v - ch.offset) / ch.scale, f.data.data());
            len = std::max(len, ch.field.byte_offset + ch.field.length_bytes);
        }
        f.len = static_cast<std::uint8_t>(len);
        out.push_back(f);
    }
    return out;
}

}  // namespace cellbench::protocol
