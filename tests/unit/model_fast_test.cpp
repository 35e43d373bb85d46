// The fast simulation path (CellStepper, used by simulate()) against the reference step-by-step model
// (CellModel::step): the same exact ZOH step with caches, so the same numbers to rounding, on a varied profile
// (variable sampling, rests and pulses both ways, a slow ramp, the temperature and the ambient changing, SOC
// crossing table breakpoints) with no extension and with every extension present.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <random>
#include <sstream>

#include "cellbench/estimator/model.hpp"
#include "cellbench/estimator/simulate.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

ParameterSet thesis_params() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    std::stringstream ss;
    ss << in.rdbuf();
    return ParameterSet::from_json(nlohmann::json::parse(ss.str()));
}

ParameterSet with_every_extension(ParameterSet p, bool second_order) {
    auto& e = p.extensions;
    e.entropic_heat = EntropicHeatExt{5e-5, -1e-4};
    if (second_order) e.thermal_second_order = ThermalSecondOrderExt{0.7, 1.5};
    e.resistance_temperature = ResistanceTemperatureExt{30000.0};
    e.resistance_current = ResistanceCurrentExt{6.0, 4.5};
    e.ocv_hysteresis = OcvHysteresisExt{0.01, 25.0};
    e.extra_rc = ExtraRcExt{0.004, 900.0};
    e.capacity_error = CapacityErrorExt{0.97};
    e.series_resistance_offset = SeriesResistanceOffsetExt{0.0007};
    e.heat_flux_sensor_gain = HeatFluxSensorGainExt{0.9};
    e.ambient_drift = AmbientDriftExt{0.4, 1.5};
    return p;
}

// About 2.5 h of a varied profile: HPPC-like pulses at 0.1 s, a random walk at irregular 0.05-2 s steps,
// long rests at 1-10 s, a low-rate ramp, a charge, ambient steps; SOC from 0.95 down through several
// breakpoints and partly back.
Recording varied_profile(unsigned seed) {
    Recording r;
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    double t = 0.0, amb = 30.0;
    auto add = [&](double dt, double i) {
        t += dt;
        r.time_s.push_back(t);
        r.current_a.push_back(i);
        r.voltage_v.push_back(4.0);
        r.ambient_c.push_back(amb);
    };
    add(0.0, 0.0);
    for (int set = 0; set < 4; ++set) {
        for (int k = 0; k < 300; ++k) add(0.1, -4.5);    // discharge pulse
        for (int k = 0; k < 400; ++k) add(0.1, 0.0);     // rest
        for (int k = 0; k < 100; ++k) add(0.1, 3.375);   // charge pulse
        for (int k = 0; k < 200; ++k) add(0.2, 0.0);
        for (int k = 0; k < 340; ++k) add(1.0, -4.0);    // SOC step
        for (int k = 0; k < 120; ++k) add(10.0, 0.0);    // long rest, 1 s -> 10 s sampling
        amb += set % 2 ? -3.0 : 5.0;
    }
    for (int k = 0; k < 8000; ++k) {  // random walk at irregular steps, bursts of equal dt
        const double dt = k % 50 < 30 ? 0.1 : 0.05 + 1.95 * u(rng);
        add(dt, -7.5 + 13.0 * u(rng));
    }
    for (int k = 0; k < 600; ++k) add(1.0, -0.2 - 0.001 * k);  // slow ramp
    for (int k = 0; k < 900; ++k) add(2.0, 4.0);                // charge
    return r;
}

// The fast path against CellModel::step, row by row with the same inputs (each row's current held over the interval
// before it; simulate() feeds the stepper the Coulomb count's interval currents, sparse_logging_test.cpp), and
// where simulate() starts the state.
void expect_same(const CellModel& model, const Recording& rec) {
    CellState s, f;
    s.soc = simulate(model, rec.slice(0, 1)).initial_soc;
    s.temperature_c = rec.ambient_c[0];
    if (const auto& h = model.params().extensions.ocv_hysteresis) s.hysteresis_v = (s.soc > 0.5 ? 1.0 : -1.0) * h->magnitude_v;
    f = s;
    CellStepper stepper(model);
    std::vector<double> fast_soc, fast_temperature_c;
    double worst_v = 0, worst_t = 0, worst_soc = 0, worst_heat = 0;
    for (std::size_t k = 0; k < rec.size(); ++k) {
        const double dt = k == 0 ? 0.0 : rec.time_s[k] - rec.time_s[k - 1];
        const auto o = model.step(s, rec.current_a[k], rec.ambient_c[k], dt);
        const auto q = stepper.step(f, rec.current_a[k], rec.ambient_c[k], dt);
        const auto rel = [](double a, double b) { return std::abs(a - b) / std::max(1.0, std::abs(b)); };
        worst_v = std::max(worst_v, rel(q.voltage_v, o.voltage_v));
        worst_t = std::max(worst_t, rel(f.temperature_c, s.temperature_c));
        worst_soc = std::max(worst_soc, rel(f.soc, s.soc));
        worst_heat = std::max(worst_heat, rel(q.heat_irreversible_w + q.heat_reversible_w,
                                              o.heat_irreversible_w + o.heat_reversible_w));
        ASSERT_TRUE(std::isfinite(q.voltage_v)) << "row " << k;
        fast_soc.push_back(f.soc);
        fast_temperature_c.push_back(f.temperature_c);
    }
    EXPECT_LT(worst_v, 1e-12);
    EXPECT_LT(worst_t, 1e-12);
    EXPECT_LT(worst_soc, 1e-12);
    EXPECT_LT(worst_heat, 1e-12);
    // The profile does what it is meant to: SOC crosses table breakpoints and the cell heats.
    const auto [lo, hi] = std::minmax_element(fast_soc.begin(), fast_soc.end());
    EXPECT_GT(*hi - *lo, 0.3);
    const auto [tlo, thi] = std::minmax_element(fast_temperature_c.begin(), fast_temperature_c.end());
    EXPECT_GT(*thi - *tlo, 2.0);
}

}  // namespace

TEST(CellStepper, EqualsTheReferenceStepWithoutExtensions) {
    expect_same(CellModel(thesis_params()), varied_profile(1));
}

TEST(CellStepper, EqualsTheReferenceStepWithEveryExtension) {
    expect_same(CellModel(with_every_extension(thesis_params(), false)), varied_profile(2));
}

TEST(CellStepper, EqualsTheReferenceStepWithTheTwoNodeThermalModel) {
    expect_same(CellModel(with_every_extension(thesis_params(), true)), varied_profile(3));
}

TEST(CellStepper, EqualsTheReferenceStepBeyondTheTablesEnds) {
    // Tables that cover SOC 30-70 % only (the entropic table 40-60 %, on its own axis): the profile runs from 95 %
    // to below 60 %, so the R/C columns are held beyond the ends, the OCV is extended along its end segments, and
    // the cached segments are left and re-placed at every breakpoint in both directions.
    ParameterSet p = with_every_extension(thesis_params(), false);
    auto keep = [](const std::vector<double>& axis, std::vector<double>& column, double lo, double hi) {
        std::vector<double> out;
        for (std::size_t k = 0; k < axis.size(); ++k)
            if (axis[k] >= lo - 1e-9 && axis[k] <= hi + 1e-9) out.push_back(column[k]);
        column = out;
    };
    for (auto* rc : {&p.discharge, &p.charge})
        for (auto* col : {&rc->r0_ohm, &rc->r1_ohm, &rc->c1_f, &rc->r2_ohm, &rc->c2_f}) keep(p.soc, *col, 0.3, 0.7);
    keep(p.soc, p.ocv_v, 0.3, 0.7);
    keep(p.thermal.ehc_soc, p.thermal.ehc_v_per_k, 0.4, 0.6);
    std::vector<double> ehc_axis = p.thermal.ehc_soc;
    keep(p.thermal.ehc_soc, ehc_axis, 0.4, 0.6);
    p.thermal.ehc_soc = ehc_axis;
    std::vector<double> axis = p.soc;
    keep(p.soc, axis, 0.3, 0.7);
    p.soc = axis;
    ASSERT_GE(p.soc.size(), 3u);
    ASSERT_GE(p.thermal.ehc_soc.size(), 2u);
    expect_same(CellModel(p), varied_profile(4));
}

TEST(CellStepper, ARowReadsItsOwnCurrentWhereAnotherFlowedOverTheIntervalBeforeIt) {
    // A cycler's row at a step's start: the old current flowed over the interval before it, the row shows the new
    // one and its R0 drop. The fast path's two-current step equals the reference stepped with the old current and
    // then read (dt 0) with the new one; the state is the one the old current left.
    const CellModel model(with_every_extension(thesis_params(), false));
    const auto rec = varied_profile(5);
    CellState s, f;
    s.soc = 0.9;
    s.temperature_c = rec.ambient_c[0];
    f = s;
    CellStepper stepper(model);
    double worst_v = 0;
    std::size_t differing = 0;
    for (std::size_t k = 1; k < rec.size(); ++k) {
        const double dt = rec.time_s[k] - rec.time_s[k - 1];
        const double flowed = rec.current_a[k - 1], shown = rec.current_a[k];
        model.step(s, flowed, rec.ambient_c[k], dt);
        const auto o = model.step(s, shown, rec.ambient_c[k], 0.0);
        const auto q = stepper.step(f, flowed, rec.ambient_c[k], dt, shown);
        worst_v = std::max(worst_v, std::abs(q.voltage_v - o.voltage_v));
        ASSERT_NEAR(f.soc, s.soc, 1e-12) << "row " << k;
        differing += flowed != shown;
    }
    EXPECT_GT(differing, 100u);
    // The reference reads R0 at the state the interval left, the fast path where the interval began (as its one-
    // current step does): 17 uV apart at worst here, against R0 times the step (tens of mV) for the wrong current.
    EXPECT_LT(worst_v, 1e-4);
}

TEST(CellStepper, ExponentialCacheStaysExactAsTheArgumentDrifts) {
    // exp(-x) and expm1(-x) from the cache, for x drifting in small and large steps, both directions.
    CellStepper::DecayCache c;
    double x = 0.05;
    for (int k = 0; k < 20000; ++k) {
        x *= k % 3000 < 1500 ? 1.0 + 1e-4 : 1.0 - 3e-4;
        if (k % 997 == 0) x += 0.02;
        double e, m;
        c.eval(x, e, m);
        ASSERT_NEAR(e, std::exp(-x), 1e-15 * std::exp(-x)) << k;
        ASSERT_NEAR(m, std::expm1(-x), 2e-15 * std::abs(std::expm1(-x))) << k;
    }
}

TEST(CellStepper, ARelaxedPairIsExactlyZeroNeverSubnormal) {
    // A pulse, then three hours of rest at 0.1 s: the RC voltages relax through every positive double. Left to
    // decay they pass the subnormal range, where each step costs about a hundred cycles per multiplication (the
    // 0.1 s HPPC simulated at half the speed); below a femtovolt both paths hold them at exactly zero.
    const CellModel model(with_every_extension(thesis_params(), false));
    CellState fast, reference;
    fast.soc = reference.soc = 0.8;
    fast.temperature_c = reference.temperature_c = 25.0;
    CellStepper stepper(model);
    for (int k = 1; k <= 300 + 108000; ++k) {
        const double current_a = k <= 300 ? -4.5 : 0.0;
        stepper.step(fast, current_a, 25.0, 0.1);
        model.step(reference, current_a, 25.0, 0.1);
        if (k == 300) {
            ASSERT_LT(fast.rc.v1_discharge_v, -1e-3) << "the pulse polarizes the pair";
        }
        for (const CellState* s : {&fast, &reference})
            for (double v : {s->rc.v1_discharge_v, s->rc.v2_discharge_v, s->rc.v1_charge_v, s->rc.v2_charge_v, s->extra_rc_v})
                ASSERT_NE(std::fpclassify(v), FP_SUBNORMAL) << "row " << k;
    }
    EXPECT_EQ(fast.rc.v1_discharge_v, 0.0);
    EXPECT_EQ(reference.rc.v1_discharge_v, 0.0);
}
