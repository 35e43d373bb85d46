#pragma once
// The `diagnose --report` page: one self-contained HTML file (inline SVG and CSS, no script, no network) that a
// modelling engineer can forward or print to PDF (A4, cards and charts kept whole on a page). Header: recording,
// parameter set, date, cellbench version. Findings as cards (effect in words, kind, verdict, evidence, fitted
// parameters with units and uncertainty where known, rounded). Traces of voltage, voltage error (mV), surface
// temperature and heat flow, with labelled axes. The residual-by-condition table.
#include <string>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/diagnose.hpp"

namespace cellbench::cli {

struct ReportSources {
    std::string recording;   // path as given on the command line
    std::string params;      // parameter set path
    std::string cell;        // the parameter set's cell name
    std::string date_utc;    // "2026-11-23 09:50 UTC"; empty: now
};

std::string render_diagnosis_report(const estimator::Diagnosis& d, const Recording& rec, const ReportSources& sources);

// Escapes text for HTML element content and attribute values.
std::string html_escape(const std::string& s);

// A number with `digits` significant digits, without float noise or trailing zeros ("25400", "0.00734", "3.1").
std::string round_sig(double x, int digits = 3);

// "activation_energy_j_per_mol" -> {"activation energy", "J/mol"}: a parameter name with its unit suffix split
// off and written as a unit ("" when dimensionless).
std::pair<std::string, std::string> parameter_name_and_unit(const std::string& name);

}  // namespace cellbench::cli
