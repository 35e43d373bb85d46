// kill -9 of cellbenchd (issue 6, "Crash and restart"), with the instruments in their own process as on the real
// bench: `cellbench sim` hosts the Neware tester, the Modbus chamber and the DEWE CAN stream; cellbenchd runs
// config/bench.hil.json against it (ports, socket and database in a temp dir). The daemon runs a program with a
// step change every few wall seconds and is SIGKILLed at three moments (right after a step change, mid-step
// at a random point, and at a random moment), drawn from a fixed seed. After each kill:
//  - the SQLite file is sound: `pragma integrity_check` = ok (sqlite3 C API, the daemon dead);
//  - data loss: the last committed DAQ, cycler and chamber samples were taken at most 1 s of WALL time before
//    the kill. The daemon commits every flush_period_ms (200 ms) of wall time, so the bound is a wall-time one;
//    on the real bench (time scale 1) that is one second of bench time. Here the bench runs kTimeScale times
//    faster, so the same bound covers kTimeScale bench seconds (printed);
//  - the tester still runs the program while the daemon is dead (precondition: the restart has to stop it);
//  - restart: as soon as the API is up, the tester's channels are stopped with no current and the chamber's
//    set point register holds the safe set point (read from the simulated instruments directly over their
//    own protocols); the daemon's recovery runs before its API listens, and its log says so in that order;
//    the run is "interrupted" (state and outcome), a "recovery" event says both commands were acknowledged,
//    and the run's sample count does not grow afterwards (it never silently continues).
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <modbus/modbus.h>
#include <signal.h>
#include <sqlite3.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>

#include "unit/api_test_support.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using namespace std::chrono_literals;
namespace http = boost::beast::http;

namespace {

const fs::path kBinDir = CELLBENCH_BIN_DIR;
const fs::path kSource = CELLBENCH_SOURCE_DIR;
constexpr double kTimeScale = 10.0;  // bench s per wall s (sim and daemon agree)
constexpr const char* kToken = "crash-token";
constexpr const char* kTerminator = "\n\n#\r\n";
constexpr double kSafeSetpointC = 25.0;  // config/bench.hil.json
constexpr double kRunSetpointC = 32.0;   // the crash program's

double unix_now() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

bool eventually(const std::function<bool()>& pred, std::chrono::seconds limit, std::chrono::milliseconds poll = 20ms) {
    const auto end = std::chrono::steady_clock::now() + limit;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(poll);
    }
    return pred();
}

struct Child {
    pid_t pid = -1;
    FILE* out = nullptr;  // its stdout
};

// Runs bin with args, stderr appended to log, stdout to a pipe (or to the log too).
Child spawn(const std::vector<std::string>& args, const fs::path& log, bool stdout_to_log = false) {
    int fds[2];
    if (::pipe(fds) != 0) return {};
    Child c;
    c.pid = ::fork();
    if (c.pid == 0) {
        FILE* f = std::fopen(log.c_str(), "a");
        if (f) ::dup2(::fileno(f), STDERR_FILENO);
        ::dup2(stdout_to_log && f ? ::fileno(f) : fds[1], STDOUT_FILENO);
        ::close(fds[0]);
        ::close_range(3, ~0U, 0);  // the test's own sockets stay with the test
        std::vector<char*> argv;
        for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
        argv.push_back(nullptr);
        ::execv(argv[0], argv.data());
        ::_exit(127);
    }
    ::close(fds[1]);
    c.out = ::fdopen(fds[0], "r");
    return c;
}

std::string read_line(FILE* f) {
    char line[1024];
    if (!f || !std::fgets(line, sizeof line, f)) return {};
    std::string s(line);
    while (!s.empty() && (s.back() == '\n' || s.back() == '\r')) s.pop_back();
    return s;
}

void reap(Child& c, int sig) {
    if (c.pid <= 0) return;
    ::kill(c.pid, sig);
    int st = 0;
    ::waitpid(c.pid, &st, 0);
    c.pid = -1;
    if (c.out) std::fclose(c.out);
    c.out = nullptr;
}

std::string slurp(const fs::path& p) {
    std::ifstream in(p);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

// -- the simulated instruments, read over their own protocols ----------------------------------------------

struct TesterState {
    bool ok = false;
    std::string statuses;   // workstatus of every channel, comma separated
    bool all_stopped = true;
    double current_a = 0.0;  // sum of |current| over the channels
};

TesterState inquire_tester(int port) {
    TesterState t;
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    timeval tv{5, 0};
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<std::uint16_t>(port));
    inet_pton(AF_INET, "127.0.0.1", &addr.sin_addr);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        ::close(fd);
        return t;
    }
    std::string list = "<list count=\"3\">";
    for (int ch = 1; ch <= 3; ++ch)
        list += "<inquire ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"" + std::to_string(ch) +
                "\" aux=\"0\" barcode=\"1\">true</inquire>";
    list += "</list>\r\n";
    const std::string req = "<?xml version=\"1.0\" encoding=\"UTF-8\" ?>\r\n<bts version=\"1.0\">\r\n<cmd>inquire</cmd>\r\n" +
                            list + "</bts>" + kTerminator;
    std::string got;
    if (::send(fd, req.data(), req.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(req.size())) {
        char buf[4096];
        while (got.find(kTerminator) == std::string::npos) {
            const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
            if (n <= 0) break;
            got.append(buf, static_cast<std::size_t>(n));
        }
    }
    ::close(fd);
    int channels = 0;
    for (std::size_t at = got.find("workstatus=\""); at != std::string::npos; at = got.find("workstatus=\"", at + 1)) {
        const auto b = at + 12, e = got.find('"', b);
        const std::string st = got.substr(b, e - b);
        t.statuses += (channels ? "," : "") + st;
        if (st != "stop" && st != "finish") t.all_stopped = false;
        ++channels;
    }
    for (std::size_t at = got.find(" current=\""); at != std::string::npos; at = got.find(" current=\"", at + 1))
        t.current_a += std::abs(std::stod(got.substr(at + 10)));
    t.ok = channels == 3;
    return t;
}

std::optional<double> chamber_setpoint(int port) {
    modbus_t* mb = modbus_new_tcp("127.0.0.1", port);
    if (!mb) return std::nullopt;
    std::optional<double> sp;
    std::uint16_t reg = 0;
    modbus_set_slave(mb, 1);
    modbus_set_response_timeout(mb, 10, 0);  // not libmodbus' 0.5 s: a busy machine answers late, not never
    if (modbus_connect(mb) == 0 && modbus_read_registers(mb, 2, 1, &reg) == 1)
        sp = static_cast<std::int16_t>(reg) * 0.1;  // holding 2: set point, int16, 0.1 degC
    modbus_close(mb);
    modbus_free(mb);
    return sp;
}

// -- the database, read with the daemon dead ----------------------------------------------------------------

struct DbFacts {
    std::string integrity;
    std::string state;
    double last_daq_unix = NAN, last_cycler_unix = NAN, last_chamber_unix = NAN;
};

DbFacts read_db(const fs::path& db, long long run) {
    DbFacts f;
    sqlite3* h = nullptr;
    if (sqlite3_open_v2(db.c_str(), &h, SQLITE_OPEN_READONLY, nullptr) != SQLITE_OK) {
        f.integrity = std::string("cannot open: ") + sqlite3_errmsg(h);
        sqlite3_close(h);
        return f;
    }
    auto text = [&](const std::string& sql) {
        sqlite3_stmt* s = nullptr;
        std::string out;
        if (sqlite3_prepare_v2(h, sql.c_str(), -1, &s, nullptr) != SQLITE_OK) return std::string("error: ") + sqlite3_errmsg(h);
        while (sqlite3_step(s) == SQLITE_ROW)
            if (const auto* t = sqlite3_column_text(s, 0)) out += (out.empty() ? "" : "; ") + std::string(reinterpret_cast<const char*>(t));
        sqlite3_finalize(s);
        return out;
    };
    auto real = [&](const std::string& sql) {
        sqlite3_stmt* s = nullptr;
        double v = NAN;
        if (sqlite3_prepare_v2(h, sql.c_str(), -1, &s, nullptr) == SQLITE_OK) {
            sqlite3_bind_int64(s, 1, run);
            if (sqlite3_step(s) == SQLITE_ROW && sqlite3_column_type(s, 0) != SQLITE_NULL) v = sqlite3_column_double(s, 0);
        }
        sqlite3_finalize(s);
        return v;
    };
    f.integrity = text("PRAGMA integrity_check");
    f.state = text("SELECT state FROM runs WHERE id = " + std::to_string(run));
    f.last_daq_unix = real("SELECT MAX(unix_s) FROM daq_samples WHERE run_id = ?1");
    f.last_cycler_unix = real("SELECT MAX(unix_s) FROM cycler_samples WHERE run_id = ?1");
    f.last_chamber_unix = real("SELECT MAX(unix_s) FROM chamber_samples WHERE run_id = ?1");
    sqlite3_close(h);
    return f;
}

// -- the campaign of kills ----------------------------------------------------------------------------------

class CrashTest : public ::testing::Test {
protected:
    fs::path dir;
    Child sim, daemon;
    int neware_port = 0, chamber_port = 0;
    std::uint16_t api_port = 0;

    void SetUp() override {
        dir = fs::temp_directory_path() / ("cellbench-crash-" + std::to_string(::getpid()));
        fs::remove_all(dir);
        fs::create_directories(dir / "programs");
        fs::create_directory_symlink(kSource / "config/cells", dir / "cells");
        // A program with a step change every 2-4 wall seconds at kTimeScale, for long enough.
        std::ofstream(dir / "programs/crash.json") << R"({
  "schema": "cellbench.bench-program/1", "name": "crash",
  "description": "kill -9 test: chamber set point, then rest / 1C discharge / rest / 1C charge, repeated",
  "parameters": {"blocks": 100},
  "segments": [
    {"type": "chamber_setpoint", "setpoint_c": )" << kRunSetpointC << R"(},
    {"type": "cycler", "name": "crash", "steps": [
      {"type": "rest", "time_s": 20},
      {"type": "cc_discharge", "current_a": "one_c_a", "cutoff_voltage_v": "min_voltage_v", "time_s": 40},
      {"type": "rest", "time_s": 20},
      {"type": "cc_charge", "current_a": "one_c_a", "cutoff_voltage_v": "max_voltage_v", "time_s": 40},
      {"type": "cycle", "start_step": 1, "count": "blocks"},
      {"type": "end"}]}]})";
        json simcfg = json::parse(std::ifstream(kSource / "config/bench.sim.json"));
        simcfg["instruments"]["cycler"]["port"] = 0;
        simcfg["instruments"]["chamber"]["port"] = 0;
        simcfg["instruments"]["daq"]["socket_path"] = (dir / "dewe.sock").string();
        simcfg["simulation"]["initial_soc"] = 0.6;
        simcfg["simulation"]["params"] = "cells/p45b-thesis.json";
        std::ofstream(dir / "sim.json") << simcfg.dump(2);

        sim = spawn({(kBinDir / "cellbench").string(), "-q", "sim", "--config", (dir / "sim.json").string(),
                     "--time-scale", std::to_string(kTimeScale)},
                    dir / "sim.log");
        for (int k = 0; k < 3; ++k) {
            const std::string s = read_line(sim.out);
            const auto colon = s.rfind(':');
            if (s.rfind("neware tcp ", 0) == 0) neware_port = std::stoi(s.substr(colon + 1));
            if (s.rfind("chamber modbus-tcp ", 0) == 0) chamber_port = std::stoi(s.substr(colon + 1));
        }
        ASSERT_GT(neware_port, 0) << slurp(dir / "sim.log");
        ASSERT_GT(chamber_port, 0) << slurp(dir / "sim.log");

        json hil = json::parse(std::ifstream(kSource / "config/bench.hil.json"));
        hil["instruments"]["cycler"]["port"] = neware_port;
        hil["instruments"]["chamber"]["port"] = chamber_port;
        hil["instruments"]["daq"]["socket_path"] = (dir / "dewe.sock").string();
        hil["database"] = {{"path", (dir / "bench.sqlite").string()}, {"flush_period_ms", 200}};
        hil["safety"]["instrument_loss_grace_s"] = 30.0;
        std::ofstream(dir / "hil.json") << hil.dump(2);
    }

    void TearDown() override {
        reap(daemon, SIGKILL);
        reap(sim, SIGTERM);
        if (!HasFailure()) fs::remove_all(dir);
        else std::printf("kept %s (sim.log, daemon.log, bench.sqlite)\n", dir.c_str());
    }

    // Starts cellbenchd; returns the log offset where this start's lines begin.
    std::size_t start_daemon() {
        const std::size_t log_at = fs::exists(dir / "daemon.log") ? fs::file_size(dir / "daemon.log") : 0;
        daemon = spawn({(kBinDir / "cellbenchd").string(), "--config", (dir / "hil.json").string(), "--listen",
                        "127.0.0.1:0", "--token", kToken, "--time-scale", std::to_string(kTimeScale)},
                       dir / "daemon.log", true);
        // "cellbenchd: API http://127.0.0.1:PORT/api/v1" is printed once start() returned: after recovery.
        api_port = 0;
        const std::string key = "cellbenchd: API http://127.0.0.1:";
        eventually([&] {
            const std::string log = slurp(dir / "daemon.log").substr(log_at);
            const auto at = log.find(key);
            if (at != std::string::npos && log.find('/', at + key.size()) != std::string::npos)
                api_port = static_cast<std::uint16_t>(std::stoi(log.substr(at + key.size())));
            int st = 0;
            return api_port != 0 || ::waitpid(daemon.pid, &st, WNOHANG) != 0;
        }, 60s);
        return log_at;
    }

    json get(const std::string& target) {
        const auto r = cellbench::testing::request(api_port, http::verb::get, "/api/v1" + target);
        return json::parse(r.body());
    }

    long long start_run() {
        const auto r = cellbench::testing::request(api_port, http::verb::post, "/api/v1/runs",
                                                   R"({"program": "crash", "cell": "p45b"})",
                                                   {{"Authorization", std::string("Bearer ") + kToken},
                                                    {"Content-Type", "application/json"}});
        if (r.result_int() != 201) {
            ADD_FAILURE() << "POST /runs: " << r.result_int() << " " << r.body();
            return 0;
        }
        return json::parse(r.body())["id"].get<long long>();
    }

    int step_index() {
        const json s = get("/status");
        if (!s["run"].is_object() || !s["run"]["step"].is_object()) return 0;
        return s["run"]["step"]["index"].get<int>();
    }
};

TEST_F(CrashTest, KillNineAtAnyMomentLeavesASoundFileAndTheRestartMakesTheBenchSafeFirst) {
    std::mt19937 rng(20240606);  // fixed seed: the same moments every run
    struct Kill {
        const char* what;
        int after_step;       // wait until the run is in this step (index), or beyond
        double extra_wall_s;  // then wait this long
    };
    std::uniform_real_distribution<double> mid(0.8, 2.5), any(0.0, 6.0);
    const Kill kills[] = {
        {"right after a step change", 3, 0.0},
        {"mid-step (random point in a 1C step)", 2, mid(rng)},
        {"at a random moment", 1, any(rng)},
    };

    start_daemon();
    ASSERT_GT(api_port, 0) << slurp(dir / "daemon.log");
    double worst_gap_s = 0.0;
    for (const auto& k : kills) {
        SCOPED_TRACE(k.what);
        ASSERT_TRUE(eventually([&] {
            const json st = get("/status");  // a named object: a range-for over a temporary's member dangles
            for (const auto& i : st["instruments"])
                if (i["state"] != "connected") return false;
            return true;
        }, 30s)) << get("/status").dump(2);
        const long long run = start_run();
        ASSERT_GT(run, 0);

        // The kill moment.
        if (k.after_step > 0) {
            int first = 0;
            ASSERT_TRUE(eventually([&] { return (first = step_index()) >= 1; }, 30s)) << "the run never reached the tester";
            const int target = std::max(k.after_step, first);
            ASSERT_TRUE(eventually([&] { return step_index() >= target; }, 30s)) << "no step change";
            // "right after": poll fast until the index changes once more, then kill at once.
            if (k.extra_wall_s == 0.0) {
                const int now = step_index();
                ASSERT_TRUE(eventually([&] { return step_index() > now; }, 30s, 2ms));
            }
        }
        std::this_thread::sleep_for(std::chrono::duration<double>(k.extra_wall_s));
        const double kill_unix = unix_now();
        ASSERT_EQ(::kill(daemon.pid, SIGKILL), 0);
        int st = 0;
        ::waitpid(daemon.pid, &st, 0);
        ASSERT_TRUE(WIFSIGNALED(st)) << "the daemon had already exited";
        daemon.pid = -1;
        std::fclose(daemon.out);
        daemon.out = nullptr;
        const auto sp_before = chamber_setpoint(chamber_port);
        ASSERT_TRUE(sp_before);
        EXPECT_NEAR(*sp_before, kRunSetpointC, 0.05) << "precondition: the run's set point";

        // The instruments live on without the daemon: the tester still runs the program.
        const TesterState before = inquire_tester(neware_port);
        ASSERT_TRUE(before.ok);
        EXPECT_FALSE(before.all_stopped) << "the tester stopped on its own (" << before.statuses
                                         << "): the restart's stop would prove nothing";

        // The file: sound, the run still marked live, at most 1 s (wall) of samples lost.
        const DbFacts f = read_db(dir / "bench.sqlite", run);
        EXPECT_EQ(f.integrity, "ok");
        EXPECT_EQ(f.state, "running");
        for (const auto& [source, last] : {std::pair{"daq", f.last_daq_unix}, std::pair{"cycler", f.last_cycler_unix},
                                           std::pair{"chamber", f.last_chamber_unix}}) {
            ASSERT_TRUE(std::isfinite(last)) << source << ": no sample committed";
            const double gap = kill_unix - last;
            // The chamber is polled once per bench second (0.1 s wall here): its last sample may precede the
            // last commit by that period too.
            EXPECT_LE(gap, 1.0) << source << ": the last committed sample was taken " << gap
                                << " s (wall) before the kill";
            worst_gap_s = std::max(worst_gap_s, gap);
            std::printf("  %-40s %-8s last committed sample %.3f s wall (%.1f s bench) before the kill\n", k.what, source,
                        gap, gap * kTimeScale);
        }

        // Restart: by the time the API answers, the bench is safe.
        const std::size_t log_at = start_daemon();
        ASSERT_GT(api_port, 0) << slurp(dir / "daemon.log");
        const TesterState after = inquire_tester(neware_port);
        ASSERT_TRUE(after.ok);
        EXPECT_TRUE(after.all_stopped) << after.statuses;
        EXPECT_LT(after.current_a, 1e-3) << after.statuses;
        const auto sp = chamber_setpoint(chamber_port);
        ASSERT_TRUE(sp);
        EXPECT_NEAR(*sp, kSafeSetpointC, 0.05) << "the chamber was at " << kRunSetpointC << " degC during the run";
        const std::string log = slurp(dir / "daemon.log").substr(log_at);
        const auto rec = log.find("recovery: the cycler stopped and the chamber is at its safe set point");
        const auto api = log.find("cellbenchd: API");
        EXPECT_NE(rec, std::string::npos) << log;
        EXPECT_TRUE(api == std::string::npos || rec < api) << "recovery must precede the API:\n" << log;

        // The run: interrupted, with its recovery event; it does not continue.
        const json r = get("/runs/" + std::to_string(run));
        EXPECT_EQ(r["state"], "interrupted") << r.dump(2);
        EXPECT_EQ(r["outcome"], "interrupted") << r.dump(2);
        EXPECT_TRUE(r["error"].is_string()) << r.dump(2);
        EXPECT_TRUE(get("/status")["run"].is_null());
        bool recovery_event = false;
        const json events = get("/runs/" + std::to_string(run) + "/events");
        for (const auto& e : events["events"])
            if (e["kind"] == "recovery") {
                recovery_event = true;
                EXPECT_EQ(e["detail"]["cycler_stop"], "acknowledged") << e.dump();
                EXPECT_EQ(e["detail"]["chamber_setpoint"], "acknowledged") << e.dump();
            }
        EXPECT_TRUE(recovery_event);
        const auto samples = r["samples"].get<long long>();
        std::this_thread::sleep_for(500ms);  // 5 bench s: many samples, were the run still recorded
        EXPECT_EQ(get("/runs/" + std::to_string(run))["samples"].get<long long>(), samples);
        EXPECT_TRUE(inquire_tester(neware_port).all_stopped);
    }
    std::printf("worst loss: %.3f s wall = %.1f s bench at time scale %.0f (bound: 1 s wall; 1 s bench at scale 1)\n",
                worst_gap_s, worst_gap_s * kTimeScale, kTimeScale);
    reap(daemon, SIGTERM);
}

}  // namespace
