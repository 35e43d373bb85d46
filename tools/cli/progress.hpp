#pragma once
// The progress line of long offline commands (fit, diagnose): one line on stderr rewritten in place with
// "\r", only when stderr is a terminal. Piped or redirected, it writes nothing at all (no "\r", no escape
// sequences), so logs and scripts stay clean.
#include <cstdio>
#include <mutex>
#include <string>
#include <string_view>

#include "cellbench/estimator/progress.hpp"

namespace cellbench::cli {

class ProgressLine {
public:
    // `label` prefixes the line ("fit"); enabled = show it (default: stderr is a terminal).
    explicit ProgressLine(std::string label);
    ProgressLine(std::string label, bool enabled, std::FILE* out = stderr);
    ~ProgressLine();  // finish()
    ProgressLine(const ProgressLine&) = delete;
    ProgressLine& operator=(const ProgressLine&) = delete;

    // Thread-safe. Redraws when the shown percentage or the stage changes.
    void update(double fraction, std::string_view stage);
    // Erases the line (the results follow on a clean line). Idempotent.
    void finish();
    // A callback for the estimator's options (refers to this object).
    estimator::Progress callback();

    // The text of the line, without control characters: "fit  37 % [#######.............] pulse sets 12/40".
    static std::string render(std::string_view label, double fraction, std::string_view stage);

private:
    std::string label_;
    bool enabled_;
    std::FILE* out_;
    std::mutex m_;
    int last_percent_ = -1;
    std::string last_stage_;
    bool drawn_ = false;
};

}  // namespace cellbench::cli
