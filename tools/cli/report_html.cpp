#include "cli/report_html.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>

namespace cellbench::cli {

namespace {

std::string fmt(const char* f, double x) {
    char b[64];
    std::snprintf(b, sizeof b, f, x);
    return b;
}

struct Series {
    std::string label, color;
    std::vector<double> y;  // same length as t; NaN = gap
};

// Min/max per pixel bucket, so that spikes survive the decimation (the estimator's decimate_rows, which the
// daemon's Diagnosis page uses too).
std::vector<std::pair<double, double>> decimate(const std::vector<double>& t, const std::vector<double>& y, int buckets) {
    std::vector<std::pair<double, double>> pts;
    for (const std::size_t k : estimator::decimate_rows(t, {&y}, 2 * static_cast<std::size_t>(buckets)))
        pts.emplace_back(t[k], y[k]);
    return pts;
}

std::string chart(const std::string& title, const std::string& unit, const std::vector<double>& t,
                  const std::vector<Series>& series) {
    const int w = 960, h = 240, ml = 60, mr = 10, mt = 24, mb = 30;
    if (t.empty()) return {};
    const double t0 = t.front(), t1 = std::max(t.back(), t0 + 1e-9);
    double ymin = INFINITY, ymax = -INFINITY;
    for (const auto& s : series)
        for (double v : s.y)
            if (std::isfinite(v)) ymin = std::min(ymin, v), ymax = std::max(ymax, v);
    if (!std::isfinite(ymin)) return {};
    if (ymax - ymin < 1e-9) ymax = ymin + 1.0;
    const double pad = 0.05 * (ymax - ymin);
    ymin -= pad;
    ymax += pad;
    auto X = [&](double x) { return ml + (x - t0) / (t1 - t0) * (w - ml - mr); };
    auto Y = [&](double y) { return mt + (ymax - y) / (ymax - ymin) * (h - mt - mb); };
    std::ostringstream o;
    o << "<svg viewBox='0 0 " << w << ' ' << h << "' width='100%' role='img' aria-label='" << html_escape(title) << "'>";
    o << "<text x='" << ml << "' y='16' class='title'>" << html_escape(title) << " (" << html_escape(unit) << ")</text>";
    for (int k = 0; k <= 4; ++k) {
        const double yv = ymin + (ymax - ymin) * k / 4.0;
        o << "<line x1='" << ml << "' x2='" << w - mr << "' y1='" << Y(yv) << "' y2='" << Y(yv) << "' class='grid'/>";
        o << "<text x='" << ml - 4 << "' y='" << Y(yv) + 4 << "' class='tick' text-anchor='end'>" << fmt("%.4g", yv) << "</text>";
        const double xv = t0 + (t1 - t0) * k / 4.0;
        o << "<text x='" << X(xv) << "' y='" << h - 8 << "' class='tick' text-anchor='middle'>" << fmt("%.0f s", xv) << "</text>";
    }
    int lx = w - mr - 330;
    for (const auto& s : series) {
        const auto pts = decimate(t, s.y, 900);
        if (pts.empty()) continue;
        o << "<polyline fill='none' stroke='" << s.color << "' stroke-width='1' points='";
        for (const auto& [x, y] : pts) o << fmt("%.1f", X(x)) << ',' << fmt("%.1f", Y(y)) << ' ';
        o << "'/>";
        o << "<rect x='" << lx << "' y='8' width='10' height='3' fill='" << s.color << "'/><text x='" << lx + 14
          << "' y='13' class='tick'>" << html_escape(s.label) << "</text>";
        lx += 110;
    }
    o << "</svg>";
    return o.str();
}

std::string rms_cell(const std::optional<double>& x, double scale, const char* unit) {
    return x ? fmt("%.3f", *x * scale) + " " + unit : "-";
}

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

std::string render_diagnosis_report(const estimator::Diagnosis& d, const Recording& rec, const std::string& source) {
    std::ostringstream o;
    o << "<!doctype html><html lang='en'><head><meta charset='utf-8'><title>cellbench diagnosis: "
      << html_escape(source) << "</title><style>"
      << "body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1000px;color:#222}"
      << "h1{font-size:20px}h2{font-size:16px;margin-top:28px}table{border-collapse:collapse;width:100%}"
      << "td,th{border-bottom:1px solid #ddd;padding:4px 6px;text-align:left;vertical-align:top}"
      << ".sig{color:#0a6;font-weight:600}.no{color:#888}.title{font:600 12px sans-serif}"
      << ".tick{font:11px sans-serif;fill:#555}.grid{stroke:#eee}.bar{fill:#c33}.summary{background:#f5f5f0;padding:10px}"
      << "</style></head><body>";
    o << "<h1>Diagnosis of " << html_escape(source) << "</h1>";
    o << "<p class='summary'>" << html_escape(d.summary) << "</p>";

    o << "<h2>Errors (RMS, simulated minus measured)</h2><table><tr><th></th><th>voltage</th><th>surface temperature</th>"
         "<th>heat flux</th></tr>";
    o << "<tr><td>baseline</td><td>" << rms_cell(d.baseline.voltage_v, 1e3, "mV") << "</td><td>"
      << rms_cell(d.baseline.temperature_c, 1, "degC") << "</td><td>" << rms_cell(d.baseline.heat_flux_w, 1, "W") << "</td></tr>";
    o << "<tr><td>improved (" << html_escape(d.accepted.empty() ? std::string("nothing accepted") : [&] {
        std::string s;
        for (const auto& a : d.accepted) s += (s.empty() ? "" : " + ") + a;
        return s;
    }()) << ")</td><td>" << rms_cell(d.improved.voltage_v, 1e3, "mV") << "</td><td>"
      << rms_cell(d.improved.temperature_c, 1, "degC") << "</td><td>" << rms_cell(d.improved.heat_flux_w, 1, "W")
      << "</td></tr></table>";

    o << "<h2>Traces</h2>";
    const double area = d.improved_params.thermal.area_m2;
    std::vector<double> q_meas;
    if (rec.has_heat_flux())
        for (double q : rec.heat_flux_w_per_m2) q_meas.push_back(q * area);
    o << chart("Voltage", "V", rec.time_s,
               {{"measured", "#222", rec.voltage_v}, {"baseline", "#d33", d.baseline_trace.voltage_v},
                {"improved", "#27c", d.improved_trace.voltage_v}});
    if (rec.has_surface())
        o << chart("Surface temperature", "degC", rec.time_s,
                   {{"measured", "#222", rec.surface_c}, {"baseline", "#d33", d.baseline_trace.temperature_c},
                    {"improved", "#27c", d.improved_trace.temperature_c}});
    if (rec.has_heat_flux())
        o << chart("Heat flow out (whole surface)", "W", rec.time_s,
                   {{"measured", "#222", q_meas}, {"baseline", "#d33", d.baseline_trace.heat_flow_out_w},
                    {"improved", "#27c", d.improved_trace.heat_flow_out_w}});
    {
        std::vector<double> eb(rec.size()), ei(rec.size());
        for (std::size_t k = 0; k < rec.size(); ++k) {
            eb[k] = d.baseline_trace.voltage_v[k] - rec.voltage_v[k];
            ei[k] = d.improved_trace.voltage_v[k] - rec.voltage_v[k];
        }
        o << chart("Voltage error", "V", rec.time_s, {{"baseline", "#d33", eb}, {"improved", "#27c", ei}});
    }

    o << "<h2>Where the voltage error concentrates (baseline)</h2><table><tr><th>dimension</th><th>condition</th>"
         "<th>share of squared error</th><th>share of time</th><th>RMS</th><th>bias</th><th>temperature RMS</th></tr>";
    for (const auto& c : d.breakdown) {
        const int bar = static_cast<int>(std::round(200 * c.share_of_voltage_error));
        o << "<tr><td>" << html_escape(c.dimension) << "</td><td>" << html_escape(c.condition) << "</td><td><svg width='210' "
          << "height='12'><rect class='bar' width='" << bar << "' height='12'/></svg> " << fmt("%.1f %%", 100 * c.share_of_voltage_error)
          << "</td><td>" << fmt("%.1f %%", 100 * c.time_share) << "</td><td>" << fmt("%.1f mV", c.voltage_rms_v * 1e3)
          << "</td><td>" << fmt("%+.1f mV", c.voltage_bias_v * 1e3) << "</td><td>"
          << (c.temperature_rms_c ? fmt("%.2f degC", *c.temperature_rms_c) : std::string("-")) << "</td></tr>";
    }
    o << "</table>";

    o << "<h2>Candidate physics</h2><table><tr><th>effect</th><th>verdict</th><th>held-out error removed</th>"
         "<th>blocks improved</th><th>&Delta;BIC</th><th>parameters</th><th>RMS with it</th><th>explanation</th></tr>";
    for (const auto& f : d.findings) {
        o << "<tr><td>" << html_escape(f.effect) << "</td><td class='" << (f.significant ? "sig'>significant" : "no'>not significant")
          << "</td><td>" << fmt("%.1f %%", 100 * f.score) << "</td><td>" << f.folds_improved << "</td><td>"
          << fmt("%.1f", f.delta_bic) << "</td><td>" << html_escape(f.parameters.dump()) << "</td><td>"
          << rms_cell(f.improved.voltage_v, 1e3, "mV") << "<br>" << rms_cell(f.improved.temperature_c, 1, "degC") << "<br>"
          << rms_cell(f.improved.heat_flux_w, 1, "W") << "</td><td>" << html_escape(f.explanation) << "</td></tr>";
    }
    o << "</table><p class='no'>Significant: removes at least 25 % of the error on held-out time blocks on average, improves "
         "all but one block, and lowers BIC by more than 10. Generated by cellbench.</p></body></html>\n";
    return o.str();
}

}  // namespace cellbench::cli
