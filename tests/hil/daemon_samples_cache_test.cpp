// GET /runs/{id}/samples answers (serialized bodies) from a cache while the store has committed nothing since the answer was
// computed (many dashboards polling one run read the database once per commit). What a user relies on: an
// answer is never older than what the database holds when it is given, and repeated polls between commits agree.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <thread>
#include <optional>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/run_store.hpp"
#include "hil/hil_support.hpp"

using namespace cellbench;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;

TEST(DaemonSamples, AnswersFollowEveryCommitWhileTheRunGoesOn) {
    test::TempDir tmp("samples-cache");
    auto cfg = test::sim_bench_config(fs::path(CELLBENCH_SOURCE_DIR) / "config/bench.sim.json");
    daemon::BenchDaemon d(cfg, test::daemon_options_in(tmp, 100.0, "t"));
    d.start();
    ASSERT_TRUE(test::eventually([&] { return test::instruments_connected(d); }, 30s));
    const auto id = d.start_run({"hppc_short", "p45b", {{"program", "hppc_short"}, {"cell", "p45b"}}})["id"]
                        .get<daemon::RunId>();
    daemon::SampleQuery q;
    q.max_points = 500;
    int compared = 0, agreed = 0;
    double last_to = -1;
    for (int k = 0; k < 40; ++k) {
        std::this_thread::sleep_for(100ms);
        // Whatever the API answers after a commit is what the database holds at that commit.
        ASSERT_TRUE(d.store().flush());
        const std::uint64_t before = d.store().commit_count();
        const json answer = json::parse(*d.samples_body(id, q));
        const auto fresh = d.store().samples(id, std::nullopt, std::nullopt, 500);
        const json again = json::parse(*d.samples_body(id, q));
        if (d.store().commit_count() != before) continue;  // a commit in between: nothing to compare
        ++compared;
        if (!std::isfinite(fresh.to_s)) continue;  // no row yet
        ASSERT_TRUE(answer["to_s"].is_number()) << answer.dump().substr(0, 200);
        EXPECT_DOUBLE_EQ(answer["to_s"].get<double>(), fresh.to_s) << "poll " << k;
        EXPECT_EQ(answer, again) << "poll " << k;
        if (answer == again) ++agreed;
        EXPECT_GE(answer["to_s"].get<double>(), last_to);  // never goes back
        last_to = answer["to_s"].get<double>();
    }
    // The body is the API's answer serialized: the same as samples() computed afresh now.
    ASSERT_TRUE(d.store().flush());
    const std::uint64_t at = d.store().commit_count();
    const json body = json::parse(*d.samples_body(id, q));
    const json direct = d.samples(id, q);
    if (d.store().commit_count() == at) {
        EXPECT_EQ(body, direct);
    }
    std::printf("%d polls compared without a commit in between, %d identical\n", compared, agreed);
    EXPECT_GT(compared, 0) << "every poll raced a commit: nothing was checked";
    EXPECT_GT(last_to, 0.0) << "the run stored no rows";
    d.stop_run(id);
    d.shutdown();
}
