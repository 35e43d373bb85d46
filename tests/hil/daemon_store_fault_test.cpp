// The run store failing under a live run (issue 6, "Disk full or database locked"), in process: BenchDaemon on
// config/bench.sim.json (simulated instruments, 50x), a short HPPC charging the cell, then
//  - disk full: the database's size limit (PRAGMA max_page_count through BenchDaemonOptions, the same SQLITE_FULL
//    a full file system gives) is reached during the run;
//  - locked: another connection holds the write lock (BEGIN EXCLUSIVE) beyond the daemon's busy timeout.
// Either way: the run aborts (state and outcome "aborted", the reason names the database), the simulated cell
// carries no current and the chamber goes to its safe set point, and the file passes integrity_check. The abort
// records, which the database refused at that moment, are not lost: locked -> written as soon as the lock is
// released (the store retries them every second); disk full -> committed as soon as they fit, else kept and at
// shutdown written to the sidecar DB.unsaved.jsonl, which the next open imports.
#include <gtest/gtest.h>

#include <sqlite3.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <thread>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/bench_daemon.hpp"
#include "hil/hil_support.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/sim/plant.hpp"

using namespace cellbench;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using cellbench::test::eventually;

const fs::path kSource = CELLBENCH_SOURCE_DIR;
constexpr double kScale = 50.0;
constexpr double kSafeSetpointC = 25.0;  // config/bench.sim.json

struct Fixture {
    test::TempDir tmp;
    fs::path dir;
    std::unique_ptr<daemon::BenchDaemon> d;

    explicit Fixture(const std::string& tag, std::optional<std::int64_t> max_pages)
        : tmp("storefault-" + tag), dir(tmp.path) {
        auto cfg = test::sim_bench_config(kSource / "config/bench.sim.json");
        cfg.simulation->initial_soc = 0.5;  // the run's first charge lasts ~0.5 h of bench time: current flows
        auto o = test::daemon_options_in(tmp, kScale, "t");
        o.db_max_page_count = max_pages;
        o.db_busy_timeout = 500ms;
        d = std::make_unique<daemon::BenchDaemon>(cfg, o);
        d->start();
    }
    ~Fixture() { d.reset(); }  // before the folder goes

    bool connected() { return test::instruments_connected(*d); }
    double current() { return d->plant()->read().current_a; }
    double setpoint() { return d->plant()->read().chamber_setpoint_c; }
};

std::string integrity(const fs::path& db) {
    sqlite3* h = nullptr;
    std::string out;
    sqlite3_open_v2(db.c_str(), &h, SQLITE_OPEN_READONLY, nullptr);
    sqlite3_stmt* s = nullptr;
    if (sqlite3_prepare_v2(h, "PRAGMA integrity_check", -1, &s, nullptr) == SQLITE_OK)
        while (sqlite3_step(s) == SQLITE_ROW) out += reinterpret_cast<const char*>(sqlite3_column_text(s, 0));
    sqlite3_finalize(s);
    sqlite3_close(h);
    return out;
}

bool has_database_abort(const std::vector<daemon::EventRecord>& events) {
    for (const auto& e : events)
        if (e.kind == "abort" && e.message.find("database") != std::string::npos) return true;
    return false;
}

}  // namespace

TEST(DaemonStoreFault, ALockedDatabaseAbortsTheRunSafelyAndTheAbortIsRecordedOnceTheLockIsReleased) {
    Fixture f("locked", std::nullopt);
    ASSERT_TRUE(eventually([&] { return f.connected(); }, 30s));
    const auto id = f.d->start_run({"hppc_short", "p45b", {{"program", "hppc_short"}, {"cell", "p45b"}}})["id"].get<daemon::RunId>();
    ASSERT_TRUE(eventually([&] { return std::abs(f.current()) > 1.0; }, 60s)) << "precondition: the cell charging";

    sqlite3* other = nullptr;  // another process holding the write lock
    ASSERT_EQ(sqlite3_open(f.d->database_path().c_str(), &other), SQLITE_OK);
    // The daemon may be inside one of its own write transactions at this instant (it commits samples every few
    // hundred ms): wait for it to end, as any other process taking the lock would (clean clone at 5207b62, on a
    // loaded machine, got SQLITE_BUSY here at once).
    sqlite3_busy_timeout(other, 30000);
    ASSERT_EQ(sqlite3_exec(other, "BEGIN EXCLUSIVE", nullptr, nullptr, nullptr), SQLITE_OK) << sqlite3_errmsg(other);

    json run;
    ASSERT_TRUE(eventually([&] { return (run = f.d->get_run(id))["state"] == "aborted"; }, 60s)) << run.dump(2);
    EXPECT_EQ(run["outcome"], "aborted");
    EXPECT_NE(run.value("error", json("")).dump().find("database"), std::string::npos) << run.dump(2);
    EXPECT_TRUE(eventually([&] { return std::abs(f.current()) < 1e-3 && std::abs(f.setpoint() - kSafeSetpointC) < 0.05; }, 30s))
        << "current " << f.current() << " A, set point " << f.setpoint();
    // Still locked: the abort is not in the file yet.
    EXPECT_FALSE(has_database_abort(f.d->store().events(id)));

    ASSERT_EQ(sqlite3_exec(other, "COMMIT", nullptr, nullptr, nullptr), SQLITE_OK);
    sqlite3_close(other);
    EXPECT_TRUE(eventually([&] { return has_database_abort(f.d->store().events(id)); }, 30s))
        << "the abort event never reached the database after the lock was released";
    EXPECT_TRUE(eventually([&] { return f.d->store().get_run(id)->state == daemon::RunState::aborted; }, 30s));
    f.d->shutdown();
    EXPECT_EQ(integrity(f.dir / "bench.sqlite"), "ok");
    EXPECT_FALSE(fs::exists(f.dir / "bench.sqlite.unsaved.jsonl"));
}

TEST(DaemonStoreFault, AFullDiskAbortsTheRunSafelyAndTheAbortIsRecorded) {
    // 700 pages of 4 KiB: full after some hundreds of bench seconds of samples, i.e. during the first charge.
    Fixture f("full", 700);
    ASSERT_TRUE(eventually([&] { return f.connected(); }, 30s));
    const auto id = f.d->start_run({"hppc_short", "p45b", {{"program", "hppc_short"}, {"cell", "p45b"}}})["id"].get<daemon::RunId>();
    json run;
    double current_while_running = 0.0;
    ASSERT_TRUE(eventually([&] {
        run = f.d->get_run(id);
        if (run["state"] == "running") current_while_running = std::max(current_while_running, std::abs(f.current()));
        return !test::live_run_state(run["state"].get<std::string>());
    }, 120s)) << run.dump(2);
    EXPECT_GT(current_while_running, 1.0) << "precondition: the cell was charging when the disk filled up";
    EXPECT_EQ(run["state"], "aborted") << run.dump(2);
    EXPECT_EQ(run["outcome"], "aborted");
    EXPECT_NE(run.value("error", json("")).dump().find("disk full"), std::string::npos) << run.dump(2);
    EXPECT_TRUE(eventually([&] { return std::abs(f.current()) < 1e-3 && std::abs(f.setpoint() - kSafeSetpointC) < 0.05; }, 30s))
        << "current " << f.current() << " A, set point " << f.setpoint();

    // The abort's few records usually still fit in the pages a failed sample batch left free (then they are
    // committed at once); what does not fit is kept, retried, and at shutdown goes to the sidecar.
    f.d->shutdown();
    const fs::path db = f.dir / "bench.sqlite";
    EXPECT_EQ(integrity(db), "ok");
    const bool sidecar = fs::exists(fs::path(db.string() + ".unsaved.jsonl"));
    std::printf("abort records %s\n", sidecar ? "went to the sidecar" : "were committed to the database");
    // "Space freed" (no size limit): the next open imports a sidecar before anything else.
    auto store = daemon::RunStore::open(db);
    EXPECT_TRUE(has_database_abort(store->events(id)));
    EXPECT_EQ(store->get_run(id)->state, daemon::RunState::aborted);
    if (sidecar) {
        EXPECT_TRUE(fs::exists(fs::path(db.string() + ".unsaved.jsonl.imported")));
    }
    EXPECT_EQ(store->integrity_check(), "ok");
}
