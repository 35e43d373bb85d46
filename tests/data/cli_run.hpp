#pragma once
// Running the built `cellbench` from the data tests, as a user does, and reading what it wrote.
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

namespace cellbench::test {

struct CliRun {
    int status;
    std::string output;  // stdout and stderr
};

inline CliRun run_cli(const std::string& args) {
    const std::string cmd = (std::filesystem::path(CELLBENCH_BIN_DIR) / "cellbench").string() + " " + args + " 2>&1";
    CliRun r{0, {}};
    FILE* p = popen(cmd.c_str(), "r");
    char buf[4096];
    while (p && fgets(buf, sizeof buf, p)) r.output += buf;
    const int st = p ? pclose(p) : -1;
    r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return r;
}

inline nlohmann::json read_json(const std::filesystem::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}

}  // namespace cellbench::test
