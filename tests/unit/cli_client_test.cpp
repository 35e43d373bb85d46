// `cellbench status | runs | start | stop | pause | resume | export` run as the built binary against an
// in-test server with a fake backend: output, exit codes (0 ok, 1 failed, 2 usage) and the files written.
#include <gtest/gtest.h>

#include <poll.h>
#include <pty.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <vector>

#include "unit/api_test_support.hpp"

namespace fs = std::filesystem;
using namespace cellbench::testing;
using cellbench::daemon::HttpServerOptions;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const std::string kToken = "cli-test-token";

struct CliRun {
    int status = -1;
    std::string out, err;
};

std::string slurp(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::ostringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

class CliClient : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("cellbench-cli-client-" + std::to_string(::getpid()) + "-" +
                                            ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        fs::create_directories(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }

    void serve(HttpServerOptions opt = {}) {
        if (opt.token.empty()) opt.token = kToken;
        server_ = std::make_unique<TestServer>(backend_, opt);
        url_ = "http://127.0.0.1:" + std::to_string(server_->port());
    }

    // Runs cellbench with stdout and stderr captured separately (both pipes: not a terminal).
    CliRun run(const std::string& args, const std::string& env = "CELLBENCH_TOKEN= CELLBENCH_SERVER=") {
        const auto out = dir_ / "stdout.txt", err = dir_ / "stderr.txt";
        const std::string cmd =
            "env " + env + " " + kBin.string() + " " + args + " >" + out.string() + " 2>" + err.string() + " </dev/null";
        const int st = std::system(cmd.c_str());
        CliRun r;
        r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
        r.out = slurp(out);
        r.err = slurp(err);
        return r;
    }
    std::string server_args() const { return "--server " + url_; }

    FakeBackend backend_;
    std::unique_ptr<TestServer> server_;
    std::string url_;
    fs::path dir_;
};

bool contains(const std::string& s, const std::string& what) { return s.find(what) != std::string::npos; }

}  // namespace

TEST_F(CliClient, StatusPrintsInstrumentsRunAndLiveValues) {
    serve();
    auto r = run("status " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "neware")) << r.out;
    EXPECT_TRUE(contains(r.out, "connected")) << r.out;
    EXPECT_TRUE(contains(r.out, "offline")) << r.out;
    EXPECT_TRUE(contains(r.out, "no active run")) << r.out;
    EXPECT_TRUE(contains(r.out, "3.712 V")) << r.out;
    EXPECT_TRUE(contains(r.out, "SOC 62.1 %")) << r.out;
    EXPECT_TRUE(contains(r.out, "up 2 h 03 min")) << r.out;

    r = run("status --json " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    const auto j = json::parse(r.out);
    EXPECT_EQ(j["instruments"].size(), 2u);
    EXPECT_TRUE(j["run"].is_null());
}

TEST_F(CliClient, RunsTableAndJson) {
    serve();
    auto r = run("runs " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "PROGRAM")) << r.out;
    EXPECT_TRUE(contains(r.out, "hppc")) << r.out;
    EXPECT_TRUE(contains(r.out, "completed")) << r.out;
    r = run("runs --json " + server_args());
    ASSERT_EQ(r.status, 0);
    EXPECT_EQ(json::parse(r.out)["runs"][0]["id"], 1);
}

TEST_F(CliClient, StartNeedsTheTokenFromOptionOrEnvironment) {
    serve();
    auto r = run("start --program hppc --cell p45b " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "401")) << r.err;
    EXPECT_TRUE(contains(r.err, "bearer token")) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << "one clear message: " << r.err;

    r = run("start --program hppc --cell p45b --token wrong " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "invalid bearer token")) << r.err;
    EXPECT_EQ(backend_.start_calls, 0);

    r = run("start --program hppc --cell p45b " + server_args(), "CELLBENCH_TOKEN=" + kToken);
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "run 2 started")) << r.out;
    ASSERT_TRUE(backend_.last_start);
    EXPECT_EQ(backend_.last_start->program, "hppc");
    EXPECT_EQ(backend_.last_start->cell, "p45b");

    // A second start conflicts with the active run.
    r = run("start --program cc --cell p45b --token " + kToken + " " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "409")) << r.err;
    EXPECT_TRUE(contains(r.err, "already active")) << r.err;

    // Status shows the active run.
    r = run("status " + server_args());
    EXPECT_TRUE(contains(r.out, "run 2: hppc on p45b, running")) << r.out;
}

TEST_F(CliClient, StartParamsGoToTheDaemonTypedAndMalformedOnesStopBeforeIt) {
    serve();
    // Malformed arguments: every one named, nothing sent.
    auto r = run("start --program hppc --cell p45b --param c_rate --param x=1 --param x=2 --token " + kToken +
                 " " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "got \"c_rate\"")) << r.err;
    EXPECT_TRUE(contains(r.err, "--param x: given more than once")) << r.err;
    EXPECT_EQ(backend_.start_calls, 0);
    // Numbers as numbers, anything else as text (the daemon's program loader names the wrong type).
    r = run("start --program hppc --cell p45b --param c_rate=2 --param soc_step=5e-2 --param pulse_sets=many --token " +
            kToken + " " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    ASSERT_TRUE(backend_.last_start);
    EXPECT_EQ(backend_.last_start->parameters.at("c_rate"), json(2.0));
    EXPECT_EQ(backend_.last_start->parameters.at("soc_step"), json(0.05));
    EXPECT_EQ(backend_.last_start->parameters.at("pulse_sets"), json("many"));
    EXPECT_EQ(backend_.last_start->body["parameters"].size(), 3u);
}

TEST_F(CliClient, StartFollowWaitsForTheEndAndIsQuietWhenPiped) {
    backend_.polls_until_done = 4;
    serve();
    auto r = run("start --program hppc --cell p45b --follow --interval 0.02 --token " + kToken + " " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "run 2 started")) << r.out;
    EXPECT_TRUE(contains(r.out, "run 2: hppc on p45b, completed")) << r.out;
    EXPECT_FALSE(contains(r.err, "\r")) << "no progress line when piped: " << r.err;
    EXPECT_FALSE(contains(r.err, "SOC")) << r.err;

    // A run that fails makes --follow exit 1, with the reason.
    {
        std::lock_guard lock(backend_.mu);
        backend_.final_state = "aborted";
    }
    r = run("start --program hppc --cell p45b --follow --interval 0.02 --token " + kToken + " " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.out, "aborted")) << r.out;
    EXPECT_TRUE(contains(r.out, "over-voltage")) << r.out;
}

TEST_F(CliClient, StartFollowShowsAProgressLineOnATerminal) {
    backend_.polls_until_done = 5;
    serve();
    // Everything the child needs is prepared before forking (the test process has server threads).
    std::vector<std::string> args = {"cellbench", "start", "--program", "hppc", "--cell", "p45b", "--follow",
                                     "--interval", "0.02", "--server", url_};
    std::vector<std::string> env = {"CELLBENCH_TOKEN=" + kToken, "TERM=dumb", "PATH=/usr/bin:/bin"};
    std::vector<char*> argv, envp;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    for (auto& e : env) envp.push_back(e.data());
    envp.push_back(nullptr);
    const std::string bin = kBin.string();
    int master = -1;
    const pid_t pid = ::forkpty(&master, nullptr, nullptr, nullptr);
    ASSERT_GE(pid, 0);
    if (pid == 0) {
        ::execve(bin.c_str(), argv.data(), envp.data());
        ::_exit(127);
    }
    std::string screen;
    for (;;) {
        pollfd p{master, POLLIN, 0};
        if (::poll(&p, 1, 20000) <= 0) break;  // bounded: a hang fails the test below
        char buf[4096];
        const auto n = ::read(master, buf, sizeof buf);
        if (n <= 0) break;  // EIO once the child has exited
        screen.append(buf, static_cast<std::size_t>(n));
    }
    int st = 0;
    ::waitpid(pid, &st, 0);
    ::close(master);
    EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0) << screen;
    // The live line: step, SOC, V, I, T, rewritten in place.
    EXPECT_TRUE(contains(screen, "\r")) << screen;
    EXPECT_TRUE(contains(screen, "step ")) << screen;
    EXPECT_TRUE(contains(screen, "/140 CC discharge")) << screen;
    EXPECT_TRUE(contains(screen, "SOC 62.1 %")) << screen;
    EXPECT_TRUE(contains(screen, "3.712 V")) << screen;
    EXPECT_TRUE(contains(screen, "-3.820 A")) << screen;
    EXPECT_TRUE(contains(screen, "30.4 degC")) << screen;
    EXPECT_TRUE(contains(screen, "completed")) << screen;
}

TEST_F(CliClient, StopPauseResume) {
    backend_.polls_until_done = 1000;  // the run stays active however often status is asked
    serve();
    ASSERT_EQ(run("start --program hppc --cell p45b --token " + kToken + " " + server_args()).status, 0);
    auto r = run("pause --token " + kToken + " " + server_args());  // the active run
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "paused")) << r.out;
    r = run("resume 2 --token " + kToken + " " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_TRUE(contains(r.out, "running")) << r.out;
    r = run("stop --json --token " + kToken + " " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_EQ(json::parse(r.out)["state"], "stopped");

    r = run("stop --token " + kToken + " " + server_args());  // nothing active any more
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "no active run")) << r.err;
    r = run("stop 99 --token " + kToken + " " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "404")) << r.err;
    EXPECT_TRUE(contains(r.err, "no run 99")) << r.err;
}

TEST_F(CliClient, ExportWritesTheFileAtomically) {
    serve();
    const auto out = dir_ / "run1.bdf.csv";
    auto r = run("export 1 -o " + out.string() + " " + server_args());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_EQ(slurp(out), backend_.export_text());

    // Unknown run: exit 1, no file.
    const auto missing = dir_ / "run9.bdf.csv";
    r = run("export 9 -o " + missing.string() + " " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "no run 9")) << r.err;
    EXPECT_FALSE(fs::exists(missing));
}

TEST_F(CliClient, ExportCutMidwayLeavesNoFile) {
    backend_.export_fail_after_chunks = 4;
    serve();
    const auto out = dir_ / "cut.bdf.csv";
    const auto r = run("export 1 -o " + out.string() + " " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_FALSE(fs::exists(out));
    for (const auto& e : fs::directory_iterator(dir_))
        EXPECT_FALSE(contains(e.path().filename().string(), ".tmp")) << e.path();
}

TEST_F(CliClient, ConnectionRefusedIsOneClearMessage) {
    // A port that was free a moment ago: nothing listens there.
    std::uint16_t port = 0;
    {
        FakeBackend be;
        TestServer probe(be);
        port = probe.port();
    }
    for (const char* cmd : {"status", "runs", "start --program hppc --cell p45b --token x", "stop 1 --token x",
                            "export 1 -o /tmp/never-written.bdf.csv"}) {
        const auto r = run(std::string(cmd) + " --server http://127.0.0.1:" + std::to_string(port));
        EXPECT_EQ(r.status, 1) << cmd;
        EXPECT_TRUE(contains(r.err, "cannot connect to cellbenchd at http://127.0.0.1:" + std::to_string(port)))
            << cmd << ": " << r.err;
        EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    }
    EXPECT_FALSE(fs::exists("/tmp/never-written.bdf.csv"));
}

TEST_F(CliClient, UsageAndBadServerAddresses) {
    serve();
    EXPECT_EQ(run("start --program hppc " + server_args()).status, 2);  // --cell missing
    EXPECT_EQ(run("export " + server_args()).status, 2);                // RUN_ID and -o missing
    EXPECT_EQ(run("stop abc " + server_args()).status, 2);
    auto r = run("status --help");
    EXPECT_EQ(r.status, 0);
    EXPECT_TRUE(contains(r.out, "--server")) << r.out;
    r = run("status --server https://127.0.0.1:8750");
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "https")) << r.err;
    r = run("status --server http://127.0.0.1:notaport");
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "HOST:PORT")) << r.err;
    // The server address also comes from CELLBENCH_SERVER.
    r = run("status", "CELLBENCH_SERVER=" + url_);
    EXPECT_EQ(r.status, 0) << r.err;
}

TEST_F(CliClient, HttpErrorsFromTheDaemonAreReported) {
    backend_.explode = true;
    serve();
    const auto r = run("status " + server_args());
    EXPECT_EQ(r.status, 1);
    EXPECT_TRUE(contains(r.err, "500")) << r.err;
    EXPECT_TRUE(contains(r.err, "internal error")) << r.err;
}
