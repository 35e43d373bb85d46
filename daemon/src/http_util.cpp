// Parsing helpers of the HTTP server (http_internal.hpp) and the free functions of http_server.hpp.
#include "http_internal.hpp"

#include <charconv>

namespace cellbench::daemon {

namespace http_detail {

std::string dump(const nlohmann::json& j) { return api_json_text(j); }

bool iequals(std::string_view a, std::string_view b) {
    return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), [](char x, char y) {
               return std::tolower(static_cast<unsigned char>(x)) == std::tolower(static_cast<unsigned char>(y));
           });
}

namespace {
int hex_value(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}
}  // namespace

std::optional<std::string> percent_decode(std::string_view s, bool plus_is_space) {
    std::string out;
    out.reserve(s.size());
    for (std::size_t i = 0; i < s.size(); ++i) {
        if (s[i] == '%') {
            if (i + 2 >= s.size()) return std::nullopt;
            const int hi = hex_value(s[i + 1]), lo = hex_value(s[i + 2]);
            if (hi < 0 || lo < 0) return std::nullopt;
            out.push_back(static_cast<char>(hi * 16 + lo));
            i += 2;
        } else if (plus_is_space && s[i] == '+') {
            out.push_back(' ');
        } else {
            out.push_back(s[i]);
        }
    }
    return out;
}

std::vector<std::string_view> split(std::string_view s, char sep) {
    std::vector<std::string_view> parts;
    std::size_t start = 0;
    while (true) {
        const auto pos = s.find(sep, start);
        parts.push_back(s.substr(start, pos == std::string_view::npos ? std::string_view::npos : pos - start));
        if (pos == std::string_view::npos) break;
        start = pos + 1;
    }
    return parts;
}

std::optional<std::vector<std::pair<std::string, std::string>>> query_params(std::string_view query) {
    std::vector<std::pair<std::string, std::string>> params;
    for (const auto part : split(query, '&')) {
        if (part.empty()) continue;
        const auto eq = part.find('=');
        auto key = percent_decode(part.substr(0, eq), true);
        auto value = percent_decode(eq == std::string_view::npos ? "" : part.substr(eq + 1), true);
        if (!key || !value) return std::nullopt;
        params.emplace_back(std::move(*key), std::move(*value));
    }
    return params;
}

const char* mime_type(const fs::path& p) {
    static const std::unordered_map<std::string, const char*> types = {
        {".html", "text/html; charset=utf-8"},
        {".htm", "text/html; charset=utf-8"},
        {".js", "text/javascript; charset=utf-8"},
        {".mjs", "text/javascript; charset=utf-8"},
        {".css", "text/css; charset=utf-8"},
        {".json", "application/json"},
        {".map", "application/json"},
        {".webmanifest", "application/manifest+json"},
        {".svg", "image/svg+xml"},
        {".png", "image/png"},
        {".jpg", "image/jpeg"},
        {".jpeg", "image/jpeg"},
        {".gif", "image/gif"},
        {".webp", "image/webp"},
        {".ico", "image/vnd.microsoft.icon"},
        {".woff", "font/woff"},
        {".woff2", "font/woff2"},
        {".ttf", "font/ttf"},
        {".wasm", "application/wasm"},
        {".txt", "text/plain; charset=utf-8"},
        {".csv", "text/csv; charset=utf-8"},
    };
    std::string ext = p.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    const auto it = types.find(ext);
    return it == types.end() ? "application/octet-stream" : it->second;
}

bool is_within(const fs::path& root, const fs::path& p) {
    const auto [r, q] = std::mismatch(root.begin(), root.end(), p.begin(), p.end());
    return r == root.end();
}

bool valid_name(std::string_view s) {
    if (s.empty() || s.size() > 128 || s.front() == '.') return false;
    return std::all_of(s.begin(), s.end(), [](unsigned char c) {
        return std::isalnum(c) || c == '_' || c == '-' || c == '.';
    });
}

std::optional<RunId> parse_run_id(std::string_view s) {
    RunId id = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), id);
    if (ec != std::errc() || p != s.data() + s.size() || id <= 0) return std::nullopt;
    return id;
}

}  // namespace http_detail

using namespace http_detail;

// ---------------------------------------------------------------------------------------------------------
// Free helpers declared in the header.

ListenAddress parse_listen_address(std::string_view text) {
    const std::string expected = "expected HOST:PORT (e.g. 127.0.0.1:8750, [::1]:8750 or :8750), got \"" +
                                 std::string(text) + "\"";
    ListenAddress out;
    std::string_view port_text;
    if (!text.empty() && text.front() == '[') {
        const auto close = text.find(']');
        if (close == std::string_view::npos || close + 1 >= text.size() || text[close + 1] != ':')
            throw std::invalid_argument(expected);
        out.host = std::string(text.substr(1, close - 1));
        port_text = text.substr(close + 2);
    } else {
        const auto colon = text.rfind(':');
        if (colon == std::string_view::npos) throw std::invalid_argument(expected);
        out.host = std::string(text.substr(0, colon));
        if (out.host.find(':') != std::string::npos) throw std::invalid_argument(expected);  // bare IPv6
        port_text = text.substr(colon + 1);
    }
    if (out.host.empty()) out.host = "127.0.0.1";
    unsigned port = 0;
    const auto [p, ec] = std::from_chars(port_text.data(), port_text.data() + port_text.size(), port);
    if (port_text.empty() || ec != std::errc() || p != port_text.data() + port_text.size() || port > 65535)
        throw std::invalid_argument(expected);
    out.port = static_cast<std::uint16_t>(port);
    return out;
}

bool token_equals(std::string_view expected, std::string_view given) {
    // Fold every byte of `expected` in; bytes of `given` beyond its length read as 0 and the length
    // difference is folded in too. No early exit, so timing reveals at most the expected length.
    unsigned diff = static_cast<unsigned>(expected.size() != given.size());
    for (std::size_t i = 0; i < expected.size(); ++i) {
        const unsigned char g = i < given.size() ? static_cast<unsigned char>(given[i]) : 0;
        diff |= static_cast<unsigned>(static_cast<unsigned char>(expected[i]) ^ g);
    }
    // Keep the compiler from turning the loop into an early-exit comparison.
    asm volatile("" : "+r"(diff));
    return diff == 0;
}

}  // namespace cellbench::daemon
