// Recordings logged the way cyclers log them: a row when a step begins and ends, and between those only when the
// voltage has moved by a set amount or a set time has passed (record conditions such as "5 mV or 60 s"). A CV taper
// is then a row a minute whose current falls by more than 5 % each time, and a pulse's
// first row shows the new current the moment it begins. What a user relies on: the charge of such a recording is
// its charge (the SOC axis does not drift), and the model simulated on it predicts the voltages it would predict on
// the dense recording, so that `simulate` and `diagnose` report the model's error, not the logger's.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/estimator/model.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "unit/thesis_params.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;

struct Step {
    double duration_s;
    std::function<double(double)> current_a;  // of the time since the step began
};

struct Logged {
    Recording rec;
    std::vector<double> true_charge_ah;  // the exact charge moved up to every row
    std::vector<double> true_heat_j;     // the heat the cell generated up to every row
    double soc0 = 0.0;
};

// The thesis cell driven through `steps` on a 10 ms grid (the current piecewise constant over each 10 ms, at its
// midpoint), logged as a cycler does: a row at every step's start (the new current, the voltage the moment it
// flows) and 10 ms before its end, and in between when the voltage moved by 5 mV or 60 s passed since the last row.
Logged log_like_a_cycler(const est::CellModel& model, const std::vector<Step>& steps, double soc0) {
    constexpr double h = 0.01;
    Logged out;
    out.soc0 = soc0;
    est::CellState s;
    s.soc = soc0;
    s.temperature_c = 25.0;
    double t0 = 0.0, charge_as = 0.0, heat_j = 0.0;
    double last_t = -1e9, last_v = 0.0;
    for (std::size_t j = 0; j < steps.size(); ++j) {
        const auto& st = steps[j];
        const auto n = static_cast<long>(std::lround(st.duration_s / h));
        for (long m = 0; m < n; ++m) {
            const double tau = static_cast<double>(m) * h, t = t0 + tau;
            const double i_row = st.current_a(tau);
            const double v = model.step(s, i_row, 25.0, 0.0).voltage_v;  // evaluation at this instant
            const bool first = m == 0, last = m == n - 1;
            if (first || last || std::abs(v - last_v) >= 0.005 || t - last_t >= 60.0 - 1e-9) {
                out.rec.time_s.push_back(t);
                out.rec.current_a.push_back(i_row);
                out.rec.voltage_v.push_back(v);
                out.rec.step_count.push_back(static_cast<double>(j + 1));
                out.true_charge_ah.push_back(charge_as / 3600.0);
                out.true_heat_j.push_back(heat_j);
                last_t = t, last_v = v;
            }
            const double i_mid = st.current_a(tau + 0.5 * h);
            const auto o = model.step(s, i_mid, 25.0, h);
            charge_as += i_mid * h;
            heat_j += (o.heat_irreversible_w + o.heat_reversible_w) * h;
        }
        t0 += static_cast<double>(n) * h;
    }
    return out;
}

// 1C CCCV charge (the CV taper falling from 4.5 A with a 15 min time constant), a rest, a 2C discharge pulse, a rest,
// a 1C discharge and a rest: the layout of an HPPC's first hours.
std::vector<Step> cccv_pulse_discharge() {
    auto constant = [](double a) { return [a](double) { return a; }; };
    return {{300.0, constant(0.0)},
            {1200.0, constant(4.5)},
            {3600.0, [](double tau) { return 4.5 * std::exp(-tau / 900.0); }},
            {1800.0, constant(0.0)},
            {30.0, constant(-9.0)},
            {1800.0, constant(0.0)},
            {1200.0, constant(-4.5)},
            {1800.0, constant(0.0)}};
}

}  // namespace

TEST(SparseLogging, ACvTaperLoggedOnceAMinuteCountsItsWholeCharge) {
    const est::CellModel model(cellbench::test::thesis_parameter_set());
    const auto logged = log_like_a_cycler(model, cccv_pulse_discharge(), 0.2);
    const auto& rec = logged.rec;
    // The taper is logged sparsely: rows a minute apart whose current falls by more than 5 % each.
    std::size_t taper_rows = 0;
    for (std::size_t k = 1; k < rec.size(); ++k)
        if (rec.step_count[k] == 3 && rec.step_count[k - 1] == 3 && rec.time_s[k] - rec.time_s[k - 1] > 59.0 &&
            est::is_current_step(rec.current_a[k - 1], rec.current_a[k]))
            ++taper_rows;
    ASSERT_GE(taper_rows, 10u) << "the taper should hold rows a minute apart that fall by more than 5 %";

    const auto q = est::cumulative_charge_ah(rec);
    double worst = 0;
    for (std::size_t k = 0; k < rec.size(); ++k) worst = std::max(worst, std::abs(q[k] - logged.true_charge_ah[k]));
    // Counted as current steps (each row's current, or the one before it, held over the minute before the row), the
    // taper's rows put the count 29 mAh off; counted as the curve they sample, 0.4 mAh.
    EXPECT_LT(worst, 0.002) << "worst charge error over the recording, Ah (the CCCV charge moves "
                            << logged.true_charge_ah.back() << " Ah net)";
}

TEST(SparseLogging, TheModelOnACyclersSparseRowsPredictsWhatItPredictsOnTheDenseOnes) {
    const est::CellModel model(cellbench::test::thesis_parameter_set());
    const auto logged = log_like_a_cycler(model, cccv_pulse_discharge(), 0.2);
    est::SimulationOptions o;
    o.initial_soc = logged.soc0;
    o.ambient_c = 25.0;
    o.initial_temperature_c = 25.0;
    const auto tr = est::simulate(model, logged.rec, o);
    ASSERT_EQ(tr.voltage_v.size(), logged.rec.size());
    double sse = 0, worst = 0;
    for (std::size_t k = 0; k < logged.rec.size(); ++k) {
        const double e = tr.voltage_v[k] - logged.rec.voltage_v[k];
        sse += e * e;
        worst = std::max(worst, std::abs(e));
    }
    const double rms = std::sqrt(sse / static_cast<double>(logged.rec.size()));
    // Each row's heat is its interval's mean: summed over the rows, the heat the cell generated.
    double heat_j = 0;
    for (std::size_t k = 1; k < logged.rec.size(); ++k)
        heat_j += tr.heat_generated_w[k] * (logged.rec.time_s[k] - logged.rec.time_s[k - 1]);
    EXPECT_NEAR(heat_j, logged.true_heat_j.back(), 0.005 * logged.true_heat_j.back());
    // The model that wrote the rows, simulated on them. Each row's current held over the interval before it (the
    // taper a staircase of its minute rows) put it 6.4 mV RMS and 8.3 mV at worst off them; the tables read at
    // each interval's start (rows 40 s apart at 1C) 0.46 and 2.4 mV; now 0.10 and 0.28 mV.
    EXPECT_LT(rms, 0.3e-3) << logged.rec.size() << " rows";
    EXPECT_LT(worst, 1e-3);
}
