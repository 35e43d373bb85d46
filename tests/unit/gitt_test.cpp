// A GITT or incremental-OCV test (titration steps between long rests, no pulses) is a characterization: its steps'
// edges and relaxations identify R0 and the pairs as pulses do, at the steps' one current. Before session 46 such a
// recording was refused ("no recording holds pulses between rests"), and its first step after the full charge was
// taken for a pilot discharge (a capacity of 10 % of the cell's).
//
// On every step sampled at one interval, when a step happens within it trades exactly against R0 and the pairs
// (R_i' = R_i exp(L dt / tau_i), R0' = R0 - sum(R_i' - R_i)): the fit holds it at 0 and carries its spread into the
// tables' sd. And R0 apart from the pairs is only as precise as the one-sample jumps across the steps hold it.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "cellbench/estimator/fit.hpp"
#include "unit/hppc_synthetic.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;
using cellbench::test::Step;

constexpr double kStepCurrentA = 0.2 * cellbench::test::kCapacityAh;  // C/5
constexpr double kNoiseV = 2e-4;

// From 90 % SOC: a CCCV charge to full, an hour's rest, then ten 10 % steps at C/5, each followed by 30 min of rest.
std::vector<Step> gitt_program() {
    std::vector<Step> p = {{600.0, 0.0, "Rest"}, {3600.0, cellbench::test::kCapacityAh, "CCCV Chg", 4.18}, {3600.0, 0.0, "Rest"}};
    for (int k = 0; k < 10; ++k) {
        p.push_back({0.1 * 3600.0 / 0.2 * 0.98, -kStepCurrentA, "CC DChg"});
        p.push_back({1800.0, 0.0, "Rest"});
    }
    return p;
}

Recording gitt(double dt_s) {
    cellbench::test::SyntheticOptions so;
    so.dt_s = dt_s;
    so.soc0 = 0.9;
    so.voltage_noise_v = kNoiseV;
    return cellbench::test::synthesize(gitt_program(), so);
}

bool has_warning(const est::Characterization& c, const std::string& start) {
    return std::any_of(c.warnings.begin(), c.warnings.end(), [&](const std::string& w) { return w.rfind(start, 0) == 0; });
}

TEST(Gitt, ATitrationTestIsFittedFromItsStepsAndSaysSo) {
    const auto c = est::characterize({gitt(1.0)}, cellbench::test::characterization_options());
    ASSERT_TRUE(c.global.has_value());
    EXPECT_TRUE(has_warning(c, "no pulses: R0 and the RC pairs come from the 10 current steps")) << c.warnings.front();
    // The first step after the full charge is no pilot discharge: it does not reach the cut-off.
    EXPECT_NE(c.capacity.method, "pilot discharge");
    EXPECT_GT(c.capacity.capacity_ah, 0.9 * cellbench::test::kCapacityAh);
    std::size_t steps = 0;
    for (const auto& w : c.global->windows) steps += w.kind == "step";
    EXPECT_GE(steps, 9u);
    EXPECT_FALSE(c.global->cross_validation.empty()) << "the steps are what the smoothness is cross-validated on";

    // Every step is sampled at 1 s: the step timing is held at 0 with the spread of a lag in [0, 1].
    EXPECT_EQ(c.global->step_lag.value, 0.0);
    EXPECT_NEAR(c.global->step_lag.sd, 1.0 / std::sqrt(12.0), 1e-9);
    EXPECT_TRUE(std::any_of(c.global->notes.begin(), c.global->notes.end(), [](const std::string& n) {
        return n.rfind("every current step is sampled at 1 s", 0) == 0;
    }));

    // What the steps hold at mid SOC: R0 + R1 + R2 (their level) closely, R0 within what its sd says. The
    // synthetic cell's rows report the current of the whole interval before them (a lag of 1), which the fit
    // cannot tell from 0 here: R0 is off by up to R1 (exp(1 s / tau1) - 1), and its sd must carry that.
    const auto truth = cellbench::test::p45b_discharge();
    for (const double soc : {0.4, 0.5, 0.6}) {
        const auto rc = c.params.rc_at(soc, -1);
        EXPECT_NEAR(rc.r0_ohm + rc.r1_ohm + rc.r2_ohm, truth.r0_ohm + truth.r1_ohm + truth.r2_ohm,
                    0.03 * (truth.r0_ohm + truth.r1_ohm + truth.r2_ohm))
            << "soc " << soc;
    }
    const auto& knots = c.global->discharge;
    const auto mid = std::min_element(knots.begin(), knots.end(), [&](const auto& a, const auto& b) {
        return std::abs(c.params.soc[&a - knots.data()] - 0.5) < std::abs(c.params.soc[&b - knots.data()] - 0.5);
    });
    EXPECT_LT(std::abs(mid->at(0).value - truth.r0_ohm), 3.0 * mid->at(0).sd);
}

TEST(Gitt, ATitrationTestWhoseRestsAreTooShortToReadTheOcvSaysSo) {
    std::vector<Step> p = {{600.0, 0.0, "Rest"}};
    for (int k = 0; k < 8; ++k) {
        p.push_back({600.0, -kStepCurrentA, "CC DChg"});
        p.push_back({300.0, 0.0, "Rest"});
    }
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    try {
        (void)est::characterize({cellbench::test::synthesize(p, so)}, cellbench::test::characterization_options());
        ADD_FAILURE() << "a test with 5-minute rests has no OCV to anchor its steps";
    } catch (const cellbench::InputError& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("5 or more current steps between rests of 600 s or more (a GITT"), std::string::npos) << m;
        EXPECT_NE(m.find("synthetic: 8 current phases (0 of them pulses of at most 60 s)"), std::string::npos) << m;
        EXPECT_NE(m.find("the rests between its current phases 300 s (median)"), std::string::npos) << m;
    }
}

TEST(Gitt, TheR0SdIsNoSmallerThanTheOneSampleJumpsHoldIt) {
    const auto c = est::characterize({gitt(0.5)}, cellbench::test::characterization_options());
    ASSERT_TRUE(c.global.has_value());
    // Each table point between 20 and 80 % SOC lies within 10 % of SOC of at most four step edges (two steps), each
    // a jump of 0.76 A seen against the noise of a one-sample difference (sqrt(2) of the rows' noise): R0 apart from
    // the pairs cannot be known better than that, whatever the pairs' shape and the smoothness say.
    const double floor_ohm = 0.9 * std::sqrt(2.0) * kNoiseV / (kStepCurrentA * std::sqrt(4.0));
    std::size_t checked = 0;
    for (std::size_t j = 0; j < c.params.soc.size(); ++j) {
        if (c.params.soc[j] < 0.2 || c.params.soc[j] > 0.8) continue;
        EXPECT_GE(c.global->discharge[j][0].sd, floor_ohm) << "soc " << c.params.soc[j];
        ++checked;
    }
    EXPECT_GT(checked, 5u);
}

TEST(Gitt, StepsSampledAtDifferentIntervalsTellTheStepTiming) {
    // The same test at 0.5 s, its rests thinned to a row every 2 s and the last rest row before each step dropped:
    // steps out of a rest are seen over 1-2.5 s, steps into one over 0.5 s. The lag is then the fit's to tell.
    const Recording full = gitt(0.5);
    Recording r = full;
    r.time_s.clear(), r.voltage_v.clear(), r.current_a.clear(), r.step_type.clear(), r.step_count.clear();
    std::size_t since_current = 0;
    for (std::size_t k = 0; k < full.size(); ++k) {
        const bool rest = full.current_a[k] == 0.0;
        const bool before_step = rest && k + 1 < full.size() && full.current_a[k + 1] != 0.0;
        since_current = rest ? since_current + 1 : 0;
        if (rest && (before_step || since_current % 4 != 1)) continue;
        r.time_s.push_back(full.time_s[k]), r.voltage_v.push_back(full.voltage_v[k]), r.current_a.push_back(full.current_a[k]);
        r.step_type.push_back(full.step_type[k]), r.step_count.push_back(full.step_count[k]);
    }
    r.pad_optional_channels();
    const auto c = est::characterize({r}, cellbench::test::characterization_options());
    ASSERT_TRUE(c.global.has_value());
    EXPECT_FALSE(std::any_of(c.global->notes.begin(), c.global->notes.end(), [](const std::string& n) {
        return n.rfind("every current step is sampled at", 0) == 0;
    }));
}

}  // namespace
