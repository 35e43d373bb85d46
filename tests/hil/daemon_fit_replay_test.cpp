// Issue 14's promises at the API edge, on the simulated bench:
//  - run parameters: POST /runs "parameters" override a program's declared parameters, validated like the
//    program (every problem named in one 400, nothing started); valid ones shape the run (2 pulse sets, 2C);
//  - /status gives each instrument's data age;
//  - `cellbench fit --db BENCH.sqlite --run ID` replays the stored run through the online fitter and gives the
//    parameters the daemon gave (GET /runs/{id}/fits): every fitted value equal, SOC within a count's batch.
#include <gtest/gtest.h>

#include <sys/wait.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/bench_daemon.hpp"
#include "hil/hil_support.hpp"
#include "support/command.hpp"

using namespace cellbench;
using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;
using cellbench::test::eventually;

namespace {

const fs::path kSource = CELLBENCH_SOURCE_DIR;
const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";

using CliRun = cellbench::test::CommandRun;

CliRun run_cli(const std::string& command) { return cellbench::test::run_command(command, 600); }

bool terminal(const std::string& s) { return !test::live_run_state(s); }

double num(const json& j, const char* key) { return j.contains(key) && j[key].is_number() ? j[key].get<double>() : NAN; }

// Equal to the last bit, or both absent.
void expect_same(const json& replay, const json& daemon, const std::string& what) {
    if (daemon.is_null()) {
        EXPECT_TRUE(replay.is_null()) << what;
        return;
    }
    ASSERT_TRUE(replay.is_object()) << what;
    for (const char* k : {"r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f"}) {
        const double a = num(replay, k), b = num(daemon, k);
        if (std::isnan(b)) EXPECT_TRUE(std::isnan(a)) << what << " " << k;
        else EXPECT_DOUBLE_EQ(a, b) << what << " " << k;
    }
}

}  // namespace

TEST(DaemonFitReplay, RunParametersAreValidatedAndFitDbGivesTheDaemonsParameters) {
    test::TempDir tmp("fit-replay");
    daemon::BenchDaemon d(test::sim_bench_config(kSource / "config/bench.sim.json"), test::daemon_options_in(tmp, 100.0));
    d.start();
    ASSERT_TRUE(eventually([&] { return test::instruments_connected(d); }, 30s)) << d.status().dump(2);
    // /status: each instrument says how old its newest reading is (issue 15: data age per instrument).
    ASSERT_TRUE(eventually([&] {
        const json st = d.status();
        for (const auto& i : st["instruments"])
            if (!i.contains("data_age_s") || !i["data_age_s"].is_number() || i["data_age_s"].get<double>() < 0) return false;
        return true;
    }, 30s)) << d.status()["instruments"].dump(2);
    // The cycler's entry lists the tester channels wired in parallel (three in bench.sim.json), each with its own
    // voltage, current and status, in the configured order.
    {
        const json members = d.status()["instruments"][0]["members"];
        ASSERT_EQ(members.size(), 3u) << members.dump(2);
        for (std::size_t k = 0; k < 3; ++k) {
            EXPECT_EQ(members[k]["channel"], "24-1-1-" + std::to_string(k + 1)) << members.dump(2);
            EXPECT_GT(members[k]["voltage_v"].get<double>(), 2.0) << members.dump(2);
            EXPECT_TRUE(members[k]["current_a"].is_number()) << members.dump(2);
            EXPECT_TRUE(members[k]["status"].is_string()) << members.dump(2);
        }
    }

    // Every problem of the overrides in one refusal; no run is recorded.
    daemon::StartRequest bad{"hppc_short", "p45b", {}, {}};
    bad.parameters = {{"c_rate", "fast"}, {"pulse_sets", 2.5}, {"soc_step", 0.9}, {"crate", 1}};
    try {
        d.start_run(bad);
        ADD_FAILURE() << "bad parameters started a run";
    } catch (const daemon::BadRequest& e) {
        const std::string m = e.what();
        for (const char* words : {"$.parameters.c_rate: override: expected a number", "$.parameters.pulse_sets: override: expected a whole number",
                                  "$.parameters.soc_step: override: 0.9 is out of the declared range",
                                  "override \"crate\" is not a parameter"})
            EXPECT_NE(m.find(words), std::string::npos) << words << "\n" << m;
    }
    EXPECT_TRUE(d.store().list_runs().empty());

    // A valid override shapes the run: 2 pulse sets instead of 3.
    daemon::StartRequest good{"hppc_short", "p45b", {}, {}};
    good.parameters = {{"pulse_sets", 2}};
    const auto id = d.start_run(good)["id"].get<daemon::RunId>();
    std::string state;
    json progress;  // GET /status "progress" seen during the run: by expected time
    double last_fraction = -1.0;
    bool progress_monotonic = true;
    ASSERT_TRUE(eventually([&] {
        const json st = d.status();
        if (st.contains("progress") && st["progress"].is_object()) {
            progress = st["progress"];
            const double f = progress["fraction"].get<double>();
            progress_monotonic = progress_monotonic && f >= last_fraction;
            last_fraction = f;
        }
        state = d.get_run(id)["state"].get<std::string>();
        return terminal(state);
    }, 900s, 200ms));
    ASSERT_TRUE(progress.is_object()) << "no progress in /status during the run";
    EXPECT_GT(progress["expected_duration_s"].get<double>(), 3000.0);  // 2 pulse sets of hppc_short: about 1 h
    EXPECT_GT(last_fraction, 0.3) << progress.dump();  // the estimate assumes a half-charged start; the sim starts full
    EXPECT_LE(last_fraction, 0.99) << progress.dump();
    EXPECT_TRUE(progress_monotonic);
    ASSERT_EQ(state, "completed") << d.events(id).dump(1);
    // The fits and the final parameter set land after the end: GET /status says when ("fits_running" false),
    // and then the parameter set is in the store.
    ASSERT_TRUE(eventually([&] { return d.status().value("fits_running", true) == false; }, 300s, 200ms)) << d.status().dump();
    d.store().flush();
    ASSERT_TRUE(d.store().latest_parameter_set(id).has_value()) << "fits_running turned false before the end fit was stored";
    const json daemon_fits = d.fits(id)["fits"];
    ASSERT_EQ(daemon_fits.size(), 2u) << daemon_fits.dump(1);
    const auto run = d.store().get_run(id);
    ASSERT_TRUE(run);
    EXPECT_EQ(run->config["program"]["parameters"]["pulse_sets"]["default"], 2);

    // The replay, read-only, while the daemon still has the database open.
    const fs::path params = tmp.path / "replay.params.json", summary = tmp.path / "replay.summary.json";
    const auto r = run_cli(kBin.string() + " fit --db " + d.store().path().string() + " --run " + std::to_string(id) +
                           " -o " + params.string() + " --json " + summary.string());
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_NE(r.output.find("same as the daemon's 2 stored pulse-set fits"), std::string::npos) << r.output;
    const json s = json::parse(std::ifstream(summary));
    const json& replay = s["replay"]["fits"];
    ASSERT_EQ(replay.size(), daemon_fits.size()) << s["replay"].dump(1);
    for (std::size_t k = 0; k < replay.size(); ++k) {
        const std::string what = "pulse set " + std::to_string(k + 1);
        EXPECT_EQ(replay[k]["pulse_set"], daemon_fits[k]["pulse_set"]) << what;
        EXPECT_DOUBLE_EQ(num(replay[k], "ocv_v"), num(daemon_fits[k], "ocv_v")) << what;
        EXPECT_DOUBLE_EQ(num(replay[k], "rms_v"), num(daemon_fits[k], "rms_v")) << what;
        EXPECT_EQ(replay[k]["method"], daemon_fits[k]["method"]) << what;
        expect_same(replay[k]["discharge"], daemon_fits[k]["discharge"], what + " discharge");
        expect_same(replay[k]["charge"], daemon_fits[k]["charge"], what + " charge");
        // SOC: the same rule on the same rows, but the daemon's charge count runs a batch of rows ahead.
        EXPECT_NEAR(num(replay[k], "soc"), num(daemon_fits[k], "soc"), 0.01) << what;
    }
    EXPECT_EQ(s["replay"]["comparison"]["same"], true) << s["replay"]["comparison"].dump();
    const json p = json::parse(std::ifstream(params));
    EXPECT_EQ(p["schema"], "cellbench.params/1");
    std::printf("fit --db: %s\n", s["replay"]["comparison"].dump().c_str());
    d.shutdown();
}
