// `cellbench check --program NAME --cell CELL [--config BENCH] [--param K=V]... [--json]`: validates a program
// for a cell and a bench without starting anything, with the daemon's own loaders (daemon/config.hpp: the
// bench config, the cell, the program compiler with its overrides and limit checks). Every problem of every
// file at once (exit 1), or the compiled plan (exit 0): parameters used, then each segment and each tester step
// with its expressions evaluated, as `POST /runs` would run it.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <variant>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/estimator/segment.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "cli/commands.hpp"

namespace cellbench::cli {

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

std::string num(double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.6g", v);
    return buf;
}

// Problems of one stage: a ConfigError's issues one per line, anything else as its message.
void collect(std::vector<std::string>& problems, const std::exception& e) {
    if (const auto* ce = dynamic_cast<const daemon::ConfigError*>(&e)) {
        for (const auto& i : ce->issues()) problems.push_back(i.to_string());
        return;
    }
    problems.emplace_back(e.what());
}

std::string step_text(const protocol::Step& s) {
    using protocol::StepType;
    std::string t(protocol::to_string(s.type));
    if (s.type == StepType::cycle)
        return t + ": back to step " + std::to_string(s.start_step) + ", " + std::to_string(s.count) + " times";
    if (s.current_a) t += "  " + num(*s.current_a) + " A";
    if (s.voltage_v) t += "  CV " + num(*s.voltage_v) + " V";
    std::string until;
    const auto add = [&](const std::string& x) { until += (until.empty() ? "" : " or ") + x; };
    if (s.time_s) add(num(*s.time_s) + " s");
    if (s.cutoff_voltage_v) add(num(*s.cutoff_voltage_v) + " V");
    if (s.cutoff_current_a) add("|I| < " + num(*s.cutoff_current_a) + " A");
    if (s.cutoff_capacity_ah) add(s.cutoff_capacity_ah->to_string() + " Ah");
    if (!until.empty()) t += "  until " + until;
    if (!s.note.empty()) t += "  (" + s.note + ")";
    return t;
}

// How many pulse sets the daemon's online fitter will find in a cycler program as the tester runs it: its steps in
// execution order (protocol::execution_order) as phases of the segmentation's kinds (estimator::classify_phase; a
// step without a time limit is a long phase), tested by the same estimator::begins_pulse_set as the recording will
// be. A lab engineer learns before the run whether the dashboard will show fits while it goes, or only
// `cellbench fit` of the recording afterwards (any layout).
std::size_t online_pulse_sets(const protocol::StepProgram& program) {
    std::vector<estimator::Phase> phases;
    for (const std::size_t k : protocol::execution_order(program, 100000)) {
        const auto& st = program.steps[k];
        estimator::Phase ph;
        ph.direction = protocol::step_direction(st.type);
        ph.duration_s = st.time_s.value_or(1e9);
        ph.kind = estimator::classify_phase(ph.direction, ph.duration_s);
        phases.push_back(ph);
    }
    std::size_t n = 0;
    for (std::size_t i = 0; i < phases.size(); ++i) n += estimator::begins_pulse_set(phases, i);
    return n;
}

std::size_t online_pulse_sets(const daemon::Program& p) {
    std::size_t n = 0;
    for (const auto& seg : p.segments)
        if (const auto* cy = std::get_if<daemon::CyclerSegment>(&seg)) n += online_pulse_sets(cy->program);
    return n;
}

void print_plan(const daemon::Program& p, const daemon::CellConfig& cell, const daemon::BenchConfig& bench) {
    std::printf("ok: program %s for cell %s (%s) on bench %s\n", p.name.c_str(), cell.id.c_str(), cell.name.c_str(),
                bench.name.c_str());
    if (!p.parameters.empty()) {
        std::printf("parameters:\n");
        for (const auto& [k, v] : p.parameters) {
            std::string extra;
            if (const auto it = p.parameter_specs.find(k); it != p.parameter_specs.end()) {
                const auto& s = it->second;
                if (!s.unit.empty()) extra += " " + s.unit;
                if (s.min || s.max)
                    extra += "  (allowed " + (s.min ? num(*s.min) : std::string("-inf")) + ".." +
                             (s.max ? num(*s.max) : std::string("inf")) + ")";
                if (!s.description.empty()) extra += "  " + s.description;
            }
            std::printf("  %-14s %s%s\n", k.c_str(), num(v).c_str(), extra.c_str());
        }
    }
    std::printf("segments:\n");
    for (std::size_t i = 0; i < p.segments.size(); ++i) {
        const auto& seg = p.segments[i];
        if (const auto* c = std::get_if<daemon::ChamberSetpointSegment>(&seg)) {
            std::printf("  %zu. chamber set point %s degC\n", i + 1, num(c->setpoint_c).c_str());
        } else if (const auto* w = std::get_if<daemon::WaitEquilibriumSegment>(&seg)) {
            std::printf("  %zu. wait for equilibrium: within %s degC for %s s (timeout %s s, then %s)\n", i + 1,
                        num(w->tolerance_c).c_str(), num(w->hold_s).c_str(), num(w->timeout_s).c_str(),
                        w->abort_on_timeout ? "abort" : "alarm and continue");
        } else if (const auto* cy = std::get_if<daemon::CyclerSegment>(&seg)) {
            const auto parts = protocol::tester_parts(cy->program);
            std::printf("  %zu. cycler program %s: %zu steps, max %s A%s\n", i + 1, cy->program.name.c_str(),
                        cy->program.steps.size(), num(cy->program.max_current_a()).c_str(),
                        parts.size() > 1 ? ", sent as two step files (a capacity limit needs a measured step)" : "");
            for (std::size_t k = 0; k < cy->program.steps.size(); ++k)
                std::printf("     %3zu  %s\n", k + 1, step_text(cy->program.steps[k]).c_str());
        }
    }
    if (const std::size_t pulse_sets = online_pulse_sets(p); pulse_sets > 0)
        std::printf("online fits: %zu pulse sets (each a long rest, then up to four pulses, one of them "
                    "discharging), each fitted as it completes\n", pulse_sets);
    else
        std::printf("online fits: none (no long rest followed by at most four pulses, one of them discharging, in "
                    "this program): the run is recorded, and `cellbench fit` of its export characterizes it "
                    "afterwards\n");
    const auto est = daemon::estimate_duration(p, cell);
    std::printf("expected duration about %.2f h of bench time (estimate: starting at %.0f %% SOC, nominal capacity)\n",
                est.total_s / 3600.0, daemon::ProgramEstimate::kStartSoc * 100.0);
    std::printf("largest current %s A (cell: charge %s A, discharge %s A; bench group %s A)\n",
                num(p.max_current_a()).c_str(), num(cell.max_charge_current_a).c_str(),
                num(cell.max_discharge_current_a).c_str(), num(bench.cycler.group_max_current_a()).c_str());
}

}  // namespace

int run_check(const CheckOptions& o) {
    std::vector<std::string> problems;

    // Malformed --param arguments are problems of their own; the well-formed ones still go to the loader.
    daemon::ProgramOverrides overrides;
    for (const auto& p : o.params) {
        try {
            auto [k, v] = daemon::parse_override_argument(p);
            if (overrides.count(k)) problems.push_back("--param " + k + ": given more than once");
            overrides[k] = std::move(v);
        } catch (const std::exception& e) {
            problems.push_back(std::string("--param: ") + e.what());
        }
    }

    // The bench: when it does not load, its problems are listed and the program is still checked against the
    // cell alone, from the bench file's folder.
    std::optional<daemon::BenchConfig> bench;
    fs::path config_dir = fs::path(o.config).parent_path();
    try {
        bench = daemon::load_bench_config(o.config);
        config_dir = bench->config_dir;
    } catch (const std::exception& e) {
        collect(problems, e);
    }

    std::optional<daemon::CellConfig> cell;
    try {
        cell = daemon::load_cell_config(daemon::cell_file(config_dir, o.cell));
    } catch (const std::exception& e) {
        collect(problems, e);
    }

    std::optional<daemon::Program> program;
    fs::path program_path;
    try {
        program_path = daemon::program_file(config_dir, o.program);
        if (cell) program = daemon::load_program(program_path, *cell, overrides, bench ? &*bench : nullptr);
    } catch (const std::exception& e) {
        collect(problems, e);
    }
    if (!cell && !program_path.empty())
        problems.push_back(program_path.string() + ": not checked (the cell did not load)");

    if (!problems.empty()) {
        if (o.json_output) {
            std::printf("%s\n", json{{"ok", false}, {"problems", problems}}.dump(2).c_str());
        } else {
            std::fprintf(stderr, "cellbench check: %zu problem%s; nothing was started:\n", problems.size(),
                         problems.size() == 1 ? "" : "s");
            for (const auto& p : problems) std::fprintf(stderr, "  %s\n", p.c_str());
        }
        return 1;
    }
    if (o.json_output)
        std::printf("%s\n", json{{"ok", true},
                                  {"program", program->to_json()},
                                  {"expected_duration_s", daemon::estimate_duration(*program, *cell).total_s},
                                  {"online_pulse_sets", online_pulse_sets(*program)}}
                                 .dump(2)
                                 .c_str());
    else
        print_plan(*program, *cell, *bench);
    return 0;
}

}  // namespace cellbench::cli
