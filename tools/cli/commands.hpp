#pragma once
// The `cellbench` commands. Each run_* returns the process exit status (0 ok, 1 bad input or failed run);
// InputError escaping from them is reported by the caller as one clear line and status 1.
#include <memory>
#include <optional>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/simulate.hpp"

namespace CLI {
class App;
}

namespace cellbench::cli {

struct ImportOptions {
    std::string neware, dewesoft, bdf, output;
    double sensitivity_v_per_w_per_m2 = 17.39e-6;
    double max_offset_s = 3600.0;
};
int run_import(const ImportOptions& o);

struct FitOptions {
    std::vector<std::string> recordings;
    std::string db;
    long long run_id = -1;
    std::string output, summary_json;
    std::string cell_name = "unnamed cell";  // a label only; a default naming one real cell would mislabel every other
    double capacity_ah = 0.0;        // used when no recording measures the capacity
    double c_th_j_per_k = 0.0, r_th_k_per_w = 0.0;  // used where no recording measures them (0: not given)
    double area_m2 = estimator::CharacterizationOptions{}.area_m2;  // cell surface (heat flux density -> heat flow)
    double smoothness = std::numeric_limits<double>::quiet_NaN();   // NaN: cross-validated
    double knot_spacing = std::numeric_limits<double>::quiet_NaN(); // NaN: the test's SOC levels
    bool per_pulse_set = false;      // the thesis' per-pulse-set tables instead of the global fit
};
int run_fit(const FitOptions& o);

struct SimulateOptions {
    std::string params, recording, metrics_json, output;
    std::optional<double> initial_soc, ambient_c;
};
int run_simulate(const SimulateOptions& o);

struct DiagnoseCliOptions {
    std::string params, recording, json, report, improved;
    std::vector<std::string> effects;  // empty = whole catalogue
    std::vector<std::string> confirm;  // other BDF recordings of the cell the findings must not make worse
    // The instruments' accuracy (DiagnoseOptions' floors); unset: the library's defaults.
    std::optional<double> voltage_floor_mv, temperature_floor_c, heat_flux_floor_w;
};
int run_diagnose(const DiagnoseCliOptions& o);

struct GenerateOptions {
    std::string base = "config/cells/p45b-thesis.json";
    std::string effect = "none";
    unsigned seed = 1;
    double magnitude = 1.0;
    std::string output_dir;
};
int run_generate(const GenerateOptions& o);

struct SimOptions {
    std::string config = "config/bench.sim.json";
    std::optional<double> time_scale;
};
int run_sim(const SimOptions& o);

struct StepsOptions {
    std::string program, cell, config = "config/bench.sim.json", output;
};
int run_steps(const StepsOptions& o);  // cmd_steps.cpp

// check --program NAME --cell CELL [--config BENCH] [--param K=V]... (cmd_check.cpp): the daemon's loaders on
// the bench, the cell and the program with its overrides; every problem at once (1) or the compiled plan (0).
struct CheckOptions {
    std::string program, cell, config = "config/bench.sim.json";
    std::vector<std::string> params;
    bool json_output = false;
};
int run_check(const CheckOptions& o);
// export-params --format pybamm PARAMS.json -o FILE (cmd_export_params.cpp): a Python module for PyBaMM's
// Thevenin model (get_parameter_values() with PyBaMM's ECM names and units).
struct ExportParamsOptions {
    std::string format = "pybamm";
    std::string params, output;
    double initial_soc = 1.0;
    double upper_cutoff_v = 4.2, lower_cutoff_v = 2.5;
};
int run_export_params(const ExportParamsOptions& o);

// The metrics JSON of INTERFACES.md ("cellbench.metrics/1"); an unmeasured quantity is null.
nlohmann::json metrics_to_json(const estimator::SimulationMetrics& m);

// Client of cellbenchd (cmd_client.cpp): status, runs, start, stop, pause, resume, export. Registers the
// subcommands on `app`; run_client_command runs the one parsed (nullopt when none of them was).
struct ClientCommands;
std::shared_ptr<ClientCommands> add_client_commands(CLI::App& app);
std::optional<int> run_client_command(const ClientCommands& commands);

// `--param K=V` arguments as a JSON object of overrides (POST /runs "parameters"): V typed as a number where it
// reads as one. Throws InputError naming every malformed argument (no '=', a name given twice).
nlohmann::json overrides_json(const std::vector<std::string>& params);

// Entry point used by main(): parses argv (usage errors -> 2), runs the command.
int run_cli(int argc, char** argv);

}  // namespace cellbench::cli
