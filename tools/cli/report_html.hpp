#pragma once
// The `diagnose --report` page: one self-contained HTML file (inline SVG and CSS, no script, no network).
#include <string>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/diagnose.hpp"

namespace cellbench::cli {

std::string render_diagnosis_report(const estimator::Diagnosis& d, const Recording& rec, const std::string& source);

// Escapes text for HTML element content and attribute values.
std::string html_escape(const std::string& s);

}  // namespace cellbench::cli
