#pragma once
// How fast a paced bench clock (sim::BenchClock) may run: the bench must not outrun the process that reads it.
//
// BenchClock's bounded steps stop a starved process from jumping hundreds of bench seconds at once, but a
// process that gets some CPU keeps pacing at the full scale while the work that turns instrument answers into
// readings (the cycler driver's parsing, the hosted tester's own thread) waits behind other work. Bench time
// then runs past the last reading the daemon has, and the run engine finds the instrument silent (issue 14:
// "cycler silent for more than 10000 s" at x1000 beside a proof run, every instrument healthy).
//
// The gate closes when an instrument's last reading is more than half its silence grace behind bench time: the
// clock then runs at most at `slow_scale` until a reading comes (which opens the gate). A peer that is really
// silent is still found silent: the gate stays closed for at most one grace of wall time (grace / time scale)
// per episode, after which bench time runs at full scale again and the grace ends the run as before. So a
// dead instrument is declared silent at most one grace (in wall time) later than without the gate.
//
// Pure logic, no clock of its own: the caller passes bench and wall time (tests drive it by hand).
#include <chrono>
#include <string>
#include <vector>

namespace cellbench::sim {

// Seconds of a span of the simulated bench's wall clock (the pace gate's and the bench clock's).
inline double wall_seconds(std::chrono::steady_clock::duration d) { return std::chrono::duration<double>(d).count(); }

class PaceGate {
public:
    using WallClock = std::chrono::steady_clock;

    // One instrument whose readings the bench must not outrun.
    struct Source {
        std::string name;                   // for the log ("neware", "dewe", "chamber")
        double last_reading_bench_s = -1;   // bench time of its last reading; < 0: none yet (not gated on)
        double grace_bench_s = 0;           // its silence grace (bench seconds); <= 0 or not finite: not gated on
    };

    // What this decision changed against the previous one (for the caller's log and status).
    enum class Change { none, closed, caught_up, gave_up };

    struct Decision {
        double scale = 0;          // bench seconds per wall second allowed for the next step
        bool gated = false;        // the gate is closed (scale < the clock's time scale because of a source)
        Change change = Change::none;
        std::string waiting_for;   // the source furthest behind (in units of its grace) while gated or giving up
        double lag_bench_s = 0;    // how far that source's last reading is behind bench time
    };

    // slow_scale: bench seconds per wall second while gated (small against the time scale, but enough to keep
    // the simulated instruments that stream by bench time, such as the DAQ, from looking silent). A clock whose
    // time scale is not above it is never gated.
    explicit PaceGate(double time_scale, double slow_scale = 10.0);

    // The scale for the step that ends at `wall` (bench time `bench_now_s` before it).
    Decision decide(double bench_now_s, const std::vector<Source>& sources, WallClock::time_point wall);

    [[nodiscard]] double time_scale() const { return time_scale_; }
    [[nodiscard]] int episodes() const { return episodes_; }            // times the gate closed
    [[nodiscard]] double gated_wall_s() const { return gated_wall_s_; }  // wall seconds spent closed
    // Episodes in which the gate gave up (a source silent for a whole grace of wall time while gated).
    [[nodiscard]] int expired() const { return expired_; }

private:
    double time_scale_;
    double slow_scale_;
    bool in_episode_ = false;   // a source is behind by more than half its grace
    bool gave_up_ = false;      // ... for longer than the budget: full scale until it catches up
    WallClock::time_point episode_start_{};
    WallClock::time_point last_wall_{};
    bool last_gated_ = false;
    int episodes_ = 0;
    int expired_ = 0;
    double gated_wall_s_ = 0;
};

}  // namespace cellbench::sim
