#pragma once
// The thesis' P45B parameter set shipped with the project (config/cells/p45b-thesis.json), for tests that need a
// realistic cell model.
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "cellbench/estimator/params.hpp"

namespace cellbench::test {

inline estimator::ParameterSet thesis_parameter_set() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    return estimator::ParameterSet::from_json(nlohmann::json::parse(in), "p45b-thesis.json");
}

}  // namespace cellbench::test
