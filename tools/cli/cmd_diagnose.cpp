#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

#include "cellbench/estimator/diagnose.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"
#include "cli/progress.hpp"
#include "cli/report_html.hpp"

namespace cellbench::cli {

int run_diagnose(const DiagnoseCliOptions& o) {
    OutputFiles outputs({o.json, o.improved, o.report});  // folders checked before the work, all written or none
    const auto params = load_params(o.params);
    const auto rec = load_recording(o.recording);
    std::vector<Recording> confirm;
    for (const auto& path : o.confirm) confirm.push_back(load_recording(path));
    estimator::DiagnoseOptions opt;
    opt.effects = o.effects;
    for (const auto& c : confirm) opt.confirm.push_back(&c);
    if (o.voltage_floor_mv) opt.voltage_floor_v = *o.voltage_floor_mv * 1e-3;
    if (o.temperature_floor_c) opt.temperature_floor_c = *o.temperature_floor_c;
    if (o.heat_flux_floor_w) opt.heat_flux_floor_w = *o.heat_flux_floor_w, opt.scale_heat_flux_floor_with_area = false;
    ProgressLine progress("diagnose");  // on a terminal only
    opt.progress = progress.callback();
    const auto d = estimator::diagnose(params, rec, opt);
    progress.finish();
    for (const auto& note : d.notes) spdlog::warn("{}", note);

    auto q = [](const estimator::QuantityRms& r) {
        return fmt::format("voltage {}, temperature {}, heat flux {}",
                           r.voltage_v ? fmt::format("{:.2f} mV", *r.voltage_v * 1e3) : "-",
                           r.temperature_c ? fmt::format("{:.3f} degC", *r.temperature_c) : "-",
                           r.heat_flux_w ? fmt::format("{:.3f} W", *r.heat_flux_w) : "-");
    };
    std::printf("baseline RMS: %s\n", q(d.baseline).c_str());
    std::printf("where the voltage error concentrates:\n");
    for (const auto& w : d.where)
        std::printf("  %-40s %5.1f %% of the squared error in %4.1f %% of the time (RMS %.1f mV, bias %+.1f mV)\n",
                    w.condition.c_str(), 100 * w.share_of_voltage_error, 100 * w.time_share, w.voltage_rms_v * 1e3,
                    w.voltage_bias_v * 1e3);
    std::printf("findings (score = share of the held-out error removed):\n");
    for (const auto& f : d.findings)
        std::printf("  %-26s %s score %6.3f  folds %zu  dBIC %8.1f%s\n", f.effect.c_str(),
                    f.significant ? "SIGNIFICANT" : "           ", f.score, f.folds_improved, f.delta_bic,
                    f.implausible ? "  implausible" : "");
    if (!confirm.empty()) {
        // What the other recordings say, for every candidate that helped here.
        std::printf("on the other recordings (--confirm; RMS with the current base -> with the finding):\n");
        for (const auto& f : d.findings) {
            if (f.score <= 0 && !f.significant) continue;
            if (f.confirmation.empty()) {
                std::printf("  %-26s not checked: a state of this recording, not of the cell\n", f.effect.c_str());
                continue;
            }
            for (const auto& c : f.confirmation) {
                auto v = [](const std::optional<double>& b, const std::optional<double>& a, double scale, const char* unit) {
                    if (!b || !a) return std::string("-");
                    char text[96];
                    std::snprintf(text, sizeof text, "%.3g -> %.3g %s", *b * scale, *a * scale, unit);
                    return std::string(text);
                };
                std::printf("  %-26s %-11s %s: voltage %s, temperature %s, heat flux %s\n", f.effect.c_str(),
                            c.verdict.c_str(), std::filesystem::path(c.recording).filename().c_str(),
                            v(c.before.voltage_v, c.after.voltage_v, 1e3, "mV").c_str(),
                            v(c.before.temperature_c, c.after.temperature_c, 1, "degC").c_str(),
                            v(c.before.heat_flux_w, c.after.heat_flux_w, 1, "W").c_str());
            }
        }
    }
    for (const auto& f : d.findings)
        if (f.significant) std::printf("- %s: %s\n", f.effect.c_str(), f.explanation.c_str());
    std::printf("%s\n", d.summary.c_str());
    std::printf("improved RMS: %s\n", q(d.improved).c_str());

    if (!o.json.empty()) outputs.write_json(o.json, estimator::diagnosis_to_json(d));
    if (!o.improved.empty()) outputs.write_json(o.improved, d.improved_params.to_json());
    if (!o.report.empty())
        outputs.write(o.report, [&](std::ostream& out) {
            out << render_diagnosis_report(d, rec, {o.recording, o.params, params.cell, {}});
        });
    outputs.commit();
    return 0;
}

}  // namespace cellbench::cli
