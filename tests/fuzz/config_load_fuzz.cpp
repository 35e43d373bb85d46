// libFuzzer target: the daemon's configuration loaders (bench, cell, program files as JSON text, and the
// expression language of programs) must load any text or throw InputError/ConfigError naming the source;
// never crash, hang or misbehave. A program that loads must read back unchanged from its expanded JSON
// (config.hpp: Program::to_json). Relative file references resolve against the repository's config/, so
// the seeds reach the referenced parameter sets.
// Mode: the first byte (0 bench, 1 cell, 2 program for the p45b cell, 3 program against the simulated
// bench too, 4 an expression); the rest is the text.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

#include "cellbench/core/recording.hpp"
#include "cellbench/daemon/config.hpp"

using namespace cellbench;
using namespace cellbench::daemon;
namespace fs = std::filesystem;

namespace {

void check(bool condition) {
    if (!condition) __builtin_trap();
}

const fs::path kConfigDir = fs::path(CELLBENCH_SOURCE_DIR) / "config";

constexpr std::string_view kCell = R"({
  "schema": "cellbench.cell/1", "name": "P45B", "nominal_capacity_ah": 4.5,
  "min_voltage_v": 2.9, "max_voltage_v": 4.1, "max_charge_current_a": 13.5, "max_discharge_current_a": 45.0,
  "min_temperature_c": 0.0, "max_temperature_c": 60.0, "surface_area_m2": 0.005311})";

const CellConfig& cell() {
    static const CellConfig c = parse_cell_config_text(kCell, "p45b.json", kConfigDir / "cells", "p45b");
    return c;
}

const BenchConfig& bench() {
    static const BenchConfig b = load_bench_config(kConfigDir / "bench.sim.json");
    return b;
}

void check_error(const InputError& e, const std::string& source) {
    const std::string_view what = e.what();
    check(!what.empty());
    if (const auto* ce = dynamic_cast<const ConfigError*>(&e)) {
        check(!ce->issues().empty());
        // Issues in the file itself name it; a referenced file (a parameter set) names itself instead.
        bool names_source = false;
        for (const auto& issue : ce->issues()) names_source |= issue.file == source;
        check(names_source);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0) return 0;
    const unsigned mode = data[0] % 5;
    const std::string_view text(reinterpret_cast<const char*>(data) + 1, size - 1);
    const std::string source = "fuzz.json";
    (void)cell();
    (void)bench();
    try {
        switch (mode) {
            case 0:
                (void)parse_bench_config_text(text, source, kConfigDir);
                break;
            case 1:
                (void)parse_cell_config_text(text, source, kConfigDir / "cells", "fuzz");
                break;
            case 2:
            case 3: {
                const BenchConfig* b = mode == 3 ? &bench() : nullptr;
                const Program p = parse_program_text(text, source, cell(), {}, b);
                Program back;
                try {
                    back = parse_program(p.to_json(), "expanded.json", cell(), {}, b);
                } catch (const InputError&) {
                    check(false);  // an expanded program must load again
                }
                check(back == p);
                break;
            }
            default: {
                const double v = evaluate_expression(text, {{"c_rate", 1.0}, {"one_c_a", 4.5}, {"x", -0.0}});
                check(std::isfinite(v));
                break;
            }
        }
    } catch (const InputError& e) {
        if (mode != 4) check_error(e, source);
    }
    return 0;
}
