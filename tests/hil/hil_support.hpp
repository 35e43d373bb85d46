#pragma once
// What the in-process daemon HIL tests share: a scratch folder, polling until a condition holds, daemon
// options and a simulated-bench config that keep clear of a cellbenchd on the default ports.
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <system_error>
#include <thread>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"

namespace cellbench::test {

// A fresh folder under the system temp dir, removed with everything in it when the test ends.
struct TempDir {
    std::filesystem::path path;
    explicit TempDir(const std::string& tag) {
        static int serial = 0;
        path = std::filesystem::temp_directory_path() /
               ("cellbench-" + tag + "-" + std::to_string(::getpid()) + "-" + std::to_string(serial++));
        std::filesystem::remove_all(path);
        std::filesystem::create_directories(path);
    }
    ~TempDir() {
        std::error_code ec;
        std::filesystem::remove_all(path, ec);
    }
    TempDir(const TempDir&) = delete;
    TempDir& operator=(const TempDir&) = delete;
};

// A config folder of the test's own: the shipped simulated bench (bench.sim.json), the P45B cell and the parameter
// set its simulation runs (cells/), and one program, programs/NAME.json. Returns the bench file.
inline std::filesystem::path write_bench_folder(const std::filesystem::path& dir, const std::string& program_name,
                                                const std::string& program_json) {
    const auto config = std::filesystem::path(CELLBENCH_SOURCE_DIR) / "config";
    std::filesystem::create_directories(dir / "cells");
    std::filesystem::create_directories(dir / "programs");
    std::filesystem::copy_file(config / "bench.sim.json", dir / "bench.sim.json");
    std::filesystem::copy_file(config / "cells/p45b.json", dir / "cells/p45b.json");
    std::filesystem::copy_file(config / "cells/p45b-thesis.json", dir / "cells/p45b-thesis.json");
    std::ofstream(dir / "programs" / (program_name + ".json")) << program_json;
    return dir / "bench.sim.json";
}

// Waits (polling) until pred holds; the limit only bounds a broken test's runtime, it is no timing claim.
inline bool eventually(const std::function<bool()>& pred, std::chrono::milliseconds limit,
                       std::chrono::milliseconds poll = std::chrono::milliseconds(50)) {
    const auto end = std::chrono::steady_clock::now() + limit;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(poll);
    }
    return pred();
}

// Daemon options for a test: API on an ephemeral loopback port, database and DAQ socket in dir.
inline daemon::BenchDaemonOptions daemon_options_in(const TempDir& dir, double time_scale,
                                                    const std::string& token = "hil-token") {
    daemon::BenchDaemonOptions o;
    o.listen = daemon::Endpoint{"127.0.0.1", 0};
    o.db_path = dir.path / "bench.sqlite";
    o.token = token;
    o.time_scale = time_scale;
    o.daq_socket_path = (dir.path / "dewe.sock").string();
    return o;
}

// A bench config with the simulated instruments on free ports, so tests may run beside a cellbenchd.
inline daemon::BenchConfig sim_bench_config(const std::filesystem::path& file) {
    auto cfg = daemon::load_bench_config(file);
    cfg.cycler.endpoint.port = 0;
    cfg.chamber.endpoint.port = 0;
    return cfg;
}

// A live run state of the API (INTERFACES.md): the run has not ended.
inline bool live_run_state(const std::string& s) {
    return s == "starting" || s == "waiting_equilibrium" || s == "running" || s == "paused" || s == "stopping";
}
// An end state of the API (INTERFACES.md): completed, stopped, aborted or interrupted.
inline bool ended_run_state(const std::string& s) {
    return s == "completed" || s == "stopped" || s == "aborted" || s == "interrupted";
}

// Polls run id until it has ended (ended_run_state) or limit passes; returns the last state read.
inline std::string wait_for_run_end(daemon::BenchDaemon& d, daemon::RunId id, std::chrono::milliseconds limit,
                                    std::chrono::milliseconds poll = std::chrono::milliseconds(50)) {
    std::string state;
    eventually([&] {
        state = d.get_run(id)["state"].get<std::string>();
        return ended_run_state(state);
    }, limit, poll);
    return state;
}

inline bool instruments_connected(daemon::BenchDaemon& d) {
    const nlohmann::json s = d.status();  // kept alive while its members are iterated
    for (const auto& i : s["instruments"])
        if (i["state"] != "connected") return false;
    return true;
}

}  // namespace cellbench::test
