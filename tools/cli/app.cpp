#include <cstdio>
#include <exception>
#include <string>

#include <CLI/CLI.hpp>
#include <spdlog/fmt/fmt.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "cellbench/core/recording.hpp"
#include "cellbench/core/version.hpp"
#include "cellbench/estimator/diagnose.hpp"
#include "cli/commands.hpp"

namespace cellbench::cli {

int run_cli(int argc, char** argv) {
    // Logs (and progress) go to stderr; stdout carries the results.
    spdlog::set_default_logger(spdlog::stderr_color_mt("cellbench"));
    spdlog::set_pattern("%^%l%$: %v");

    CLI::App app{"cellbench: electrothermal characterization of Li-ion cells (fit, simulate, diagnose recordings)"};
    app.require_subcommand(1);
    app.set_version_flag("--version", cellbench::version_string(), "Print the version and exit");
    app.fallthrough();  // -v/-q work after the subcommand too
    bool verbose = false, quiet = false;
    app.add_flag("-v,--verbose", verbose, "More log output");
    app.add_flag("-q,--quiet", quiet, "Only warnings and errors");

    ImportOptions imp;
    auto* import_cmd = app.add_subcommand("import", "Merge instrument exports (Neware, DewesoftX, BDF) into one BDF recording");
    import_cmd->add_option("--neware", imp.neware, "Neware BTS record export (CSV)")->check(CLI::ExistingFile);
    import_cmd->add_option("--dewesoft", imp.dewesoft, "DewesoftX export (CSV) with thermopile voltage and Type-T")
        ->check(CLI::ExistingFile);
    import_cmd->add_option("--bdf", imp.bdf, "BDF recording to merge (e.g. cycler+DAQ already on one clock)")
        ->check(CLI::ExistingFile);
    import_cmd->add_option("-o,--output", imp.output, "Output BDF CSV")->required();
    import_cmd->add_option("--sensitivity", imp.sensitivity_v_per_w_per_m2,
                           "Heat flux sensor sensitivity S at 20 degC in V/(W/m^2)")
        ->capture_default_str();
    import_cmd->add_option("--max-offset", imp.max_offset_s, "Largest clock offset searched between exports, s")
        ->capture_default_str();

    FitOptions fit;
    auto* fit_cmd = app.add_subcommand("fit", "Fit the cell's parameter set from characterization recordings");
    fit_cmd->add_option("recordings", fit.recordings, "BDF recordings of one cell (HPPC or GITT, CC discharges, ...)")
        ->check(CLI::ExistingFile);
    fit_cmd->add_option("--db", fit.db, "cellbenchd SQLite database (with --run)");
    fit_cmd->add_option("--run", fit.run_id, "Run id in --db to replay through the online fitter");
    fit_cmd->add_option("-o,--output", fit.output, "Output parameter set (cellbench.params/1 JSON)")->required();
    fit_cmd->add_option("--json", fit.summary_json, "Also write a summary JSON of every fit and its uncertainty");
    fit_cmd->add_option("--cell", fit.cell_name, "Cell name stored in the parameter set (a label, e.g. \"Panasonic NCR18650PF\")")->capture_default_str();
    fit_cmd->add_option("--capacity-ah", fit.capacity_ah,
                        "Capacity (Ah) used when no recording measures it (no pilot discharge, no test to the cut-off)")
        ->check(CLI::PositiveNumber);
    fit_cmd->add_option("--area-m2", fit.area_m2,
                        "Cell surface in m^2 that turns the heat flux density into heat flow (default: a 21700's; "
                        "an 18650 has 4.18e-3)")
        ->check(CLI::Range(1e-5, 1.0))
        ->capture_default_str();
    auto* c_th = fit_cmd->add_option("--c-th-j-per-k", fit.c_th_j_per_k,
                                     "Heat capacity (J/K) used when no recording measures it (no heat flux sensor); "
                                     "R_th is then fitted with it from the surface temperature")
                     ->check(CLI::PositiveNumber);
    fit_cmd->add_option("--r-th-k-per-w", fit.r_th_k_per_w,
                        "Thermal resistance to ambient (K/W) used when no recording has a surface temperature "
                        "(with --c-th-j-per-k)")
        ->check(CLI::PositiveNumber)
        ->needs(c_th);
    fit_cmd->add_option("--smoothness", fit.smoothness,
                        "Weight of the smoothness penalty along SOC (default: chosen by cross-validation)")
        ->check(CLI::PositiveNumber);
    fit_cmd->add_option("--knot-spacing", fit.knot_spacing, "SOC spacing of the fitted tables (default: the test's SOC levels)")
        ->check(CLI::Range(0.02, 0.25));
    fit_cmd->add_flag("--per-pulse-set", fit.per_pulse_set,
                      "Tables from independent per-pulse-set fits (thesis method) instead of the global identification");

    SimulateOptions sim;
    auto* sim_cmd = app.add_subcommand("simulate", "Simulate the model on a recording's current and report the errors");
    sim_cmd->add_option("--params", sim.params, "Parameter set JSON")->required()->check(CLI::ExistingFile);
    sim_cmd->add_option("recording", sim.recording, "BDF recording")->required()->check(CLI::ExistingFile);
    sim_cmd->add_option("--json", sim.metrics_json, "Write the metrics JSON (cellbench.metrics/1)");
    sim_cmd->add_option("--out", sim.output, "Write the simulated traces beside the measured ones (BDF CSV)");
    sim_cmd->add_option("--initial-soc", sim.initial_soc, "Initial SOC (0..1); default: from the first voltage less R0 I, or, for a recording that starts under load and whose first stretch contradicts that, the SOC that predicts its first stretch best");
    sim_cmd->add_option("--ambient", sim.ambient_c, "Ambient temperature, degC; default: measured, else first surface reading");

    DiagnoseCliOptions diag;
    auto* diag_cmd = app.add_subcommand(
        "diagnose", "Locate where the model misses a recording, name the physics left out, model it, show the gain");
    diag_cmd->add_option("--params", diag.params, "Parameter set JSON")->required()->check(CLI::ExistingFile);
    diag_cmd->add_option("recording", diag.recording, "BDF recording")->required()->check(CLI::ExistingFile);
    diag_cmd->add_option("--json", diag.json, "Write the diagnosis JSON (cellbench.diagnosis/1)");
    diag_cmd->add_option("--report", diag.report, "Write a self-contained HTML report");
    diag_cmd->add_option("--improved", diag.improved, "Write the parameter set with the accepted extensions");
    diag_cmd->add_option("--effects", diag.effects, "Only try these effect ids (default: the whole catalogue)");
    diag_cmd->add_option("--confirm", diag.confirm,
                         "Other BDF recordings of the same cell and bench set-up, best ones the parameter set was not "
                         "fitted to (another drive cycle): candidates are fitted to them too, and a finding that makes one "
                         "of them worse is contradicted and never significant")
        ->check(CLI::ExistingFile);
    // The evidence only counts a quantity the parameter set misses by more than its instrument's accuracy.
    diag_cmd->add_option("--voltage-floor-mv", diag.voltage_floor_mv,
                         "Voltage accuracy, mV (default 5: a cycler's 0.05 % of 10 V); smaller errors are no evidence")
        ->check(CLI::PositiveNumber);
    diag_cmd->add_option("--temperature-floor-c", diag.temperature_floor_c,
                         "Temperature accuracy, degC (default 0.3); smaller errors are no evidence, unless no other "
                         "quantity is and the error about its mean exceeds " +
                             fmt::format("{:g}", estimator::DiagnoseOptions{}.temperature_shape_noise_factor) +
                             "x the recording's noise (a thermocouple's accuracy is an offset)")
        ->check(CLI::PositiveNumber);
    diag_cmd->add_option("--heat-flux-floor-w", diag.heat_flux_floor_w,
                         "Heat flux accuracy over the cell's surface, W (default 0.05 for a 21700's surface, scaled with a larger "
                         "cell's area); smaller errors are no evidence")
        ->check(CLI::PositiveNumber);

    ExportParamsOptions exp;
    auto* exp_cmd = app.add_subcommand(
        "export-params", "Write a parameter set for another modelling tool (PyBaMM's Thevenin equivalent-circuit model)");
    exp_cmd->add_option("--format", exp.format, "Output format: pybamm (a Python module defining get_parameter_values())")
        ->check(CLI::IsMember({"pybamm"}))
        ->capture_default_str();
    exp_cmd->add_option("params", exp.params, "Parameter set JSON (cellbench.params/1)")->required()->check(CLI::ExistingFile);
    exp_cmd->add_option("-o,--output", exp.output, "Output file (e.g. p45b_pybamm.py)")->required();
    exp_cmd->add_option("--initial-soc", exp.initial_soc, "\"Initial SoC\" of the exported set (0..1)")
        ->check(CLI::Range(0.0, 1.0))
        ->capture_default_str();
    exp_cmd->add_option("--upper-cutoff", exp.upper_cutoff_v, "\"Upper voltage cut-off [V]\"")->capture_default_str();
    exp_cmd->add_option("--lower-cutoff", exp.lower_cutoff_v, "\"Lower voltage cut-off [V]\"")->capture_default_str();

    const auto client = add_client_commands(app);  // status, runs, start, stop, pause, resume, export

    GenerateOptions gen;
    auto* gen_cmd = app.add_subcommand(
        "generate", "Make a characterization and a validation recording of a simulated cell with one hidden effect");
    gen_cmd->add_option("--effect", gen.effect, "Hidden effect id, or none for a control cell")->capture_default_str();
    gen_cmd->add_option("--seed", gen.seed, "Seed (varies magnitudes, noise and base parameters)")->capture_default_str();
    gen_cmd->add_option("--magnitude", gen.magnitude, "Scale of the effect around its nominal strength")->capture_default_str();
    gen_cmd->add_option("--base", gen.base, "Nominal cell parameter set")->capture_default_str()->check(CLI::ExistingFile);
    gen_cmd->add_option("-o,--output", gen.output_dir, "Output folder")->required();

    SimOptions simb;
    auto* simb_cmd = app.add_subcommand("sim", "Run the simulated bench (Neware BTS server, Modbus chamber, DEWE CAN stream)");
    simb_cmd->add_option("--config", simb.config, "Bench configuration")->capture_default_str()->check(CLI::ExistingFile);
    simb_cmd->add_option("--time-scale", simb.time_scale, "Bench seconds per wall second (default: from the config)");

    StepsOptions steps;
    auto* steps_cmd = app.add_subcommand("steps", "Write the Neware step file (BTS Client schema) the daemon would send");
    steps_cmd->add_option("--program", steps.program, "Program name (config/programs/NAME.json)")->required();
    steps_cmd->add_option("--cell", steps.cell, "Cell name (config/cells/NAME.json)")->required();
    steps_cmd->add_option("--config", steps.config, "Bench configuration")->capture_default_str()->check(CLI::ExistingFile);
    steps_cmd->add_option("-o,--output", steps.output, "Step file to write (.xml)")->required();

    CheckOptions check;
    auto* check_cmd = app.add_subcommand(
        "check", "Validate a program for a cell and a bench without starting anything; print the compiled plan");
    check_cmd->add_option("--program", check.program, "Program name (config/programs/NAME.json)")->required();
    check_cmd->add_option("--cell", check.cell, "Cell name (config/cells/NAME.json)")->required();
    check_cmd->add_option("--config", check.config, "Bench configuration (its folder holds cells/ and programs/)")
        ->capture_default_str();
    check_cmd->add_option("--param", check.params, "Override a declared program parameter, K=V (repeatable)");
    check_cmd->add_flag("--json", check.json_output, "Print {\"ok\", \"program\" | \"problems\"} as JSON");

    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        const int code = app.exit(e);
        return code == 0 ? 0 : 2;
    }
    spdlog::set_level(quiet ? spdlog::level::warn : verbose ? spdlog::level::debug : spdlog::level::info);

    try {
        if (*import_cmd) return run_import(imp);
        if (*fit_cmd) {
            if (fit.recordings.empty() == fit.db.empty()) {
                std::fprintf(stderr, "cellbench fit: give either RECORDING... or --db FILE --run ID\n");
                return 2;
            }
            return run_fit(fit);
        }
        if (*sim_cmd) return run_simulate(sim);
        if (const auto status = run_client_command(*client)) return *status;
        if (*diag_cmd) return run_diagnose(diag);
        if (*gen_cmd) return run_generate(gen);
        if (*exp_cmd) return run_export_params(exp);
        if (*simb_cmd) return run_sim(simb);
        if (*steps_cmd) return run_steps(steps);
        if (*check_cmd) return run_check(check);
    } catch (const InputError& e) {
        spdlog::error("{}", e.what());
        return 1;
    } catch (const std::exception& e) {
        spdlog::error("failed: {}", e.what());
        return 1;
    }
    return 2;
}

}  // namespace cellbench::cli
