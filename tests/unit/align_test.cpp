// Clock alignment of a cycler and a DAQ recording from the heat balance, on synthetic pairs with a known offset.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "cellbench/estimator/align.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

constexpr double kC = 63.3, kR = 5.26, kA = 5.311e-3, kAmb = 29.5;

struct Pair {
    std::vector<double> tc, i;          // cycler
    std::vector<double> td, temp, q;    // DAQ
};

// Random-walk current (thesis Table 5.1 style: a level from {-4C..+3C} held 60..140 s) for cycler_s seconds at
// 0.1 s; heat R_int*I^2 (optionally through a first-order lag lag_s before it reaches the lumped node);
// DAQ sampled every 0.1 s on its own clock: daq_time = true_time - offset_s, starting daq_lead_s before the
// cycler and recording daq_tail_s of cool-down after it stops.
Pair make_pair(double offset_s, double lag_s, double cycler_s, double daq_lead_s, double daq_tail_s, unsigned seed) {
    std::mt19937 rng(seed);
    std::uniform_int_distribution<int> level(-4, 3);
    std::uniform_real_distribution<double> hold(60.0, 140.0);
    std::normal_distribution<double> nt(0.0, 0.004), nq(0.0, 2.0);
    const double dt = 0.1, r_int = 0.03, tau = kR * kC;
    Pair p;
    // True-time current, including the lead and the tail (zero current outside the cycler's record).
    const double t0 = -daq_lead_s, t1 = cycler_s + daq_tail_s;
    double next_change = 0.0, current = 0.0, heat_lagged = 0.0, T = kAmb;
    for (double t = t0; t <= t1 + 1e-9; t += dt) {
        const bool cycler_on = t >= 0.0 && t <= cycler_s;
        if (cycler_on && t >= next_change) {
            current = 4.5 * level(rng);
            next_change = t + hold(rng);
        }
        const double i = cycler_on ? current : 0.0;
        if (cycler_on) {
            p.tc.push_back(t);
            p.i.push_back(i);
        }
        const double heat = r_int * i * i;
        heat_lagged = lag_s > 0 ? heat + (heat_lagged - heat) * std::exp(-dt / lag_s) : heat;
        const double t_ss = kAmb + kR * heat_lagged;
        T = t_ss + (T - t_ss) * std::exp(-dt / tau);
        p.td.push_back(t - offset_s);
        p.temp.push_back(T + nt(rng));
        p.q.push_back((T - kAmb) / (kR * kA) + nq(rng));
    }
    return p;
}

}  // namespace

TEST(ClockAlignment, RecoversKnownOffsetWithCoolDownTail) {
    const Pair p = make_pair(123.45, 0.0, 2600.0, 30.0, 1200.0, 1);
    const auto al = estimate_clock_offset(p.tc, p.i, p.td, p.temp, p.q, kC, kA, 600.0);
    EXPECT_NEAR(al.offset_s, 123.45, 0.3) << al.note;
    EXPECT_GT(al.correlation, 0.95) << al.note;
    EXPECT_LE(al.lag_s, 3.0);
    EXPECT_NEAR(al.offset_no_lag_s, 123.45, 0.3);
    EXPECT_NEAR(al.joule_resistance_ohm, 0.03, 0.005);
    EXPECT_FALSE(al.at_search_limit);
    EXPECT_GT(al.overlap_s, 2500.0);
}

TEST(ClockAlignment, NegativeOffset) {
    const Pair p = make_pair(-57.8, 0.0, 2400.0, 0.0, 600.0, 2);
    const auto al = estimate_clock_offset(p.tc, p.i, p.td, p.temp, p.q, kC, kA, 300.0);
    EXPECT_NEAR(al.offset_s, -57.8, 0.3) << al.note;
    EXPECT_GT(al.correlation, 0.95);
}

TEST(ClockAlignment, ResponseLagIsNotBookedAsOffset) {
    // Heat reaches the sensor node through a 12 s lag: plain cross-correlation is biased by about the lag,
    // the lag-aware fit is not.
    const Pair p = make_pair(40.0, 12.0, 2600.0, 20.0, 900.0, 3);
    const auto al = estimate_clock_offset(p.tc, p.i, p.td, p.temp, p.q, kC, kA, 300.0);
    EXPECT_NEAR(al.offset_s, 40.0, 1.5) << al.note;
    EXPECT_NEAR(al.lag_s, 12.0, 4.0) << al.note;
    EXPECT_LT(al.offset_no_lag_s, 40.0 - 4.0) << "the lag should bias the plain estimate";
    EXPECT_GE(al.correlation, al.correlation_no_lag);
    EXPECT_GE(al.uncertainty_s, 0.05);
}

TEST(ClockAlignment, UnrelatedRecordingsCorrelateWeakly) {
    const Pair a = make_pair(0.0, 0.0, 2600.0, 0.0, 0.0, 4);
    const Pair b = make_pair(0.0, 0.0, 2600.0, 0.0, 0.0, 5);  // another random walk
    const auto al = estimate_clock_offset(a.tc, a.i, b.td, b.temp, b.q, kC, kA, 300.0);
    EXPECT_LT(al.correlation, 0.8);
}

TEST(ClockAlignment, BadInputThrows) {
    const Pair p = make_pair(0.0, 0.0, 300.0, 0.0, 0.0, 6);
    std::vector<double> short_i(p.i.begin(), p.i.end() - 1);
    EXPECT_THROW(estimate_clock_offset(p.tc, short_i, p.td, p.temp, p.q, kC, kA, 60.0), InputError);
    EXPECT_THROW(estimate_clock_offset(p.tc, p.i, p.td, p.temp, p.q, kC, kA, 0.0), InputError);
    // No offset gives enough overlap: DAQ of 300 s vs a 10 s search window is fine, but a DAQ far away is not.
    std::vector<double> far = p.td;
    for (double& t : far) t += 1e5;
    EXPECT_THROW(estimate_clock_offset(p.tc, p.i, far, p.temp, p.q, kC, kA, 60.0), InputError);
}
