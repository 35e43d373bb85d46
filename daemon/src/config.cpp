// Configuration loading: see config.hpp. Split by what is read:
//   config.cpp             errors, endpoints, files by name (this file)
//   config_bench.cpp       the bench configuration
//   config_cell.cpp        cell configurations
//   config_program.cpp     programs and their expected duration
//   config_expression.cpp  the expression grammar of programs
//   config_reader.*        helpers shared by the readers (internal): issues, checked members, file reading
// Configuration loading: see config.hpp. The readers below never stop at the first problem: each one records
// an issue (file, JSON path, what was expected) and returns a default, so one load reports everything.
#include "config_reader.hpp"

#include <algorithm>
#include <charconv>

namespace cellbench::daemon {

using namespace config_read;

// ---------------------------------------------------------------------------------------------------------
// Errors

std::string ConfigIssue::to_string() const {
    std::string s = file;
    if (!path.empty()) s += (s.empty() ? "" : ": ") + path;
    return s + (s.empty() ? "" : ": ") + message;
}

namespace {
std::string join_issues(const std::vector<ConfigIssue>& issues) {
    std::string s;
    for (const auto& i : issues) {
        if (!s.empty()) s += '\n';
        s += i.to_string();
    }
    return s.empty() ? std::string("invalid configuration") : s;
}
}  // namespace

ConfigError::ConfigError(std::vector<ConfigIssue> issues) : InputError(join_issues(issues)), issues_(std::move(issues)) {}

// ---------------------------------------------------------------------------------------------------------
// Endpoint

std::string Endpoint::to_string() const { return host + ":" + std::to_string(port); }

std::optional<Endpoint> parse_endpoint(std::string_view text) {
    const auto colon = text.rfind(':');
    if (colon == std::string_view::npos || colon == 0 || colon + 1 >= text.size()) return std::nullopt;
    int port = 0;
    const auto digits = text.substr(colon + 1);
    const auto r = std::from_chars(digits.data(), digits.data() + digits.size(), port);
    if (r.ec != std::errc() || r.ptr != digits.data() + digits.size() || port < 0 || port > 65535) return std::nullopt;
    std::string host(text.substr(0, colon));
    if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
    if (host.empty() || host.find_first_of(" \t/") != std::string::npos) return std::nullopt;
    return Endpoint{host, port};
}

// ---------------------------------------------------------------------------------------------------------
// Files by name

namespace {

fs::path named_file(const fs::path& config_dir, const char* folder, std::string_view name) {
    const bool ok = !name.empty() && name.size() <= 100 && name.front() != '.' &&
                    std::all_of(name.begin(), name.end(), [](char c) {
                        return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-' || c == '.';
                    });
    if (!ok)
        throw InputError("\"" + std::string(name.substr(0, 100)) + "\": expected a " +
                         (std::string(folder) == "cells" ? "cell" : "program") +
                         " name of letters, digits, '_', '-' and '.' (a file under " +
                         (config_dir / folder).string() + ", without .json)");
    std::string file(name);
    if (file.size() < 5 || file.substr(file.size() - 5) != ".json") file += ".json";
    return config_dir / folder / file;
}

std::vector<std::string> list_json(const fs::path& dir, const char* schema_or_null_for_any_but) {
    std::vector<std::string> out;
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) return out;
    for (const auto& e : fs::directory_iterator(dir, ec)) {
        if (!e.is_regular_file() || e.path().extension() != ".json") continue;
        if (schema_or_null_for_any_but) {
            // Skip files of another known kind (a parameter set among the cells); keep broken ones so that
            // loading them explains what is wrong.
            try {
                const json j = read_json_file(e.path());
                if (j.is_object() && j.contains("schema") && j["schema"].is_string() &&
                    j["schema"] != schema_or_null_for_any_but)
                    continue;
            } catch (const std::exception&) {
            }
        }
        out.push_back(e.path().stem().string());
    }
    std::sort(out.begin(), out.end());
    return out;
}

}  // namespace

fs::path program_file(const fs::path& config_dir, std::string_view name) { return named_file(config_dir, "programs", name); }
fs::path cell_file(const fs::path& config_dir, std::string_view name) { return named_file(config_dir, "cells", name); }
std::vector<std::string> list_programs(const fs::path& config_dir) { return list_json(config_dir / "programs", nullptr); }
std::vector<std::string> list_cells(const fs::path& config_dir) { return list_json(config_dir / "cells", kCellSchema); }

}  // namespace cellbench::daemon
