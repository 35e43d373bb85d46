#pragma once
// The DEWE-43A's CAN output (2 x CAN 2.0B, thesis 2.1.3) carrying the heat flux bench channels: the thermopile
// voltage of the FHF05, its integrated Type-T thermocouple, and the two Type-K thermocouples at the terminals.
//
// Pure: bytes in, structs out (no sockets, no clocks; the caller passes receive times). Three parts:
//  - CanFrame: a classic CAN frame and its exact 16-byte `struct can_frame` record, as a SocketCAN raw socket
//    delivers it and as `can-dgram` carries it (INTERFACES.md): can_id (u32, little-endian as on Linux/x86,
//    with the EFF/RTR/ERR flags in bits 31/30/29), len (0..8), __pad, __res0, len8_dlc, data[8].
//  - DeweCanLayout: where each channel sits in which frame (CAN id, byte offset, length, unsigned/signed/
//    float32, byte order, value = raw * scale + offset), and the sample counter field every frame carries.
//    Fields are byte-aligned (as the DEWE CAN output writes them). JSON form "cellbench.dewe-can/1".
//  - DeweCanDecoder / encode_dewe_sample: frames -> timestamped samples (counter gaps counted as lost samples,
//    garbage counted and dropped, never a crash), and the inverse used by the simulated DAQ.
#include <array>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace cellbench::protocol {

// ---------------------------------------------------------------------------------------------------------
// CAN frames (linux/can.h names and values).
inline constexpr std::uint32_t kCanEffFlag = 0x80000000u;  // extended (29-bit) identifier
inline constexpr std::uint32_t kCanRtrFlag = 0x40000000u;  // remote transmission request
inline constexpr std::uint32_t kCanErrFlag = 0x20000000u;  // error message frame
inline constexpr std::uint32_t kCanSffMask = 0x000007FFu;
inline constexpr std::uint32_t kCanEffMask = 0x1FFFFFFFu;
inline constexpr std::size_t kCanMaxDlen = 8;
inline constexpr std::size_t kCanRecordBytes = 16;  // sizeof(struct can_frame)

using CanRecord = std::array<std::uint8_t, kCanRecordBytes>;

struct CanFrame {
    std::uint32_t can_id = 0;  // identifier plus EFF/RTR/ERR flags, as struct can_frame
    std::uint8_t len = 0;      // payload length 0..8 (can_dlc)
    std::uint8_t len8_dlc = 0; // optional raw DLC 9..15 when len == 8 (carried verbatim)
    std::array<std::uint8_t, kCanMaxDlen> data{};

    [[nodiscard]] bool extended() const { return (can_id & kCanEffFlag) != 0; }
    [[nodiscard]] bool remote() const { return (can_id & kCanRtrFlag) != 0; }
    [[nodiscard]] bool error() const { return (can_id & kCanErrFlag) != 0; }
    // The bare identifier (11 or 29 bits).
    [[nodiscard]] std::uint32_t id() const { return can_id & (extended() ? kCanEffMask : kCanSffMask); }

    // A data frame with an 11-bit (extended = false) or 29-bit identifier; payload truncated to 8 bytes.
    static CanFrame data_frame(std::uint32_t id, bool extended, std::span<const std::uint8_t> payload);

    friend bool operator==(const CanFrame&, const CanFrame&) = default;
};

// Why a record is not a usable frame.
enum class CanRecordError {
    wrong_size,     // not exactly 16 bytes (short datagram, CAN FD record, ...)
    bad_length,     // len > 8
};

// The 16 bytes of struct can_frame (pad/reserved bytes zero, unused data bytes zero).
CanRecord encode_can_record(const CanFrame& frame);
void encode_can_record(const CanFrame& frame, std::uint8_t* out16);
// Parses a record; nullopt (and the reason in *error when given) for garbage.
std::optional<CanFrame> decode_can_record(std::span<const std::uint8_t> bytes, CanRecordError* error = nullptr);

// ---------------------------------------------------------------------------------------------------------
// Channel layout.
enum class CanValueType { unsigned_int, signed_int, float32 };
enum class ByteOrder { little_endian, big_endian };  // Intel / Motorola

// The bench channels of the DAQ, in this order everywhere.
enum class DeweChannel : std::size_t { thermopile_v = 0, type_t_c = 1, t1_c = 2, t2_c = 3 };
inline constexpr std::size_t kDeweChannelCount = 4;
// JSON names: "thermopile_v", "type_t_c", "t1_c", "t2_c".
const char* dewe_channel_name(DeweChannel channel);

// One numeric field inside a frame's payload.
struct CanField {
    std::size_t byte_offset = 0;
    std::size_t length_bytes = 2;  // 1..8 for integers, 4 for float32
    CanValueType type = CanValueType::unsigned_int;
    ByteOrder byte_order = ByteOrder::little_endian;
};

struct DeweChannelSpec {
    DeweChannel channel = DeweChannel::thermopile_v;
    std::uint32_t can_id = 0;  // bare identifier of the frame carrying it
    bool extended = false;
    CanField field;
    double scale = 1.0;   // value = raw * scale + offset (in V for the thermopile, degC for temperatures)
    double offset = 0.0;
};

// One frame of the layout: its identifier and its sample counter (unsigned, wraps at 2^(8*length)).
struct DeweFrameSpec {
    std::uint32_t can_id = 0;
    bool extended = false;
    CanField counter{0, 1, CanValueType::unsigned_int, ByteOrder::little_endian};
};

struct DeweCanLayout {
    std::vector<DeweFrameSpec> frames;
    std::vector<DeweChannelSpec> channels;  // thermopile_v and type_t_c required; t1_c, t2_c optional

    // The layout the simulated DAQ uses by default: 0x310 = {u16 counter, float32 thermopile V}, 0x311 =
    // {u16 counter, int16 Type-T, int16 T1, int16 T2 in 0.01 degC}, all little-endian.
    static DeweCanLayout bench_default();

    // Throws InputError naming the JSON path and what was expected (source prefixes the message).
    static DeweCanLayout from_json(const nlohmann::json& j, const std::string& source = "dewe can layout");
    [[nodiscard]] nlohmann::json to_json() const;
    // Throws InputError on an inconsistent layout (fields outside 8 bytes or overlapping, channel in an
    // undeclared frame, duplicate frames/channels, missing required channels, identifiers out of range).
    void validate(const std::string& source = "dewe can layout") const;

    [[nodiscard]] const DeweChannelSpec* channel(DeweChannel c) const;
};

inline constexpr const char* kDeweCanLayoutSchema = "cellbench.dewe-can/1";

// Raw field access (exposed for tests and the encoder). read_field returns the value as double (integers
// exactly up to 2^53); write_field rounds to the nearest representable raw value and saturates.
double read_field(const CanField& field, const std::uint8_t* payload);
void write_field(const CanField& field, double raw_value, std::uint8_t* payload);

// ---------------------------------------------------------------------------------------------------------
// Samples.
struct DeweSample {
    double time_s = 0.0;          // receive time of the frame that completed the sample (caller's clock)
    std::uint64_t sequence = 0;   // unwrapped sample counter (starts at the first counter value seen)
    std::array<double, kDeweChannelCount> values{};  // by DeweChannel; NaN for channels the layout lacks

    [[nodiscard]] double value(DeweChannel c) const { return values[static_cast<std::size_t>(c)]; }
    [[nodiscard]] double thermopile_v() const { return value(DeweChannel::thermopile_v); }
    [[nodiscard]] double type_t_c() const { return value(DeweChannel::type_t_c); }
    [[nodiscard]] double t1_c() const { return value(DeweChannel::t1_c); }
    [[nodiscard]] double t2_c() const { return value(DeweChannel::t2_c); }
};

struct DeweStreamStats {
    std::uint64_t records = 0;          // everything pushed
    std::uint64_t frames = 0;           // accepted frames of the layout
    std::uint64_t samples = 0;          // complete samples produced
    std::uint64_t lost_samples = 0;     // counter gaps plus incomplete samples
    std::uint64_t lost_frames = 0;      // per-frame counter gaps
    std::uint64_t garbage = 0;          // sum of the garbage kinds below
    std::uint64_t wrong_size = 0;       // records that are not 16 bytes
    std::uint64_t bad_length = 0;       // len > 8, or too short for the layout's fields
    std::uint64_t unknown_id = 0;       // identifiers not in the layout
    std::uint64_t not_data = 0;         // remote and error frames
    std::uint64_t duplicates = 0;       // a frame repeating the counter of its previous one
    std::uint64_t resyncs = 0;          // counter jumps back or by more than half its range (DAQ restart)
};

class DeweCanDecoder {
public:
    explicit DeweCanDecoder(DeweCanLayout layout);  // validates

    // Feeds one frame received at time_s (any clock); returns the sample this frame completes, if any.
    std::optional<DeweSample> push(const CanFrame& frame, double time_s);
    // Same from the raw record bytes (garbage records are counted here).
    std::optional<DeweSample> push_record(std::span<const std::uint8_t> record, double time_s);

    [[nodiscard]] const DeweStreamStats& stats() const { return stats_; }
    [[nodiscard]] const DeweCanLayout& layout() const { return layout_; }
    // Forgets the stream position (counters), keeps the statistics.
    void resync();

private:
    struct FrameState {
        DeweFrameSpec spec;
        std::uint32_t can_id_with_flags = 0;
        std::size_t min_length = 0;                 // bytes the layout needs in this frame
        std::vector<std::size_t> channels;          // indices into layout_.channels
        std::uint64_t counter_modulus = 0;
        std::optional<std::uint64_t> last_counter;  // raw
    };

    DeweCanLayout layout_;
    std::vector<FrameState> frames_;
    std::uint64_t sample_modulus_ = 0;  // smallest counter range over the frames
    DeweStreamStats stats_;

    // The sample being assembled.
    bool pending_ = false;
    std::uint64_t pending_counter_ = 0;  // raw, modulo sample_modulus_
    std::uint64_t pending_sequence_ = 0;
    std::uint32_t pending_mask_ = 0;     // frames received for it
    std::uint32_t full_mask_ = 0;
    std::array<double, kDeweChannelCount> pending_values_{};
    // The last complete or abandoned sample.
    std::optional<std::uint64_t> last_counter_;
    std::uint64_t sequence_ = 0;  // unwrapped sequence of last_counter_
};

// The frames of one sample with the given counter (wrapped to each frame's counter width), in layout order.
std::vector<CanFrame> encode_dewe_sample(const DeweCanLayout& layout,
                                         const std::array<double, kDeweChannelCount>& values,
                                         std::uint64_t counter);

}  // namespace cellbench::protocol
