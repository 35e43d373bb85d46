// Issue 16, the daemon's records and storage: a run whose final fit did not land (kill -9 between the run's end
// and its fit) is visible at the next start as a fit_pending event and its fit is redone from the stored
// records; a database that cannot be written is reported truthfully (GET /health, POST /runs 503 with the
// reason); a database folder where no file can be created is refused at start with a message that says so.
#include <gtest/gtest.h>

#include <sqlite3.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <string>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/run_store.hpp"
#include "hil/hil_support.hpp"

using namespace cellbench;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;
using cellbench::test::eventually;

namespace {
const fs::path kSource = CELLBENCH_SOURCE_DIR;

bool has_event(const std::vector<daemon::EventRecord>& events, const std::string& kind, const std::string& words = "") {
    for (const auto& e : events)
        if (e.kind == kind && e.message.find(words) != std::string::npos) return true;
    return false;
}
}  // namespace

TEST(DaemonHostile, ARunWhoseFinalFitDidNotLandIsFlaggedAndRefittedAtRestart) {
    test::TempDir tmp("fitpending");
    const fs::path db = tmp.path / "bench.sqlite";
    daemon::RunId id = 0;
    {
        // What kill -9 right after the end of a run leaves: completed, samples, no parameter set, no fit event.
        auto store = daemon::RunStore::open(db);
        daemon::NewRun nr;
        nr.program = "cc";
        nr.cell = "p45b";
        nr.config = json::object();
        id = store->create_run(nr);
        for (int k = 0; k < 600; ++k) {
            daemon::CyclerSample s;
            s.t_s = k;
            s.unix_s = 1.7e9 + k;
            s.current_a = k < 300 ? -4.5 : 0.0;
            s.voltage_v = 4.1 - 0.001 * std::min(k, 300) + (k >= 300 ? 0.05 : 0.0);
            store->push(id, s);
        }
        store->set_run_state(id, daemon::RunState::completed, "program finished");
        ASSERT_TRUE(store->flush());
    }
    auto o = test::daemon_options_in(tmp, 100.0, "t");
    daemon::BenchDaemon d(test::sim_bench_config(kSource / "config/bench.sim.json"), o);
    d.start();
    EXPECT_TRUE(eventually([&] { return has_event(d.store().events(id), "fit_pending", "did not land"); }, 30s));
    // The redone fit reports: a parameter set, or why there is none (this recording has no HPPC pulses).
    EXPECT_TRUE(eventually([&] { return has_event(d.store().events(id), "fit", "redone at restart"); }, 120s));
    d.shutdown();

    // Once redone, a further restart flags nothing.
    daemon::BenchDaemon again(test::sim_bench_config(kSource / "config/bench.sim.json"), o);
    again.start();
    std::size_t pending = 0;
    for (const auto& e : again.store().events(id)) pending += e.kind == "fit_pending";
    EXPECT_EQ(pending, 1u);
    again.shutdown();
}

TEST(DaemonHostile, AFullDatabaseIsReportedByHealthAndPostRunsAnswers503) {
    test::TempDir tmp("dbfull");
    auto o = test::daemon_options_in(tmp, 100.0, "t");
    {
        daemon::BenchDaemon first(test::sim_bench_config(kSource / "config/bench.sim.json"), o);
        first.start();
        first.shutdown();
    }
    // Restart on a "still full disk": the database's size limit (the same SQLITE_FULL a full file system gives)
    // at the pages it holds, and every free byte taken by filler rows, so no run record fits any more.
    std::int64_t pages = 0;
    {
        sqlite3* h = nullptr;
        ASSERT_EQ(sqlite3_open((tmp.path / "bench.sqlite").c_str(), &h), SQLITE_OK);
        ASSERT_EQ(sqlite3_exec(h, "CREATE TABLE filler (x BLOB)", nullptr, nullptr, nullptr), SQLITE_OK);
        sqlite3_stmt* st = nullptr;
        sqlite3_prepare_v2(h, "PRAGMA page_count", -1, &st, nullptr);
        if (sqlite3_step(st) == SQLITE_ROW) pages = sqlite3_column_int64(st, 0);
        sqlite3_finalize(st);
        ASSERT_EQ(sqlite3_exec(h, ("PRAGMA max_page_count = " + std::to_string(pages)).c_str(), nullptr, nullptr, nullptr),
                  SQLITE_OK);
        for (const char* table : {"filler", "runs"})  // the runs table's own pages too
            for (const int size : {4000, 1000, 200, 20, 1})
                for (int k = 0; k < 100000; ++k) {
                    const std::string blob = "zeroblob(" + std::to_string(size) + ")";
                    const std::string sql =
                        std::string(table) == "filler"
                            ? "INSERT INTO filler VALUES (" + blob + ")"
                            : "INSERT INTO runs(program, cell, state, created_unix_s, config_json) VALUES "
                              "('filler', 'filler', 'completed', 0, " + blob + ")";
                    if (sqlite3_exec(h, sql.c_str(), nullptr, nullptr, nullptr) != SQLITE_OK) break;
                }
        sqlite3_close(h);
    }
    o.db_max_page_count = pages;
    daemon::BenchDaemon d(test::sim_bench_config(kSource / "config/bench.sim.json"), o);
    d.start();
    ASSERT_TRUE(eventually([&] { return test::instruments_connected(d); }, 30s));
    try {
        d.start_run({"hppc_short", "p45b", {{"program", "hppc_short"}, {"cell", "p45b"}}});
        ADD_FAILURE() << "a run started on a full database";
    } catch (const daemon::ApiError& e) {
        EXPECT_EQ(e.status(), 503) << e.what();
        EXPECT_NE(std::string(e.what()).find("database cannot record a run"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("full"), std::string::npos) << e.what();
    }
    const json h = d.health();
    EXPECT_EQ(h["status"], "degraded") << h.dump();
    EXPECT_EQ(h["database"]["writable"], false) << h.dump();
    EXPECT_NE(h["database"].value("detail", "").find("full"), std::string::npos) << h.dump();
    d.shutdown();
}

TEST(DaemonHostile, ADatabaseFolderWhereNoFileCanBeCreatedIsAClearErrorAtStart) {
    // /sys refuses new files even to root (EACCES): the message names the folder and why.
    try {
        daemon::RunStore::open("/sys/cellbench-hostile-test.sqlite");
        ADD_FAILURE() << "opened a database in /sys";
    } catch (const InputError& e) {
        const std::string msg = e.what();
        EXPECT_NE(msg.find("cannot create files in the folder /sys"), std::string::npos) << msg;
        EXPECT_NE(msg.find("must be writable"), std::string::npos) << msg;
    }
}
