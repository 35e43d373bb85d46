// Configuration reading helpers: see config_reader.hpp.
#include "config_reader.hpp"

#include <charconv>
#include <cctype>
#include <fstream>
#include <sstream>

#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/json_input.hpp"

namespace cellbench::daemon::config_read {

std::string format_number(double v) {
    char buf[64];
    const auto r = std::to_chars(buf, buf + sizeof buf, v);
    return std::string(buf, r.ptr);
}

std::string got(const json& j) {
    switch (j.type()) {
        case json::value_t::null: return "got null";
        case json::value_t::boolean: return std::string("got ") + (j.get<bool>() ? "true" : "false");
        case json::value_t::string: {
            std::string s = j.get<std::string>();
            if (s.size() > 40) s = s.substr(0, 37) + "...";
            return "got \"" + s + "\"";
        }
        case json::value_t::number_integer:
        case json::value_t::number_unsigned:
        case json::value_t::number_float: return "got " + j.dump();
        case json::value_t::array: return "got an array";
        case json::value_t::object: return "got an object";
        default: return std::string("got ") + j.type_name();
    }
}

std::string read_text_file(const fs::path& file) {
    // Only regular files: a device or FIFO named by mistake (/dev/zero, a pipe) would never end.
    std::error_code ec;
    const auto status = fs::status(file, ec);
    if (fs::exists(status) && !fs::is_regular_file(status))
        throw InputError(file.string() + ": cannot read: not a regular file");
    // Every config, program and cell is a few kB; a huge file is a mistake, not something to read into memory.
    constexpr std::uintmax_t kMaxConfigBytes = 16u << 20;
    if (fs::is_regular_file(status) && fs::file_size(file, ec) > kMaxConfigBytes && !ec)
        throw InputError(file.string() + ": cannot read: larger than 16 MiB (not a cellbench JSON file)");
    std::ifstream in(file, std::ios::binary);
    if (!in) {
        const bool exists = fs::exists(file, ec);
        throw InputError(file.string() + ": cannot read: " + (exists ? "permission denied or not a file" : "no such file"));
    }
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

json parse_json_text(std::string_view text, const std::string& source) {
    // Nesting bounded, numbers that overflow a double (1e400) rejected: InputError naming the file.
    return protocol::parse_json_input(text, source);
}

json read_json_file(const fs::path& file) { return parse_json_text(read_text_file(file), file.string()); }

void check_schema(Obj& o, const char* expected) {
    const json* v = o.get("schema", true);
    if (!v) return;
    if (!v->is_string() || v->get<std::string>() != expected) {
        std::string hint;
        if (v->is_string() && v->get<std::string>() == estimator::kParamsSchema)
            hint = " (this file is a parameter set, not a " + std::string(expected) + " file)";
        o.ctx().add(o.child("schema"), std::string("expected \"") + expected + "\", " + got(*v) + hint);
    }
}

fs::path resolve(const fs::path& base_dir, const std::string& p) {
    fs::path path(p);
    return path.is_absolute() ? path : (base_dir / path).lexically_normal();
}

void check_params_file(Ctx& ctx, const std::string& json_path, const fs::path& file) {
    try {
        estimator::ParameterSet::from_json(read_json_file(file), file.string());
    } catch (const InputError& e) {
        ctx.add(json_path, std::string("parameter set does not load: ") + e.what());
    }
}

std::optional<Endpoint> endpoint_of(Obj& o, bool allow_port_zero) {
    const auto host = o.string("host", true);
    const auto port = o.integer("port", true, allow_port_zero ? 0 : 1, 65535);
    if (!host || !port) return std::nullopt;
    return Endpoint{*host, static_cast<int>(*port)};
}

bool valid_env_name(const std::string& s) {
    if (s.empty() || std::isdigit(static_cast<unsigned char>(s[0]))) return false;
    return std::all_of(s.begin(), s.end(), [](char c) { return std::isupper(static_cast<unsigned char>(c)) || std::isdigit(static_cast<unsigned char>(c)) || c == '_'; });
}

}  // namespace cellbench::daemon::config_read
