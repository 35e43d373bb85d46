#include "cellbench/protocol/neware_bts.hpp"

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <limits>
#include <type_traits>

#include <boost/property_tree/ptree.hpp>

#include "neware_xml.hpp"

namespace cellbench::protocol::neware {
namespace {

namespace pt = boost::property_tree;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// ASCII only (no locale look-up: names and keywords of the protocol are ASCII).
constexpr char ascii_lower(char c) { return c >= 'A' && c <= 'Z' ? static_cast<char>(c - 'A' + 'a') : c; }

bool iequals(std::string_view a, std::string_view b) {
    if (a.size() != b.size()) return false;
    for (std::size_t i = 0; i < a.size(); ++i)
        if (ascii_lower(a[i]) != ascii_lower(b[i])) return false;
    return true;
}

std::string_view trim(std::string_view s) {
    auto is_space = [](char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\n'; };
    while (!s.empty() && is_space(s.front())) s.remove_prefix(1);
    while (!s.empty() && is_space(s.back())) s.remove_suffix(1);
    return s;
}

// A value quoted in an error message: bounded and printable, so garbage never floods a log.
std::string shown(std::string_view value) {
    std::string out = "'";
    const std::size_t limit = 40;
    for (std::size_t i = 0; i < value.size() && i < limit; ++i) {
        const auto c = static_cast<unsigned char>(value[i]);
        if (c >= 0x20 && c < 0x7f) {
            out += static_cast<char>(c);
        } else {
            char hex[8];
            std::snprintf(hex, sizeof hex, "\\x%02x", c);
            out += hex;
        }
    }
    if (value.size() > limit) out += "...";
    return out + "'";
}

// ---------------------------------------------------------------------------------------------------------
// Normalisation of vendor quirks before the XML parser sees the text.

bool starts_with_at(std::string_view s, std::size_t i, std::string_view prefix) {
    return s.size() - i >= prefix.size() && s.compare(i, prefix.size(), prefix) == 0;
}

// Typographic double quotes (U+201C, U+201D in UTF-8) as written in vendor examples.
bool typographic_quote_at(std::string_view s, std::size_t i) {
    return s[i] == '\xE2' && (starts_with_at(s, i, "\xE2\x80\x9C") || starts_with_at(s, i, "\xE2\x80\x9D"));
}

std::string normalise(std::string_view in) {
    if (in.size() >= kFrameTerminator.size() && in.substr(in.size() - kFrameTerminator.size()) == kFrameTerminator)
        in.remove_suffix(kFrameTerminator.size());
    if (starts_with_at(in, 0, "\xEF\xBB\xBF")) in.remove_prefix(3);  // UTF-8 BOM
    in = trim(in);
    if (in.empty()) throw ProtocolError("empty frame: expected an XML document");
    if (in.find('\0') != std::string_view::npos) throw ProtocolError("NUL byte in frame");

    std::string out;
    out.reserve(in.size());
    int depth = 0;
    std::size_t i = 0;
    const std::size_t n = in.size();
    while (i < n) {
        if (in[i] != '<') {  // text up to the next markup, in one piece
            const std::size_t next = std::min(in.find('<', i), n);
            out.append(in.substr(i, next - i));
            i = next;
            continue;
        }
        // Markup that may contain '>' or quotes: copy verbatim up to its own end.
        auto copy_through = [&](std::string_view end_marker, const char* what) {
            const std::size_t end = in.find(end_marker, i);
            if (end == std::string_view::npos) throw ProtocolError(std::string("unterminated ") + what);
            out.append(in.substr(i, end + end_marker.size() - i));
            i = end + end_marker.size();
        };
        if (starts_with_at(in, i, "<!--")) {
            copy_through("-->", "comment");
            continue;
        }
        if (starts_with_at(in, i, "<![CDATA[")) {
            copy_through("]]>", "CDATA section");
            continue;
        }
        if (starts_with_at(in, i, "<?")) {
            copy_through("?>", "processing instruction");
            continue;
        }
        if (starts_with_at(in, i, "<!")) throw ProtocolError("DOCTYPE/declarations are not accepted in a BTS frame");

        // An element tag: typographic quotes become '"'; '>' inside a quoted value does not end the tag.
        const bool closing = starts_with_at(in, i, "</");
        std::size_t j = i + 1;
        char quote = 0;
        out += '<';
        bool ended = false;
        while (j < n) {
            char c = in[j];
            std::size_t width = 1;
            if (typographic_quote_at(in, j)) {
                c = '"';
                width = 3;
            }
            if (quote != 0) {
                if (c == quote) quote = 0;
            } else if (c == '"' || c == '\'') {
                quote = c;
            } else if (c == '>') {
                ended = true;
                break;
            } else if (c == '<') {
                throw ProtocolError("'<' inside a tag");
            }
            out += c;
            j += width;
        }
        if (!ended) throw ProtocolError("unterminated tag");
        const bool self_closing = out.back() == '/';
        out += '>';
        i = j + 1;
        if (closing) {
            --depth;
        } else if (!self_closing && ++depth > kMaxXmlDepth) {
            throw ProtocolError("elements nested deeper than " + std::to_string(kMaxXmlDepth));
        }
    }
    return out;
}

// The <bts> element of a frame and its <cmd> text.
struct Document {
    pt::ptree tree;  // whole document
    const pt::ptree* bts = nullptr;
    std::string cmd;
};

Document parse_document(std::string_view frame) {
    Document doc;
    doc.tree = xml::read_document(frame, "");
    for (const auto& [key, child] : doc.tree) {
        if (key == "<xmlcomment>") continue;
        if (key != "bts" || doc.bts != nullptr)
            throw ProtocolError("expected one <bts> root element, found <" + shown(key) + ">");
        doc.bts = &child;
    }
    if (doc.bts == nullptr) throw ProtocolError("expected one <bts> root element");
    const auto cmd = doc.bts->find("cmd");
    if (cmd == doc.bts->not_found()) throw ProtocolError("<bts> without <cmd>");
    doc.cmd = std::string(trim(cmd->second.data()));
    if (doc.cmd.empty()) throw ProtocolError("empty <cmd>");
    return doc;
}

// ---------------------------------------------------------------------------------------------------------
// Attribute and element access (case-insensitive names: the vendor writes "Channelid" and "chlid").

std::optional<std::string_view> find_attr(const pt::ptree& node, std::string_view name) {
    const auto attrs = node.find("<xmlattr>");
    if (attrs == node.not_found()) return std::nullopt;
    for (const auto& [key, value] : attrs->second)
        if (iequals(key, name)) return std::string_view(value.data());
    return std::nullopt;
}

const pt::ptree* find_child(const pt::ptree& node, std::string_view name) {
    for (const auto& [key, child] : node)
        if (iequals(key, name)) return &child;
    return nullptr;
}

template <typename Int>
std::optional<Int> to_int(std::string_view text) {
    text = trim(text);
    if (!text.empty() && text.front() == '+') text.remove_prefix(1);
    Int value{};
    const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (ec != std::errc() || ptr != text.data() + text.size() || text.empty()) return std::nullopt;
    return value;
}

std::optional<double> to_double(std::string_view text) {
    text = trim(text);
    if (!text.empty() && text.front() == '+') text.remove_prefix(1);
    double value = 0.0;
    const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (ec != std::errc() || ptr != text.data() + text.size() || text.empty() || !std::isfinite(value))
        return std::nullopt;
    return value;
}

int required_int(const pt::ptree& node, std::string_view name, const std::string& where) {
    const auto text = find_attr(node, name);
    if (!text) throw ProtocolError(where + ": attribute '" + std::string(name) + "' missing");
    const auto value = to_int<int>(*text);
    if (!value || *value < 0)
        throw ProtocolError(where + ": attribute '" + std::string(name) + "': expected a non-negative integer, got " +
                            shown(*text));
    return *value;
}

int optional_int(const pt::ptree& node, std::string_view name, const std::string& where) {
    const auto text = find_attr(node, name);
    if (!text || trim(*text).empty() || trim(*text) == "--") return 0;
    const auto value = to_int<int>(*text);
    if (!value)
        throw ProtocolError(where + ": attribute '" + std::string(name) + "': expected an integer, got " +
                            shown(*text));
    return *value;
}

double optional_double(const pt::ptree& node, std::string_view name, const std::string& where) {
    const auto text = find_attr(node, name);
    if (!text || trim(*text).empty() || trim(*text) == "--") return kNaN;
    const auto value = to_double(*text);
    if (!value)
        throw ProtocolError(where + ": attribute '" + std::string(name) + "': expected a number, got " +
                            shown(*text));
    return *value;
}

std::int64_t optional_int64(const pt::ptree& node, std::string_view name, const std::string& where,
                            std::int64_t fallback) {
    const auto text = find_attr(node, name);
    if (!text || trim(*text).empty() || trim(*text) == "--") return fallback;
    const auto value = to_int<std::int64_t>(*text);
    if (!value || *value < 0)
        throw ProtocolError(where + ": attribute '" + std::string(name) + "': expected a non-negative integer, got " +
                            shown(*text));
    return *value;
}

std::string optional_string(const pt::ptree& node, std::string_view name) {
    const auto text = find_attr(node, name);
    return text ? std::string(trim(*text)) : std::string();
}

bool flag_attr(const pt::ptree& node, std::string_view name, bool fallback, const std::string& where) {
    const auto text = find_attr(node, name);
    if (!text) return fallback;
    const auto t = trim(*text);
    if (t == "1" || iequals(t, "true")) return true;
    if (t == "0" || iequals(t, "false")) return false;
    throw ProtocolError(where + ": attribute '" + std::string(name) + "': expected 0 or 1, got " + shown(t));
}

ChannelAddress channel_attrs(const pt::ptree& node, const std::string& where) {
    ChannelAddress a;
    a.ip = optional_string(node, "ip");
    a.devtype = required_int(node, "devtype", where);
    a.devid = required_int(node, "devid", where);
    a.subdevid = required_int(node, "subdevid", where);
    // getdevinfo_resp spells it Channelid; the rest chlid.
    a.chlid = find_attr(node, "chlid") ? required_int(node, "chlid", where) : required_int(node, "Channelid", where);
    return a;
}

// The <list> of a frame and its entries with the given tag (other children are ignored: e.g. <backup>).
struct ListEntries {
    std::vector<const pt::ptree*> entries;
    const pt::ptree* list = nullptr;
};

ListEntries list_entries(const Document& doc, std::string_view tag, bool required = true) {
    ListEntries out;
    out.list = find_child(*doc.bts, "list");
    if (out.list == nullptr) {
        if (required) throw ProtocolError(doc.cmd + ": <list> missing");
        return out;
    }
    for (const auto& [key, child] : *out.list)
        if (iequals(key, tag)) out.entries.push_back(&child);
    return out;
}

std::string entry_where(const Document& doc, std::string_view tag, std::size_t index) {
    return doc.cmd + ": <" + std::string(tag) + "> #" + std::to_string(index + 1);
}

// ---------------------------------------------------------------------------------------------------------
// Encoding helpers

void append_escaped(std::string& out, std::string_view text) {
    xml::append_escaped(out, text, xml::Escape::apostrophe);
}

void attr(std::string& out, std::string_view name, std::string_view value) {
    out += ' ';
    out += name;
    out += "=\"";
    append_escaped(out, value);
    out += '"';
}
void attr(std::string& out, std::string_view name, int value) { attr(out, name, std::to_string(value)); }

// A channel's address without the ip: what public clients send and what the tester's test-level answers carry.
void device_attrs_out(std::string& out, const ChannelAddress& a, std::string_view chlid_name = "chlid") {
    attr(out, "devtype", a.devtype);
    attr(out, "devid", a.devid);
    attr(out, "subdevid", a.subdevid);
    attr(out, chlid_name, a.chlid);
}

void channel_attrs_out(std::string& out, const ChannelAddress& a, std::string_view chlid_name = "chlid") {
    attr(out, "ip", a.ip);
    device_attrs_out(out, a, chlid_name);
}

constexpr std::string_view kRequestProlog = R"(<?xml version="1.0" encoding="UTF-8" ?><bts version="1.0">)";
constexpr std::string_view kResponseProlog = "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\r\n<bts version=\"1.0\">\r\n";

std::string_view list_tag(Command c) {
    switch (c) {
        case Command::getchlstatus: return "status";
        case Command::inquire: return "inquire";
        case Command::start: return "start";
        case Command::stop: return "stop";
        case Command::pause: return "pause";
        case Command::continue_: return "continue";
        case Command::light: return "light";
        case Command::clearflag: return "clearflag";
        case Command::inquiredf: return "chl";
        default: return "";
    }
}

bool is_channel_list_command(Command c) {
    return c == Command::getchlstatus || c == Command::stop || c == Command::pause || c == Command::continue_ ||
           c == Command::light || c == Command::clearflag || c == Command::inquiredf;
}
bool is_channel_result_command(Command c) {
    return c == Command::start || c == Command::stop || c == Command::pause || c == Command::continue_ ||
           c == Command::light || c == Command::clearflag;
}

Command command_or_throw(std::string_view name) {
    const auto c = command_from_name(name);
    if (!c) throw ProtocolError("unknown command " + shown(name));
    return *c;
}

}  // namespace

// -------------------------------------------------------------------------------------------------------------
// FrameSplitter

FrameSplitter::FrameSplitter(std::size_t max_frame_bytes) : max_frame_bytes_(std::max<std::size_t>(max_frame_bytes, 64)) {}

void FrameSplitter::feed(std::string_view bytes) {
    // Compact before growing: consumed bytes at the front are dead weight. Once everything is consumed, a
    // buffer a large frame or a burst of garbage grew (up to max_frame_bytes) is given back rather than kept for
    // the life of the connection.
    if (head_ > 0 && head_ == buffer_.size() && buffer_.capacity() > kKeptCapacity) {
        std::string().swap(buffer_);
        head_ = 0;
    } else if (head_ > 0 && (head_ >= buffer_.size() / 2 || head_ > (1u << 16))) {
        buffer_.erase(0, head_);
        head_ = 0;
    }
    buffer_.append(bytes.data(), bytes.size());
}

void FrameSplitter::clear() {
    std::string().swap(buffer_);
    head_ = 0;
    scanned_ = 0;
    skipping_ = false;
}

// A frame ends at "</bts>", optional whitespace, "#\r\n". The scan looks for "#\r\n" (the last kMarker bytes
// of every terminator form) and then checks what precedes it; a "#\r\n" after anything else (junk, a stray
// terminator) ends a run of garbage.
std::optional<std::string> FrameSplitter::next() {
    constexpr std::string_view kMarker = "#\r\n";
    constexpr std::string_view kEnd = "</bts>";
    for (;;) {
        const std::string_view pending(buffer_.data() + head_, buffer_.size() - head_);
        const std::size_t pos = pending.find(kMarker, scanned_);
        if (pos == std::string_view::npos) {
            // Keep the last kMarker-1 bytes: they may be the start of a terminator.
            const std::size_t keep = std::min(pending.size(), kMarker.size() - 1);
            if (skipping_) {
                garbage_bytes_ += pending.size() - keep;
                head_ += pending.size() - keep;
                scanned_ = 0;
                return std::nullopt;
            }
            scanned_ = pending.size() - keep;
            if (pending.size() > max_frame_bytes_ + kFrameTerminator.size()) {
                garbage_bytes_ += pending.size() - keep;
                head_ += pending.size() - keep;
                scanned_ = 0;
                skipping_ = true;
                throw ProtocolError("frame exceeds " + std::to_string(max_frame_bytes_) +
                                    " bytes without a terminator; discarding it");
            }
            return std::nullopt;
        }
        std::string_view segment = pending.substr(0, pos);
        head_ += pos + kMarker.size();
        scanned_ = 0;
        const std::size_t consumed = pos + kMarker.size();
        if (skipping_) {  // the tail of an oversized frame
            garbage_bytes_ += consumed;
            skipping_ = false;
            continue;
        }
        while (!segment.empty() && (segment.back() == '\n' || segment.back() == '\r' || segment.back() == ' ' ||
                                    segment.back() == '\t'))
            segment.remove_suffix(1);
        if (segment.size() < kEnd.size() || !iequals(segment.substr(segment.size() - kEnd.size()), kEnd)) {
            if (!segment.empty()) garbage_bytes_ += consumed;  // junk (a lone stray terminator is not counted)
            continue;
        }
        // The frame starts at the last "<?xml" (or "<bts" without a declaration): whatever precedes it is
        // garbage, including a truncated frame that was never terminated.
        std::size_t start = segment.rfind("<?xml");
        if (start == std::string_view::npos) start = segment.rfind("<bts");
        if (start == std::string_view::npos) {
            garbage_bytes_ += consumed;
            continue;
        }
        const std::string_view frame = segment.substr(start);
        garbage_bytes_ += start;
        if (frame.size() > max_frame_bytes_) {
            garbage_bytes_ += frame.size();
            throw ProtocolError("frame of " + std::to_string(frame.size()) + " bytes exceeds the limit of " +
                                std::to_string(max_frame_bytes_) + " bytes; discarded");
        }
        return std::string(frame);
    }
}

// -------------------------------------------------------------------------------------------------------------
// Vocabulary

std::string_view command_name(Command command) {
    switch (command) {
        case Command::connect: return "connect";
        case Command::getdevinfo: return "getdevinfo";
        case Command::getchlstatus: return "getchlstatus";
        case Command::inquire: return "inquire";
        case Command::start: return "start";
        case Command::stop: return "stop";
        case Command::pause: return "pause";
        case Command::continue_: return "continue";
        case Command::download: return "download";
        case Command::inquiredf: return "inquiredf";
        case Command::downloadlog: return "downloadlog";
        case Command::downloadStepLayer: return "downloadStepLayer";
        case Command::light: return "light";
        case Command::clearflag: return "clearflag";
    }
    return "";
}

std::string response_name(Command command) {
    if (command == Command::download) return "donwload_resp";  // sic, as the real server spells it
    if (command == Command::downloadlog) return "donwloadlog_resp";
    return std::string(command_name(command)) + "_resp";
}

std::optional<Command> response_command_from_name(std::string_view cmd) {
    if (cmd.size() <= 5 || !iequals(cmd.substr(cmd.size() - 5), "_resp")) return std::nullopt;
    const auto name = cmd.substr(0, cmd.size() - 5);
    if (iequals(name, "donwload")) return Command::download;
    if (iequals(name, "donwloadlog")) return Command::downloadlog;
    return command_from_name(name);
}

std::optional<Command> command_from_name(std::string_view name) {
    static constexpr std::array all{Command::connect,   Command::getdevinfo,  Command::getchlstatus,
                                    Command::inquire,   Command::start,       Command::stop,
                                    Command::pause,     Command::continue_,   Command::download,
                                    Command::inquiredf, Command::downloadlog, Command::downloadStepLayer,
                                    Command::light,     Command::clearflag};
    for (const auto c : all)
        if (iequals(command_name(c), name)) return c;
    return std::nullopt;
}

std::string_view to_string(ChannelStatus status) {
    switch (status) {
        case ChannelStatus::working: return "working";
        case ChannelStatus::stop: return "stop";
        case ChannelStatus::finish: return "finish";
        case ChannelStatus::protect: return "protect";
        case ChannelStatus::pause: return "pause";
        case ChannelStatus::unknown: return "unknown";
    }
    return "unknown";
}

ChannelStatus channel_status_from_string(std::string_view text) {
    text = trim(text);
    for (const auto s : {ChannelStatus::working, ChannelStatus::stop, ChannelStatus::finish, ChannelStatus::protect,
                         ChannelStatus::pause})
        if (iequals(to_string(s), text)) return s;
    return ChannelStatus::unknown;
}

bool ChannelAddress::same_channel(const ChannelAddress& o) const {
    return devtype == o.devtype && devid == o.devid && subdevid == o.subdevid && chlid == o.chlid;
}

std::string ChannelAddress::key() const {
    return std::to_string(devtype) + "-" + std::to_string(devid) + "-" + std::to_string(subdevid) + "-" +
           std::to_string(chlid);
}

Command request_command(const Request& request) {
    return std::visit(
        [](const auto& r) -> Command {
            using T = std::decay_t<decltype(r)>;
            if constexpr (std::is_same_v<T, ConnectRequest>) return Command::connect;
            else if constexpr (std::is_same_v<T, GetDevInfoRequest>) return Command::getdevinfo;
            else if constexpr (std::is_same_v<T, ChannelListRequest>) return r.command;
            else if constexpr (std::is_same_v<T, InquireRequest>) return Command::inquire;
            else if constexpr (std::is_same_v<T, DownloadRequest>) return Command::download;
            else if constexpr (std::is_same_v<T, TestRequest>) return r.command;
            else return Command::start;
        },
        request);
}

Command response_command(const Response& response) {
    return std::visit(
        [](const auto& r) -> Command {
            using T = std::decay_t<decltype(r)>;
            if constexpr (std::is_same_v<T, ConnectResponse>) return Command::connect;
            else if constexpr (std::is_same_v<T, GetDevInfoResponse>) return Command::getdevinfo;
            else if constexpr (std::is_same_v<T, ChannelStatusResponse>) return Command::getchlstatus;
            else if constexpr (std::is_same_v<T, InquireResponse>) return Command::inquire;
            else if constexpr (std::is_same_v<T, DownloadResponse>) return Command::download;
            else if constexpr (std::is_same_v<T, InquireDfResponse>) return Command::inquiredf;
            else if constexpr (std::is_same_v<T, DownloadLogResponse>) return Command::downloadlog;
            else if constexpr (std::is_same_v<T, StepLayerResponse>) return Command::downloadStepLayer;
            else if constexpr (std::is_same_v<T, ErrorResponse>)
                return command_from_name(r.command).value_or(Command::connect);
            else return r.command;
        },
        response);
}

std::string format_number(double value, int max_decimals) {
    if (!std::isfinite(value)) return "--";
    max_decimals = std::clamp(max_decimals, 0, 12);
    char buf[64];
    const int len = std::snprintf(buf, sizeof buf, "%.*f", max_decimals, value);
    if (len <= 0 || len >= static_cast<int>(sizeof buf)) {  // |value| beyond 1e50: plain exponent form
        std::snprintf(buf, sizeof buf, "%.6g", value);
        return buf;
    }
    std::string s(buf, static_cast<std::size_t>(len));
    if (s.find('.') != std::string::npos) {
        while (s.back() == '0') s.pop_back();
        if (s.back() == '.') s.pop_back();
    }
    if (s == "-0") s = "0";
    return s;
}

// -------------------------------------------------------------------------------------------------------------
// Encoding

std::string encode_request(const Request& request) {
    std::string out(kRequestProlog);
    const Command command = request_command(request);
    out += "<cmd>";
    out += command_name(command);
    out += "</cmd>";
    std::visit(
        [&](const auto& r) {
            using T = std::decay_t<decltype(r)>;
            if constexpr (std::is_same_v<T, ConnectRequest>) {
                out += "<username>";
                append_escaped(out, r.username);
                out += "</username><password>";
                append_escaped(out, r.password);
                out += "</password><type>";
                append_escaped(out, r.type);
                out += "</type>";
            } else if constexpr (std::is_same_v<T, GetDevInfoRequest>) {
            } else if constexpr (std::is_same_v<T, ChannelListRequest>) {
                if (!is_channel_list_command(r.command))
                    throw ProtocolError("a channel-list request cannot carry command " +
                                        std::string(command_name(r.command)));
                const auto tag = list_tag(r.command);
                out += "<list count=\"" + std::to_string(r.channels.size()) + "\">";
                for (const auto& c : r.channels) {
                    out += '<';
                    out += tag;
                    if (r.command == Command::inquiredf) {  // public clients: no ip, testid 0 = latest test
                        device_attrs_out(out, c);
                        out += " testid=\"0\" />";
                        continue;
                    }
                    channel_attrs_out(out, c);
                    out += r.on ? ">true</" : ">false</";
                    out += tag;
                    out += '>';
                }
                out += "</list>";
            } else if constexpr (std::is_same_v<T, InquireRequest>) {
                out += "<list count=\"" + std::to_string(r.channels.size()) + "\">";
                for (const auto& c : r.channels) {
                    out += "<inquire";
                    channel_attrs_out(out, c);
                    attr(out, "aux", r.aux ? 1 : 0);
                    attr(out, "barcode", r.barcode ? 1 : 0);
                    out += ">true</inquire>";
                }
                out += "</list>";
            } else if constexpr (std::is_same_v<T, TestRequest>) {
                if (r.command != Command::downloadlog && r.command != Command::downloadStepLayer)
                    throw ProtocolError("a test request cannot carry command " + std::string(command_name(r.command)));
                out += r.command == Command::downloadlog ? "<download" : "<downloadStepLayer";
                device_attrs_out(out, r.channel);
                attr(out, "testid", std::to_string(r.testid));
                out += " />";
            } else if constexpr (std::is_same_v<T, DownloadRequest>) {
                if (r.count < 0 || r.count > kMaxDownloadCount)
                    throw ProtocolError("download: count must be 0.." + std::to_string(kMaxDownloadCount));
                out += "<download";
                channel_attrs_out(out, r.channel);
                attr(out, "auxid", r.auxid);
                attr(out, "testid", std::to_string(r.testid));
                attr(out, "startpos", std::to_string(r.startpos));
                attr(out, "count", r.count);
                out += "/>";
            } else {  // StartRequest
                out += "<list count=\"" + std::to_string(r.entries.size()) + "\">";
                for (const auto& e : r.entries) {
                    out += "<start";
                    channel_attrs_out(out, e.channel);
                    attr(out, "barcode", e.barcode);
                    if (!e.remark.empty()) attr(out, "remark", e.remark);
                    out += '>';
                    append_escaped(out, e.step_file_path);
                    out += "</start>";
                }
                // Public BTS 8 clients put <backup> inside the list; the parser accepts it in either place.
                if (r.backup) {
                    out += "<backup";
                    attr(out, "backupdir", r.backup->backupdir);
                    attr(out, "filetype", r.backup->filetype);
                    attr(out, "filenametype", r.backup->filenametype);
                    out += "/>";
                }
                out += "</list>";
            }
        },
        request);
    out += "</bts>";
    out += kFrameTerminator;
    return out;
}

std::string encode_response(const Response& response) {
    std::string out(kResponseProlog);
    const Command command = response_command(response);
    out += "  <cmd>";
    if (const auto* e = std::get_if<ErrorResponse>(&response)) {
        append_escaped(out, (e->command.empty() ? std::string("unknown") : e->command.substr(0, 64)) + "_resp");
    } else {
        out += response_name(command);
    }
    out += "</cmd>\r\n";
    std::visit(
        [&](const auto& r) {
            using T = std::decay_t<decltype(r)>;
            if constexpr (std::is_same_v<T, ConnectResponse>) {
                out += "  <result>";
                append_escaped(out, r.result.empty() ? (r.ok ? "ok" : "false") : r.result);
                out += "</result>\r\n";
            } else if constexpr (std::is_same_v<T, GetDevInfoResponse>) {
                out += "  <serverip count=\"" + std::to_string(r.servers.size()) + "\">\r\n";
                for (const auto& s : r.servers) {
                    out += "    <server";
                    attr(out, "ip", s.ip);
                    attr(out, "port", s.port);
                    out += " />\r\n";
                }
                out += "  </serverip>\r\n  <middle count=\"" + std::to_string(r.channels.size()) + "\">\r\n";
                for (const auto& c : r.channels) {
                    out += "    <channel";
                    channel_attrs_out(out, c.channel, "Channelid");
                    out += c.online ? ">true</channel>\r\n" : ">false</channel>\r\n";
                }
                out += "  </middle>\r\n";
            } else if constexpr (std::is_same_v<T, ChannelStatusResponse>) {
                out += "  <list count=\"" + std::to_string(r.channels.size()) + "\">\r\n";
                for (const auto& s : r.channels) {
                    out += "    <status";
                    channel_attrs_out(out, s.channel);
                    attr(out, "reservepause", s.reserve_pause ? 1 : 0);
                    out += '>';
                    append_escaped(out, s.status == ChannelStatus::unknown && !s.status_text.empty()
                                            ? std::string_view(s.status_text)
                                            : to_string(s.status));
                    out += "</status>\r\n";
                }
                out += "  </list>\r\n";
            } else if constexpr (std::is_same_v<T, InquireResponse>) {
                out += "  <list count=\"" + std::to_string(r.channels.size()) + "\">\r\n";
                for (const auto& e : r.channels) {
                    out += "    <inquire";
                    attr(out, "dev", e.channel.key() + "-" + std::to_string(e.auxid));
                    attr(out, "cycle_id", e.cycle_id);
                    if (e.step_id > 0) attr(out, "step_id", e.step_id);  // idle channels omit it (field examples)
                    attr(out, "step_type", e.step_type.empty() ? std::string("--") : e.step_type);
                    attr(out, "workstatus",
                         e.workstatus == ChannelStatus::unknown && !e.workstatus_text.empty()
                             ? std::string(e.workstatus_text)
                             : std::string(to_string(e.workstatus)));
                    attr(out, "barcode", e.barcode);
                    attr(out, "current", format_number(e.current_a, 4));
                    attr(out, "voltage", format_number(e.voltage_v, 4));
                    attr(out, "capacity", format_number(e.capacity_ah, 6));
                    attr(out, "energy", format_number(e.energy_wh, 6));
                    attr(out, "totaltime", format_number(e.total_time_s, 3));
                    attr(out, "relativetime", format_number(e.relative_time_s, 3));
                    attr(out, "open_or_close", e.open ? 1 : 0);
                    attr(out, "log_code", e.log_code);
                    out += " />\r\n";
                }
                out += "  </list>\r\n";
            } else if constexpr (std::is_same_v<T, DownloadResponse>) {
                out += "  <download";
                device_attrs_out(out, r.channel);
                attr(out, "testid", std::to_string(r.testid));
                attr(out, "startpos", std::to_string(r.startpos));
                attr(out, "count", r.count);
                attr(out, "auxid", r.auxid);
                out += " />\r\n  <list count=\"" + std::to_string(r.records.size()) + "\">\r\n";
                for (const auto& d : r.records) {
                    out += "    <data";
                    attr(out, "seqid", std::to_string(d.seqid));
                    attr(out, "stepid", d.step_id);
                    attr(out, "cycleid", d.cycle_id);
                    attr(out, "steptype", d.step_type.empty() ? std::string("--") : d.step_type);
                    attr(out, "testtime", format_number(d.test_time_s * 1000.0, 0));
                    attr(out, "atime", d.atime);
                    attr(out, "volt", format_number(d.voltage_v, 6));
                    attr(out, "curr", format_number(d.current_a, 6));
                    attr(out, "cap", format_number(d.capacity_ah, 9));
                    attr(out, "eng", format_number(d.energy_wh, 9));
                    out += " />\r\n";
                }
                out += "  </list>\r\n";
            } else if constexpr (std::is_same_v<T, InquireDfResponse>) {
                out += "  <list count=\"" + std::to_string(r.channels.size()) + "\">\r\n";
                for (const auto& c : r.channels) {
                    out += "    <chl";
                    device_attrs_out(out, c.channel);
                    attr(out, "testid", std::to_string(c.testid));
                    attr(out, "count", std::to_string(c.count));
                    out += c.flag ? ">true</chl>\r\n" : ">false</chl>\r\n";
                }
                out += "  </list>\r\n";
            } else if constexpr (std::is_same_v<T, DownloadLogResponse>) {
                out += "  <download";
                device_attrs_out(out, r.channel);
                attr(out, "testid", std::to_string(r.testid));
                attr(out, "log_lever", r.log_level);
                out += " />\r\n  <list count=\"" + std::to_string(r.entries.size()) + "\">\r\n";
                for (const auto& e : r.entries) {
                    out += "    <data";
                    attr(out, "seqid", std::to_string(e.seqid));
                    attr(out, "log_code", e.log_code);
                    attr(out, "atime", e.atime);
                    out += " />\r\n";
                }
                out += "  </list>\r\n";
            } else if constexpr (std::is_same_v<T, StepLayerResponse>) {
                out += "  <downloadStepLayer";
                device_attrs_out(out, r.channel);
                attr(out, "testid", std::to_string(r.testid));
                out += " />\r\n  <list count=\"" + std::to_string(r.steps.size()) + "\">\r\n";
                for (const auto& d : r.steps) {
                    out += "    <data";
                    attr(out, "startseqid", std::to_string(d.start_seqid));
                    attr(out, "endseqid", std::to_string(d.end_seqid));
                    attr(out, "stepindex", d.step_index);
                    attr(out, "stepid", d.step_id);
                    attr(out, "cycleid", d.cycle_id);
                    attr(out, "steptype", d.step_type.empty() ? std::string("--") : d.step_type);
                    attr(out, "steptime", format_number(d.step_time_s * 1000.0, 0));
                    attr(out, "endatime", d.end_atime);
                    attr(out, "startvolt", format_number(d.start_voltage_v, 6));
                    attr(out, "endvolt", format_number(d.end_voltage_v, 6));
                    attr(out, "startcurr", format_number(d.start_current_a, 6));
                    attr(out, "endcurr", format_number(d.end_current_a, 6));
                    attr(out, "cap", format_number(d.capacity_ah, 9));
                    attr(out, "eng", format_number(d.energy_wh, 9));
                    attr(out, "dcir", format_number(d.dcir_ohm, 6));
                    out += " />\r\n";
                }
                out += "  </list>\r\n";
            } else if constexpr (std::is_same_v<T, ErrorResponse>) {
                out += "  <result>false</result>\r\n  <error>";
                append_escaped(out, r.message);
                out += "</error>\r\n";
            } else {  // ChannelCommandResponse
                if (!is_channel_result_command(r.command))
                    throw ProtocolError("a channel-result response cannot carry command " +
                                        std::string(command_name(r.command)));
                const auto tag = list_tag(r.command);
                out += "  <list count=\"" + std::to_string(r.channels.size()) + "\">\r\n";
                for (const auto& c : r.channels) {
                    out += "    <";
                    out += tag;
                    channel_attrs_out(out, c.channel);
                    out += '>';
                    append_escaped(out, c.text.empty() ? (c.ok ? "ok" : "false") : c.text);
                    out += "</";
                    out += tag;
                    out += ">\r\n";
                }
                out += "  </list>\r\n";
            }
        },
        response);
    out += "</bts>";
    out += kFrameTerminator;
    return out;
}

// -------------------------------------------------------------------------------------------------------------
// Parsing

std::string frame_command(std::string_view frame) { return parse_document(frame).cmd; }

std::string normalize_vendor_xml(std::string_view xml) { return normalise(xml); }

Request parse_request(std::string_view frame) {
    const Document doc = parse_document(frame);
    if (doc.cmd.size() > 5 && iequals(std::string_view(doc.cmd).substr(doc.cmd.size() - 5), "_resp"))
        throw ProtocolError("expected a request, got response " + shown(doc.cmd));
    const Command command = command_or_throw(doc.cmd);
    switch (command) {
        case Command::connect: {
            ConnectRequest r;
            auto text = [&](std::string_view name) {
                const auto* c = find_child(*doc.bts, name);
                return c ? std::string(trim(c->data())) : std::string();
            };
            r.username = text("username");
            r.password = text("password");
            r.type = text("type");
            return r;
        }
        case Command::getdevinfo: return GetDevInfoRequest{};
        case Command::download: {
            const auto* node = find_child(*doc.bts, "download");
            if (node == nullptr) throw ProtocolError(doc.cmd + ": <download> missing");
            const std::string where = doc.cmd + ": <download>";
            DownloadRequest r;
            r.channel = channel_attrs(*node, where);
            r.auxid = optional_int(*node, "auxid", where);
            r.testid = optional_int64(*node, "testid", where, 0);
            r.startpos = optional_int64(*node, "startpos", where, 1);
            r.count = find_attr(*node, "count") ? required_int(*node, "count", where) : kMaxDownloadCount;
            if (r.count > kMaxDownloadCount)
                throw ProtocolError(where + ": attribute 'count': expected 0.." + std::to_string(kMaxDownloadCount) +
                                    ", got " + std::to_string(r.count));
            if (r.startpos < 1 && r.count > 0)
                throw ProtocolError(where + ": attribute 'startpos': expected 1 or more (0 only with count=\"0\", "
                                            "the test-id query)");
            return r;
        }
        case Command::downloadlog:
        case Command::downloadStepLayer: {
            const std::string tag = command == Command::downloadlog ? "download" : "downloadStepLayer";
            const auto* node = find_child(*doc.bts, tag);
            if (node == nullptr) throw ProtocolError(doc.cmd + ": <" + tag + "> missing");
            const std::string where = doc.cmd + ": <" + tag + ">";
            TestRequest r;
            r.command = command;
            r.channel = channel_attrs(*node, where);
            r.testid = optional_int64(*node, "testid", where, 0);
            return r;
        }
        case Command::inquire: {
            InquireRequest r;
            const auto list = list_entries(doc, "inquire");
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto where = entry_where(doc, "inquire", i);
                r.channels.push_back(channel_attrs(*list.entries[i], where));
                if (i == 0) {
                    r.aux = flag_attr(*list.entries[i], "aux", false, where);
                    r.barcode = flag_attr(*list.entries[i], "barcode", true, where);
                }
            }
            return r;
        }
        case Command::start: {
            StartRequest r;
            const auto list = list_entries(doc, "start");
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto where = entry_where(doc, "start", i);
                StartEntry e;
                e.channel = channel_attrs(*list.entries[i], where);
                e.step_file_path = std::string(trim(list.entries[i]->data()));
                if (e.step_file_path.empty()) throw ProtocolError(where + ": step file path (element text) missing");
                e.barcode = optional_string(*list.entries[i], "barcode");
                e.remark = optional_string(*list.entries[i], "remark");
                r.entries.push_back(std::move(e));
            }
            const pt::ptree* backup = find_child(*list.list, "backup");
            if (backup == nullptr) backup = find_child(*doc.bts, "backup");
            if (backup != nullptr) {
                BackupOptions b;
                b.backupdir = optional_string(*backup, "backupdir");
                b.filetype = optional_int(*backup, "filetype", doc.cmd + ": <backup>");
                b.filenametype = optional_int(*backup, "filenametype", doc.cmd + ": <backup>");
                r.backup = std::move(b);
            }
            return r;
        }
        case Command::getchlstatus:
        case Command::stop:
        case Command::pause:
        case Command::continue_:
        case Command::light:
        case Command::clearflag:
        case Command::inquiredf: {
            ChannelListRequest r;
            r.command = command;
            const auto tag = list_tag(command);
            const auto list = list_entries(doc, tag);
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                r.channels.push_back(channel_attrs(*list.entries[i], entry_where(doc, tag, i)));
                if (i == 0 && command == Command::light) r.on = !iequals(trim(list.entries[i]->data()), "false");
            }
            return r;
        }
    }
    throw ProtocolError("unhandled command " + shown(doc.cmd));
}

Response parse_response(std::string_view frame) {
    const Document doc = parse_document(frame);
    const std::string_view cmd = doc.cmd;
    if (cmd.size() <= 5 || !iequals(cmd.substr(cmd.size() - 5), "_resp"))
        throw ProtocolError("expected a response (<cmd>NAME_resp</cmd>), got " + shown(cmd));
    if (const auto* error = find_child(*doc.bts, "error")) {
        const auto known = response_command_from_name(cmd);
        if (!known || find_child(*doc.bts, "list") == nullptr)
            return ErrorResponse{std::string(cmd.substr(0, cmd.size() - 5)), std::string(trim(error->data()))};
    }
    const auto parsed = response_command_from_name(cmd);
    if (!parsed) throw ProtocolError("unknown command " + shown(cmd));
    const Command command = *parsed;
    auto test_header = [&](std::string_view tag, ChannelAddress& channel, std::int64_t& testid) -> const pt::ptree* {
        const auto* node = find_child(*doc.bts, tag);
        if (node == nullptr) throw ProtocolError(doc.cmd + ": <" + std::string(tag) + "> missing");
        const std::string where = doc.cmd + ": <" + std::string(tag) + ">";
        channel = channel_attrs(*node, where);
        testid = optional_int64(*node, "testid", where, 0);
        return node;
    };
    switch (command) {
        case Command::inquiredf: {
            InquireDfResponse r;
            const auto list = list_entries(doc, "chl");
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto where = entry_where(doc, "chl", i);
                TestInfo t;
                t.channel = channel_attrs(*list.entries[i], where);
                t.testid = optional_int64(*list.entries[i], "testid", where, 0);
                t.count = optional_int64(*list.entries[i], "count", where, 0);
                const auto text = trim(list.entries[i]->data());
                t.flag = iequals(text, "true") || text == "1";
                r.channels.push_back(std::move(t));
            }
            return r;
        }
        case Command::downloadlog: {
            DownloadLogResponse r;
            const auto* node = test_header("download", r.channel, r.testid);
            r.log_level = optional_int(*node, "log_lever", doc.cmd + ": <download>");
            const auto list = list_entries(doc, "data", false);
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto at = entry_where(doc, "data", i);
                LogEntry e;
                e.seqid = optional_int64(*list.entries[i], "seqid", at, 0);
                e.log_code = optional_int(*list.entries[i], "log_code", at);
                e.atime = optional_string(*list.entries[i], "atime");
                r.entries.push_back(std::move(e));
            }
            return r;
        }
        case Command::downloadStepLayer: {
            StepLayerResponse r;
            test_header("downloadStepLayer", r.channel, r.testid);
            const auto list = list_entries(doc, "data", false);
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto& d = *list.entries[i];
                const auto at = entry_where(doc, "data", i);
                StepLayerEntry e;
                e.start_seqid = optional_int64(d, "startseqid", at, 0);
                e.end_seqid = optional_int64(d, "endseqid", at, 0);
                e.step_index = optional_int(d, "stepindex", at);
                e.step_id = optional_int(d, "stepid", at);
                e.cycle_id = optional_int(d, "cycleid", at);
                e.step_type = optional_string(d, "steptype");
                e.step_time_s = optional_double(d, "steptime", at) / 1000.0;
                e.end_atime = optional_string(d, "endatime");
                e.start_voltage_v = optional_double(d, "startvolt", at);
                e.end_voltage_v = optional_double(d, "endvolt", at);
                e.start_current_a = optional_double(d, "startcurr", at);
                e.end_current_a = optional_double(d, "endcurr", at);
                e.capacity_ah = optional_double(d, "cap", at);
                e.energy_wh = optional_double(d, "eng", at);
                e.dcir_ohm = optional_double(d, "dcir", at);
                r.steps.push_back(std::move(e));
            }
            return r;
        }
        case Command::connect: {
            ConnectResponse r;
            const auto* result = find_child(*doc.bts, "result");
            if (result == nullptr) throw ProtocolError(doc.cmd + ": <result> missing");
            r.result = std::string(trim(result->data()));
            r.ok = iequals(r.result, "ok") || iequals(r.result, "true");
            return r;
        }
        case Command::getdevinfo: {
            GetDevInfoResponse r;
            if (const auto* servers = find_child(*doc.bts, "serverip")) {
                std::size_t i = 0;
                for (const auto& [key, s] : *servers) {
                    if (!iequals(key, "server")) continue;
                    const auto where = doc.cmd + ": <server> #" + std::to_string(++i);
                    r.servers.push_back({optional_string(s, "ip"), optional_int(s, "port", where)});
                }
            }
            const auto* middle = find_child(*doc.bts, "middle");
            if (middle == nullptr) throw ProtocolError(doc.cmd + ": <middle> missing");
            std::size_t i = 0;
            for (const auto& [key, c] : *middle) {
                if (!iequals(key, "channel")) continue;
                const auto where = doc.cmd + ": <channel> #" + std::to_string(++i);
                DeviceChannel dc;
                dc.channel = channel_attrs(c, where);
                const auto text = trim(c.data());
                dc.online = iequals(text, "true") || text == "1";
                r.channels.push_back(std::move(dc));
            }
            return r;
        }
        case Command::getchlstatus: {
            ChannelStatusResponse r;
            const auto list = list_entries(doc, "status");
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto where = entry_where(doc, "status", i);
                StatusEntry s;
                s.channel = channel_attrs(*list.entries[i], where);
                s.status_text = std::string(trim(list.entries[i]->data()));
                if (s.status_text.empty()) throw ProtocolError(where + ": status text missing");
                s.status = channel_status_from_string(s.status_text);
                s.reserve_pause = flag_attr(*list.entries[i], "reservepause", false, where);
                r.channels.push_back(std::move(s));
            }
            return r;
        }
        case Command::inquire: {
            InquireResponse r;
            const auto list = list_entries(doc, "inquire");
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto& node = *list.entries[i];
                const auto where = entry_where(doc, "inquire", i);
                InquireEntry e;
                const auto dev = find_attr(node, "dev");
                if (!dev) throw ProtocolError(where + ": attribute 'dev' missing");
                // dev="devtype-devid-subdevid-chlid-auxid" (auxid may be absent)
                std::array<int, 5> parts{};
                std::size_t count = 0;
                std::string_view rest = trim(*dev);
                while (true) {
                    const auto dash = rest.find('-');
                    const auto part = rest.substr(0, dash);
                    const auto value = to_int<int>(part);
                    if (!value || *value < 0 || count >= parts.size())
                        throw ProtocolError(where + ": attribute 'dev': expected devtype-devid-subdevid-chlid-auxid, got " +
                                            shown(*dev));
                    parts[count++] = *value;
                    if (dash == std::string_view::npos) break;
                    rest.remove_prefix(dash + 1);
                }
                if (count < 4)
                    throw ProtocolError(where + ": attribute 'dev': expected devtype-devid-subdevid-chlid-auxid, got " +
                                        shown(*dev));
                e.channel = {"", parts[0], parts[1], parts[2], parts[3]};
                e.auxid = count == 5 ? parts[4] : 0;
                e.cycle_id = optional_int(node, "cycle_id", where);
                e.step_id = optional_int(node, "step_id", where);
                e.step_type = optional_string(node, "step_type");
                e.workstatus_text = optional_string(node, "workstatus");
                e.workstatus = channel_status_from_string(e.workstatus_text);
                e.barcode = optional_string(node, "barcode");
                e.current_a = optional_double(node, "current", where);
                e.voltage_v = optional_double(node, "voltage", where);
                e.capacity_ah = optional_double(node, "capacity", where);
                e.energy_wh = optional_double(node, "energy", where);
                e.total_time_s = optional_double(node, "totaltime", where);
                e.relative_time_s = optional_double(node, "relativetime", where);
                e.open = optional_int(node, "open_or_close", where) != 0;
                e.log_code = optional_int(node, "log_code", where);
                r.channels.push_back(std::move(e));
            }
            return r;
        }
        case Command::download: {
            const auto* node = find_child(*doc.bts, "download");
            if (node == nullptr) throw ProtocolError(doc.cmd + ": <download> missing");
            const std::string where = doc.cmd + ": <download>";
            DownloadResponse r;
            r.channel = channel_attrs(*node, where);
            r.testid = optional_int64(*node, "testid", where, 0);
            r.startpos = optional_int64(*node, "startpos", where, 1);
            r.count = find_attr(*node, "count") ? optional_int(*node, "count", where) : kMaxDownloadCount;
            r.auxid = optional_int(*node, "auxid", where);
            const auto list = list_entries(doc, "data", false);
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                const auto& d = *list.entries[i];
                const auto at = entry_where(doc, "data", i);
                DownloadRecord rec;
                rec.seqid = optional_int64(d, "seqid", at, -1);
                if (rec.seqid < 0) throw ProtocolError(at + ": attribute 'seqid' missing");
                rec.step_id = optional_int(d, "stepid", at);
                rec.cycle_id = optional_int(d, "cycleid", at);
                rec.step_type = optional_string(d, "steptype");
                const double ms = optional_double(d, "testtime", at);
                if (!std::isfinite(ms)) throw ProtocolError(at + ": attribute 'testtime' missing");
                rec.test_time_s = ms / 1000.0;
                rec.atime = optional_string(d, "atime");
                rec.voltage_v = optional_double(d, "volt", at);
                rec.current_a = optional_double(d, "curr", at);
                rec.capacity_ah = optional_double(d, "cap", at);
                rec.energy_wh = optional_double(d, "eng", at);
                if (!r.records.empty() && rec.seqid <= r.records.back().seqid)
                    throw ProtocolError(at + ": seqid " + std::to_string(rec.seqid) + " does not follow " +
                                        std::to_string(r.records.back().seqid));
                r.records.push_back(std::move(rec));
            }
            return r;
        }
        case Command::start:
        case Command::stop:
        case Command::pause:
        case Command::continue_:
        case Command::light:
        case Command::clearflag: {
            ChannelCommandResponse r;
            r.command = command;
            const auto tag = list_tag(command);
            const auto list = list_entries(doc, tag);
            for (std::size_t i = 0; i < list.entries.size(); ++i) {
                ChannelResult c;
                c.channel = channel_attrs(*list.entries[i], entry_where(doc, tag, i));
                c.text = std::string(trim(list.entries[i]->data()));
                c.ok = iequals(c.text, "ok") || iequals(c.text, "true");
                r.channels.push_back(std::move(c));
            }
            return r;
        }
    }
    throw ProtocolError("unhandled response " + shown(doc.cmd));
}

}  // namespace cellbench::protocol::neware
