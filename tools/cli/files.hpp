#pragma once
// File plumbing for the command-line tool: read whole files, write outputs atomically (never a partial
// output file), and load recordings / parameter sets with errors that name the file.
#include <filesystem>
#include <functional>
#include <initializer_list>
#include <ostream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

namespace cellbench::cli {

// Text files only: refuses binary data (a NUL byte), a line longer than max_line_bytes and files larger than
// kMaxInputFileBytes, each as soon as it is seen (InputError naming the file and line).
inline constexpr std::size_t kMaxInputFileBytes = std::size_t{1} << 30;
std::string read_file(const std::filesystem::path& path,
                      std::size_t max_line_bytes = protocol::csv::kMaxRecordBytes);

// Warnings for what the BDF reader accepted but the user must know (repairs, dropped values, gaps, a cut end).
void warn_bdf_report(const std::string& source, const protocol::BdfReadReport& report);

// Writes through a temporary file in the same folder and renames it into place when writer returns, so a
// failed command leaves no half-written output behind.
void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer);
void write_json_file(const std::filesystem::path& path, const nlohmann::json& j);

// The output files of one command, all or none. The constructor checks, before any work, that every given
// (non-empty) path can be an output (its folder exists, it is not a folder). write() puts the content in a
// temporary file beside its destination; commit() renames them all into place. Destroyed without commit()
// (the command failed), it removes the temporary files: a failed command leaves no output behind, not even
// the ones it could write, and output files that existed before are unchanged.
class OutputFiles {
public:
    explicit OutputFiles(std::initializer_list<std::filesystem::path> paths = {});
    ~OutputFiles();
    OutputFiles(const OutputFiles&) = delete;
    OutputFiles& operator=(const OutputFiles&) = delete;

    void write(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer);
    void write_json(const std::filesystem::path& path, const nlohmann::json& j);
    void commit();

private:
    struct Staged {
        std::filesystem::path tmp, path;
    };
    std::vector<Staged> staged_;
};

// A recording in BDF CSV or a Neware record export (recognised from the header).
Recording load_recording(const std::filesystem::path& path);
estimator::ParameterSet load_params(const std::filesystem::path& path);
nlohmann::json parse_json_file(const std::filesystem::path& path);

// True when stderr is a terminal (progress lines are shown only then).
bool stderr_is_terminal();

}  // namespace cellbench::cli
