#pragma once
// Test support for the cellbenchd configuration tests (config_test, fault_policy_config_test): where the shipped
// configuration lives, and how a test collects and looks up the issues of a ConfigError.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/config.hpp"

namespace cellbench::testing {

// The shipped configuration files (config/ of the source tree).
inline const std::filesystem::path kConfigDir = std::filesystem::path(CELLBENCH_SOURCE_DIR) / "config";

inline nlohmann::json read_json(const std::filesystem::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}

// The issues of the ConfigError that f throws, or fails the test (f must reject its input).
inline std::vector<daemon::ConfigIssue> issues_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const daemon::ConfigError& e) {
        return e.issues();
    }
    ADD_FAILURE() << "expected a ConfigError";
    return {};
}

// Whether an issue names exactly this JSON path and its message contains words.
inline bool has_issue(const std::vector<daemon::ConfigIssue>& issues, const std::string& path,
                      const std::string& words = "") {
    for (const auto& i : issues)
        if (i.path == path && i.message.find(words) != std::string::npos) return true;
    return false;
}

}  // namespace cellbench::testing
