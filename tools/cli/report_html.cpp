#include "cli/report_html.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <map>
#include <sstream>
#include <utility>
#include <vector>

#include "cellbench/core/version.hpp"

namespace cellbench::cli {

namespace {

std::string fmt(const char* f, double x) {
    char b[64];
    std::snprintf(b, sizeof b, f, x);
    return b;
}

// Tick values 1-2-5 x 10^k covering [lo, hi] with about `count` intervals.
std::vector<double> nice_ticks(double lo, double hi, int count, double& step) {
    const double raw = (hi - lo) / std::max(1, count);
    const double mag = std::pow(10.0, std::floor(std::log10(raw)));
    const double r = raw / mag;
    step = (r <= 1 ? 1 : r <= 2 ? 2 : r <= 5 ? 5 : 10) * mag;
    std::vector<double> t;
    for (double v = std::ceil(lo / step - 1e-9) * step; v <= hi + 1e-9 * step; v += step) t.push_back(std::abs(v) < step * 1e-9 ? 0.0 : v);
    return t;
}

// A tick label with just the decimals the step needs.
std::string tick_label(double v, double step) {
    const int decimals = std::clamp(static_cast<int>(-std::floor(std::log10(step) + 1e-9)), 0, 6);
    char b[48];
    std::snprintf(b, sizeof b, "%.*f", decimals, v);
    std::string s = b;
    if (s == "-0" || s.find_first_not_of("-0.") == std::string::npos) s = "0";
    return s;
}

struct Series {
    std::string label, color;
    std::vector<double> y;  // same length as t; NaN = gap
    bool dashed = false;
};

// Min/max per pixel bucket, so that spikes survive the decimation (the estimator's decimate_rows, which the
// daemon's Diagnosis page uses too).
std::vector<std::pair<double, double>> decimate(const std::vector<double>& t, const std::vector<double>& y, int buckets) {
    std::vector<std::pair<double, double>> pts;
    for (const std::size_t k : estimator::decimate_rows(t, {&y}, 2 * static_cast<std::size_t>(buckets)))
        if (k < y.size() && std::isfinite(y[k])) pts.emplace_back(t[k], y[k]);
    return pts;
}

// One chart: title, labelled axes (y: quantity / unit; x: test time in s, min or h), 1-2-5 ticks, a legend
// above the plot area.
std::string chart(const std::string& title, const std::string& y_label, const std::vector<double>& t_s,
                  const std::vector<Series>& series) {
    const int w = 960, h = 260, ml = 72, mr = 12, mt = 40, mb = 44;
    if (t_s.empty()) return {};
    const double span_s = t_s.back() - t_s.front();
    const double t_div = span_s > 3 * 3600 ? 3600.0 : span_s > 600 ? 60.0 : 1.0;
    const char* t_unit = t_div == 3600.0 ? "h" : t_div == 60.0 ? "min" : "s";
    std::vector<double> t(t_s.size());
    for (std::size_t k = 0; k < t.size(); ++k) t[k] = t_s[k] / t_div;
    const double t0 = t.front(), t1 = std::max(t.back(), t0 + 1e-9);
    double ymin = INFINITY, ymax = -INFINITY;
    for (const auto& s : series)
        for (double v : s.y)
            if (std::isfinite(v)) ymin = std::min(ymin, v), ymax = std::max(ymax, v);
    if (!std::isfinite(ymin)) return {};
    if (ymax - ymin < 1e-9) ymin -= 0.5, ymax += 0.5;
    const double pad = 0.05 * (ymax - ymin);
    ymin -= pad;
    ymax += pad;
    auto X = [&](double x) { return ml + (x - t0) / (t1 - t0) * (w - ml - mr); };
    auto Y = [&](double y) { return mt + (ymax - y) / (ymax - ymin) * (h - mt - mb); };
    std::ostringstream o;
    o << "<figure class='chart'><svg viewBox='0 0 " << w << ' ' << h << "' role='img' aria-label='" << html_escape(title)
      << "'>";
    o << "<text x='" << ml << "' y='16' class='title'>" << html_escape(title) << "</text>";
    double ystep = 1, xstep = 1;
    for (double yv : nice_ticks(ymin, ymax, 5, ystep)) {
        o << "<line x1='" << ml << "' x2='" << w - mr << "' y1='" << fmt("%.1f", Y(yv)) << "' y2='" << fmt("%.1f", Y(yv))
          << "' class='grid'/>";
        o << "<text x='" << ml - 6 << "' y='" << fmt("%.1f", Y(yv) + 4) << "' class='tick' text-anchor='end'>"
          << tick_label(yv, ystep) << "</text>";
    }
    for (double xv : nice_ticks(t0, t1, 8, xstep)) {
        o << "<line x1='" << fmt("%.1f", X(xv)) << "' x2='" << fmt("%.1f", X(xv)) << "' y1='" << h - mb << "' y2='"
          << h - mb + 4 << "' class='axis'/>";
        o << "<text x='" << fmt("%.1f", X(xv)) << "' y='" << h - mb + 17 << "' class='tick' text-anchor='middle'>"
          << tick_label(xv, xstep) << "</text>";
    }
    o << "<rect x='" << ml << "' y='" << mt << "' width='" << w - ml - mr << "' height='" << h - mt - mb
      << "' class='frame'/>";
    o << "<text x='" << (ml + w - mr) / 2 << "' y='" << h - 6 << "' class='axislabel' text-anchor='middle'>Test time / "
      << t_unit << "</text>";
    o << "<text transform='translate(16 " << (mt + h - mb) / 2 << ") rotate(-90)' class='axislabel' text-anchor='middle'>"
      << html_escape(y_label) << "</text>";
    int lx = ml;
    for (const auto& s : series) {
        const auto pts = decimate(t, s.y, 900);
        if (pts.empty()) continue;
        // Gaps (NaN) split the line.
        o << "<path fill='none' stroke='" << s.color << "' stroke-width='1.2'" << (s.dashed ? " stroke-dasharray='4 3'" : "")
          << " d='";
        bool pen = false;
        double prev_t = pts.front().first;
        const double gap = (t1 - t0) / 200.0;
        for (const auto& [x, y] : pts) {
            o << (pen && x - prev_t < gap ? 'L' : 'M') << fmt("%.1f", X(x)) << ',' << fmt("%.1f", Y(y)) << ' ';
            pen = true;
            prev_t = x;
        }
        o << "'/>";
        o << "<rect x='" << lx << "' y='25' width='14' height='3' fill='" << s.color << "'/><text x='" << lx + 18
          << "' y='30' class='tick'>" << html_escape(s.label) << "</text>";
        lx += 30 + 7 * static_cast<int>(s.label.size());
    }
    o << "</svg></figure>";
    return o.str();
}

std::string rms_cell(const std::optional<double>& x, double scale, int decimals, const char* unit) {
    if (!x) return "<span class='muted'>not measured</span>";
    char b[64];
    std::snprintf(b, sizeof b, "%.*f %s", decimals, *x * scale, unit);
    return b;
}

std::string rms_cell_json(const nlohmann::json& j, const char* key, double scale, int decimals, const char* unit) {
    if (!j.is_object() || !j.contains(key) || !j[key].is_number()) return rms_cell(std::nullopt, scale, decimals, unit);
    return rms_cell(j[key].get<double>(), scale, decimals, unit);
}

const std::map<std::string, std::string>& effect_words() {
    static const std::map<std::string, std::string> m = {
        {"entropic_heat", "Reversible (entropic) heat I·T·dU/dT"},
        {"thermal_second_order", "Core–surface temperature difference (two thermal nodes)"},
        {"resistance_temperature", "Resistances depend on cell temperature (Arrhenius)"},
        {"resistance_current", "Charge-transfer overpotential non-linear in current (Butler–Volmer)"},
        {"ocv_hysteresis", "OCV hysteresis (depends on the last current direction)"},
        {"extra_rc", "A slow diffusion time constant beyond the two RC pairs"},
        {"capacity_error", "Usable capacity differs from the parameter set's"},
        {"series_resistance_offset", "Extra series resistance (harness, contacts)"},
        {"heat_flux_sensor_gain", "Heat flux sensor sensitivity or coverage differs"},
        {"ambient_drift", "Ambient (chamber) temperature not constant"},
        {"ocv_offset", "OCV table off (re-identified on this recording)"},
        {"ocv_band", "OCV table off in one SOC band (re-identified on this recording)"},
        {"resistance_band", "Resistance tables off in one SOC band (re-identified on this recording)"},
        {"thermal_parameters", "Lumped thermal parameters off (C_th, R_th re-identified)"},
    };
    return m;
}

const std::map<std::string, std::string>& dimension_words() {
    static const std::map<std::string, std::string> m = {
        {"direction", "Current direction"},   {"c_rate", "C-rate"},
        {"soc", "State of charge"},           {"temperature_rise", "Temperature rise since the start"},
        {"since_step", "Time since a current step"}, {"throughput", "Charge throughput"},
        {"combined", "Combined conditions"},
    };
    return m;
}

std::string kind_words(const std::string& kind) {
    if (kind == "physics_missing") return "physics missing";
    if (kind == "parameters_wrong") return "parameters wrong";
    return kind;
}

std::string utc_now() {
    const std::time_t now = std::time(nullptr);
    char b[32];
    std::strftime(b, sizeof b, "%Y-%m-%d %H:%M UTC", std::gmtime(&now));
    return b;
}

const char* kStyle = R"CSS(
*{box-sizing:border-box}
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",sans-serif;margin:0 auto;padding:24px;max-width:1000px;color:#1d232a;background:#fff}
h1{font-size:22px;margin:0 0 4px}h2{font-size:17px;margin:28px 0 10px;border-bottom:2px solid #e3e7ec;padding-bottom:4px}
.meta{display:grid;grid-template-columns:max-content 1fr;gap:2px 14px;margin:10px 0 14px;font-size:13px}
.meta dt{color:#5b6672}.meta dd{margin:0;overflow-wrap:anywhere}
.summary{background:#f3f6f9;border-left:4px solid #2f6fb2;padding:10px 14px;margin:12px 0}
.notes li{color:#7a4b00;margin:4px 0}
table{border-collapse:collapse;width:100%;table-layout:auto}
td,th{border-bottom:1px solid #e3e7ec;padding:5px 8px;text-align:left;vertical-align:top;overflow-wrap:anywhere}
th{font-weight:600;color:#44505c;font-size:12.5px}td.num,th.num{text-align:right;white-space:nowrap}
.cards{display:grid;grid-template-columns:repeat(auto-fill,minmax(300px,1fr));gap:12px}
.card{border:1px solid #dde3e9;border-radius:8px;padding:12px 14px;break-inside:avoid;page-break-inside:avoid;min-width:0}
.card h3{font-size:15px;margin:0 0 2px}.card .id{font:12px ui-monospace,monospace;color:#5b6672}
.badges{margin:6px 0}.badge{display:inline-block;font-size:11.5px;border-radius:10px;padding:1px 8px;margin-right:4px;background:#eef1f4;color:#44505c}
.badge.sig{background:#dcf3e6;color:#0b6b3a;font-weight:600}.badge.no{background:#eef1f4;color:#6b7580}
.badge.wrong{background:#fdeedd;color:#8a4b00}
.card p{margin:6px 0;overflow-wrap:anywhere}.card table td,.card table th{padding:2px 4px;font-size:12.5px}
.card table td:first-child,.card table th:first-child{overflow-wrap:normal;word-break:normal}.card table td:last-child,.card table th:last-child{white-space:nowrap}
.flag{display:block;white-space:normal;text-align:left;color:#a3261b;font-size:11.5px;font-weight:600}
.evidence{font-size:12.5px;color:#44505c}
.muted{color:#8a939c}.bar{fill:#c2463a}
figure.chart{margin:8px 0 14px;break-inside:avoid;page-break-inside:avoid}
figure.chart svg{width:100%;height:auto;display:block}
.title{font:600 13px system-ui,sans-serif;fill:#1d232a}.tick{font:11px system-ui,sans-serif;fill:#44505c}
.axislabel{font:12px system-ui,sans-serif;fill:#1d232a}.grid{stroke:#edf0f3}.axis{stroke:#8a939c}.frame{fill:none;stroke:#c9d0d7}
footer{margin-top:28px;font-size:12px;color:#6b7580}
@media print{body{padding:0;max-width:none;font-size:12px}h2{break-after:avoid;page-break-after:avoid}@page{size:A4;margin:14mm}}
)CSS";

}  // namespace

std::string html_escape(const std::string& s) {
    std::string o;
    o.reserve(s.size());
    for (char c : s) {
        switch (c) {
            case '&': o += "&amp;"; break;
            case '<': o += "&lt;"; break;
            case '>': o += "&gt;"; break;
            case '"': o += "&quot;"; break;
            case '\'': o += "&#39;"; break;
            default: o += c;
        }
    }
    return o;
}

bool contains_flag(const nlohmann::json& flags, const char* flag) {
    for (const auto& f : flags)
        if (f == flag) return true;
    return false;
}

std::string round_sig(double x, int digits) {
    if (!std::isfinite(x)) return "–";
    if (x == 0.0) return "0";
    const int mag = static_cast<int>(std::floor(std::log10(std::abs(x))));
    const int decimals = std::max(0, digits - 1 - mag);
    char b[64];
    if (mag >= 6 || mag <= -5) {
        std::snprintf(b, sizeof b, "%.*e", digits - 1, x);
        return b;
    }
    std::snprintf(b, sizeof b, "%.*f", decimals, x);
    std::string s = b;
    if (s.find('.') != std::string::npos) {
        while (s.back() == '0') s.pop_back();
        if (s.back() == '.') s.pop_back();
    }
    return s;
}

std::pair<std::string, std::string> parameter_name_and_unit(const std::string& name) {
    static const std::vector<std::pair<std::string, std::string>> suffixes = {
        {"_j_per_mol", "J/mol"}, {"_v_per_k", "V/K"}, {"_k_per_w", "K/W"}, {"_j_per_k", "J/K"},
        {"_c_per_h", "°C/h"},    {"_w_per_m2", "W/m²"}, {"_per_capacity", "per capacity"}, {"_ohm", "Ω"},
        {"_m2", "m²"},           {"_s", "s"},          {"_v", "V"},     {"_a", "A"},
        {"_c", "°C"},            {"_f", "F"},          {"_w", "W"},
    };
    for (const auto& [suffix, unit] : suffixes)
        if (name.size() > suffix.size() && name.ends_with(suffix)) {
            std::string base = name.substr(0, name.size() - suffix.size());
            std::replace(base.begin(), base.end(), '_', ' ');
            return {base, unit};
        }
    std::string base = name;
    std::replace(base.begin(), base.end(), '_', ' ');
    return {base, ""};
}

std::string render_diagnosis_report(const estimator::Diagnosis& d, const Recording& rec, const ReportSources& src) {
    const nlohmann::json dj = estimator::diagnosis_to_json(d);  // the JSON users also get (kind, unexplained, ...)
    const std::string rec_name = std::filesystem::path(src.recording).filename().string();
    std::ostringstream o;
    o << "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
      << "<meta name='viewport' content='width=device-width,initial-scale=1'><title>cellbench diagnosis: "
      << html_escape(rec_name) << "</title><style>" << kStyle << "</style></head><body>";

    // Header: what produced this page.
    o << "<header><h1>Model diagnosis: " << html_escape(rec_name) << "</h1><dl class='meta'>";
    const double dur_s = rec.empty() ? 0.0 : rec.time_s.back() - rec.time_s.front();
    std::string measured = "voltage, current";
    if (rec.has_surface()) measured += ", surface temperature";
    if (rec.has_heat_flux()) measured += ", heat flux";
    if (rec.has_ambient()) measured += ", ambient temperature";
    o << "<dt>Recording</dt><dd>" << html_escape(src.recording) << " — " << rec.size() << " rows, "
      << (dur_s >= 3600 ? fmt("%.2f h", dur_s / 3600) : fmt("%.0f s", dur_s)) << "; measures " << measured << "</dd>";
    o << "<dt>Parameter set</dt><dd>" << html_escape(src.params)
      << (src.cell.empty() ? "" : " — " + html_escape(src.cell)) << "</dd>";
    o << "<dt>Date</dt><dd>" << html_escape(src.date_utc.empty() ? utc_now() : src.date_utc) << "</dd>";
    o << "<dt>Produced by</dt><dd>cellbench " << html_escape(cellbench::version_string()) << " (diagnose --report)</dd>";
    o << "</dl></header>";
    o << "<p class='summary'>" << html_escape(d.summary) << "</p>";
    // What the log warned about the recording against this parameter set (another cell's set, another temperature,
    // a logger's timing): the figures below are read with it.
    if (!d.notes.empty()) {
        o << "<h2>Read the figures with these notes</h2><ul class='notes'>";
        for (const auto& note : d.notes) o << "<li>" << html_escape(note) << "</li>";
        o << "</ul>";
    }

    o << "<h2>Model error (RMS, simulated minus measured)</h2><table><tr><th>model</th><th class='num'>voltage</th>"
         "<th class='num'>surface temperature</th><th class='num'>heat flow</th></tr>";
    o << "<tr><td>parameter set as given</td><td class='num'>" << rms_cell(d.baseline.voltage_v, 1e3, 1, "mV")
      << "</td><td class='num'>" << rms_cell(d.baseline.temperature_c, 1, 2, "°C") << "</td><td class='num'>"
      << rms_cell(d.baseline.heat_flux_w, 1, 3, "W") << "</td></tr>";
    std::string accepted;
    for (const auto& a : d.accepted) accepted += (accepted.empty() ? "" : " + ") + a;
    o << "<tr><td>with " << html_escape(accepted.empty() ? std::string("nothing accepted") : accepted)
      << "</td><td class='num'>" << rms_cell(d.improved.voltage_v, 1e3, 1, "mV") << "</td><td class='num'>"
      << rms_cell(d.improved.temperature_c, 1, 2, "°C") << "</td><td class='num'>"
      << rms_cell(d.improved.heat_flux_w, 1, 3, "W") << "</td></tr></table>";

    // Findings as cards.
    o << "<h2>Findings</h2>";
    if (dj["findings"].empty()) o << "<p class='muted'>No candidate physics was tried.</p>";
    o << "<div class='cards'>";
    for (const auto& f : dj["findings"]) {
        const std::string effect = f.value("effect", "");
        const auto words = effect_words().find(effect);
        const std::string kind = f.value("kind", std::string("physics_missing"));
        const bool sig = f.value("significant", false);
        o << "<section class='card'><h3>" << html_escape(words != effect_words().end() ? words->second : effect)
          << "</h3><div class='id'>" << html_escape(effect) << "</div><div class='badges'><span class='badge "
          << (sig ? "sig'>significant" : "no'>not significant") << "</span><span class='badge"
          << (kind == "parameters_wrong" ? " wrong" : "") << "'>" << html_escape(kind_words(kind)) << "</span></div>";
        const double score = f.value("score", 0.0);
        o << "<div class='evidence'>" << (score >= 0 ? "Removes " + fmt("%.0f %%", 100 * score) + " of the held-out error"
                                                     : "Makes the held-out error " + fmt("%.0f %%", -100 * score) + " worse")
          << "; improves " << f.value("folds_improved", 0) << " time blocks; ΔBIC "
          << fmt("%.0f", f.value("delta_bic", 0.0)) << "</div>";
        const auto& params = f.contains("parameters") && f["parameters"].is_object() ? f["parameters"] : nlohmann::json::object();
        if (!params.empty()) {
            o << "<table><tr><th>fitted parameter</th><th class='num'>value</th><th>unit</th></tr>";
            for (const auto& [name, value] : params.items()) {
                if (name.ends_with("_sd") || name.ends_with("_flags") || !value.is_number()) continue;
                const auto [label, unit] = parameter_name_and_unit(name);
                std::string shown = round_sig(value.get<double>(), 3);
                if (params.contains(name + "_sd") && params[name + "_sd"].is_number())
                    shown += " ± " + round_sig(params[name + "_sd"].get<double>(), 2);
                // The flag wraps under the value (the value itself never wraps, so a long flag on one line
                // squeezed the name column to one letter per line).
                std::string flags;
                if (params.contains(name + "_flags") && params[name + "_flags"].is_array()) {
                    for (const auto& flag : params[name + "_flags"]) {
                        if (flag == "at_bound")
                            flags += "<span class='flag'>at its search bound: not an estimate</span>";
                        else if (flag == "contradicts_characterization")
                            flags += "<span class='flag'>contradicts the characterization: beyond 5 sd of the OCV it measured</span>";
                        else if (flag == "implausible" && !contains_flag(params[name + "_flags"], "contradicts_characterization"))
                            flags += "<span class='flag'>implausible: the largest plausible size, compensating something else</span>";
                    }
                }
                o << "<tr><td>" << html_escape(label) << "</td><td class='num'>" << html_escape(shown) << flags
                  << "</td><td>" << html_escape(unit) << "</td></tr>";
            }
            o << "</table>";
        }
        const auto& imp = f.contains("improved") ? f["improved"] : nlohmann::json();
        o << "<div class='evidence'>RMS with it: " << rms_cell_json(imp, "voltage_rms_v", 1e3, 1, "mV") << " · "
          << rms_cell_json(imp, "temperature_rms_c", 1, 2, "°C") << " · " << rms_cell_json(imp, "heat_flux_rms_w", 1, 3, "W")
          << "</div>";
        // What the other recordings of the cell (diagnose --confirm) say about it.
        if (f.contains("confirmation") && f["confirmation"].is_array()) {
            if (f["confirmation"].empty() && f.contains("contradicted"))
                o << "<div class='evidence'>Not checked on the other recordings: a state of this recording, not of the cell</div>";
            for (const auto& c : f["confirmation"]) {
                const std::string verdict = c.value("verdict", "");
                const auto& b = c.contains("before") ? c["before"] : nlohmann::json();
                const auto& a = c.contains("after") ? c["after"] : nlohmann::json();
                o << "<div class='evidence'>" << (verdict == "contradicts" ? "<span class='flag'>contradicted</span> " : "")
                  << html_escape(std::filesystem::path(c.value("recording", "")).filename().string()) << ": "
                  << html_escape(verdict) << " — voltage " << rms_cell_json(b, "voltage_rms_v", 1e3, 1, "mV") << " → "
                  << rms_cell_json(a, "voltage_rms_v", 1e3, 1, "mV") << ", temperature "
                  << rms_cell_json(b, "temperature_rms_c", 1, 2, "°C") << " → " << rms_cell_json(a, "temperature_rms_c", 1, 2, "°C")
                  << ", heat flux " << rms_cell_json(b, "heat_flux_rms_w", 1, 3, "W") << " → "
                  << rms_cell_json(a, "heat_flux_rms_w", 1, 3, "W") << "</div>";
            }
        }
        o << "<p>" << html_escape(f.value("explanation", "")) << "</p></section>";
    }
    o << "</div>";
    if (dj.contains("unexplained") && dj["unexplained"].is_object()) {
        // What no finding explains: how large against the recording's own noise, where, what it correlates with,
        // and the terms a sparse regression of the residual keeps.
        const auto& u = dj["unexplained"];
        o << "<h2>Unexplained error</h2><p class='summary'><b>Not adequate:</b> " << html_escape(u.value("summary", ""))
          << "</p><table><tr><th>quantity</th><th class='num'>RMS left</th><th class='num'>noise (from rests)</th></tr>";
        const auto& r = u["rms"];
        const auto& nz = u["noise"];
        o << "<tr><td>voltage</td><td class='num'>" << rms_cell_json(r, "voltage_rms_v", 1e3, 1, "mV") << "</td><td class='num'>"
          << rms_cell_json(nz, "voltage_rms_v", 1e3, 2, "mV") << "</td></tr><tr><td>surface temperature</td><td class='num'>"
          << rms_cell_json(r, "temperature_rms_c", 1, 2, "°C") << "</td><td class='num'>"
          << rms_cell_json(nz, "temperature_rms_c", 1, 3, "°C") << "</td></tr><tr><td>heat flow</td><td class='num'>"
          << rms_cell_json(r, "heat_flux_rms_w", 1, 3, "W") << "</td><td class='num'>"
          << rms_cell_json(nz, "heat_flux_rms_w", 1, 4, "W") << "</td></tr></table>";
        if (u.contains("where") && !u["where"].empty()) {
            o << "<table><tr><th>where it remains</th><th class='num'>share of squared error</th><th class='num'>bias</th></tr>";
            for (const auto& w : u["where"])
                o << "<tr><td>" << html_escape(w.value("condition", "")) << "</td><td class='num'>"
                  << fmt("%.1f %%", 100 * w.value("share_of_voltage_error", 0.0)) << "</td><td class='num'>"
                  << fmt("%+.1f mV", 1e3 * w.value("voltage_bias_v", 0.0)) << "</td></tr>";
            o << "</table>";
        }
        for (const char* q : {"voltage", "temperature"}) {
            if (!u.contains("sparse_model") || !u["sparse_model"].contains(q)) continue;
            const auto& m = u["sparse_model"][q];
            if (!m.contains("terms") || m["terms"].empty()) continue;
            o << "<p>Sparse model of the " << q << " residual (explains " << fmt("%.0f %%", 100 * m.value("explained", 0.0))
              << " of its variance):</p><table><tr><th>term</th><th>suggests</th><th class='num'>coefficient</th>"
                 "<th class='num'>share</th></tr>";
            for (const auto& t : m["terms"])
                o << "<tr><td>" << html_escape(t.value("term", "")) << "</td><td>" << html_escape(t.value("meaning", ""))
                  << "</td><td class='num'>" << html_escape(round_sig(t.value("coefficient", 0.0), 3)) << "</td><td class='num'>"
                  << fmt("%.0f %%", 100 * t.value("share", 0.0)) << "</td></tr>";
            o << "</table>";
        }
    }

    // Traces.
    o << "<h2>Traces</h2>";
    const double area = d.improved_params.thermal.area_m2;
    o << chart("Terminal voltage", "Voltage / V", rec.time_s,
               {{"measured", "#1d232a", rec.voltage_v}, {"parameter set", "#c2463a", d.baseline_trace.voltage_v, true},
                {"with accepted effects", "#2f6fb2", d.improved_trace.voltage_v}});
    {
        std::vector<double> eb(rec.size(), NAN), ei(rec.size(), NAN);
        for (std::size_t k = 0; k < rec.size(); ++k) {
            if (k < d.baseline_trace.voltage_v.size()) eb[k] = (d.baseline_trace.voltage_v[k] - rec.voltage_v[k]) * 1e3;
            if (k < d.improved_trace.voltage_v.size()) ei[k] = (d.improved_trace.voltage_v[k] - rec.voltage_v[k]) * 1e3;
        }
        o << chart("Voltage error (simulated minus measured)", "Error / mV", rec.time_s,
                   {{"parameter set", "#c2463a", eb}, {"with accepted effects", "#2f6fb2", ei}});
    }
    if (rec.has_surface())
        o << chart("Surface temperature", "Temperature / °C", rec.time_s,
                   {{"measured", "#1d232a", rec.surface_c}, {"parameter set", "#c2463a", d.baseline_trace.temperature_c, true},
                    {"with accepted effects", "#2f6fb2", d.improved_trace.temperature_c}});
    if (rec.has_heat_flux()) {
        std::vector<double> q_meas;
        for (double q : rec.heat_flux_w_per_m2) q_meas.push_back(q * area);
        o << chart("Heat flow out of the cell (heat flux × " + round_sig(area * 1e4, 3) + " cm² surface)",
                   "Heat flow / W", rec.time_s,
                   {{"measured", "#1d232a", q_meas}, {"parameter set", "#c2463a", d.baseline_trace.heat_flow_out_w, true},
                    {"with accepted effects", "#2f6fb2", d.improved_trace.heat_flow_out_w}});
    }

    // Residual by condition.
    o << "<h2>Where the voltage error sits (parameter set as given)</h2><table><tr><th>condition</th>"
         "<th class='num'>share of squared error</th><th class='num'>share of time</th><th class='num'>RMS</th>"
         "<th class='num'>bias</th><th class='num'>temperature RMS</th></tr>";
    std::vector<std::string> order;
    for (const auto& c : d.breakdown)
        if (std::find(order.begin(), order.end(), c.dimension) == order.end()) order.push_back(c.dimension);
    for (const auto& dim : order) {
        const auto words = dimension_words().find(dim);
        o << "<tr><th colspan='6'>" << html_escape(words != dimension_words().end() ? words->second : dim) << "</th></tr>";
        for (const auto& c : d.breakdown) {
            if (c.dimension != dim) continue;
            const int bar = static_cast<int>(std::round(80 * c.share_of_voltage_error));
            o << "<tr><td>" << html_escape(c.condition) << "</td><td class='num'><svg width='82' height='10'><rect class='bar' "
              << "width='" << bar << "' height='10'/></svg> " << fmt("%.1f %%", 100 * c.share_of_voltage_error)
              << "</td><td class='num'>" << fmt("%.1f %%", 100 * c.time_share) << "</td><td class='num'>"
              << fmt("%.1f mV", c.voltage_rms_v * 1e3) << "</td><td class='num'>" << fmt("%+.1f mV", c.voltage_bias_v * 1e3)
              << "</td><td class='num'>"
              << (c.temperature_rms_c ? fmt("%.2f °C", *c.temperature_rms_c) : std::string("<span class='muted'>–</span>"))
              << "</td></tr>";
        }
    }
    o << "</table>";
    o << "<footer>A finding is significant when it removes at least 25 % of the error on held-out interleaved time "
         "blocks on average, improves all but one fold, and lowers BIC by more than 10. Kinds: physics missing (an "
         "effect of the catalogue) or parameters wrong (part of the parameter set re-identified on this recording). Errors are simulated minus measured; heat "
         "flow is the heat flux density over the whole cell surface. Generated by cellbench "
      << html_escape(cellbench::version_string()) << ".</footer></body></html>\n";
    return o.str();
}

}  // namespace cellbench::cli
