// Long offline commands (`cellbench fit`, `cellbench diagnose`) show a progress line on a terminal and print
// no progress at all when piped. The terminal is a pseudo-terminal here (forkpty), so the same binary is
// checked both ways on the same input.
#include <gtest/gtest.h>

#include "support/command.hpp"

#include <pty.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

namespace fs = std::filesystem;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kThesis = fs::path(CELLBENCH_SOURCE_DIR) / "config/cells/p45b-thesis.json";

using CliRun = cellbench::test::CommandRun;  // output: stdout and stderr together

// stdout and stderr into one pipe: what a script or `| tee log` sees.
CliRun run_piped(const std::string& args) { return cellbench::test::run_cellbench(args); }

// stdout and stderr on a pseudo-terminal: what an operator at a shell sees.
CliRun run_on_terminal(const std::string& args) {
    int master = -1;
    winsize ws{};
    ws.ws_col = 120;
    ws.ws_row = 40;
    const pid_t pid = forkpty(&master, nullptr, nullptr, &ws);
    if (pid == 0) {
        const std::string cmd = kBin.string() + " " + args;
        execl("/bin/sh", "sh", "-c", cmd.c_str(), static_cast<char*>(nullptr));
        _exit(127);
    }
    CliRun r;
    if (pid < 0) return r;
    char buf[4096];
    for (;;) {
        const ssize_t n = read(master, buf, sizeof buf);
        if (n > 0) r.output.append(buf, static_cast<std::size_t>(n));
        else if (n < 0 && errno == EINTR) continue;
        else break;  // EIO once the child has closed the terminal
    }
    close(master);
    int st = 0;
    waitpid(pid, &st, 0);
    r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return r;
}

bool has_control_characters(const std::string& s) {
    return s.find('\r') != std::string::npos || s.find('\033') != std::string::npos;
}

class CliProgress : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("cellbench-cli-progress-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        const auto gen = run_piped("generate --base " + kThesis.string() + " --effect none --seed 1 -o " + dir_.string());
        ASSERT_EQ(gen.status, 0) << gen.output;
    }
    static void TearDownTestSuite() { fs::remove_all(dir_); }
    static fs::path dir_;
};
fs::path CliProgress::dir_;

}  // namespace

TEST_F(CliProgress, FitShowsProgressOnATerminalOnly) {
    const std::string args = "fit " + (dir_ / "characterization.bdf.csv").string() + " -o " + (dir_ / "p.json").string();
    const auto piped = run_piped(args);
    ASSERT_EQ(piped.status, 0) << piped.output;
    EXPECT_FALSE(has_control_characters(piped.output)) << "progress control characters in piped output:\n"
                                                       << piped.output;
    EXPECT_EQ(piped.output.find("pulse sets "), std::string::npos) << piped.output;
    EXPECT_NE(piped.output.find("capacity"), std::string::npos) << "the results are still printed:\n" << piped.output;

    const auto tty = run_on_terminal(args);
    ASSERT_EQ(tty.status, 0) << tty.output;
    EXPECT_NE(tty.output.find("\rfit "), std::string::npos) << tty.output;
    EXPECT_NE(tty.output.find("% ["), std::string::npos) << tty.output;
    EXPECT_NE(tty.output.find("pulse sets "), std::string::npos) << tty.output;
    EXPECT_NE(tty.output.find("\r\033[K"), std::string::npos) << "the line is erased before the results";
}

TEST_F(CliProgress, DiagnoseShowsProgressOnATerminalOnly) {
    const std::string args = "diagnose --params " + kThesis.string() + " " + (dir_ / "validation.bdf.csv").string() +
                             " --effects capacity_error";
    const auto piped = run_piped(args);
    ASSERT_EQ(piped.status, 0) << piped.output;
    EXPECT_FALSE(has_control_characters(piped.output)) << "progress control characters in piped output:\n"
                                                       << piped.output;
    EXPECT_NE(piped.output.find("baseline RMS"), std::string::npos) << piped.output;

    const auto tty = run_on_terminal(args);
    ASSERT_EQ(tty.status, 0) << tty.output;
    EXPECT_NE(tty.output.find("\rdiagnose "), std::string::npos) << tty.output;
    EXPECT_NE(tty.output.find("round 1 candidates"), std::string::npos) << tty.output;
}
