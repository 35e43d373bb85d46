#include "cli/files.hpp"

#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <random>
#include <sstream>

#include <spdlog/spdlog.h>

#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/neware_export.hpp"

namespace cellbench::cli {

std::string read_file(const std::filesystem::path& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw InputError(path.string() + ": cannot open for reading");
    std::ostringstream ss;
    ss << in.rdbuf();
    if (in.bad()) throw InputError(path.string() + ": read error");
    return std::move(ss).str();
}

void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer) {
    const auto dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
    if (!std::filesystem::is_directory(dir)) throw InputError(path.string() + ": folder " + dir.string() + " does not exist");
    std::random_device rd;
    std::string tmp_name = ".";  // appended piecewise: GCC 12 warns (-Wrestrict) on a chain of operator+
    tmp_name += path.filename().string();
    tmp_name += ".tmp";
    tmp_name += std::to_string(rd());
    const auto tmp = dir / tmp_name;
    try {
        {
            std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
            if (!out) throw InputError(path.string() + ": cannot open for writing");
            writer(out);
            out.flush();
            if (!out) throw InputError(path.string() + ": write failed (disk full?)");
        }
        std::filesystem::rename(tmp, path);
    } catch (...) {
        std::error_code ec;
        std::filesystem::remove(tmp, ec);
        throw;
    }
}

void write_json_file(const std::filesystem::path& path, const nlohmann::json& j) {
    write_file_atomic(path, [&](std::ostream& out) { out << j.dump(2) << '\n'; });
}

nlohmann::json parse_json_file(const std::filesystem::path& path) {
    const std::string text = read_file(path);
    try {
        return nlohmann::json::parse(text);
    } catch (const nlohmann::json::parse_error& e) {
        // e.byte is the 1-based offset of the error; turn it into a line number.
        const std::size_t upto = std::min<std::size_t>(e.byte, text.size());
        const auto line = 1 + std::count(text.begin(), text.begin() + static_cast<std::ptrdiff_t>(upto), '\n');
        throw InputError(path.string() + ":" + std::to_string(line) + ": invalid JSON: " + e.what());
    }
}

estimator::ParameterSet load_params(const std::filesystem::path& path) {
    return estimator::ParameterSet::from_json(parse_json_file(path), path.string());
}

Recording load_recording(const std::filesystem::path& path) {
    const std::string text = read_file(path);
    const auto header = text.substr(0, text.find('\n'));
    Recording rec;
    if (header.find("Test Time / s") != std::string::npos) {
        protocol::BdfReadReport report;
        rec = protocol::parse_bdf_csv(text, path.string(), &report);
        if (report.repaired_timestamps > 0)
            spdlog::warn("{}: repaired {} repeated or slightly backward timestamps", path.string(),
                         report.repaired_timestamps);
    } else if (header.find("Current(A)") != std::string::npos || header.find("Voltage(V)") != std::string::npos) {
        rec = protocol::parse_neware_export(text, path.string());
        if (rec.repaired_timestamps > 0)
            spdlog::warn("{}: repaired {} repeated or slightly backward timestamps", path.string(),
                         rec.repaired_timestamps);
    } else {
        throw InputError(path.string() +
                         ":1: not a recording: expected a BDF CSV header with \"Test Time / s\", \"Voltage / V\", "
                         "\"Current / A\" (use `cellbench import` for instrument exports)");
    }
    return rec;
}

bool stderr_is_terminal() { return ::isatty(STDERR_FILENO) == 1; }

}  // namespace cellbench::cli
