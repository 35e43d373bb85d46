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

namespace {

void check_output_path(const std::filesystem::path& path) {
    const auto dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
    std::error_code ec;
    if (!std::filesystem::is_directory(dir, ec)) throw InputError(path.string() + ": folder " + dir.string() + " does not exist");
    if (std::filesystem::is_directory(path, ec)) throw InputError(path.string() + ": is a folder, expected a file name");
}

// Writes a temporary file beside `path` and returns its name; removes it and throws on failure.
std::filesystem::path stage(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer) {
    check_output_path(path);
    const auto dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
    std::random_device rd;
    std::string tmp_name = ".";  // appended piecewise: GCC 12 warns (-Wrestrict) on a chain of operator+
    tmp_name += path.filename().string();
    tmp_name += ".tmp";
    tmp_name += std::to_string(rd());
    const auto tmp = dir / tmp_name;
    try {
        std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
        if (!out) throw InputError(path.string() + ": cannot open for writing");
        writer(out);
        out.flush();
        if (!out) throw InputError(path.string() + ": write failed (disk full?)");
    } catch (...) {
        std::error_code ec;
        std::filesystem::remove(tmp, ec);
        throw;
    }
    return tmp;
}

void move_into_place(const std::filesystem::path& tmp, const std::filesystem::path& path) {
    std::error_code ec;
    std::filesystem::rename(tmp, path, ec);
    if (ec) {
        std::filesystem::remove(tmp, ec);
        throw InputError(path.string() + ": cannot write: " + ec.message());
    }
}

}  // namespace

void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer) {
    move_into_place(stage(path, writer), path);
}

OutputFiles::OutputFiles(std::initializer_list<std::filesystem::path> paths) {
    for (const auto& p : paths)
        if (!p.empty()) check_output_path(p);
}

OutputFiles::~OutputFiles() {
    for (const auto& s : staged_) {
        std::error_code ec;
        std::filesystem::remove(s.tmp, ec);
    }
}

void OutputFiles::write(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer) {
    staged_.push_back({stage(path, writer), path});
}

void OutputFiles::write_json(const std::filesystem::path& path, const nlohmann::json& j) {
    write(path, [&](std::ostream& out) { out << j.dump(2) << '\n'; });
}

void OutputFiles::commit() {
    std::vector<Staged> staged;
    staged.swap(staged_);
    for (std::size_t k = 0; k < staged.size(); ++k) {
        try {
            move_into_place(staged[k].tmp, staged[k].path);
        } catch (...) {
            for (std::size_t j = k + 1; j < staged.size(); ++j) {
                std::error_code ec;
                std::filesystem::remove(staged[j].tmp, ec);
            }
            throw;
        }
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
