#include <cmath>
#include <cstdio>

#include <spdlog/spdlog.h>

#include "cellbench/estimator/fit.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"
#include "cli/progress.hpp"

namespace cellbench::cli {

namespace {

void print_parameter_table(const estimator::Characterization& c) {
    const auto& p = c.params;
    std::printf("capacity %.4f Ah (%s, %s)\n", p.capacity_ah, c.capacity.method.c_str(), c.capacity.source.c_str());
    std::printf("%5s %7s | %-36s | %-36s\n", "SOC", "OCV", "discharge R0  R1 mOhm  C1 F  R2 mOhm  C2 F",
                "charge R0  R1 mOhm  C1 F  R2 mOhm  C2 F");
    for (std::size_t k = 0; k < p.soc.size(); ++k) {
        // A flagged value (implausible, uncertain or unidentified; fit --json says which) is marked, never shown
        // as fine.
        auto mark = [&](int dir, int q) -> char {
            if (!c.global || k >= c.global->discharge.size()) return ' ';
            const auto& v = (dir > 0 ? c.global->charge : c.global->discharge)[k][static_cast<std::size_t>(q)];
            if (v.flags.empty()) return ' ';
            for (const auto& f : v.flags)
                if (f == "implausible") return '!';
            return '?';
        };
        auto row = [&](const estimator::RcTable& t, int dir) {
            std::printf(" %6.3f%c%6.3f%c%6.0f%c%7.3f%c%6.0f%c|", t.r0_ohm[k] * 1e3, mark(dir, 0), t.r1_ohm[k] * 1e3,
                        mark(dir, 1), t.c1_f[k], mark(dir, 2), t.r2_ohm[k] * 1e3, mark(dir, 3), t.c2_f[k], mark(dir, 4));
        };
        const bool ocv_flag = c.global && k < c.global->ocv.size() && !c.global->ocv[k].flags.empty();
        std::printf("%5.1f %7.4f%c|", p.soc[k] * 100, p.ocv_v[k], ocv_flag ? '?' : ' ');
        row(p.discharge, -1);
        row(p.charge, +1);
        std::printf("\n");
    }
    if (c.global) {
        std::printf("global fit: RMS %.2f mV over %zu windows, smoothness %.0f (%s), ", c.global->rms_v * 1e3,
                    c.global->windows.size(), c.global->smoothness,
                    c.global->cross_validation.empty() ? "given" : "cross-validated");
        if (c.global->temperature_dependence)
            std::printf("Ea %.1f +- %.1f kJ/mol, ", c.global->activation_energy_j_per_mol.value / 1e3,
                        c.global->activation_energy_j_per_mol.sd / 1e3);
        if (c.global->current_dependence)
            std::printf("I0 %.2f +- %.2f A (ref %.2f A), ", c.global->exchange_current_a.value,
                        c.global->exchange_current_a.sd, c.global->reference_current_a);
        std::printf("%zu values flagged (? uncertain or unidentified, ! implausible)\n", c.global->flagged_count());
    }
    std::printf("pulse sets: %zu fitted;", c.pulse_fits.size());
    std::size_t joint = 0;
    double rms_t = 0, rms_j = 0;
    std::size_t n = 0;
    for (const auto& f : c.pulse_fits) {
        joint += f.chosen == estimator::PulseSetFit::Method::Joint;
        if (std::isfinite(f.thesis_rms_v) && std::isfinite(f.joint_rms_v)) rms_t += f.thesis_rms_v, rms_j += f.joint_rms_v, ++n;
    }
    std::printf(" joint fit chosen for %zu, thesis per-segment for %zu", joint, c.pulse_fits.size() - joint);
    if (n) std::printf(" (mean pulse-set RMS: thesis %.2f mV, joint %.2f mV)", rms_t / n * 1e3, rms_j / n * 1e3);
    std::printf("\nthermal: C_th %.2f J/K", p.thermal.c_th_j_per_k);
    if (std::isfinite(c.thermal.c_th_sigma_j_per_k)) std::printf(" +- %.2f", c.thermal.c_th_sigma_j_per_k);
    if (std::isfinite(c.thermal.c_th_r_squared)) std::printf(" (R^2 %.3f)", c.thermal.c_th_r_squared);
    std::printf(", R_th %.3f K/W (%s)\n", p.thermal.r_th_k_per_w, c.thermal.r_th_method.c_str());
    if (!p.thermal.ehc_soc.empty()) {
        std::printf("entropic coefficient dU/dT (mV/K) by SOC:");
        for (std::size_t k = 0; k < p.thermal.ehc_soc.size(); ++k)
            std::printf(" %.0f%%:%.3f", p.thermal.ehc_soc[k] * 100, p.thermal.ehc_v_per_k[k] * 1e3);
        std::printf("\n");
    }
}

}  // namespace

int run_fit(const FitOptions& o) {
    if (!o.db.empty())
        throw InputError(o.db + ": replaying a daemon run (--db/--run) needs cellbenchd's database support, "
                                "which this build does not have yet");
    OutputFiles outputs({o.output, o.summary_json});  // folders checked before the fit, all written or none
    std::vector<Recording> recs;
    for (const auto& path : o.recordings) {
        recs.push_back(load_recording(path));
        spdlog::info("{}: {} rows, {:.0f} s", path, recs.back().size(), recs.back().time_s.back() - recs.back().time_s.front());
    }
    estimator::CharacterizationOptions co;
    co.cell = o.cell_name;
    co.fallback_capacity_ah = o.capacity_ah;
    co.fallback_capacity_source = "--capacity-ah";
    co.global.smoothness = o.smoothness;
    co.global.knot_spacing = o.knot_spacing;
    co.global_fit = !o.per_pulse_set;
    ProgressLine progress("fit");  // on a terminal only
    co.progress = progress.callback();
    const auto c = estimator::characterize(recs, co);
    progress.finish();
    for (const auto& w : c.warnings) spdlog::warn("{}", w);
    print_parameter_table(c);
    outputs.write_json(o.output, c.params.to_json());
    if (!o.summary_json.empty()) outputs.write_json(o.summary_json, c.summary_json());
    outputs.commit();
    spdlog::info("wrote {}", o.output);
    return 0;
}

}  // namespace cellbench::cli
