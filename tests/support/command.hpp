#pragma once
// Running a command line from a test as a user's shell does (the built `cellbench`, `cellbenchd`), and reading
// what it wrote. Every run is bounded by `timeout`, so a regression that hangs fails with status 124 instead of
// blocking the suite.
#include <sys/wait.h>

#include <cstddef>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

namespace cellbench::test {

struct CommandRun {
    int status = -1;     // the exit status (124: timed out; -1: did not exit)
    std::string output;  // what it printed: stdout and stderr, or stderr alone
};

enum class Capture { stdout_and_stderr, stderr_only };

// `command` in single quotes for a shell (a ' in it closed, escaped and reopened).
inline std::string shell_quoted(const std::string& command) {
    std::string q = "'";
    for (char c : command) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
    return q + "'";
}

// `command` is a shell command line; the whole of it (pipes, lists and redirections included) runs under
// `timeout timeout_s`, in a shell of its own.
inline CommandRun run_command(const std::string& command, int timeout_s = 60,
                              Capture capture = Capture::stdout_and_stderr) {
    const char* redirect = capture == Capture::stderr_only ? " 2>&1 1>/dev/null" : " 2>&1";
    CommandRun r;
    FILE* p = popen(("timeout " + std::to_string(timeout_s) + " sh -c " + shell_quoted(command) + redirect).c_str(), "r");
    if (!p) return r;
    char buf[4096];
    for (std::size_t n; (n = fread(buf, 1, sizeof buf, p)) > 0;) r.output.append(buf, n);
    const int st = pclose(p);
    r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return r;
}

// The built command-line tool.
inline std::filesystem::path cellbench_bin() { return std::filesystem::path(CELLBENCH_BIN_DIR) / "cellbench"; }

// `cellbench ARGS` (stdout and stderr); fits and diagnoses of real recordings take up to a minute.
inline CommandRun run_cellbench(const std::string& args, int timeout_s = 600) {
    return run_command(cellbench_bin().string() + " " + args, timeout_s);
}

inline std::string slurp(const std::filesystem::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

inline nlohmann::json read_json(const std::filesystem::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}

inline std::size_t count_lines_starting(const std::string& text, const std::string& prefix) {
    std::istringstream in(text);
    std::size_t n = 0;
    for (std::string line; std::getline(in, line);) n += line.rfind(prefix, 0) == 0;
    return n;
}

// The cellbench contract for bad input: status 1 and exactly one error line, which names `what` (a file:line, a
// path...). `r.output` holds what the command wrote to stderr.
inline ::testing::AssertionResult fails_once_naming(const CommandRun& r, const std::string& what) {
    if (r.status != 1) return ::testing::AssertionFailure() << "status " << r.status << ", stderr:\n" << r.output;
    if (count_lines_starting(r.output, "error: ") != 1)
        return ::testing::AssertionFailure() << "expected one error line, stderr:\n" << r.output;
    if (r.output.find(what) == std::string::npos)
        return ::testing::AssertionFailure() << "message does not name \"" << what << "\":\n" << r.output;
    return ::testing::AssertionSuccess();
}

}  // namespace cellbench::test
