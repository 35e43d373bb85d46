#pragma once
// File plumbing for the command-line tool: read whole files, write outputs atomically (never a partial
// output file), and load recordings / parameter sets with errors that name the file.
#include <filesystem>
#include <functional>
#include <ostream>
#include <string>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"

namespace cellbench::cli {

std::string read_file(const std::filesystem::path& path);

// Writes through a temporary file in the same folder and renames it into place when writer returns, so a
// failed command leaves no half-written output behind.
void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer);
void write_json_file(const std::filesystem::path& path, const nlohmann::json& j);

// A recording in BDF CSV or a Neware record export (recognised from the header).
Recording load_recording(const std::filesystem::path& path);
estimator::ParameterSet load_params(const std::filesystem::path& path);
nlohmann::json parse_json_file(const std::filesystem::path& path);

// True when stderr is a terminal (progress lines are shown only then).
bool stderr_is_terminal();

}  // namespace cellbench::cli
