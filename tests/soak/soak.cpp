// cellbench_soak (issue 6, "Soak"; `make soak`, not part of `make test`): an unattended campaign of bench time at a
// high time scale with instrument faults injected at random, against a real cellbenchd process.
//
// This process plays the bench: it hosts the simulated instruments itself (the Neware tester, the Modbus chamber
// and the DEWE CAN stream on one simulated cell, as `cellbench sim` does) so that it can throw their fault
// switches, and it runs `cellbenchd --config <config/bench.hil.json pointed at them>` as a child, driving it over
// the REST API like an operator's script. The campaign cycles CC, short HPPC and Random Walk at two chamber
// temperatures (program copies with temperature_c set, in a temp config dir) until --hours of bench time
// have passed, then stops the active run and the daemon (SIGTERM). The first run (a short HPPC) runs without
// faults: it is the baseline of the memory check (RSS after the last run within 10 % of RSS after the first).
//
// Faults, one every 15-45 s of wall time (seeded): Neware connection drop / refused connections / stalled
// responses / malformed responses / garbage between frames, DEWE silence / dropped samples / garbage frames,
// chamber unresponsive / exception responses. Durations are short (below the daemon's instrument-loss grace,
// expected: the run survives) or long (beyond it, expected: the run is aborted, current off, chamber safe).
//
// Checks (exit status 1 when one fails): the daemon never dies; every run ends completed, stopped or failed
// with its events, and an aborted run has an abort event, no current on the simulated cell and the chamber at
// its safe set point; the database passes `pragma integrity_check`. Measured: faults by kind, survived, runs
// aborted, samples lost by the run store, cellbenchd's RSS over time (min, max, slope) and settled after each
// run (anonymous + file-backed). Report: markdown on stdout and in --report. CELLBENCH_SOAK_WRAP="heaptrack -o
// F" (or any command prefix) runs the daemon under a profiler; the memory figures are then cellbenchd's own.
#include <utility>  // before Boost.Asio (Boost 1.74 + g++ 12, C++20)

#include <signal.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <limits>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/sim/chamber_server.hpp"
#include "cellbench/sim/dewe_publisher.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/plant.hpp"
#include "unit/api_test_support.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cellbench;
using namespace std::chrono_literals;
namespace http = boost::beast::http;

namespace {

const fs::path kSource = CELLBENCH_SOURCE_DIR;
const fs::path kBinDir = CELLBENCH_BIN_DIR;
constexpr const char* kToken = "soak-token";

struct Options {
    double hours = 12.0;
    double time_scale = 100.0;
    unsigned seed = 6;
    fs::path report;
    double fault_min_s = 15.0, fault_max_s = 45.0;  // wall seconds between faults
    std::vector<std::string> skip;                  // fault kinds left out (--no-fault KIND)
};

double wall_s() {
    static const auto t0 = std::chrono::steady_clock::now();
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

std::string slurp(const fs::path& p) {
    std::ifstream in(p);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

// A field of /proc/PID/status in KiB (VmRSS, and its parts RssAnon, RssFile, RssShmem), -1 when unreadable.
long status_kib(pid_t pid, const std::string& field) {
    std::ifstream in("/proc/" + std::to_string(pid) + "/status");
    std::string line;
    while (std::getline(in, line))
        if (line.rfind(field + ":", 0) == 0) return std::stol(line.substr(field.size() + 1));
    return -1;
}
long rss_kib(pid_t pid) { return status_kib(pid, "VmRSS"); }

// /proc/PID/smaps copied to `to` (each mapping's Rss, Anonymous, ...): which mapping holds what a run left
// resident (heap arenas, thread stacks, library code), to compare between runs offline.
void dump_smaps(pid_t pid, const fs::path& to) {
    std::ifstream in("/proc/" + std::to_string(pid) + "/smaps");
    std::ofstream out(to);
    out << in.rdbuf();
}

// The cellbenchd process under `pid`: `pid` itself, or (CELLBENCH_SOAK_WRAP, e.g. heaptrack, which runs its
// client as a child) the first descendant whose command name is cellbenchd.
pid_t daemon_process(pid_t pid) {
    std::map<pid_t, std::vector<pid_t>> children;
    std::map<pid_t, std::string> comm;
    for (const auto& e : fs::directory_iterator("/proc")) {
        const std::string name = e.path().filename().string();
        if (name.empty() || !std::all_of(name.begin(), name.end(), ::isdigit)) continue;
        const std::string stat = slurp(e.path() / "stat");
        const auto open = stat.find('('), close = stat.rfind(')');
        if (open == std::string::npos || close == std::string::npos) continue;
        std::istringstream rest(stat.substr(close + 2));
        char state = 0;
        pid_t ppid = 0;
        rest >> state >> ppid;
        const pid_t p = static_cast<pid_t>(std::stol(name));
        comm[p] = stat.substr(open + 1, close - open - 1);
        children[ppid].push_back(p);
    }
    std::vector<pid_t> todo{pid};
    for (std::size_t k = 0; k < todo.size(); ++k) {
        if (comm[todo[k]] == "cellbenchd") return todo[k];
        for (pid_t c : children[todo[k]]) todo.push_back(c);
    }
    return pid;
}

struct Fault {
    std::string kind;
    double wall_at = 0, bench_at = 0, duration_wall_s = 0;  // 0: instantaneous
    bool long_loss = false;                                 // beyond the grace: the run should abort
    std::optional<long long> run;                           // run active when injected
    std::string outcome = "no run";                         // survived | aborted | run ended otherwise | no run
};

struct RunRecord {
    long long id = 0;
    std::string program, state, outcome, error;
    double bench_start = 0, bench_end = 0;
    std::size_t events = 0;
    bool abort_event = false, safe_after_abort = true;
    std::string safe_detail;
    std::string stop_note;  // the stop was delayed by a fault the soak held (tester unreachable)
    long rss_settled_kib = -1, anon_kib = -1, file_kib = -1;  // cellbenchd settled after the run's end
    std::size_t fits = 0;                                      // pulse-set fits the run delivered (GET .../fits)
};

}  // namespace

int main(int argc, char** argv) {
    Options o;
    for (int k = 1; k < argc; ++k) {
        const std::string a = argv[k];
        auto next = [&]() -> std::string {
            if (k + 1 >= argc) {
                std::fprintf(stderr, "%s: missing value\n", a.c_str());
                std::exit(2);
            }
            return argv[++k];
        };
        if (a == "--hours") o.hours = std::stod(next());
        else if (a == "--time-scale") o.time_scale = std::stod(next());
        else if (a == "--seed") o.seed = static_cast<unsigned>(std::stoul(next()));
        else if (a == "--report") o.report = next();
        else if (a == "--no-fault") o.skip.push_back(next());
        else if (a == "--fault-every") {
            const std::string v = next();  // MIN:MAX wall seconds
            o.fault_min_s = std::stod(v.substr(0, v.find(':')));
            o.fault_max_s = std::stod(v.substr(v.find(':') + 1));
        } else {
            std::fprintf(stderr,
                         "usage: cellbench_soak [--hours BENCH_HOURS] [--time-scale X] [--seed N] [--report FILE.md] "
                         "[--fault-every MIN:MAX] [--no-fault KIND]...\n");
            return 2;
        }
    }
    spdlog::set_level(spdlog::level::warn);
    std::mt19937 rng(o.seed);
    const fs::path dir = fs::temp_directory_path() / ("cellbench-soak-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    fs::create_directories(dir / "programs");
    fs::create_directory_symlink(kSource / "config/cells", dir / "cells");

    // Campaign programs: CC, short HPPC, Random Walk, each at two chamber temperatures.
    const std::vector<double> temperatures = {25.0, 40.0};
    std::vector<std::string> campaign;
    for (double t : temperatures)
        for (const char* base : {"hppc_short", "rw", "cc"}) {
            json p = json::parse(std::ifstream(kSource / "config/programs" / (std::string(base) + ".json")));
            const std::string name = std::string(base) + "_" + std::to_string(static_cast<int>(t)) + "c";
            p["name"] = name;
            p["parameters"]["temperature_c"] = t;
            std::ofstream(dir / "programs" / (name + ".json")) << p.dump(2);
            campaign.push_back(name);
        }

    // The simulated bench, in this process (fault switches).
    const auto simcfg = daemon::load_bench_config(kSource / "config/bench.sim.json");
    json pj = json::parse(std::ifstream(simcfg.simulation->params_path));
    sim::BenchPlant plant(daemon::simulated_plant_options(
        simcfg, estimator::ParameterSet::from_json(pj, simcfg.simulation->params_path.string())));
    auto clock = std::make_shared<sim::BenchClock>(o.time_scale);
    boost::asio::io_context io;
    auto guard = boost::asio::make_work_guard(io);
    sim::NewareServerOptions no;
    no.port = 0;
    no.cell_channels.clear();
    for (const auto& ch : simcfg.cycler.channels) no.cell_channels.push_back(ch.chlid);
    no.max_channel_current_a = simcfg.cycler.channel_max_current_a;
    sim::NewareServer neware(plant, clock, no);
    neware.start();
    sim::ChamberServerOptions co;
    co.port = 0;
    sim::ChamberServer chamber(plant, clock, co);
    chamber.start();
    drivers::CanEndpoint ep;
    ep.kind = drivers::CanEndpoint::Kind::can_dgram;
    ep.name = (dir / "dewe.sock").string();
    sim::DewePublisher dewe(io, plant, clock, drivers::open_can_publisher(io, ep), sim::DewePublisherOptions{});
    dewe.start();
    std::thread io_thread([&] { io.run(); });

    json hil = json::parse(std::ifstream(kSource / "config/bench.hil.json"));
    hil["instruments"]["cycler"]["port"] = neware.port();
    hil["instruments"]["chamber"]["port"] = chamber.port();
    hil["instruments"]["daq"]["socket_path"] = ep.name;
    hil["database"] = {{"path", (dir / "soak.sqlite").string()}, {"flush_period_ms", 200}};
    std::ofstream(dir / "hil.json") << hil.dump(2);
    const double safe_setpoint_c = hil["instruments"]["chamber"].value("safe_setpoint_c", 25.0);
    // The daemon's instrument-loss grace in wall seconds: max(config grace in bench s, its floor: 10 s of wall
    // on an accelerated bench, 3 s at scale 1).
    const double grace_wall_s = std::max(hil["safety"].value("instrument_loss_grace_s", 5.0) / o.time_scale,
                                         o.time_scale > 1.0 ? 10.0 : 3.0);

    // cellbenchd.
    const fs::path log = dir / "cellbenchd.log";
    const pid_t pid = ::fork();
    if (pid == 0) {
        FILE* f = std::fopen(log.c_str(), "w");
        if (f) {
            ::dup2(::fileno(f), STDOUT_FILENO);
            ::dup2(::fileno(f), STDERR_FILENO);
        }
        // Nothing of ours beyond stdio: an inherited listening socket of the simulated tester would keep
        // its port listening in the daemon (never accepting) after the tester closes it for a refuse fault.
        ::close_range(3, ~0U, 0);
        const std::string bin = (kBinDir / "cellbenchd").string(), cfg = (dir / "hil.json").string(),
                          scale = std::to_string(o.time_scale);
        // CELLBENCH_SOAK_WRAP: a command the daemon runs under (a profiler: "heaptrack -o /tmp/hp", "valgrind
        // --tool=massif"); the memory figures are then those of the cellbenchd process below it.
        if (const char* wrap = std::getenv("CELLBENCH_SOAK_WRAP"); wrap && *wrap) {
            const std::string cmd = std::string("exec ") + wrap + " \"$@\"";
            ::execl("/bin/sh", "sh", "-c", cmd.c_str(), "sh", bin.c_str(), "--config", cfg.c_str(), "--listen",
                    "127.0.0.1:0", "--token", kToken, "--time-scale", scale.c_str(), nullptr);
            ::_exit(127);
        }
        ::execl(bin.c_str(), bin.c_str(), "--config", cfg.c_str(), "--listen", "127.0.0.1:0", "--token", kToken,
                "--time-scale", scale.c_str(), nullptr);
        ::_exit(127);
    }
    std::uint16_t port = 0;
    bool daemon_died = false;
    int daemon_status = 0;
    auto alive = [&] {
        if (daemon_died) return false;
        if (::waitpid(pid, &daemon_status, WNOHANG) == pid) daemon_died = true;
        return !daemon_died;
    };
    for (int k = 0; k < 600 && port == 0 && alive(); ++k) {
        const std::string text = slurp(log), key = "cellbenchd: API http://127.0.0.1:";
        if (const auto at = text.find(key); at != std::string::npos && text.find('/', at + key.size()) != std::string::npos)
            port = static_cast<std::uint16_t>(std::stoi(text.substr(at + key.size())));
        std::this_thread::sleep_for(100ms);
    }
    if (port == 0) {
        std::fprintf(stderr, "cellbenchd did not start:\n%s\n", slurp(log).c_str());
        return 1;
    }
    const pid_t mem_pid = daemon_process(pid);  // whose memory is measured (pid unless wrapped)
    auto api = [&](http::verb verb, const std::string& target, const std::string& body = {}) -> std::pair<int, json> {
        try {
            cellbench::testing::Headers h;
            if (verb == http::verb::post) h = {{"Authorization", std::string("Bearer ") + kToken}, {"Content-Type", "application/json"}};
            const auto r = cellbench::testing::request(port, verb, "/api/v1" + target, body, h);
            return {r.result_int(), json::parse(r.body(), nullptr, false)};
        } catch (const std::exception& e) {
            return {0, json{{"error", e.what()}}};
        }
    };

    // -- the campaign -------------------------------------------------------------------------------------------
    std::vector<Fault> faults;
    std::vector<RunRecord> runs;
    std::vector<std::pair<double, long>> rss;  // (wall s, KiB)
    long rss_after_first_run = -1;             // KiB, when the first run had ended
    long rss_after_last_run = -1;              // KiB, when the last run had ended (measured the same way)
    std::vector<std::string> problems;
    std::uniform_real_distribution<double> gap(o.fault_min_s, o.fault_max_s), unit(0.0, 1.0);
    std::vector<std::string> kinds = {"neware_drop",      "neware_refuse",  "neware_stall",  "neware_malformed",
                                      "neware_garbage",   "dewe_silence",   "dewe_drop",     "dewe_garbage",
                                      "chamber_unresponsive", "chamber_exception"};
    std::erase_if(kinds, [&](const std::string& k) { return std::find(o.skip.begin(), o.skip.end(), k) != o.skip.end(); });
    const double bench_end = o.hours * 3600.0;
    const double t_wall0 = wall_s();
    // The first run is the memory baseline: fault-free, and an HPPC (online pulse fits, then the end fit), so it
    // pages in every code path the campaign uses and holds a complete run's working set. Faults start once it
    // has ended.
    double next_fault = std::numeric_limits<double>::infinity(), next_rss = 0.0;
    std::size_t next_program = 0;
    std::optional<long long> active;
    std::optional<std::size_t> open_fault;  // a fault being held (duration not over)
    double fault_release = 0.0;
    std::function<void()> release;

    auto finish_run = [&](long long id) {
        RunRecord r;
        r.id = id;
        const auto [code, j] = api(http::verb::get, "/runs/" + std::to_string(id));
        r.program = j.value("program", "");
        r.state = j.value("state", "");
        r.outcome = j.contains("outcome") && j["outcome"].is_string() ? j["outcome"].get<std::string>() : "";
        r.error = j.contains("error") && j["error"].is_string() ? j["error"].get<std::string>() : "";
        r.bench_end = clock->now_s();
        const auto [ec, ev] = api(http::verb::get, "/runs/" + std::to_string(id) + "/events");
        if (ev.contains("events"))
            for (const auto& e : ev["events"]) {
                ++r.events;
                if (e.value("kind", "") == "abort") r.abort_event = true;
            }
        if (const auto [fc, fj] = api(http::verb::get, "/runs/" + std::to_string(id) + "/fits");
            fj.contains("fits") && fj["fits"].is_array())
            r.fits = fj["fits"].size();
        if (r.state != "completed" && r.state != "stopped" && r.state != "aborted" && r.state != "interrupted")
            problems.push_back("run " + std::to_string(id) + " ended in an undefined state '" + r.state + "'");
        if (r.events == 0) problems.push_back("run " + std::to_string(id) + " has no events");
        if (r.outcome == "aborted") {
            // The abort must have left the cell without current and the chamber going to its safe set point:
            // give the commands a moment (they were sent when the run ended; the tester ticks on its own timer).
            // "No current": below 10x the simulated current noise (2 mA), far below any program's current.
            constexpr double kNoCurrentA = 0.02;
            bool safe = false;
            sim::PlantReading p;
            auto bench_safe = [&] {
                p = plant.read();
                return std::abs(p.current_a) < kNoCurrentA && std::abs(p.chamber_setpoint_c - safe_setpoint_c) < 0.05;
            };
            // An instrument the soak itself keeps unreachable (a fault still held: the tester refusing or not
            // answering, the chamber silent or failing) cannot take the safe command: the tester runs its step
            // file on its own, the chamber holds its set point. Such a fault is released at its scheduled end,
            // and the commands must then get through within the daemon's reconnect and retry periods
            // (bench.hil.json: reconnect_max 5 s; stops and set points retried at least every second): 15 s of
            // wall time from the abort, or from the release. For the tester, the record must say meanwhile that
            // the stop was not acknowledged. The delay is reported.
            const std::optional<std::size_t> held_at_abort = open_fault;
            double deadline = wall_s() + 15.0, released_at = -1.0;
            while (!(safe = bench_safe())) {
                if (open_fault && wall_s() >= fault_release) {
                    if (release) release();
                    release = nullptr;
                    open_fault.reset();
                    released_at = wall_s();
                    deadline = released_at + 15.0;
                }
                if (!open_fault && wall_s() >= deadline) break;
                std::this_thread::sleep_for(100ms);
            }
            if (held_at_abort) {
                const std::string held = faults[*held_at_abort].kind;
                bool said = held.rfind("neware_", 0) != 0;  // only a stop can be pending
                if (const auto [ec2, ev2] = api(http::verb::get, "/runs/" + std::to_string(id) + "/events"); ev2.contains("events"))
                    for (const auto& e : ev2["events"])
                        said = said || (e.value("kind", "") == "cycler" && e.value("level", "") == "error");
                char d[200];
                if (released_at >= 0)
                    std::snprintf(d, sizeof d, "%s held at the abort: bench %s %.1f s after its release%s", held.c_str(),
                                  safe ? "safe" : "NOT safe", wall_s() - released_at,
                                  said ? "" : "; NO event said the stop was pending");
                else
                    std::snprintf(d, sizeof d, "%s held at the abort: bench safe before its release", held.c_str());
                r.stop_note = d;
                if (!said && released_at >= 0) problems.push_back("run " + std::to_string(id) + ": " + d);
            }
            r.safe_after_abort = safe;
            r.safe_detail = "current " + std::to_string(p.current_a) + " A, chamber set point " +
                            std::to_string(p.chamber_setpoint_c) + " degC";
            if (!r.abort_event) problems.push_back("run " + std::to_string(id) + " aborted without an abort event");
            if (!safe) problems.push_back("run " + std::to_string(id) + " aborted but the bench is not safe: " + r.safe_detail);
        }
        for (auto& rr : runs)
            if (rr.id == id) r.bench_start = rr.bench_start, rr = r;
        // RSS once the daemon has settled after the run: it hands the recording to the end fit, then gives the
        // store's caches and the freed heap back (each run measured the same way).
        // The end fit may still be running when the run is reported over (seconds at 100x for a short HPPC on a
        // busy machine): the lowest figure once it has stopped falling for 5 s (the daemon trims its heap every 2 s
        // when idle), within 30 s.
        for (int k = 0; k < 240; ++k) {  // up to 2 min for the end fit (GET /status "fits_running")
            const auto [fc2, st] = api(http::verb::get, "/status");
            if (fc2 == 200 && !st.value("fits_running", false)) break;
            std::this_thread::sleep_for(500ms);
        }
        long settled = rss_kib(mem_pid), anon = status_kib(mem_pid, "RssAnon"), file = status_kib(mem_pid, "RssFile");
        for (int k = 0, flat = 0; k < 60 && !(k >= 10 && flat >= 10); ++k) {
            std::this_thread::sleep_for(500ms);
            const long v = rss_kib(mem_pid);
            ++flat;
            if (v > 0 && (settled <= 0 || v < settled)) {
                if (settled - v > 64) flat = 0;
                settled = v, anon = status_kib(mem_pid, "RssAnon"), file = status_kib(mem_pid, "RssFile");
            }
        }
        for (auto& rr : runs)
            if (rr.id == id) rr.rss_settled_kib = settled, rr.anon_kib = anon, rr.file_kib = file;
        dump_smaps(mem_pid, dir / ("smaps-run-" + std::to_string(id) + ".txt"));
        rss_after_last_run = settled;
        if (rss_after_first_run < 0) {
            rss_after_first_run = rss_after_last_run;
            next_fault = wall_s() + gap(rng);  // the baseline run is over: faults from now on
        }
    };

    auto inject = [&](const std::string& kind, bool long_loss, double dur) {
        Fault f;
        f.kind = kind;
        f.wall_at = wall_s();
        f.bench_at = clock->now_s();
        f.long_loss = long_loss;
        f.run = active;
        f.duration_wall_s = dur;
        release = nullptr;
        if (kind == "neware_drop") neware.drop_connections(), f.duration_wall_s = 0, f.long_loss = false;
        else if (kind == "neware_refuse") {
            neware.set_refuse_connections(true);
            neware.drop_connections();
            release = [&] { neware.set_refuse_connections(false); };
        } else if (kind == "neware_stall") {
            neware.set_stall_responses(true);
            release = [&] { neware.set_stall_responses(false); };
        } else if (kind == "neware_malformed") {
            neware.set_malformed_responses(true);
            release = [&] { neware.set_malformed_responses(false); };
        } else if (kind == "neware_garbage") {
            neware.set_garbage_between_frames(true);
            release = [&] { neware.set_garbage_between_frames(false); };
            f.long_loss = false;  // frames still arrive between the junk
        } else if (kind == "dewe_silence") {
            dewe.set_silent(true);
            release = [&] { dewe.set_silent(false); };
        } else if (kind == "dewe_drop") dewe.drop_samples(20), f.duration_wall_s = 0, f.long_loss = false;
        else if (kind == "dewe_garbage") dewe.send_garbage(20), f.duration_wall_s = 0, f.long_loss = false;
        else if (kind == "chamber_unresponsive") {
            chamber.set_unresponsive(true);
            release = [&] { chamber.set_unresponsive(false); };
        } else if (kind == "chamber_exception") {
            chamber.set_exception_response(std::uint8_t{4});
            release = [&] { chamber.set_exception_response(std::nullopt); };
        }
        faults.push_back(f);
        if (release) {
            open_fault = faults.size() - 1;
            fault_release = wall_s() + f.duration_wall_s;
        }
    };

    std::printf("soak: %.1f h of bench time at %gx (about %.0f s of wall time), faults every %g-%g s, seed %u\n",
                o.hours, o.time_scale, bench_end / o.time_scale, o.fault_min_s, o.fault_max_s, o.seed);
    std::fflush(stdout);
    while (clock->now_s() < bench_end) {
        if (!alive()) {
            problems.push_back("cellbenchd died");
            break;
        }
        const double now = wall_s();
        if (now >= next_rss) {
            rss.emplace_back(now - t_wall0, rss_kib(mem_pid));
            next_rss = now + 5.0;
        }
        // Release a held fault; judge faults whose observation window (end + 2 grace periods) is over.
        if (open_fault && now >= fault_release) {
            if (release) release();
            release = nullptr;
            open_fault.reset();
        }
        // The run.
        const auto [sc, status] = api(http::verb::get, "/status");
        const bool live = sc == 200 && status.contains("run") && status["run"].is_object();
        if (active && (!live || status["run"].value("id", 0LL) != *active)) {
            finish_run(*active);
            for (auto& f : faults)
                if (f.run == active && f.outcome == "no run")
                    f.outcome = runs.back().outcome == "aborted" &&
                                        runs.back().bench_end - f.bench_at < (2 * grace_wall_s + f.duration_wall_s + 5) * o.time_scale
                                    ? "aborted"
                                    : "run ended otherwise (" + runs.back().outcome + ")";
            std::printf("  %6.0f s wall, bench %5.2f h: run %lld %-14s %s%s\n", now - t_wall0, clock->now_s() / 3600,
                        runs.back().id, runs.back().program.c_str(), runs.back().outcome.c_str(),
                        runs.back().error.empty() ? "" : (" (" + runs.back().error + ")").c_str());
            std::fflush(stdout);
            active.reset();
        }
        if (!active && !open_fault) {
            bool connected = sc == 200;
            if (connected)
                for (const auto& i : status["instruments"]) connected = connected && i["state"] == "connected";
            if (connected) {
                const std::string prog = campaign[next_program % campaign.size()];
                const auto [code, j] = api(http::verb::post, "/runs", json{{"program", prog}, {"cell", "p45b"}}.dump());
                if (code == 201) {
                    ++next_program;
                    active = j["id"].get<long long>();
                    RunRecord r;
                    r.id = *active;
                    r.program = prog;
                    r.bench_start = clock->now_s();
                    runs.push_back(r);
                } else if (code != 409 && code != 503) {
                    problems.push_back("POST /runs " + prog + ": " + std::to_string(code) + " " + j.dump());
                    ++next_program;
                }
            }
        }
        // Faults that had their time: survived when the run is still the active one 2 grace periods after.
        for (auto& f : faults)
            if (f.run && f.outcome == "no run" && active == f.run && now > f.wall_at + f.duration_wall_s + 2 * grace_wall_s + 1.0)
                f.outcome = "survived";
        if (!open_fault && now >= next_fault) {
            const std::string kind = kinds[static_cast<std::size_t>(unit(rng) * kinds.size()) % kinds.size()];
            const bool long_loss = unit(rng) < 0.3;
            const double dur = long_loss ? grace_wall_s + 1.0 + 3.0 * unit(rng) : 0.2 + 1.3 * unit(rng);
            inject(kind, long_loss, dur);
            next_fault = now + gap(rng);
        }
        std::this_thread::sleep_for(250ms);
    }
    if (open_fault && release) release();
    // The end of the campaign: stop the active run, then the daemon.
    if (active && alive()) {
        api(http::verb::post, "/runs/" + std::to_string(*active) + "/stop", "{}");
        for (int k = 0; k < 100; ++k) {
            const auto [sc, st] = api(http::verb::get, "/status");
            if (sc == 200 && !st["run"].is_object()) break;
            std::this_thread::sleep_for(100ms);
        }
        finish_run(*active);
        for (auto& f : faults)
            if (f.run == active && f.outcome == "no run") f.outcome = "survived (campaign end)";
    }
    std::string metrics;
    try {
        metrics = cellbench::testing::request(port, http::verb::get, "/metrics").body();
    } catch (const std::exception&) {
    }
    auto metric = [&](const std::string& name) -> double {
        std::istringstream in(metrics);
        std::string line;
        double sum = 0;
        while (std::getline(in, line))
            if (line.rfind(name, 0) == 0 && (line.size() > name.size() && (line[name.size()] == ' ' || line[name.size()] == '{' || line[name.size()] == '}')))
                sum += std::stod(line.substr(line.rfind(' ') + 1));
        return sum;
    };
    const bool crashed = !alive();
    int exit_code = -1;
    if (!crashed) {
        ::kill(mem_pid, SIGTERM);  // the daemon itself (a wrapper need not pass the signal on)
        ::waitpid(pid, &daemon_status, 0);
        exit_code = WIFEXITED(daemon_status) ? WEXITSTATUS(daemon_status) : -WTERMSIG(daemon_status);
        if (exit_code != 0) problems.push_back("cellbenchd exited with " + std::to_string(exit_code) + " on SIGTERM");
    } else {
        problems.push_back("cellbenchd crashed");
    }
    dewe.stop();
    chamber.stop();
    neware.stop();
    guard.reset();
    io.stop();
    io_thread.join();

    std::string integrity;
    {
        sqlite3* h = nullptr;
        sqlite3_open_v2((dir / "soak.sqlite").c_str(), &h, SQLITE_OPEN_READONLY, nullptr);
        sqlite3_stmt* s = nullptr;
        if (sqlite3_prepare_v2(h, "PRAGMA integrity_check", -1, &s, nullptr) == SQLITE_OK)
            while (sqlite3_step(s) == SQLITE_ROW) integrity += reinterpret_cast<const char*>(sqlite3_column_text(s, 0));
        sqlite3_finalize(s);
        sqlite3_close(h);
    }
    if (integrity != "ok") problems.push_back("integrity_check: " + integrity);

    // -- report ---------------------------------------------------------------------------------------------------
    std::ostringstream md;
    const double wall_total = wall_s() - t_wall0;
    md << "# cellbench soak report\n\n";
    md << "- bench time: " << std::fixed;
    md.precision(2);
    md << clock->now_s() / 3600.0 << " h at " << o.time_scale << "x (" << wall_total << " s wall), seed " << o.seed << "\n";
    md << "- campaign: ";
    for (const auto& c : campaign) md << c << " ";
    md << "(repeated in this order; the first run is fault-free: the memory baseline)\n";
    md << "- cellbenchd: " << (crashed ? "CRASHED" : "no crash; exit status " + std::to_string(exit_code) + " on SIGTERM") << "\n";
    md << "- database: integrity_check = " << integrity << "\n\n";
    std::map<std::string, std::map<std::string, int>> by_kind;
    int survived = 0, aborted_by_fault = 0, long_faults = 0, short_faults = 0, short_survived = 0, long_aborted = 0;
    for (const auto& f : faults) {
        ++by_kind[f.kind]["injected"];
        const std::string oc = f.outcome.rfind("survived", 0) == 0 ? "survived" : f.outcome == "aborted" ? "aborted" : f.run ? "other" : "no run";
        ++by_kind[f.kind][oc];
        if (oc == "survived") ++survived;
        if (oc == "aborted") ++aborted_by_fault;
        if (f.run && f.long_loss) ++long_faults, long_aborted += oc == "aborted";
        if (f.run && !f.long_loss) ++short_faults, short_survived += oc == "survived";
    }
    md << "## Faults\n\n| kind | injected | run survived | run aborted | run ended otherwise | no run active |\n|---|---|---|---|---|---|\n";
    for (const auto& [k, m] : by_kind) {
        auto g = [&](const char* key) { const auto it = m.find(key); return it == m.end() ? 0 : it->second; };
        md << "| " << k << " | " << g("injected") << " | " << g("survived") << " | " << g("aborted") << " | " << g("other") << " | " << g("no run") << " |\n";
    }
    md << "\n" << faults.size() << " faults injected; " << survived << " survived (run kept going), " << aborted_by_fault
       << " ended their run with an abort. Short faults (below the " << grace_wall_s << " s wall grace) during a run: "
       << short_survived << " of " << short_faults << " survived; long ones: " << long_aborted << " of " << long_faults
       << " aborted the run.\n\n";
    int completed = 0, stopped = 0, aborted = 0, interrupted = 0, safe_ok = 0;
    for (const auto& r : runs) {
        completed += r.outcome == "completed";
        stopped += r.outcome == "stopped";
        aborted += r.outcome == "aborted";
        interrupted += r.outcome == "interrupted";
        safe_ok += r.outcome == "aborted" && r.safe_after_abort && r.abort_event;
    }
    md << "## Runs\n\n" << runs.size() << " runs: " << completed << " completed, " << stopped << " stopped, " << aborted
       << " aborted (" << safe_ok << " of them correctly: abort event, current 0, chamber at " << safe_setpoint_c
       << " degC), " << interrupted << " interrupted.\n\n| run | program | outcome | events | RSS settled after, MiB (anon + file) | why |\n|---|---|---|---|---|---|\n";
    for (const auto& r : runs) {
        char mem[96] = "-";
        if (r.rss_settled_kib > 0)
            std::snprintf(mem, sizeof mem, "%.1f (%.1f + %.1f)", r.rss_settled_kib / 1024.0, r.anon_kib / 1024.0, r.file_kib / 1024.0);
        md << "| " << r.id << " | " << r.program << " | " << r.outcome << " | " << r.events << " | " << mem << " | " << r.error
           << (r.stop_note.empty() ? "" : "; " + r.stop_note) << " |\n";
    }
    md << "\n## Samples\n\n";
    md.precision(0);
    md << "- ingested by the run store: cycler " << metric("cellbench_samples_ingested_total{source=\"cycler\"")
       << ", daq " << metric("cellbench_samples_ingested_total{source=\"daq\"") << ", chamber "
       << metric("cellbench_samples_ingested_total{source=\"chamber\"") << "\n";
    md << "- written " << metric("cellbench_store_samples_written_total") << ", lost (failed transactions) "
       << metric("cellbench_store_samples_lost_total") << ", dropped (queue full) " << metric("cellbench_store_samples_dropped_total") << "\n";
    md << "- DAQ samples lost on the CAN stream (counter gaps; the dewe_drop/silence faults cause them): "
       << metric("cellbench_daq_lost_samples_total") << "\n\n";
    // RSS: min, max, least-squares slope over the campaign (after the first minute: warm-up).
    long mn = 0, mx = 0;
    double slope = 0.0;
    {
        std::vector<std::pair<double, long>> v;
        for (const auto& p : rss)
            if (p.second > 0) v.push_back(p);
        if (!v.empty()) {
            mn = std::min_element(v.begin(), v.end(), [](auto a, auto b) { return a.second < b.second; })->second;
            mx = std::max_element(v.begin(), v.end(), [](auto a, auto b) { return a.second < b.second; })->second;
            std::vector<std::pair<double, long>> w;
            for (const auto& p : v)
                if (p.first >= 60.0) w.push_back(p);
            if (w.size() >= 3) {
                double sx = 0, sy = 0, sxx = 0, sxy = 0;
                for (const auto& [x, y] : w) sx += x, sy += y, sxx += x * x, sxy += x * y;
                const double n = static_cast<double>(w.size());
                slope = (n * sxy - sx * sy) / (n * sxx - sx * sx);  // KiB per wall s
            }
        }
    }
    md.precision(1);
    md << "## Memory (cellbenchd VmRSS, every 5 s wall)\n\n- min " << mn / 1024.0 << " MiB, max " << mx / 1024.0
       << " MiB, slope after the first minute " << slope * 60.0 << " KiB per wall minute = "
       << slope * 3600.0 / o.time_scale << " KiB per bench hour\n- samples (wall s: MiB):";
    for (std::size_t k = 0; k < rss.size(); k += std::max<std::size_t>(1, rss.size() / 12))
        md << " " << static_cast<int>(rss[k].first) << ":" << rss[k].second / 1024.0;
    // Acceptance (issue 14): RSS at the end within 10 % of RSS after the first run; no sample lost by the store.
    // Both at the same point of a run's cycle: settled after the run's end (the last periodic sample may fall in
    // the middle of a run, with that run's data in flight).
    const long rss_end = rss_after_last_run;
    if (!rss.empty()) md << "\n- last periodic sample " << rss.back().second / 1024.0 << " MiB";
    if (rss_after_first_run > 0 && rss_end > 0) {
        const double growth = static_cast<double>(rss_end - rss_after_first_run) / static_cast<double>(rss_after_first_run);
        md << "\n- after the first run " << rss_after_first_run / 1024.0 << " MiB, after the last run " << rss_end / 1024.0
           << " MiB (" << (growth >= 0 ? "+" : "") << 100.0 * growth << " %; limit +10 %)";
        if (growth > 0.10)
            problems.push_back("RSS grew " + std::to_string(100.0 * growth) + " % after the first run (limit 10 %)");
    }
    // What the two settled figures are made of (information; the acceptance above is on VmRSS): anonymous memory
    // (heap, thread stacks) and file-backed pages (the program's code, paged in as it is first used: a first run
    // that ended before any fit has not yet touched the estimator's).
    {
        const RunRecord* first = nullptr;
        const RunRecord* last = nullptr;
        for (const auto& r : runs)
            if (r.rss_settled_kib > 0 && r.anon_kib >= 0 && r.file_kib >= 0) {
                if (!first) first = &r;
                last = &r;
            }
        // The first run may end before any fit (seed 6: aborted 54 s in), so its figure holds none of the fits'
        // working set; the same comparison from the first run that delivered a fit, for information.
        const RunRecord* fitted = nullptr;
        for (const auto& r : runs)
            if (r.rss_settled_kib > 0 && r.fits > 0) {
                fitted = &r;
                break;
            }
        if (fitted && last && fitted != first)
            md << "\n- (information, not the acceptance) from the first run that delivered a fit (run " << fitted->id << ", "
               << fitted->rss_settled_kib / 1024.0 << " MiB) to the last: "
               << (last->rss_settled_kib >= fitted->rss_settled_kib ? "+" : "")
               << 100.0 * static_cast<double>(last->rss_settled_kib - fitted->rss_settled_kib) / static_cast<double>(fitted->rss_settled_kib)
               << " %";
        if (first && last && first->anon_kib > 0)
            md << "\n- of which anonymous (heap, stacks) " << first->anon_kib / 1024.0 << " -> " << last->anon_kib / 1024.0
               << " MiB (" << (last->anon_kib >= first->anon_kib ? "+" : "")
               << 100.0 * static_cast<double>(last->anon_kib - first->anon_kib) / static_cast<double>(first->anon_kib)
               << " %), file-backed (code) " << first->file_kib / 1024.0 << " -> " << last->file_kib / 1024.0 << " MiB";
    }
    if (metric("cellbench_store_samples_lost_total") > 0 || metric("cellbench_store_samples_dropped_total") > 0)
        problems.push_back("the run store lost or dropped samples");
    md << "\n\n## Verdict\n\n";
    if (problems.empty()) md << "PASS: no crash, every run ended in a defined state with its events, every abort left the bench safe, the database is sound.\n";
    else
        for (const auto& p : problems) md << "- FAIL: " << p << "\n";
    std::printf("\n%s", md.str().c_str());
    if (!o.report.empty()) {
        if (o.report.has_parent_path()) fs::create_directories(o.report.parent_path());
        std::ofstream(o.report) << md.str();
        std::printf("report: %s; daemon log and database kept in %s\n", o.report.c_str(), dir.c_str());
    }
    return problems.empty() ? 0 : 1;
}
