#include <cmath>
#include <cstdio>
#include <initializer_list>
#include <map>
#include <utility>

#include <spdlog/spdlog.h>

#include "cellbench/daemon/fit_replay.hpp"
#include "cellbench/daemon/run_store.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"
#include "cli/progress.hpp"

namespace cellbench::cli {

namespace {

// The per-pulse-set fits in one line: how many, of which forms, which method won; for a GITT, its steps.
void print_pulse_sets_line(const estimator::Characterization& c) {
    if (c.pulse_fits.empty()) {  // a GITT, or pulses in no layout the per-pulse-set fits take
        std::size_t steps = 0;
        if (c.global)
            for (const auto& w : c.global->windows) steps += w.kind == "step";
        if (steps > 0)
            std::printf("pulse sets: none (the tables come from %zu titration steps)\n", steps);
        else
            std::printf("pulse sets: none fitted on their own (the global fit uses every pulse)\n");
        return;
    }
    std::printf("pulse sets: %zu fitted", c.pulse_fits.size());
    {  // by form, when not all are of the thesis' (estimator::PulseSetForm)
        std::map<std::string, std::size_t> forms;
        for (const auto& f : c.pulse_fits) ++forms[estimator::to_string(f.pulse_set.form)];
        if (!forms.empty() && !(forms.size() == 1 && forms.begin()->first == "thesis")) {
            std::string t;
            for (const auto& [name, k] : forms) t += (t.empty() ? "" : ", ") + std::to_string(k) + " " + name;
            std::printf(" (%s)", t.c_str());
        }
    }
    std::printf(";");
    std::size_t joint = 0;
    double rms_t = 0, rms_j = 0;
    std::size_t n = 0;
    for (const auto& f : c.pulse_fits) {
        joint += f.chosen == estimator::PulseSetFit::Method::Joint;
        if (std::isfinite(f.thesis_rms_v) && std::isfinite(f.joint_rms_v)) rms_t += f.thesis_rms_v, rms_j += f.joint_rms_v, ++n;
    }
    std::printf(" joint fit chosen for %zu, thesis per-segment for %zu", joint, c.pulse_fits.size() - joint);
    if (n) std::printf(" (mean pulse-set RMS: thesis %.2f mV, joint %.2f mV)", rms_t / n * 1e3, rms_j / n * 1e3);
    std::printf("\n");
}

void print_parameter_table(const estimator::Characterization& c) {
    const auto& p = c.params;
    if (std::isfinite(c.capacity.capacity_ah_sd))
        std::printf("capacity %.4f +- %.4f Ah (%s, %s; +- the recordings' disagreement on the charge scale)\n",
                    p.capacity_ah, c.capacity.capacity_ah_sd, c.capacity.method.c_str(), c.capacity.source.c_str());
    else
        std::printf("capacity %.4f Ah (%s, %s)\n", p.capacity_ah, c.capacity.method.c_str(), c.capacity.source.c_str());
    if (c.capacity.below_cutoff_ah > 0)
        std::printf("  of which %.1f mAh lie between the discharge's cut-off under load and OCV = cut-off (from the rest "
                    "after it)\n",
                    1e3 * c.capacity.below_cutoff_ah);
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
        if (std::isfinite(c.global->start_time_constants_s[0]))
            std::printf("from a start at tau %.0f / %.0f s (lower objective than from the initial tables), ",
                        c.global->start_time_constants_s[0], c.global->start_time_constants_s[1]);
        // Each global value with its flags (at_bound, uncertain, implausible), as the fit JSON has them.
        auto flags_of = [](std::initializer_list<const estimator::FittedValue*> values) {
            std::string flags;
            for (const auto* v : values)
                for (const auto& f : v->flags) flags += (flags.empty() ? " (" : ", ") + f;
            return flags.empty() ? flags : flags + ")";
        };
        if (c.global->temperature_dependence)
            std::printf("Ea %.1f +- %.1f kJ/mol%s, ", c.global->activation_energy_j_per_mol.value / 1e3,
                        c.global->activation_energy_j_per_mol.sd / 1e3,
                        flags_of({&c.global->activation_energy_j_per_mol}).c_str());
        if (c.global->current_dependence)
            std::printf("I0 %.2f +- %.2f A (ref %.2f A)%s, ", c.global->exchange_current_a.value,
                        c.global->exchange_current_a.sd, c.global->reference_current_a,
                        flags_of({&c.global->exchange_current_a}).c_str());
        if (c.global->params.extensions.extra_rc)
            std::printf("slow pair R3 %.2f +- %.2f mOhm, tau3 %.0f +- %.0f s%s, ", c.global->slow_r_ohm.value * 1e3,
                        c.global->slow_r_ohm.sd * 1e3, c.global->slow_tau_s.value, c.global->slow_tau_s.sd,
                        flags_of({&c.global->slow_r_ohm, &c.global->slow_tau_s}).c_str());
        std::printf("current steps %.2f +- %.2f of a sample before their row%s, ", c.global->step_lag.value,
                    c.global->step_lag.sd, flags_of({&c.global->step_lag}).c_str());
        std::printf("%zu values flagged (? uncertain or unidentified, ! implausible)\n", c.global->flagged_count());
    }
    print_pulse_sets_line(c);
    std::printf("thermal: C_th %.2f J/K", p.thermal.c_th_j_per_k);
    if (std::isfinite(c.thermal.c_th_sigma_j_per_k)) std::printf(" +- %.2f", c.thermal.c_th_sigma_j_per_k);
    if (std::isfinite(c.thermal.c_th_r_squared)) std::printf(" (R^2 %.3f)", c.thermal.c_th_r_squared);
    auto thermal_mark = [](const std::vector<std::string>& flags) -> const char* {
        if (flags.empty()) return "";
        for (const auto& f : flags)
            if (f == "implausible") return " !";
        return " ?";
    };
    std::printf("%s, R_th %.3f K/W", thermal_mark(c.thermal.c_th_flags), p.thermal.r_th_k_per_w);
    if (std::isfinite(c.thermal.r_th_sigma_k_per_w)) std::printf(" +- %.3f", c.thermal.r_th_sigma_k_per_w);
    std::printf("%s (%s)\n", thermal_mark(c.thermal.r_th_flags), c.thermal.r_th_method.c_str());
    if (!p.thermal.ehc_soc.empty()) {
        std::printf("entropic coefficient dU/dT (mV/K) by SOC:");
        for (std::size_t k = 0; k < p.thermal.ehc_soc.size(); ++k)
            std::printf(" %.0f%%:%.3f", p.thermal.ehc_soc[k] * 100, p.thermal.ehc_v_per_k[k] * 1e3);
        std::printf("\n");
    }
}

}  // namespace

// fit --db BENCH.sqlite --run ID: the run replayed through the daemon's online fitter (daemon/fit_replay.hpp),
// read-only. Prints the pulse-set table and how it compares with what the daemon stored.
int run_fit_db(const FitOptions& o) {
    if (o.run_id <= 0) throw InputError("fit --db: give the run to replay with --run ID (cellbench runs lists them)");
    OutputFiles outputs({o.output, o.summary_json});
    const auto store = daemon::RunStore::open_readonly(o.db);
    ProgressLine progress("fit --db");
    const auto r = daemon::replay_run_fits(*store, o.run_id);
    progress.finish();
    spdlog::info("{} run {}: {} on {}, {}; replayed {} cycler, {} DAQ, {} chamber samples", o.db, o.run_id,
                 r.run.program, r.run.cell, daemon::to_string(r.run.state), r.cycler_rows, r.daq_rows, r.chamber_rows);
    for (const auto& w : r.warnings) spdlog::warn("{}", w);

    // The daemon's own fits, for the comparison (largest relative difference of any fitted value).
    const auto stored = store->pulse_fits(o.run_id);
    std::printf("%3s %6s %8s %9s %9s %9s %9s %9s %9s\n", "set", "SOC", "OCV V", "R0d mOhm", "R1d mOhm", "C1d F",
                "R2d mOhm", "C2d F", "R0c mOhm");
    for (const auto& f : r.fits)
        std::printf("%3d %6.3f %8.4f %9.3f %9.3f %9.0f %9.3f %9.0f %9.3f\n", f.pulse_set, f.soc, f.ocv_v,
                    f.discharge.r0_ohm * 1e3, f.discharge.r1_ohm * 1e3, f.discharge.c1_f, f.discharge.r2_ohm * 1e3,
                    f.discharge.c2_f, f.charge.r0_ohm * 1e3);
    nlohmann::json comparison = nullptr;
    if (!stored.empty()) {
        double worst = 0.0;
        const std::size_t n = std::min(stored.size(), r.fits.size());
        auto rel = [](double a, double b) {
            if (!std::isfinite(a) && !std::isfinite(b)) return 0.0;
            return std::abs(a - b) / std::max(std::abs(b), 1e-12);
        };
        for (std::size_t k = 0; k < n; ++k) {
            const auto& a = r.fits[k];
            const auto& b = stored[k];
            for (const auto& [x, y] : std::initializer_list<std::pair<double, double>>{{a.ocv_v, b.ocv_v}, {a.discharge.r0_ohm, b.discharge.r0_ohm},
                                       {a.discharge.r1_ohm, b.discharge.r1_ohm}, {a.discharge.c1_f, b.discharge.c1_f},
                                       {a.discharge.r2_ohm, b.discharge.r2_ohm}, {a.discharge.c2_f, b.discharge.c2_f},
                                       {a.charge.r0_ohm, b.charge.r0_ohm}, {a.charge.r1_ohm, b.charge.r1_ohm},
                                       {a.charge.c1_f, b.charge.c1_f}, {a.charge.r2_ohm, b.charge.r2_ohm},
                                       {a.charge.c2_f, b.charge.c2_f}})
                worst = std::max(worst, rel(x, y));
        }
        const bool same = stored.size() == r.fits.size() && worst < 1e-9;
        comparison = {{"daemon_pulse_sets", stored.size()}, {"replayed_pulse_sets", r.fits.size()},
                      {"max_relative_difference", worst}, {"same", same}};
        if (same)
            std::printf("same as the daemon's %zu stored pulse-set fits (largest relative difference %.1e)\n",
                        stored.size(), worst);
        else
            spdlog::warn("the daemon stored {} pulse-set fits, the replay gives {} (largest relative difference of "
                         "the common ones {:.3g})", stored.size(), r.fits.size(), worst);
    } else {
        std::printf("the database holds no pulse-set fits of this run (the daemon died before they landed?): "
                    "the replay's are the run's\n");
    }
    if (!r.params) throw InputError(o.db + " run " + std::to_string(o.run_id) + ": no parameter set: " + r.params_error);
    if (const auto daemon_params = store->latest_parameter_set(o.run_id))
        std::printf("the daemon's parameter set of this run: stored (id %lld)\n", static_cast<long long>(daemon_params->id));
    nlohmann::json params = r.params->to_json();
    outputs.write_json(o.output, params);
    if (!o.summary_json.empty()) {
        nlohmann::json summary = r.summary.is_object() ? r.summary : nlohmann::json::object();
        nlohmann::json fits = nlohmann::json::array();
        for (const auto& f : r.fits) fits.push_back(daemon::to_json(f));
        summary["replay"] = {{"database", o.db}, {"run_id", o.run_id}, {"program", r.run.program}, {"cell", r.run.cell},
                             {"state", daemon::to_string(r.run.state)}, {"fits", std::move(fits)},
                             {"comparison", comparison}, {"warnings", r.warnings}};
        outputs.write_json(o.summary_json, summary);
    }
    outputs.commit();
    spdlog::info("wrote {}", o.output);
    return 0;
}

int run_fit(const FitOptions& o) {
    if (!o.db.empty()) return run_fit_db(o);
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
    co.fallback_c_th_j_per_k = o.c_th_j_per_k;
    co.fallback_r_th_k_per_w = o.r_th_k_per_w;
    co.area_m2 = o.area_m2;
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
