// The simulated bench's clock (sim::BenchClock): free (wall x scale) and paced (bounded steps, issue 14).
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <vector>

#include "cellbench/sim/pace_gate.hpp"
#include "cellbench/sim/plant.hpp"

namespace {

using cellbench::sim::BenchClock;
using cellbench::sim::PaceGate;
using namespace std::chrono_literals;

TEST(BenchClock, FreeClockMapsWallTimeByTheTimeScale) {
    const BenchClock clock(100.0, 5.0);
    EXPECT_FALSE(clock.paced());
    const auto wall = clock.wall_at(15.0);
    EXPECT_NEAR(clock.at(wall), 15.0, 1e-6);
    EXPECT_NEAR(clock.at(wall + 3s), 315.0, 1e-6);  // a free clock jumps with the wall
}

TEST(BenchClock, PacedClockKeepsTheScaleWhenPacedRegularly) {
    BenchClock clock(400.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    const double b0 = clock.pace(w0);
    for (int k = 1; k <= 300; ++k) clock.pace(w0 + k * 10ms);  // 3 s of wall time, paced every 10 ms
    EXPECT_NEAR(clock.pace(w0 + 3s) - b0, 1200.0, 1e-6);
    EXPECT_NEAR(clock.achieved_scale(), 400.0, 1e-3);
    EXPECT_NEAR(clock.lost_wall_s(), 0.0, 0.2);  // at most the gap from construction to w0
}

// The defect of issue 14: a daemon without CPU for 3 s found 1200 bench seconds gone at x400 and aborted its
// healthy run ("cycler silent for more than 1200 s"). Paced, the bench advances one bounded step.
TEST(BenchClock, PacedClockAdvancesOneBoundedStepAfterAStarvedGap) {
    BenchClock clock(400.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    const double b0 = clock.pace(w0);
    const double b1 = clock.pace(w0 + 3s);
    EXPECT_NEAR(b1 - b0, 40.0, 1e-6);  // 0.1 s x 400, not 1200
    EXPECT_NEAR(clock.max_step_s(), 40.0, 1e-9);
    EXPECT_GT(clock.lost_wall_s(), 2.8);
    // Time goes on at the full rate afterwards.
    for (int k = 1; k <= 100; ++k) clock.pace(w0 + 3s + k * 10ms);
    EXPECT_NEAR(clock.pace(w0 + 4s) - b1, 400.0, 1e-6);
    EXPECT_LT(clock.achieved_scale(), 0.5 * 400.0);  // the log and /status show the slow-down
}

TEST(BenchClock, ReadersNeverRunMoreThanOneStepAheadOfThePacer) {
    BenchClock clock(100.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    const double b0 = clock.pace(w0);
    EXPECT_NEAR(clock.at(w0 + 50ms), b0 + 5.0, 1e-6);  // between two paces: smooth
    EXPECT_NEAR(clock.at(w0 + 10s), b0 + 10.0, 1e-6);  // pacer starved: one step at most
    EXPECT_LE(clock.now_s(), b0 + 10.0 + 1e-9);
}

TEST(BenchClock, InstantsBeforeABoundedStepMapInOrder) {
    BenchClock clock(100.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    clock.pace(w0);
    clock.pace(w0 + 50ms);
    clock.pace(w0 + 2050ms);  // a 2 s gap: bench +10 s
    clock.pace(w0 + 2100ms);
    const double before = clock.at(w0 + 40ms), in_gap = clock.at(w0 + 1s), after = clock.at(w0 + 2060ms);
    EXPECT_LT(before, in_gap);
    EXPECT_LE(in_gap, after);
    EXPECT_NEAR(after - before, 0.01 * 100 + 10.0 + 0.01 * 100, 1e-6);  // 10 ms + one step + 10 ms
    EXPECT_NEAR(clock.at(w0 + 2100ms) - clock.at(w0 + 2060ms), 4.0, 1e-6);
}

// The daemon holds bench time while its queue of readings is late (a slow consumer, not a silent instrument).
TEST(BenchClock, HeldClockLetsWallTimePassWithoutBenchTime) {
    BenchClock clock(400.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    const double b0 = clock.pace(w0);
    for (int k = 1; k <= 100; ++k) {
        clock.hold(w0 + k * 10ms);  // 1 s held
        EXPECT_DOUBLE_EQ(clock.at(w0 + k * 10ms + 5ms), b0) << "a reader ran ahead of a held clock";
    }
    const double b1 = clock.pace(w0 + 1010ms);
    EXPECT_NEAR(b1 - b0, 0.01 * 400.0, 1e-6);  // only the 10 ms after the hold
    EXPECT_GT(clock.lost_wall_s(), 0.95);
    EXPECT_LE(clock.at(w0 + 500ms), b1);  // an instant inside the hold maps between its ends
    EXPECT_GE(clock.at(w0 + 500ms), b0);
}

// A reading received before hundreds of paces and holds (handled late on a busy daemon) keeps the bench time
// of its arrival: it once mapped by extrapolation from the oldest remembered bounded step, hundreds of bench
// seconds too early, and read as cycler silence.
TEST(BenchClock, AnInstantBeforeManyHoldsKeepsItsBenchTime) {
    BenchClock clock(400.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    clock.pace(w0);
    const double b1 = clock.pace(w0 + 10ms);
    for (int k = 2; k < 300; ++k) (k % 2 ? clock.hold(w0 + k * 10ms) : clock.pace(w0 + k * 10ms));
    EXPECT_NEAR(clock.at(w0 + 10ms), b1, 1e-6);
    EXPECT_NEAR(clock.at(w0 + 5ms), b1 - 2.0, 1e-6);  // 5 ms x 400
}

// Slowed down (the pace gate below): bench time and the readers between two paces move at the slow rate.
TEST(BenchClock, SlowedClockRunsAtTheRateAskedAndReadersFollowIt) {
    BenchClock clock(400.0, 0.0, BenchClock::Paced{0.1});
    const auto w0 = BenchClock::WallClock::now();
    const double b0 = clock.pace(w0);
    double b1 = b0;
    for (int k = 1; k <= 100; ++k) {
        b1 = clock.pace(w0 + k * 10ms, 10.0);  // 1 s at x10
        EXPECT_NEAR(clock.at(w0 + k * 10ms + 5ms), b1 + 0.005 * 10.0, 1e-6) << "a reader ran ahead at the full scale";
    }
    // Each pace starts from what the readers saw (never back): 5 ms at x10 ahead of the last pace at most.
    EXPECT_NEAR(b1 - b0, 10.0, 0.06);
    EXPECT_NEAR(clock.lost_wall_s(), 1.0 - 10.0 / 400.0, 0.2);
    const double b2 = clock.pace(w0 + 1010ms, 1e9);  // never above the clock's own scale
    EXPECT_NEAR(b2 - b1, 0.01 * 400.0, 0.06);
}

// The gate: the bench must not run more than half an instrument's grace past its last reading, for at most one
// grace of wall time (then the instrument is silent, and the grace must be able to end the run).
TEST(PaceGate, SlowsTheBenchWhileAnInstrumentsReadingsAreHalfAGraceLate) {
    PaceGate gate(400.0, 10.0);  // grace 4000 bench s = 10 s of wall time at x400
    const auto w0 = PaceGate::WallClock::now();
    auto src = [](double last) { return std::vector<PaceGate::Source>{{"neware", last, 4000.0}, {"dewe", -1, 4000.0}}; };
    auto d = gate.decide(1000.0, src(900.0), w0);
    EXPECT_FALSE(d.gated);
    EXPECT_DOUBLE_EQ(d.scale, 400.0);
    EXPECT_EQ(d.change, PaceGate::Change::none);
    d = gate.decide(3000.0, src(900.0), w0 + 1s);  // 2100 s behind: more than half the grace
    EXPECT_TRUE(d.gated);
    EXPECT_EQ(d.change, PaceGate::Change::closed);
    EXPECT_DOUBLE_EQ(d.scale, 10.0);
    EXPECT_EQ(d.waiting_for, "neware");
    EXPECT_NEAR(d.lag_bench_s, 2100.0, 1e-9);
    d = gate.decide(3010.0, src(900.0), w0 + 5s);
    EXPECT_TRUE(d.gated);
    EXPECT_EQ(d.change, PaceGate::Change::none);
    d = gate.decide(3020.0, src(3015.0), w0 + 6s);  // the reading came: full scale at once
    EXPECT_FALSE(d.gated);
    EXPECT_EQ(d.change, PaceGate::Change::caught_up);
    EXPECT_DOUBLE_EQ(d.scale, 400.0);
    EXPECT_TRUE(d.waiting_for.empty());
    EXPECT_EQ(gate.episodes(), 1);
    EXPECT_EQ(gate.expired(), 0);
    EXPECT_NEAR(gate.gated_wall_s(), 5.0, 1e-9);
}

TEST(PaceGate, GivesUpAfterOneGraceOfWallTimeSoASilentInstrumentStillEndsTheRun) {
    PaceGate gate(400.0, 10.0);
    const auto w0 = PaceGate::WallClock::now();
    const std::vector<PaceGate::Source> silent = {{"neware", 0.0, 4000.0}};
    EXPECT_TRUE(gate.decide(2100.0, silent, w0).gated);
    EXPECT_TRUE(gate.decide(2150.0, silent, w0 + 9s).gated);
    const auto d = gate.decide(2200.0, silent, w0 + 10100ms);  // 10 s of wall time = the grace at x400
    EXPECT_FALSE(d.gated);
    EXPECT_EQ(d.change, PaceGate::Change::gave_up);
    EXPECT_EQ(d.waiting_for, "neware");  // named in the log line that says the silence is taken as real
    EXPECT_DOUBLE_EQ(d.scale, 400.0);
    EXPECT_EQ(gate.expired(), 1);
    EXPECT_FALSE(gate.decide(4100.0, silent, w0 + 15s).gated) << "still silent: no second episode";
    EXPECT_EQ(gate.episodes(), 1);
    // Readings again, then late again: a new episode.
    EXPECT_FALSE(gate.decide(4200.0, {{"neware", 4190.0, 4000.0}}, w0 + 16s).gated);
    EXPECT_TRUE(gate.decide(6300.0, {{"neware", 4190.0, 4000.0}}, w0 + 22s).gated);
    EXPECT_EQ(gate.episodes(), 2);
}

TEST(PaceGate, ABenchNoFasterThanTheSlowScaleIsNeverGated) {
    PaceGate gate(10.0, 10.0);  // x10: the daemon's slow scale is the full scale
    const auto w0 = PaceGate::WallClock::now();
    const auto d = gate.decide(1000.0, {{"neware", 0.0, 100.0}}, w0);
    EXPECT_FALSE(d.gated);
    EXPECT_DOUBLE_EQ(d.scale, 10.0);
    EXPECT_EQ(gate.episodes(), 0);
}

TEST(PaceGate, InstrumentsWithoutReadingsOrGraceAreNotWaitedFor) {
    PaceGate gate(100.0, 10.0);
    const auto w0 = PaceGate::WallClock::now();
    const std::vector<PaceGate::Source> none = {{"neware", -1, 1000.0}, {"dewe", 0.0, 0.0}, {"chamber", 0.0, NAN}};
    EXPECT_FALSE(gate.decide(1e6, none, w0).gated);
    // The source furthest behind in units of its own grace is the one named.
    const auto d = gate.decide(1000.0, {{"neware", 0.0, 1800.0}, {"dewe", 300.0, 1000.0}}, w0 + 1s);
    EXPECT_TRUE(d.gated);
    EXPECT_EQ(d.waiting_for, "dewe");  // 0.70 of its grace against 0.56
}

}  // namespace
