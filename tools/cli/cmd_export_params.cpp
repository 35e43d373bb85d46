// cellbench export-params --format pybamm PARAMS.json -o FILE
//
// Writes the parameter set as a Python module for PyBaMM's Thevenin equivalent-circuit model
// (pybamm.equivalent_circuit.Thevenin with options {"number of rc elements": 2}). The module defines
// get_parameter_values() with the names and units of PyBaMM's own ECM example set
// (pybamm/input/parameters/ecm/example_set.py) plus "R2 [Ohm]", "C2 [F]" and "Element-2 initial overpotential
// [V]" for the second RC pair. The data are written into the module (no side files): every table is tabulated on
// a grid by cellbench's own model, so the module carries what `cellbench simulate` computes:
//   - OCV(SoC): the table, linearly extrapolated to SoC 0 and 1 (as the model does);
//   - R0, R1, C1, R2, C2 (cell temperature degC, current A, SoC), PyBaMM's argument order and its sign
//     convention (current positive when it DIScharges the cell): the discharge table for positive current, the
//     charge table for negative; the Arrhenius factor of `resistance_temperature`, the Butler-Volmer factor of
//     `resistance_current` and `series_resistance_offset` applied where the set has them; the nearest table
//     value holds outside the SOC table (as in the model);
//   - dU/dT (OCV, cell temperature): the entropic coefficient of the set (table plus `entropic_heat`),
//     which PyBaMM looks up by OCV instead of SOC;
//   - thermal: PyBaMM couples the cell to a jig and the jig to the air. cellbench's one thermal resistance
//     cell -> ambient becomes cell -> jig in series with a stiff jig -> air (99 % and 1 % of R_th), the jig's
//     thermal mass giving it a 1 s time constant, so the jig follows the air as cellbench's ambient does.
// Numbers are written in their shortest round-trip form.
#include <algorithm>
#include <charconv>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <sstream>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "cellbench/core/recording.hpp"
#include "cellbench/core/version.hpp"
#include "cellbench/estimator/model.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

namespace {

constexpr double kZeroCelsiusK = 273.15;

std::string python_float(double v) {
    if (!std::isfinite(v)) throw std::runtime_error("export-params: a value is not finite");
    if (v == 0.0) return "0.0";
    char buf[32];
    const auto r = std::to_chars(buf, buf + sizeof buf, v);
    std::string s(buf, r.ptr);
    // A Python float literal either way ("3" would be an int; harmless, but keep the arrays float).
    if (s.find_first_of(".eEn") == std::string::npos) s += ".0";
    return s;
}

std::string py_list(const std::vector<double>& v) {
    std::string s = "[";
    for (std::size_t i = 0; i < v.size(); ++i) {
        if (i) s += i % 8 == 0 ? ",\n    " : ", ";
        s += python_float(v[i]);
    }
    return s + "]";
}

std::vector<double> unique_sorted(std::vector<double> v) {
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end(), [](double a, double b) { return std::abs(a - b) < 1e-12; }), v.end());
    return v;
}

}  // namespace

int run_export_params(const ExportParamsOptions& o) {
    if (o.format != "pybamm") throw InputError("export-params: --format " + o.format + ": expected pybamm");
    OutputFiles outputs({o.output});
    const auto params = load_params(o.params);
    const estimator::CellModel model(params);
    const auto& ext = params.extensions;

    // Grids. SoC: the table's breakpoints and 0 and 1. Temperature: the usual operating range and the
    // reference temperature. Current (PyBaMM sign, A): both directions up to 5C, with small currents on either
    // side of zero so the switch between the charge and discharge tables is sharp.
    std::vector<double> soc_grid = params.soc;
    soc_grid.push_back(0.0);
    soc_grid.push_back(1.0);
    soc_grid = unique_sorted(soc_grid);
    soc_grid.erase(std::remove_if(soc_grid.begin(), soc_grid.end(), [](double s) { return s < 0.0 || s > 1.0; }),
                   soc_grid.end());
    std::vector<double> t_grid = {-20.0, -10.0, 0.0, 10.0, 20.0, 25.0, 30.0, 40.0, 50.0, 60.0};
    t_grid.push_back(params.reference_temperature_c);
    t_grid = unique_sorted(t_grid);
    const double c_a = model.capacity_ah();  // 1C in A
    std::vector<double> i_grid;
    for (double c_rate : {5.0, 2.0, 1.0, 0.5, 0.1, 0.001}) {
        i_grid.push_back(-c_rate * c_a);
        i_grid.push_back(c_rate * c_a);
    }
    i_grid = unique_sorted(i_grid);
    const double lookup_limit_a = i_grid.back();

    // Element tables, C order (temperature slowest, then current, SoC fastest) as PyBaMM's 3D interpolants.
    std::vector<double> r0, r1, c1, r2, c2;
    const double dr0 = ext.series_resistance_offset ? ext.series_resistance_offset->r_ohm : 0.0;
    for (double t : t_grid) {
        const double f_t = model.resistance_factor(t);
        for (double i : i_grid) {
            const bool discharge = i > 0;  // PyBaMM: positive current discharges
            const auto& table = discharge ? params.discharge : params.charge;
            const double f_i = model.current_factor(i);
            for (double s : soc_grid) {
                // C is held when R scales (tau = R*C scales with R), as in the model.
                r0.push_back(estimator::interp_hold(params.soc, table.r0_ohm, s) * f_t + dr0);
                r1.push_back(estimator::interp_hold(params.soc, table.r1_ohm, s) * f_t * f_i);
                c1.push_back(estimator::interp_hold(params.soc, table.c1_f, s));
                r2.push_back(estimator::interp_hold(params.soc, table.r2_ohm, s) * f_t * f_i);
                c2.push_back(estimator::interp_hold(params.soc, table.c2_f, s));
            }
        }
    }

    // OCV and the entropic coefficient (looked up by OCV in PyBaMM: the OCV axis must ascend strictly).
    std::vector<double> ocv, dudt_ocv, dudt;
    for (double s : soc_grid) ocv.push_back(params.ocv_at(s));
    std::vector<double> dudt_soc;
    for (std::size_t k = 0; k < soc_grid.size(); ++k) {
        if (!dudt_ocv.empty() && ocv[k] <= dudt_ocv.back() + 1e-9) continue;
        dudt_ocv.push_back(ocv[k]);
        dudt_soc.push_back(soc_grid[k]);
    }
    for (std::size_t k = 0; k < dudt_ocv.size(); ++k) {
        double e = params.ehc_at(dudt_soc[k]);
        if (ext.entropic_heat) e += ext.entropic_heat->ehc_v_per_k + ext.entropic_heat->ehc_slope_v_per_k * (dudt_soc[k] - 0.5);
        for (std::size_t j = 0; j < t_grid.size(); ++j) dudt.push_back(e);  // no temperature dependence known
    }
    if (dudt_ocv.size() < 2) throw InputError(o.params + ": $.ocv_v: OCV must rise with SOC to export dU/dT by OCV");

    // Thermal: cell -> jig (99 % of R_th) -> air (1 %), the jig's time constant 1 s.
    const double r_th = params.thermal.r_th_k_per_w, c_th = params.thermal.c_th_j_per_k;
    if (!(r_th > 0 && c_th > 0))
        throw InputError(o.params + ": $.thermal: c_th_j_per_k and r_th_k_per_w must be positive to export");
    const double k_cell_jig = 1.0 / (0.99 * r_th), k_jig_air = 1.0 / (0.01 * r_th);
    const double c_jig = k_jig_air * 1.0;
    const double t_ref_k = params.reference_temperature_c + kZeroCelsiusK;

    std::time_t now = std::time(nullptr);
    char date[32];
    std::strftime(date, sizeof date, "%Y-%m-%d", std::gmtime(&now));

    std::ostringstream py;
    py << "\"\"\"PyBaMM parameter set for the Thevenin equivalent-circuit model: " << params.cell << ".\n\n"
       << "Written by cellbench " << cellbench::version_string() << " (export-params --format pybamm) on " << date
       << "\nfrom " << std::filesystem::path(o.params).filename().string() << ". Names and units are those of PyBaMM's ECM example set\n"
       << "(pybamm/input/parameters/ecm/example_set.py), with a second RC element. Use it with two RC elements:\n\n"
       << "    import importlib.util, pybamm\n"
       << "    spec = importlib.util.spec_from_file_location(\"cell\", \"" << std::filesystem::path(o.output).filename().string()
       << "\")\n"
       << "    cell = importlib.util.module_from_spec(spec); spec.loader.exec_module(cell)\n"
       << "    model = pybamm.equivalent_circuit.Thevenin(options=cell.MODEL_OPTIONS)\n"
       << "    values = pybamm.ParameterValues(cell.get_parameter_values())\n"
       << "    sim = pybamm.Simulation(model, parameter_values=values)\n\n"
       << "Functions of cell temperature take degC (PyBaMM's ECM convention); currents are positive when they\n"
       << "discharge the cell (PyBaMM's convention; cellbench records charge as positive).\n"
       << "\"\"\"\n\n"
       << "import numpy as np\nimport pybamm\n\n"
       << "MODEL_OPTIONS = {\"number of rc elements\": 2}\n\n"
       << "# Grids of the look-up tables.\n"
       << "SOC = np.array(" << py_list(soc_grid) << ")\n"
       << "CELL_TEMPERATURE_DEGC = np.array(" << py_list(t_grid) << ")\n"
       << "CURRENT_A = np.array(" << py_list(i_grid) << ")  # positive discharges\n\n"
       << "OCV_V = np.array(" << py_list(ocv) << ")\n"
       << "DUDT_OCV_V = np.array(" << py_list(dudt_ocv) << ")\n"
       << "DUDT_V_PER_K = np.array(" << py_list(dudt) << ").reshape(" << dudt_ocv.size() << ", " << t_grid.size()
       << ")\n\n";
    const std::string shape = "(" + std::to_string(t_grid.size()) + ", " + std::to_string(i_grid.size()) + ", " +
                              std::to_string(soc_grid.size()) + ")";
    for (const auto& [name, v] : {std::pair{"R0_OHM", &r0}, {"R1_OHM", &r1}, {"C1_F", &c1}, {"R2_OHM", &r2}, {"C2_F", &c2}})
        py << name << " = np.array(" << py_list(*v) << ").reshape" << shape << "\n";
    py << "\n\n"
       << "def ocv(sto):\n"
       << "    return pybamm.Interpolant([SOC], OCV_V, sto, \"ocv\")\n\n\n";
    for (const auto& [fn, table] : {std::pair{"r0", "R0_OHM"}, {"r1", "R1_OHM"}, {"c1", "C1_F"}, {"r2", "R2_OHM"}, {"c2", "C2_F"}})
        py << "def " << fn << "(T_cell, current, soc):\n"
           << "    return pybamm.Interpolant(\n"
           << "        (CELL_TEMPERATURE_DEGC, CURRENT_A, SOC), " << table << ", [T_cell, current, soc], \"" << fn << "\"\n"
           << "    )\n\n\n";
    py << "def dUdT(ocv, T_cell):\n"
       << "    return pybamm.Interpolant((DUDT_OCV_V, CELL_TEMPERATURE_DEGC), DUDT_V_PER_K, [ocv, T_cell], \"dUdT\")\n\n\n"
       << "def get_parameter_values():\n"
       << "    \"\"\"Parameters of " << params.cell << " for pybamm.equivalent_circuit.Thevenin (2 RC elements).\"\"\"\n"
       << "    return {\n"
       << "        \"chemistry\": \"ecm\",\n"
       << "        \"Initial SoC\": " << python_float(o.initial_soc) << ",\n"
       << "        \"Initial temperature [K]\": " << python_float(t_ref_k) << ",\n"
       << "        \"Cell capacity [A.h]\": " << python_float(model.capacity_ah()) << ",\n"
       << "        \"Nominal cell capacity [A.h]\": " << python_float(params.capacity_ah) << ",\n"
       << "        \"Ambient temperature [K]\": " << python_float(t_ref_k) << ",\n"
       << "        \"Current function [A]\": " << python_float(c_a) << ",  # 1C discharge\n"
       << "        \"Upper voltage cut-off [V]\": " << python_float(o.upper_cutoff_v) << ",\n"
       << "        \"Lower voltage cut-off [V]\": " << python_float(o.lower_cutoff_v) << ",\n"
       << "        \"Cell thermal mass [J/K]\": " << python_float(c_th) << ",\n"
       << "        \"Cell-jig heat transfer coefficient [W/K]\": " << python_float(k_cell_jig) << ",\n"
       << "        \"Jig thermal mass [J/K]\": " << python_float(c_jig) << ",\n"
       << "        \"Jig-air heat transfer coefficient [W/K]\": " << python_float(k_jig_air) << ",\n"
       << "        \"Open-circuit voltage [V]\": ocv,\n"
       << "        \"R0 [Ohm]\": r0,\n"
       << "        \"Element-1 initial overpotential [V]\": 0.0,\n"
       << "        \"R1 [Ohm]\": r1,\n"
       << "        \"C1 [F]\": c1,\n"
       << "        \"Element-2 initial overpotential [V]\": 0.0,\n"
       << "        \"R2 [Ohm]\": r2,\n"
       << "        \"C2 [F]\": c2,\n"
       << "        \"Entropic change [V/K]\": dUdT,\n"
       << "        \"RCR lookup limit [A]\": " << python_float(lookup_limit_a) << ",\n"
       << "    }\n";

    outputs.write(o.output, [&](std::ostream& out) { out << py.str(); });
    outputs.commit();
    std::vector<std::string> left_out;
    const nlohmann::json ext_json = ext.to_json();  // items() refers to it: keep it alive through the loop
    for (const auto& [id, v] : ext_json.items())
        if (id != "resistance_temperature" && id != "resistance_current" && id != "series_resistance_offset" &&
            id != "entropic_heat" && id != "capacity_error")
            left_out.push_back(id);
    for (const auto& id : left_out)
        spdlog::warn("export-params: extension {} has no counterpart in PyBaMM's Thevenin model; left out", id);
    spdlog::info("wrote {} (PyBaMM Thevenin, 2 RC elements; {} SoC x {} temperatures x {} currents)", o.output,
                 soc_grid.size(), t_grid.size(), i_grid.size());
    return 0;
}

}  // namespace cellbench::cli
