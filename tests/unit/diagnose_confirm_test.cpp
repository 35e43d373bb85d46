// diagnose --confirm: a finding must hold on the other recordings of the cell. A correction that fits the diagnosed
// recording but makes another recording of the same cell worse (a resistance only that day's harness had) is
// contradicted and never significant; one the other recording shares is confirmed and accepted. Effects that are a
// state of the diagnosed recording (its start, its chamber's drift) are not checked on another one.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "unit/thesis_params.hpp"

using namespace cellbench;

namespace {

estimator::ParameterSet thesis() { return test::thesis_parameter_set(); }

// 40 minutes at 1 s of 1C-4C pulses with rests from initial_soc, starting the pulse pattern at `phase`, simulated
// by the thesis cell with `extra_ohm` of series resistance; voltage quantized to 0.1 mV like a cycler's reading.
Recording pulses(double extra_ohm, int phase, double initial_soc, const char* source) {
    estimator::ParameterSet truth = thesis();
    if (extra_ohm != 0.0) truth.extensions.series_resistance_offset = estimator::SeriesResistanceOffsetExt{extra_ohm};
    Recording r;
    r.source = source;
    const double c1 = truth.capacity_ah;
    const double pattern[] = {-1.0, 0.0, 2.0, 0.0, -4.0, 0.0, -2.0, 1.0, 0.0, -3.0, 0.0};
    for (int k = 0; k <= 2400; ++k) {
        r.time_s.push_back(k);
        r.current_a.push_back(k < 60 ? 0.0 : pattern[(k / 45 + phase) % 11] * c1);
        r.voltage_v.push_back(0.0);
    }
    estimator::SimulationOptions so;
    so.initial_soc = initial_soc;
    so.ambient_c = 25.0;
    const auto tr = estimator::simulate(estimator::CellModel(truth), r, so);
    for (std::size_t k = 0; k < r.size(); ++k) r.voltage_v[k] = std::round(tr.voltage_v[k] * 1e4) / 1e4;
    return r;
}

estimator::Diagnosis diagnose(const Recording& rec, std::vector<const Recording*> confirm,
                              std::vector<std::string> effects = {"series_resistance_offset"}) {
    estimator::DiagnoseOptions o;
    o.effects = std::move(effects);
    o.max_accepted = 1;
    o.threads = 1;
    o.confirm = std::move(confirm);
    return estimator::diagnose(thesis(), rec, o);
}

const estimator::Finding& finding(const estimator::Diagnosis& d, const std::string& effect) {
    const auto it = std::find_if(d.findings.begin(), d.findings.end(), [&](const auto& f) { return f.effect == effect; });
    if (it == d.findings.end()) throw std::runtime_error("no finding " + effect);
    return *it;
}

bool has(const std::vector<std::string>& v, const char* x) { return std::find(v.begin(), v.end(), x) != v.end(); }

}  // namespace

TEST(DiagnoseConfirm, AFindingAnotherRecordingOfTheCellContradictsIsNotSignificant) {
    // 5 mOhm on the diagnosed day only (a harness); the other recording is the cell as characterized.
    const Recording day = pulses(5e-3, 0, 0.7, "harness-day.bdf.csv");
    const Recording other = pulses(0.0, 5, 0.5, "other-day.bdf.csv");
    const auto alone = diagnose(day, {});
    ASSERT_TRUE(finding(alone, "series_resistance_offset").significant) << "the control: found without --confirm";
    EXPECT_TRUE(finding(alone, "series_resistance_offset").confirmation.empty());

    const auto d = diagnose(day, {&other});
    const auto& f = finding(d, "series_resistance_offset");
    EXPECT_FALSE(f.significant);
    EXPECT_TRUE(f.contradicted);
    EXPECT_TRUE(f.withdrawn) << "it passed on the diagnosed recording alone";
    EXPECT_TRUE(d.accepted.empty());
    ASSERT_EQ(f.confirmation.size(), 1u);
    const auto& c = f.confirmation.front();
    EXPECT_EQ(c.recording, "other-day.bdf.csv");
    EXPECT_EQ(c.verdict, "contradicts");
    EXPECT_TRUE(has(c.worse, "voltage"));
    ASSERT_TRUE(c.before.voltage_v && c.after.voltage_v);
    EXPECT_LT(*c.before.voltage_v, 1e-3) << "the other recording is the parameter set's own cell";
    EXPECT_GT(*c.after.voltage_v, 5e-3);
    EXPECT_NE(f.explanation.find("contradicts"), std::string::npos) << f.explanation;
    EXPECT_NE(d.summary.find("contradicts"), std::string::npos) << d.summary;
    EXPECT_EQ(d.confirm_recordings, std::vector<std::string>{"other-day.bdf.csv"});
}

TEST(DiagnoseConfirm, AFindingTheOtherRecordingSharesIsConfirmedAndAccepted) {
    const Recording day = pulses(5e-3, 0, 0.7, "day-1.bdf.csv");
    const Recording other = pulses(5e-3, 5, 0.5, "day-2.bdf.csv");
    const auto d = diagnose(day, {&other});
    const auto& f = finding(d, "series_resistance_offset");
    EXPECT_TRUE(f.significant) << f.explanation;
    EXPECT_FALSE(f.contradicted);
    EXPECT_EQ(d.accepted, std::vector<std::string>{"series_resistance_offset"});
    ASSERT_EQ(f.confirmation.size(), 1u);
    EXPECT_EQ(f.confirmation.front().verdict, "confirms");
    EXPECT_TRUE(has(f.confirmation.front().better, "voltage"));
    EXPECT_TRUE(f.confirmation.front().worse.empty());

    const auto j = estimator::diagnosis_to_json(d);
    ASSERT_TRUE(j.contains("confirmation"));
    EXPECT_EQ(j["confirmation"]["recordings"][0], "day-2.bdf.csv");
    const auto& fj = j["findings"][0];
    EXPECT_EQ(fj["confirmation"][0]["verdict"], "confirms");
    EXPECT_EQ(fj["contradicted"], false);
    EXPECT_FALSE(estimator::diagnosis_to_json(diagnose(day, {})).contains("confirmation"))
        << "without --confirm the diagnosis JSON is as before";
}

TEST(DiagnoseConfirm, AStateOfTheDiagnosedRecordingIsNotCheckedOnAnother) {
    const Recording day = pulses(5e-3, 0, 0.7, "day.bdf.csv");
    const Recording other = pulses(0.0, 5, 0.5, "other.bdf.csv");
    const auto d = diagnose(day, {&other}, {"series_resistance_offset", "initial_soc"});
    const auto& state = finding(d, "initial_soc");
    EXPECT_TRUE(state.confirmation.empty()) << "the start of one recording says nothing about another";
    EXPECT_FALSE(state.contradicted);
    EXPECT_EQ(finding(d, "series_resistance_offset").confirmation.size(), 1u);
}

TEST(DiagnoseConfirm, ChangesInsideTheAccuracyOrWithinFivePercentAreNeutral) {
    auto judge = [](double before_v, double after_v) {
        estimator::Confirmation c;
        c.before.voltage_v = before_v;
        c.after.voltage_v = after_v;
        estimator::confirmation_verdict(c, 5e-3, 0.3, 0.05);
        return c;
    };
    EXPECT_EQ(judge(0.040, 0.041).verdict, "neutral");   // +2.5 %
    EXPECT_EQ(judge(0.040, 0.043).verdict, "contradicts");
    EXPECT_EQ(judge(0.040, 0.036).verdict, "confirms");
    EXPECT_EQ(judge(0.001, 0.004).verdict, "neutral") << "both inside the 5 mV accuracy";
    EXPECT_EQ(judge(0.004, 0.006).verdict, "contradicts") << "pushed out of the accuracy by more than a tenth of it";
    EXPECT_EQ(judge(0.006, 0.0055).verdict, "neutral") << "less than a tenth of the accuracy";
    auto c = judge(0.040, 0.036);
    c.before.heat_flux_w = 0.2;
    c.after.heat_flux_w = 0.37;
    estimator::confirmation_verdict(c, 5e-3, 0.3, 0.05);
    EXPECT_EQ(c.verdict, "contradicts") << "better voltage does not outweigh a worse heat flux";
    EXPECT_TRUE(has(c.better, "voltage"));
    EXPECT_TRUE(has(c.worse, "heat_flux"));
}
