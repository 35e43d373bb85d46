#pragma once
// Neware BTS API: XML documents over TCP, each followed by the terminator "\n\n#\r\n".
//
//   <?xml version="1.0" encoding="UTF-8" ?><bts version="1.0"><cmd>NAME</cmd>...</bts>\n\n#\r\n
//
// Matched against responses captured from a real BTS 8.0 server (devtype 27) and the requests of public
// BTS 8 clients (../shared/reference/neware/): every command those exchange is here, with the real server's
// spellings (`donwload_resp`, `donwloadlog_resp`, `downloadStepLayer_resp`) and attribute layouts. Pure code:
// bytes in, structs out; no sockets, no clocks.
//
// Framing: a frame ends at `</bts>` followed by optional whitespace and `#\r\n` (so "\n\n#\r\n", the form the
// encoders write, and "#\r\n" right after `</bts>` are both frames). Requests of real clients may carry a stray
// '"' between `</list>` and `</bts>`; it is ignored.
//
// Robustness rules (the tester is a separate box; its bytes are untrusted):
//  - FrameSplitter takes arbitrary chunks and yields whole frames; bytes outside frames (before "<?xml" or
//    "<bts") are dropped and counted; a frame larger than the configured limit raises ProtocolError and is
//    discarded, after which splitting resynchronises on the next terminator.
//  - Parsing goes through Boost.PropertyTree's XML parser after normalising vendor quirks: typographic quotes
//    (U+201C, U+201D) used as attribute delimiters, a UTF-8 BOM, leading whitespace, whitespace around '=' and
//    inside text values, attribute order and the case of attribute names ("Channelid" vs "chlid").
//  - The vendor's `count` attributes are not trusted (field examples carry wrong ones); entries are counted.
//  - Anything else malformed raises ProtocolError with what was expected; nothing crashes.
//
// Units: V, A (+ = charge, the project's convention and Neware's), Ah, Wh, s.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

namespace cellbench::protocol::neware {

inline constexpr std::string_view kFrameTerminator = "\n\n#\r\n";
// A 1000-row download_resp is ~250 kB; live traffic (inquire of a few channels) is ~1 kB.
inline constexpr std::size_t kDefaultMaxFrameBytes = 4u << 20;
// Element nesting allowed in a frame (real frames nest 3 deep); bounds the XML parser's recursion.
inline constexpr int kMaxXmlDepth = 16;

class ProtocolError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

// ---------------------------------------------------------------------------------------------------------
// Framing

class FrameSplitter {
public:
    explicit FrameSplitter(std::size_t max_frame_bytes = kDefaultMaxFrameBytes);

    // Appends received bytes (any chunking). Never throws.
    void feed(std::string_view bytes);

    // The next complete frame: the XML document without the terminator and without garbage before it, or
    // nullopt when more bytes are needed. Throws ProtocolError when a frame (or unterminated data) exceeds
    // max_frame_bytes; those bytes are discarded first, so calling next() again continues with what follows.
    std::optional<std::string> next();

    [[nodiscard]] std::size_t buffered_bytes() const { return buffer_.size() - head_; }
    [[nodiscard]] std::uint64_t garbage_bytes() const { return garbage_bytes_; }  // dropped outside frames
    [[nodiscard]] std::size_t max_frame_bytes() const { return max_frame_bytes_; }
    [[nodiscard]] std::size_t capacity_bytes() const { return buffer_.capacity(); }  // memory held
    void clear();

    // Buffer capacity kept between frames; beyond it, an emptied buffer is released (see feed()).
    static constexpr std::size_t kKeptCapacity = 64u << 10;

private:
    std::string buffer_;
    std::size_t head_ = 0;       // start of unconsumed bytes
    std::size_t scanned_ = 0;    // offset (from head_) up to which no terminator starts
    bool skipping_ = false;      // inside an oversized frame: drop everything up to its terminator
    std::size_t max_frame_bytes_;
    std::uint64_t garbage_bytes_ = 0;
};

// ---------------------------------------------------------------------------------------------------------
// Vocabulary

enum class Command {
    connect, getdevinfo, getchlstatus, inquire, start, stop, pause, continue_, download,
    inquiredf, downloadlog, downloadStepLayer, light, clearflag
};
std::string_view command_name(Command command);                       // "continue" for continue_
std::optional<Command> command_from_name(std::string_view name);      // exact, case-insensitive
// The <cmd> of the tester's answer: "download" -> "donwload_resp", "downloadlog" -> "donwloadlog_resp" (the real
// server's spelling), else NAME + "_resp". response_command_from_name accepts both spellings.
std::string response_name(Command command);
std::optional<Command> response_command_from_name(std::string_view cmd);

// Channel states of getchlstatus_resp and inquire_resp/@workstatus. Unseen words map to `unknown` (the
// raw word is kept beside it) so a newer tester does not break the client.
enum class ChannelStatus { working, stop, finish, protect, pause, unknown };
std::string_view to_string(ChannelStatus status);
ChannelStatus channel_status_from_string(std::string_view text);      // trims, case-insensitive

// A channel: `ip devtype devid subdevid chlid`. inquire_resp carries only "devtype-devid-subdevid-chlid-auxid".
struct ChannelAddress {
    std::string ip;
    int devtype = 0, devid = 0, subdevid = 0, chlid = 0;

    bool operator==(const ChannelAddress&) const = default;
    // Same channel, ignoring ip (inquire_resp has none).
    [[nodiscard]] bool same_channel(const ChannelAddress& other) const;
    // "devtype-devid-subdevid-chlid" (the `dev` form without auxid), for messages and look-ups.
    [[nodiscard]] std::string key() const;
};

// ---------------------------------------------------------------------------------------------------------
// Requests (client -> tester)

// Login, seen in BTS 8 clients (not in every API version): <username>, <password>, <type>.
struct ConnectRequest {
    std::string username = "admin", password = "neware", type = "bfgs";
};
struct GetDevInfoRequest {};
// getchlstatus, stop, pause, continue, light, clearflag:
//   <list count><TAG ip devtype devid subdevid chlid>true</TAG>...</list>   (light: text false = lamp off)
// inquiredf: <list count><chl devtype devid subdevid chlid testid="0"/>...</list>
struct ChannelListRequest {
    Command command = Command::getchlstatus;
    std::vector<ChannelAddress> channels;
    bool on = true;  // element text true|false (light: lamp on/off)
};
// downloadlog: <download devtype devid subdevid chlid testid/>; downloadStepLayer:
// <downloadStepLayer devtype devid subdevid chlid [testid]/>. testid 0 (or absent): the channel's latest test.
struct TestRequest {
    Command command = Command::downloadlog;
    ChannelAddress channel;
    std::int64_t testid = 0;
};
struct InquireRequest {
    std::vector<ChannelAddress> channels;
    bool aux = false;     // aux="0|1": auxiliary channels in the answer
    bool barcode = true;  // barcode="0|1"
};
struct StartEntry {
    ChannelAddress channel;
    std::string step_file_path;  // on the BTS PC
    std::string barcode;
    std::string remark;          // optional
};
struct BackupOptions {
    std::string backupdir;
    int filetype = 0, filenametype = 0;
};
struct StartRequest {
    std::vector<StartEntry> entries;
    std::optional<BackupOptions> backup;
};
// Recorded data of one channel's test (the tester records every point itself, at its own record interval,
// whatever the client's polling): <download ip devtype devid subdevid chlid auxid testid startpos count/>.
// Rows are numbered from seqid 1 per test; `startpos` is the first seqid wanted. testid 0 asks for the
// channel's latest test (the answer names it). startpos="0" count="0" is how clients ask for the test id only.
inline constexpr int kMaxDownloadCount = 1000;
struct DownloadRequest {
    ChannelAddress channel;
    int auxid = 0;
    std::int64_t testid = 0;
    std::int64_t startpos = 1;      // 0 only with count 0
    int count = kMaxDownloadCount;  // 0..kMaxDownloadCount
};
using Request = std::variant<ConnectRequest, GetDevInfoRequest, ChannelListRequest, InquireRequest, StartRequest,
                             DownloadRequest, TestRequest>;

// ---------------------------------------------------------------------------------------------------------
// Responses (tester -> client): <cmd>NAME_resp</cmd>

struct ConnectResponse {
    bool ok = false;
    std::string result;  // "ok" or what the tester said
};
struct ServerEndpoint {
    std::string ip;
    int port = 0;
};
struct DeviceChannel {
    ChannelAddress channel;  // from `Channelid`
    bool online = false;     // element text true|false
};
struct GetDevInfoResponse {
    std::vector<ServerEndpoint> servers;
    std::vector<DeviceChannel> channels;
};
struct StatusEntry {
    ChannelAddress channel;
    ChannelStatus status = ChannelStatus::unknown;
    std::string status_text;     // as sent (trimmed)
    bool reserve_pause = false;  // reservepause="0|1"
};
struct ChannelStatusResponse {
    std::vector<StatusEntry> channels;
};
// One channel's live values (inquire_resp/list/inquire). Numbers the tester omits or sends as "--" are NaN
// (doubles) or 0 (integers).
struct InquireEntry {
    ChannelAddress channel;  // from `dev` (ip empty)
    int auxid = 0;
    int cycle_id = 0;
    int step_id = 0;
    std::string step_type;   // "rest", "cc", "dc", "cv", ... ("--" when idle), see step_type_code()
    ChannelStatus workstatus = ChannelStatus::unknown;
    std::string workstatus_text;
    std::string barcode;
    double current_a = 0.0;         // + = charge
    double voltage_v = 0.0;
    double capacity_ah = 0.0;       // of the current step
    double energy_wh = 0.0;         // of the current step
    double total_time_s = 0.0;      // since the test started
    double relative_time_s = 0.0;   // since the step started
    bool open = false;              // open_or_close="1"
    int log_code = 0;
};
struct InquireResponse {
    std::vector<InquireEntry> channels;
};
struct ChannelResult {
    ChannelAddress channel;
    bool ok = false;
    std::string text;  // "ok", "false", or what the tester said
};
// start, stop, pause, continue, light, clearflag:
//   <list count><TAG ip devtype devid subdevid chlid>ok|false</TAG>...</list>
struct ChannelCommandResponse {
    Command command = Command::start;
    std::vector<ChannelResult> channels;
};
// One recorded point (download_resp/list/data). On the wire testtime is in milliseconds (the published
// example); here it is seconds.
struct DownloadRecord {
    std::int64_t seqid = 0;
    int step_id = 0, cycle_id = 0;
    std::string step_type;     // "rest", "cc", "dc", "cv", ... as in inquire_resp
    double test_time_s = 0.0;  // since the test started
    std::string atime;         // absolute time as the tester writes it (may be empty)
    double voltage_v = 0.0, current_a = 0.0;  // + = charge
    double capacity_ah = 0.0, energy_wh = 0.0;  // of the step
};
// <cmd>donwload_resp</cmd> <download devtype devid subdevid chlid testid startpos count auxid/> then
// <list count><data .../>...</list>. Fewer rows than asked for means the client has everything recorded so far.
struct DownloadResponse {
    ChannelAddress channel;  // the real server sends no ip here
    std::int64_t testid = 0;
    std::int64_t startpos = 1;
    int count = kMaxDownloadCount;  // as asked
    int auxid = 0;
    std::vector<DownloadRecord> records;
};
// inquiredf_resp: <list count><chl devtype devid subdevid chlid testid count>true|false</chl>...</list>:
// the channel's latest test and how many rows it recorded (the element text: whether the test is finished,
// as the captures show idle channels true and working ones false).
struct TestInfo {
    ChannelAddress channel;
    std::int64_t testid = 0;
    std::int64_t count = 0;
    bool flag = false;
};
struct InquireDfResponse {
    std::vector<TestInfo> channels;
};
// donwloadlog_resp: <download devtype devid subdevid chlid testid log_lever/> then <data seqid log_code atime/>.
struct LogEntry {
    std::int64_t seqid = 0;
    int log_code = 0;
    std::string atime;
};
struct DownloadLogResponse {
    ChannelAddress channel;
    std::int64_t testid = 0;
    int log_level = 0;  // the wire's `log_lever` (sic)
    std::vector<LogEntry> entries;
};
// downloadStepLayer_resp: one <data> per executed step (the tester's step table).
struct StepLayerEntry {
    std::int64_t start_seqid = 0, end_seqid = 0;
    int step_index = 0, step_id = 0, cycle_id = 0;
    std::string step_type;         // cc, dc, cv, rest
    double step_time_s = 0.0;      // wire: ms
    std::string end_atime;
    double start_voltage_v = 0.0, end_voltage_v = 0.0, start_current_a = 0.0, end_current_a = 0.0;
    double capacity_ah = 0.0, energy_wh = 0.0, dcir_ohm = 0.0;
};
struct StepLayerResponse {
    ChannelAddress channel;
    std::int64_t testid = 0;
    std::vector<StepLayerEntry> steps;
};
// What the simulated tester answers to a command it does not know (or a request it cannot read), instead of
// silence: <cmd>NAME_resp</cmd><result>false</result><error>why</error>. `command` is the request's <cmd> text
// ("unknown" when unreadable). parse_response returns it for any frame with an <error> element and an
// unknown command.
struct ErrorResponse {
    std::string command;
    std::string message;
};
using Response = std::variant<ConnectResponse, GetDevInfoResponse, ChannelStatusResponse, InquireResponse,
                              ChannelCommandResponse, DownloadResponse, InquireDfResponse, DownloadLogResponse,
                              StepLayerResponse, ErrorResponse>;

[[nodiscard]] Command request_command(const Request& request);
// ErrorResponse: its command when known, else Command::connect (check holds_alternative<ErrorResponse> first).
[[nodiscard]] Command response_command(const Response& response);

// ---------------------------------------------------------------------------------------------------------
// Encoding: complete frames, terminator included. Requests in the compact one-line form public clients send;
// responses in the tester's pretty-printed CRLF form. Throws ProtocolError for a request that cannot be
// expressed (e.g. a ChannelListRequest whose command is not a channel-list command).
std::string encode_request(const Request& request);
std::string encode_response(const Response& response);

// Parsing: a frame as FrameSplitter yields it (a trailing terminator is tolerated). Throws ProtocolError.
Request parse_request(std::string_view frame);
Response parse_response(std::string_view frame);

// The <cmd> text of a frame ("inquire_resp"), or ProtocolError. For routing frames that parse_* rejects.
std::string frame_command(std::string_view frame);

// The normalisation parse_* applies before the XML parser (vendor quirks, nesting bound), for other XML
// from the tester's world (step files). Throws ProtocolError.
std::string normalize_vendor_xml(std::string_view xml);

// Number formatting of the encoder: fixed with at most max_decimals, trailing zeros dropped, never "-0".
std::string format_number(double value, int max_decimals);

}  // namespace cellbench::protocol::neware
