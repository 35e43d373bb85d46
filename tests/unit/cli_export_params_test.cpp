// `cellbench export-params --format pybamm PARAMS.json -o FILE` (INTERFACES.md): a Python module that PyBaMM's
// Thevenin equivalent-circuit model loads. PyBaMM itself is not installable here, so the module is executed by
// python3 (with numpy and scipy, Debian packages that `make deps` installs) against a stub of the one PyBaMM
// name it uses, pybamm.Interpolant, which checks the interpolant's argument contract (grids ascending, data
// shaped like the grids, one child per grid) and evaluates it like PyBaMM's linear interpolant does.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <string>

#include <nlohmann/json.hpp>

#include "support/command.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kThesis = fs::path(CELLBENCH_SOURCE_DIR) / "config/cells/p45b-thesis.json";

// The parameter names (with their units) of PyBaMM's ECM example parameter set, read from
// pybamm/input/parameters/ecm/example_set.py in github.com/pybamm-team/PyBaMM (src/pybamm/..., commit
// 20d3020aef287893d449e2f1b82b2ad0bb3f5e5e), get_parameter_values(). Function parameters take the arguments
// listed there: ocv(sto); r0, r1, c1(T_cell [degC], current [A, positive discharging], soc);
// dUdT(ocv [V], T_cell [degC]) (argument names from src/pybamm/parameters/ecm_parameters.py).
const std::set<std::string> kPybammEcmExampleNames = {
    "chemistry",
    "Initial SoC",
    "Initial temperature [K]",
    "Cell capacity [A.h]",
    "Nominal cell capacity [A.h]",
    "Ambient temperature [K]",
    "Current function [A]",
    "Upper voltage cut-off [V]",
    "Lower voltage cut-off [V]",
    "Cell thermal mass [J/K]",
    "Cell-jig heat transfer coefficient [W/K]",
    "Jig thermal mass [J/K]",
    "Jig-air heat transfer coefficient [W/K]",
    "Open-circuit voltage [V]",
    "R0 [Ohm]",
    "Element-1 initial overpotential [V]",
    "R1 [Ohm]",
    "C1 [F]",
    "Entropic change [V/K]",
    "RCR lookup limit [A]",
};
// The second RC element, named as PyBaMM's RC element submodel names element i (R{i} [Ohm], C{i} [F],
// Element-{i} initial overpotential [V]; examples/scripts/run_ecm.py sets exactly these for 2 elements).
const std::set<std::string> kSecondElementNames = {"R2 [Ohm]", "C2 [F]", "Element-2 initial overpotential [V]"};

// Loads the module with a stub `pybamm`, evaluates every function over SoC 0..1, -10..60 degC and both current
// directions, and prints what it found as JSON.
const char* kChecker = R"PY(
import importlib.util, inspect, json, math, sys, types
import numpy as np
from scipy.interpolate import RegularGridInterpolator

class Interpolant:
    def __init__(self, x, y, children, name):
        grids = [np.asarray(g, dtype=float) for g in x]
        kids = children if isinstance(children, (list, tuple)) else [children]
        y = np.asarray(y, dtype=float)
        assert len(grids) == len(kids) == y.ndim, name + ": grids, children and data dimensions differ"
        for k, g in enumerate(grids):
            assert g.ndim == 1 and len(g) == y.shape[k], name + ": grid and data shapes differ"
            assert np.all(np.diff(g) > 0), name + ": grid not strictly ascending"
        f = RegularGridInterpolator(tuple(grids), y, bounds_error=False, fill_value=None)
        self.value = float(f([[float(c) for c in kids]])[0])

pybamm = types.ModuleType("pybamm")
pybamm.Interpolant = Interpolant
sys.modules["pybamm"] = pybamm
spec = importlib.util.spec_from_file_location("exported", sys.argv[1])
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
values = mod.get_parameter_values()
out = {"names": sorted(values), "options": mod.MODEL_OPTIONS, "arity": {}, "scalars": {}, "bad": [], "evaluated": 0}
for k, v in values.items():
    if callable(v):
        out["arity"][k] = len(inspect.signature(v).parameters)
    else:
        out["scalars"][k] = v
val = lambda s: s.value
for soc in np.linspace(0.0, 1.0, 21):
    u = val(values["Open-circuit voltage [V]"](soc))
    if not (2.0 < u < 5.0): out["bad"].append(["ocv", soc, u])
    for t in (-10.0, 0.0, 25.0, 45.0, 60.0):
        d = val(values["Entropic change [V/K]"](u, t))
        if not (math.isfinite(d) and abs(d) < 5e-3): out["bad"].append(["dUdT", u, t, d])
        for i in (-20.0, -4.0, -0.1, 0.1, 4.0, 20.0):
            for name in ("R0 [Ohm]", "R1 [Ohm]", "C1 [F]", "R2 [Ohm]", "C2 [F]"):
                x = val(values[name](t, i, soc))
                out["evaluated"] += 1
                if not (math.isfinite(x) and x > 0): out["bad"].append([name, t, i, soc, x])
f = lambda name, t, i, s: val(values[name](t, i, s))
out["probe"] = {
    "ocv_0.5": val(values["Open-circuit voltage [V]"](0.5)),
    "r0_30C_discharge_0.5": f("R0 [Ohm]", 30.0, 4.0, 0.5),
    "r0_30C_charge_0.5": f("R0 [Ohm]", 30.0, -4.0, 0.5),
    "r0_0C_discharge_0.5": f("R0 [Ohm]", 0.0, 4.0, 0.5),
    "r1_30C_discharge_0.5": f("R1 [Ohm]", 30.0, 4.0, 0.5),
    "c2_30C_charge_0.5": f("C2 [F]", 30.0, -4.0, 0.5),
}
print(json.dumps(out))
)PY";

using Run = cellbench::test::CommandRun;

Run run(const std::string& cmd) { return cellbench::test::run_command(cmd, 120); }

// A python3 that has numpy and scipy (Debian's /usr/bin/python3 after `make deps`; a pyenv shim first on PATH
// may lack them).
std::string python_with_numpy() {
    for (const char* py : {"/usr/bin/python3", "python3"})
        if (run(std::string(py) + " -c 'import numpy, scipy'").status == 0) return py;
    return {};
}

class ExportParams : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("cellbench-export-" + std::to_string(::getpid()) + "-" +
                                            ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::create_directories(dir_);
        std::ofstream(dir_ / "check.py") << kChecker;
        python_ = python_with_numpy();
        ASSERT_FALSE(python_.empty()) << "no python3 with numpy and scipy (make deps installs python3-numpy python3-scipy)";
    }
    void TearDown() override { fs::remove_all(dir_); }

    // Exports `params` and runs the checker on the module; returns its JSON report.
    json export_and_check(const fs::path& params) {
        const auto module = dir_ / "cell_pybamm.py";
        const auto e = run(kBin.string() + " export-params --format pybamm " + params.string() + " -o " + module.string());
        EXPECT_EQ(e.status, 0) << e.output;
        const auto c = run(python_ + " " + (dir_ / "check.py").string() + " " + module.string());
        EXPECT_EQ(c.status, 0) << c.output;
        const auto brace = c.output.find('{');
        if (brace == std::string::npos) return json::object();
        return json::parse(c.output.substr(brace));
    }
    fs::path dir_;
    std::string python_;
};

}  // namespace

TEST_F(ExportParams, NamesAndUnitsAreThoseOfPybammsEcmExampleSetWithASecondRcElement) {
    const json r = export_and_check(kThesis);
    ASSERT_TRUE(r.contains("names"));
    std::set<std::string> expected = kPybammEcmExampleNames;
    expected.insert(kSecondElementNames.begin(), kSecondElementNames.end());
    const auto names = r["names"].get<std::set<std::string>>();
    EXPECT_EQ(names, expected);
    EXPECT_EQ(r["options"], json({{"number of rc elements", 2}}));
    // Functions take PyBaMM's arguments: ocv(sto), elements(T_cell, current, soc), dUdT(ocv, T_cell).
    EXPECT_EQ(r["arity"], json({{"Open-circuit voltage [V]", 1}, {"R0 [Ohm]", 3}, {"R1 [Ohm]", 3}, {"C1 [F]", 3},
                                {"R2 [Ohm]", 3}, {"C2 [F]", 3}, {"Entropic change [V/K]", 2}}));
    // Units: kelvin temperatures, the thesis cell's capacity and thermal parameters (C_th 63.3 J/K; the
    // cell -> jig -> air resistances in series give back R_th).
    const auto& s = r["scalars"];
    EXPECT_EQ(s["chemistry"], "ecm");
    EXPECT_NEAR(s["Initial temperature [K]"].get<double>(), 30.0 + 273.15, 1e-9);
    EXPECT_NEAR(s["Ambient temperature [K]"].get<double>(), 30.0 + 273.15, 1e-9);
    EXPECT_NEAR(s["Cell capacity [A.h]"].get<double>(), 4.0, 1e-12);
    EXPECT_GT(s["Cell thermal mass [J/K]"].get<double>(), 10.0);
    const double r_series = 1.0 / s["Cell-jig heat transfer coefficient [W/K]"].get<double>() +
                            1.0 / s["Jig-air heat transfer coefficient [W/K]"].get<double>();
    const json thesis = json::parse(std::ifstream(kThesis));
    EXPECT_NEAR(r_series, thesis["thermal"]["r_th_k_per_w"].get<double>(), 1e-9);
    EXPECT_NEAR(s["Cell thermal mass [J/K]"].get<double>(), thesis["thermal"]["c_th_j_per_k"].get<double>(), 1e-9);
}

TEST_F(ExportParams, FunctionsEvaluateOverSocTemperatureAndBothCurrentDirections) {
    const json r = export_and_check(kThesis);
    ASSERT_TRUE(r.contains("bad"));
    EXPECT_EQ(r["bad"], json::array()) << "values out of range";
    EXPECT_EQ(r["evaluated"].get<int>(), 21 * 5 * 6 * 5);
    // The values are the thesis table's: OCV(0.5) 3.72 V; R0 at SOC 0.5 discharge 7.34 mOhm, the charge table
    // for negative (charging, in PyBaMM's sign) current.
    const json thesis = json::parse(std::ifstream(kThesis));
    const auto& p = r["probe"];
    EXPECT_NEAR(p["ocv_0.5"].get<double>(), 3.72, 1e-9);
    EXPECT_NEAR(p["r0_30C_discharge_0.5"].get<double>(), thesis["discharge"]["r0_ohm"][5].get<double>(), 1e-9);
    EXPECT_NEAR(p["r0_30C_charge_0.5"].get<double>(), thesis["charge"]["r0_ohm"][5].get<double>(), 1e-9);
    EXPECT_NEAR(p["c2_30C_charge_0.5"].get<double>(), thesis["charge"]["c2_f"][5].get<double>(), 1e-6);
    // Without a temperature extension the tables do not depend on temperature.
    EXPECT_NEAR(p["r0_0C_discharge_0.5"].get<double>(), p["r0_30C_discharge_0.5"].get<double>(), 1e-12);
}

TEST_F(ExportParams, ArrheniusAndSeriesOffsetExtensionsReachTheTables) {
    json set = json::parse(std::ifstream(kThesis));
    set["extensions"] = {{"resistance_temperature", {{"activation_energy_j_per_mol", 30000.0}}},
                         {"series_resistance_offset", {{"r_ohm", 0.001}}}};
    const auto params = dir_ / "ext.json";
    std::ofstream(params) << set.dump();
    const json r = export_and_check(params);
    ASSERT_TRUE(r.contains("probe"));
    EXPECT_EQ(r["bad"], json::array());
    const auto& p = r["probe"];
    const double r0_table = set["discharge"]["r0_ohm"][5].get<double>();
    EXPECT_NEAR(p["r0_30C_discharge_0.5"].get<double>(), r0_table + 0.001, 1e-9);  // at the reference temperature
    // Colder: R0 = R0(30 degC) * exp(Ea/R (1/273.15 - 1/303.15)) + offset.
    const double f = std::exp(30000.0 / 8.314462618 * (1.0 / 273.15 - 1.0 / 303.15));
    EXPECT_NEAR(p["r0_0C_discharge_0.5"].get<double>(), r0_table * f + 0.001, 1e-4 * r0_table * f);
}

TEST_F(ExportParams, UnknownFormatIsAUsageErrorAndNoFileIsLeft) {
    const auto out = dir_ / "x.py";
    const auto e = run(kBin.string() + " export-params --format matlab " + kThesis.string() + " -o " + out.string());
    EXPECT_EQ(e.status, 2) << e.output;
    EXPECT_FALSE(fs::exists(out));
    const auto h = run(kBin.string() + " export-params --help");
    EXPECT_EQ(h.status, 0);
    EXPECT_NE(h.output.find("--format"), std::string::npos);
}
