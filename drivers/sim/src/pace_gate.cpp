#include "cellbench/sim/pace_gate.hpp"

#include <algorithm>
#include <cmath>

namespace cellbench::sim {

PaceGate::PaceGate(double time_scale, double slow_scale)
    : time_scale_(time_scale > 0 && std::isfinite(time_scale) ? time_scale : 1.0),
      slow_scale_(std::clamp(slow_scale > 0 && std::isfinite(slow_scale) ? slow_scale : 1.0, 0.0, time_scale_)) {}

PaceGate::Decision PaceGate::decide(double bench_now_s, const std::vector<Source>& sources, WallClock::time_point wall) {
    // The source furthest behind, in units of its grace.
    double worst = 0, worst_grace = 0;
    Decision d;
    for (const auto& s : sources) {
        if (s.last_reading_bench_s < 0 || !(s.grace_bench_s > 0) || !std::isfinite(s.grace_bench_s)) continue;
        const double lag = bench_now_s - s.last_reading_bench_s;
        const double f = lag / s.grace_bench_s;
        if (f > worst) worst = f, worst_grace = s.grace_bench_s, d.waiting_for = s.name, d.lag_bench_s = lag;
    }
    if (last_gated_ && wall > last_wall_) gated_wall_s_ += wall_seconds(wall - last_wall_);
    last_wall_ = wall;

    // A bench that runs no faster than the slow scale has nothing to slow down.
    const bool behind = worst > 0.5 && slow_scale_ < time_scale_;
    if (!behind) {
        in_episode_ = gave_up_ = false;
    } else if (!in_episode_) {
        in_episode_ = true;
        gave_up_ = false;
        episode_start_ = wall;
        ++episodes_;
    } else if (!gave_up_ && wall_seconds(wall - episode_start_) > worst_grace / time_scale_) {
        gave_up_ = true;  // silent for a whole grace of wall time while gated: a silent peer, not a slow reader
        ++expired_;
    }
    d.gated = in_episode_ && !gave_up_;
    d.scale = d.gated ? slow_scale_ : time_scale_;
    if (d.gated != last_gated_) d.change = d.gated ? Change::closed : gave_up_ ? Change::gave_up : Change::caught_up;
    if (!d.gated && d.change != Change::gave_up) d.waiting_for.clear(), d.lag_bench_s = 0;
    last_gated_ = d.gated;
    return d;
}

}  // namespace cellbench::sim
