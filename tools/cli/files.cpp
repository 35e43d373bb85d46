#include "cli/files.hpp"

#include <unistd.h>

#include <array>
#include <cstdio>
#include <fstream>
#include <random>
#include <sstream>

#include <spdlog/spdlog.h>

#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/json_input.hpp"
#include "cellbench/protocol/neware_export.hpp"

namespace cellbench::cli {

std::string read_file(const std::filesystem::path& path, std::size_t max_line_bytes) {
    // Streamed in blocks and checked as it comes: a device (/dev/zero, /dev/urandom), a binary file or a
    // huge sparse file fails within its first block, long before it could fill the memory.
    std::ifstream in(path, std::ios::binary);
    if (!in) throw InputError(path.string() + ": cannot open for reading");
    std::error_code ec;
    if (std::filesystem::is_directory(path, ec)) throw InputError(path.string() + ": is a folder, not a file");
    std::string text;
    if (const auto size = std::filesystem::file_size(path, ec); !ec && size <= kMaxInputFileBytes)
        text.reserve(static_cast<std::size_t>(size));
    std::array<char, 1 << 16> block{};
    std::size_t line = 1, line_bytes = 0;
    while (in) {
        in.read(block.data(), static_cast<std::streamsize>(block.size()));
        const auto n = static_cast<std::size_t>(in.gcount());
        if (n == 0) break;
        for (std::size_t k = 0; k < n; ++k) {
            const char c = block[k];
            if (c == '\n') {
                ++line;
                line_bytes = 0;
            } else if (c == '\r') {  // CRLF, or a lone CR line end (old Mac exports)
                line_bytes = 0;
            } else if (c == '\0') {
                throw InputError(path.string() + ":" + std::to_string(line) + ": binary data (a NUL byte at byte " +
                                 std::to_string(text.size() + k + 1) + "): not a text file");
            } else if (++line_bytes > max_line_bytes) {
                throw InputError(path.string() + ":" + std::to_string(line) + ": a line longer than " +
                                 std::to_string(max_line_bytes) + " bytes: not a recording or JSON file");
            }
        }
        if (text.size() + n > kMaxInputFileBytes)
            throw InputError(path.string() + ": larger than " + std::to_string(kMaxInputFileBytes >> 20) +
                             " MiB: not a file cellbench reads");
        text.append(block.data(), n);
    }
    if (in.bad()) throw InputError(path.string() + ": read error");
    return text;
}

void warn_bdf_report(const std::string& source, const protocol::BdfReadReport& report) {
    for (const auto& m : protocol::describe(report, source)) {
        if (m.warning)
            spdlog::warn("{}", m.text);
        else
            spdlog::info("{}", m.text);
    }
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
    const std::string text = read_file(path, kMaxInputFileBytes);
    if (protocol::json_nesting_depth(text) > protocol::kMaxJsonDepth)
        throw InputError(path.string() + ": invalid JSON: nested deeper than " +
                         std::to_string(protocol::kMaxJsonDepth) + " levels of objects and arrays");
    try {
        return nlohmann::json::parse(text);
    } catch (const nlohmann::json::out_of_range& e) {  // a number beyond a double (1e999)
        std::string what = e.what();
        if (const auto p = what.find("] "); p != std::string::npos) what = what.substr(p + 2);
        throw InputError(path.string() + ": invalid JSON: " + what);
    } catch (const nlohmann::json::parse_error& e) {
        // e.byte is the 1-based offset of the error; turn it into a line number.
        const std::size_t upto = std::min<std::size_t>(e.byte, text.size());
        const auto line = 1 + std::count(text.begin(), text.begin() + static_cast<std::ptrdiff_t>(upto), '\n');
        throw InputError(path.string() + ":" + std::to_string(line) + ": invalid JSON: " + e.what());
    }
}

estimator::ParameterSet load_params(const std::filesystem::path& path) {
    auto p = estimator::ParameterSet::from_json(parse_json_file(path), path.string());
    for (const auto& id : p.extensions.unknown_ids())
        spdlog::warn("{}: extension \"{}\" is not an effect this cellbench models: kept as it is in any parameter set "
                     "written from this one, left out of the model", path.string(), id);
    return p;
}

Recording load_recording(const std::filesystem::path& path) {
    const std::string text = read_file(path);
    const auto header = text.substr(0, text.find('\n'));
    Recording rec;
    if (header.find("Current(A)") != std::string::npos || header.find("Voltage(V)") != std::string::npos) {
        rec = protocol::parse_neware_export(text, path.string());
        if (rec.repaired_timestamps > 0)
            spdlog::warn("{}: repaired {} repeated or slightly backward timestamps", path.string(),
                         rec.repaired_timestamps);
        return rec;
    }
    // Everything else is read as BDF CSV, whose reader knows its columns under every name and unit it takes
    // (preferred labels, machine-readable names, other units) and says which required one is missing.
    protocol::BdfReadReport report;
    try {
        rec = protocol::parse_bdf_csv(text, path.string(), &report);
    } catch (const InputError& e) {
        const std::string what = e.what();
        if (what.find("missing required column") == std::string::npos) throw;
        throw InputError(what + "; not a BDF recording? `cellbench import` turns Neware and DewesoftX exports into one");
    }
    warn_bdf_report(path.string(), report);
    if (rec.take_t1_as_surface())
        spdlog::info("{}: no Surface Temperature column: the cell temperature is read from Temperature T1",
                     path.string());
    return rec;
}

bool stderr_is_terminal() { return ::isatty(STDERR_FILENO) == 1; }

}  // namespace cellbench::cli
