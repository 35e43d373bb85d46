#include <cstdio>

#include <spdlog/spdlog.h>

#include "cellbench/estimator/diagnose.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"
#include "cli/report_html.hpp"

namespace cellbench::cli {

int run_diagnose(const DiagnoseCliOptions& o) {
    const auto params = load_params(o.params);
    const auto rec = load_recording(o.recording);
    estimator::DiagnoseOptions opt;
    opt.effects = o.effects;
    const bool tty = stderr_is_terminal();
    auto progress = [tty](const std::string& stage, std::size_t done, std::size_t total) {
        if (tty) std::fprintf(stderr, "\r%s: %zu/%zu   %s", stage.c_str(), done, total, done == total ? "\n" : "");
    };
    const auto d = estimator::diagnose(params, rec, opt, progress);

    auto q = [](const estimator::QuantityRms& r) {
        char b[160];
        std::snprintf(b, sizeof b, "voltage %s, temperature %s, heat flux %s",
                      r.voltage_v ? (std::to_string(*r.voltage_v * 1e3).substr(0, 5) + " mV").c_str() : "-",
                      r.temperature_c ? (std::to_string(*r.temperature_c).substr(0, 5) + " degC").c_str() : "-",
                      r.heat_flux_w ? (std::to_string(*r.heat_flux_w).substr(0, 5) + " W").c_str() : "-");
        return std::string(b);
    };
    std::printf("baseline RMS: %s\n", q(d.baseline).c_str());
    std::printf("where the voltage error concentrates:\n");
    for (const auto& w : d.where)
        std::printf("  %-40s %5.1f %% of the squared error in %4.1f %% of the time (RMS %.1f mV, bias %+.1f mV)\n",
                    w.condition.c_str(), 100 * w.share_of_voltage_error, 100 * w.time_share, w.voltage_rms_v * 1e3,
                    w.voltage_bias_v * 1e3);
    std::printf("findings (score = share of the held-out error removed):\n");
    for (const auto& f : d.findings)
        std::printf("  %-26s %s score %6.3f  folds %zu  dBIC %8.1f\n", f.effect.c_str(),
                    f.significant ? "SIGNIFICANT" : "           ", f.score, f.folds_improved, f.delta_bic);
    for (const auto& f : d.findings)
        if (f.significant) std::printf("- %s: %s\n", f.effect.c_str(), f.explanation.c_str());
    std::printf("%s\n", d.summary.c_str());
    std::printf("improved RMS: %s\n", q(d.improved).c_str());

    if (!o.json.empty()) write_json_file(o.json, estimator::diagnosis_to_json(d));
    if (!o.improved.empty()) write_json_file(o.improved, d.improved_params.to_json());
    if (!o.report.empty())
        write_file_atomic(o.report, [&](std::ostream& out) { out << render_diagnosis_report(d, rec, o.recording); });
    return 0;
}

}  // namespace cellbench::cli
