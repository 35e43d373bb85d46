// diagnose on a one-hour recording, one core (DiagnoseOptions::threads = 1): the goal is under 10 s.
#include <benchmark/benchmark.h>

#include <fstream>
#include <sstream>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/generate.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

struct Case {
    ParameterSet fitted;
    Recording validation;
};

const Case& one_hour_case() {
    static const Case c = [] {
        std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
        std::stringstream ss;
        ss << in.rdbuf();
        GeneratorOptions g;
        g.seed = 1;
        g.hidden_effect = "resistance_temperature";
        const auto gen = generate_case(ParameterSet::from_json(nlohmann::json::parse(ss.str())), g);
        return Case{characterize({gen.characterization}).params, gen.validation};
    }();
    return c;
}

void BM_DiagnoseOneCore(benchmark::State& state) {
    const auto& c = one_hour_case();
    DiagnoseOptions o;
    o.threads = 1;
    for (auto _ : state) benchmark::DoNotOptimize(diagnose(c.fitted, c.validation, o).accepted.size());
    state.counters["recording_s"] = c.validation.time_s.back() - c.validation.time_s.front();
    state.counters["rows"] = static_cast<double>(c.validation.size());
}
BENCHMARK(BM_DiagnoseOneCore)->Unit(benchmark::kSecond)->Iterations(1);

}  // namespace

BENCHMARK_MAIN();
