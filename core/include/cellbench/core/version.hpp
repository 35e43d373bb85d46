#pragma once
// The version both binaries report (`cellbench --version`, `cellbenchd --version`, GET /health, /metrics'
// cellbench_build_info, the report's header): the CMake project version, plus `git describe` of the checkout
// at configure time when the source is a git work tree ("0.1.0 (git 250fb1f-dirty)").
#include <string>

namespace cellbench {

[[nodiscard]] const char* version();           // "0.1.0"
[[nodiscard]] const char* git_describe();      // "250fb1f-dirty", "" when not built from a git checkout
[[nodiscard]] std::string version_string();    // "0.1.0 (git 250fb1f-dirty)" or "0.1.0"

}  // namespace cellbench
