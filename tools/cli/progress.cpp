#include "cli/progress.hpp"

#include <algorithm>
#include <cmath>

#include "cli/files.hpp"

namespace cellbench::cli {

ProgressLine::ProgressLine(std::string label) : ProgressLine(std::move(label), stderr_is_terminal()) {}

ProgressLine::ProgressLine(std::string label, bool enabled, std::FILE* out)
    : label_(std::move(label)), enabled_(enabled), out_(out) {}

ProgressLine::~ProgressLine() { finish(); }

std::string ProgressLine::render(std::string_view label, double fraction, std::string_view stage) {
    constexpr int kWidth = 20;
    const double f = std::isfinite(fraction) ? std::clamp(fraction, 0.0, 1.0) : 0.0;
    const int percent = static_cast<int>(std::floor(f * 100.0));
    const int filled = static_cast<int>(std::floor(f * kWidth));
    std::string line(label);
    char pct[16];
    std::snprintf(pct, sizeof pct, " %3d %% [", percent);
    line += pct;
    line.append(static_cast<std::size_t>(filled), '#');
    line.append(static_cast<std::size_t>(kWidth - filled), '.');
    line += "] ";
    // Keep the line shorter than a narrow terminal (80 columns) so "\r" rewrites it instead of wrapping.
    line += stage.substr(0, std::min<std::size_t>(stage.size(), 44));
    return line;
}

void ProgressLine::update(double fraction, std::string_view stage) {
    if (!enabled_) return;
    std::lock_guard lock(m_);
    const int percent = static_cast<int>(std::floor(std::clamp(std::isfinite(fraction) ? fraction : 0.0, 0.0, 1.0) * 100));
    if (percent == last_percent_ && stage == last_stage_) return;
    last_percent_ = percent;
    last_stage_ = std::string(stage);
    // "\r" back to the start, the line, then erase whatever a longer previous line left (ESC [ K).
    std::fprintf(out_, "\r%s\033[K", render(label_, fraction, stage).c_str());
    std::fflush(out_);
    drawn_ = true;
}

void ProgressLine::finish() {
    if (!enabled_) return;
    std::lock_guard lock(m_);
    if (!drawn_) return;
    std::fprintf(out_, "\r\033[K");
    std::fflush(out_);
    drawn_ = false;
    last_percent_ = -1;
    last_stage_.clear();
}

estimator::Progress ProgressLine::callback() {
    return [this](double fraction, std::string_view stage) { update(fraction, stage); };
}

}  // namespace cellbench::cli
