// The tests' command runner (tests/support/command.hpp): a hung command line fails with status 124 within its
// timeout, pipes and lists included, instead of blocking the suite; what it prints and its status come back.
#include <gtest/gtest.h>

#include <chrono>

#include "support/command.hpp"

namespace {

using cellbench::test::run_command;

TEST(CommandSupport, TheWholeCommandLineRunsUnderTheTimeout) {
    const auto t0 = std::chrono::steady_clock::now();
    // Both the first and the last command of a pipe hang: before, only the first ran under `timeout`.
    const auto r = run_command("sleep 120 | sleep 120", 1);
    EXPECT_EQ(r.status, 124);
    // A bound that only a hang past the timeout breaks (the runner waits for the pipe's last writer).
    EXPECT_LT(std::chrono::steady_clock::now() - t0, std::chrono::seconds(100));
}

TEST(CommandSupport, OutputStatusAndQuotesComeThrough) {
    const auto r = run_command("echo 'it'\"'\"'s' && echo oops >&2; exit 3");
    EXPECT_EQ(r.status, 3);
    EXPECT_NE(r.output.find("it's"), std::string::npos) << r.output;
    EXPECT_NE(r.output.find("oops"), std::string::npos) << r.output;
    const auto e = run_command("echo out; echo err >&2", 60, cellbench::test::Capture::stderr_only);
    EXPECT_EQ(e.output, "err\n");
}

}  // namespace
