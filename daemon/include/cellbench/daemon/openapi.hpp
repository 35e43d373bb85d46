#pragma once
// GET /api/v1/openapi.json: the OpenAPI 3.1 description of every endpoint of cellbenchd. The document is
// daemon/src/openapi.json, compiled in at build time (daemon/CMakeLists.txt), so it ships with the binary;
// tests/unit/openapi_test.cpp checks that it names every route the server answers and nothing else.
#include <string_view>

namespace cellbench::daemon {

[[nodiscard]] std::string_view openapi_json();

}  // namespace cellbench::daemon
