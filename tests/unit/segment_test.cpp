// Segmentation of recordings into phases, HPPC pulse sets, SOC steps, pilot and CC discharges.
#include "cellbench/estimator/segment.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>

#include "unit/hppc_synthetic.hpp"

using namespace cellbench;
using namespace cellbench::estimator;
using cellbench::test::Step;

namespace {

// Rows of a step program: index of the first row of each step (row 0 is the initial rest row).
std::vector<std::size_t> step_starts(const std::vector<Step>& program, double dt = 0.1) {
    std::vector<std::size_t> s;
    std::size_t row = 1;
    for (const auto& st : program) {
        s.push_back(row);
        row += static_cast<std::size_t>(std::llround(st.duration_s / dt));
    }
    s.push_back(row);
    return s;
}

Recording strip_steps(Recording r) {
    r.step_type.clear();
    r.step_count.clear();
    return r;
}

}  // namespace

TEST(Segment, EmptyRecordingGivesEmptyResult) {
    Recording rec;
    const auto seg = segment_recording(rec);
    EXPECT_TRUE(seg.phases.empty());
    EXPECT_TRUE(seg.pulse_sets.empty());
    EXPECT_FALSE(seg.pilot_discharge);
    EXPECT_FALSE(last_complete_pulse_set(rec));
}

TEST(Segment, SingleRowAndNoPulses) {
    Recording one;
    one.time_s = {0.0};
    one.voltage_v = {3.7};
    one.current_a = {0.0};
    const auto s1 = segment_recording(one);
    ASSERT_EQ(s1.phases.size(), 1u);
    EXPECT_EQ(s1.phases[0].kind, PhaseKind::Rest);

    // Long rest, then one CC discharge, then a rest: no pulse set, one CC discharge, one long rest.
    const std::vector<Step> prog{{900, 0, "Rest"}, {600, -18.0, "CC DChg"}, {120, 0, "Rest"}};
    const auto rec = test::synthesize(prog, {.voltage_noise_v = 3e-4, .current_noise_a = 5e-3});
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.phases.size(), 3u);
    EXPECT_TRUE(seg.pulse_sets.empty());
    EXPECT_TRUE(seg.soc_steps.empty());
    ASSERT_EQ(seg.cc_discharges.size(), 1u);
    EXPECT_NEAR(seg.cc_discharges[0].mean_current_a, -18.0, 0.01);
    EXPECT_NEAR(seg.cc_discharges[0].duration_s, 600.0, 0.11);
    EXPECT_NEAR(seg.cc_discharges[0].charge_ah, -18.0 * 600 / 3600, 1e-3);
    ASSERT_EQ(seg.long_rests.size(), 1u);
    EXPECT_EQ(seg.long_rests[0].begin, 0u);
    EXPECT_FALSE(seg.pilot_discharge);  // no CCCV charge before it
}

TEST(Segment, WholeRecordingOneDischarge) {
    // Like cc_4c_30degC.bdf.csv: the recording is one 18 A discharge from its first row.
    Recording rec;
    for (int k = 0; k < 7500; ++k) {
        rec.time_s.push_back(0.1 * k);
        rec.voltage_v.push_back(4.0 - 1e-4 * k);
        rec.current_a.push_back(-18.0 + 0.002 * std::sin(k));
    }
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.phases.size(), 1u);
    EXPECT_EQ(seg.phases[0].kind, PhaseKind::Discharge);
    EXPECT_TRUE(seg.phases[0].open_end);
    ASSERT_EQ(seg.cc_discharges.size(), 1u);
    EXPECT_EQ(seg.cc_discharges[0].begin, 0u);
    EXPECT_EQ(seg.cc_discharges[0].end, rec.size());
    EXPECT_TRUE(seg.pulse_sets.empty());
}

TEST(Segment, FindsEveryPulseSetOfMultiSocHppc) {
    const auto prog = test::hppc_program(9);
    const auto starts = step_starts(prog);
    for (bool with_steps : {true, false}) {
        SCOPED_TRACE(with_steps ? "with step log" : "current only");
        auto rec = test::synthesize(prog, {.voltage_noise_v = 3e-4, .current_noise_a = 5e-3, .seed = 7});
        if (!with_steps) rec = strip_steps(rec);
        const auto seg = segment_recording(rec);
        ASSERT_EQ(seg.pulse_sets.size(), 9u);
        ASSERT_EQ(seg.soc_steps.size(), 9u);
        EXPECT_EQ(seg.long_rests.size(), 10u);
        EXPECT_EQ(seg.cc_discharges.size(), 9u);
        EXPECT_FALSE(seg.pilot_discharge);
        for (std::size_t j = 0; j < 9; ++j) {
            const auto& ps = seg.pulse_sets[j];
            const std::size_t s0 = 6 * j;  // steps per set: rest, dis, rest, chg, rest, CC
            EXPECT_EQ(ps.rest_begin, j == 0 ? 0u : starts[s0]);
            EXPECT_EQ(ps.pulse_begin, starts[s0 + 1]);
            EXPECT_EQ(ps.discharge_end, starts[s0 + 2]);
            EXPECT_EQ(ps.charge_begin, starts[s0 + 3]);
            EXPECT_EQ(ps.charge_end, starts[s0 + 4]);
            EXPECT_EQ(ps.end, starts[s0 + 5]);
            EXPECT_NEAR(ps.discharge_current_a, -4.5, 0.01);
            EXPECT_NEAR(ps.charge_current_a, 4.5, 0.01);
            EXPECT_NEAR(ps.discharge_duration_s, 30.0, 1e-6);
            EXPECT_NEAR(ps.charge_duration_s, 10.0, 1e-6);
            EXPECT_NEAR(ps.charge_relaxation_s, 40.0, 1e-6);
            EXPECT_FALSE(ps.charge_cv);
            EXPECT_FALSE(ps.relaxation_open);
            EXPECT_DOUBLE_EQ(ps.ocv_v, rec.voltage_v[ps.pulse_begin - 1]);
            EXPECT_EQ(seg.soc_steps[j].pulse_set_index, j);
            EXPECT_EQ(seg.soc_steps[j].begin, ps.end);
            EXPECT_TRUE(seg.soc_steps[j].followed_by_long_rest);
            EXPECT_NEAR(seg.soc_steps[j].charge_ah, -(0.1 * test::kCapacityAh - 20 * 4.5 / 3600), 2e-3);
        }
    }
}

TEST(Segment, RepeatedTimestampsAndNoisyCurrent) {
    auto rec = test::synthesize(test::hppc_program(4),
                                {.voltage_noise_v = 3e-4, .current_noise_a = 0.012, .seed = 3});
    rec = strip_steps(rec);
    // Vendor exports repeat a stamp now and then (after repair they can still be equal).
    std::mt19937 rng(5);
    std::uniform_int_distribution<std::size_t> pick(1, rec.size() - 1);
    for (int j = 0; j < 400; ++j) {
        const std::size_t k = pick(rng);
        rec.time_s[k] = rec.time_s[k - 1];
    }
    // A few spikes of noise in rests (one row each) must not create phases.
    for (std::size_t k : {2000u, 2500u, 3000u}) rec.current_a[k] = 0.3;
    const auto seg = segment_recording(rec);
    EXPECT_EQ(seg.pulse_sets.size(), 4u);
    EXPECT_EQ(seg.soc_steps.size(), 4u);
    EXPECT_EQ(seg.phases.size(), 4u * 6u + 1u);
}

TEST(Segment, CcCvChargeIsOneChargePhaseAndPilotIsFound) {
    // Table 2.12 steps 1-7: rest, CCCV charge to 4.1 V (0.05 A cut-off approximated by time), rest,
    // pilot discharge to the cut-off, rest, CCCV charge, rest; then one pulse set.
    std::vector<Step> prog{{10, 0, "Rest"},
                           {1800, 4.5, "CCCV Chg", 4.1},
                           {600, 0, "Rest"},
                           {2800, -4.5, "CC DChg"},
                           {900, 0, "Rest"},
                           {3300, 4.5, "CCCV Chg", 4.1},
                           {800, 0, "Rest"},
                           {30, -4.5, "CCCV DChg"},
                           {40, 0, "Rest"},
                           {10, 4.5, "CCCV Chg", 4.1},
                           {40, 0, "Rest"}};
    test::SyntheticOptions o;
    o.soc0 = 0.55;
    o.current_noise_a = 3e-3;
    const auto rec = strip_steps(test::synthesize(prog, o));
    const auto seg = segment_recording(rec);
    ASSERT_EQ(seg.phases.size(), prog.size());  // row 0 (a rest) joins the first 10 s rest
    EXPECT_EQ(seg.phases[1].kind, PhaseKind::Charge);
    EXPECT_TRUE(seg.phases[1].cv_tail);
    EXPECT_EQ(seg.phases[5].kind, PhaseKind::Charge);
    EXPECT_TRUE(seg.phases[5].cv_tail);
    ASSERT_TRUE(seg.pilot_discharge);
    EXPECT_EQ(seg.pilot_discharge->index, 3u);
    EXPECT_NEAR(seg.pilot_discharge->charge_ah, -4.5 * 2800 / 3600, 1e-3);
    ASSERT_EQ(seg.pulse_sets.size(), 1u);
    // The charge pulse right after a full charge hits 4.1 V and turns CV (the thesis' 100 % SOC pulse set).
    EXPECT_TRUE(seg.pulse_sets[0].charge_cv);
    EXPECT_FALSE(seg.pulse_sets[0].discharge_cv);
    EXPECT_TRUE(seg.soc_steps.empty());
}

TEST(Segment, StepBoundaryInsideOneDirectionSplitsOnlyWithStepLog) {
    std::vector<Step> prog{{700, 0, "Rest"}, {100, -4.5, "CC DChg"}, {100, -9.0, "CC DChg 2"}, {100, 0, "Rest"}};
    const auto rec = test::synthesize(prog);
    EXPECT_EQ(segment_recording(rec).phases.size(), 4u);
    EXPECT_EQ(segment_recording(strip_steps(rec)).phases.size(), 3u);
}

TEST(Segment, OnlineWindows) {
    const auto prog = test::hppc_program(3);
    const auto starts = step_starts(prog);
    const auto full = test::synthesize(prog, {.voltage_noise_v = 3e-4, .current_noise_a = 5e-3, .seed = 11});
    const auto offline = segment_recording(full);
    ASSERT_EQ(offline.pulse_sets.size(), 3u);
    const auto& target = offline.pulse_sets[1];

    // Window from the start of the long rest of pulse set 1 ...
    const std::size_t w0 = target.rest_begin;
    // ... ending mid discharge pulse, mid charge pulse, 20 s into the charge relaxation: not complete.
    for (std::size_t end : {target.pulse_begin + 100, target.charge_begin + 50, target.charge_end + 200}) {
        const auto w = full.slice(w0, end);
        EXPECT_FALSE(last_complete_pulse_set(w)) << "window end " << end;
    }
    // 35 s into the relaxation: complete, but open.
    {
        const auto w = full.slice(w0, target.charge_end + 350);
        const auto ps = last_complete_pulse_set(w);
        ASSERT_TRUE(ps);
        EXPECT_TRUE(ps->relaxation_open);
        EXPECT_EQ(ps->pulse_begin + w0, target.pulse_begin);
        EXPECT_EQ(ps->end + w0, target.charge_end + 350);
    }
    // Ending right after the relaxation (last rest row, or first row of the next current): same rows as offline.
    for (std::size_t extra : {0u, 1u, 25u}) {
        const auto w = full.slice(w0, target.end + extra);
        const auto ps = last_complete_pulse_set(w);
        ASSERT_TRUE(ps);
        EXPECT_EQ(ps->rest_begin + w0, target.rest_begin);
        EXPECT_EQ(ps->pulse_begin + w0, target.pulse_begin);
        EXPECT_EQ(ps->discharge_end + w0, target.discharge_end);
        EXPECT_EQ(ps->charge_begin + w0, target.charge_begin);
        EXPECT_EQ(ps->charge_end + w0, target.charge_end);
        EXPECT_EQ(ps->end + w0, target.end);
        EXPECT_EQ(ps->relaxation_open, extra == 0);
        EXPECT_DOUBLE_EQ(ps->ocv_v, target.ocv_v);
    }
    // A window that holds less than long_rest_s of the rest before the pulse does not give a pulse set.
    {
        const auto w = full.slice(target.pulse_begin - 3000, target.end + 5);
        EXPECT_FALSE(last_complete_pulse_set(w));
    }
    (void)starts;
}

// The USABC/FreedomCAR manual's layout: 30 s discharge pulse, 40 s rest, 10 s regen pulse and the SOC step at
// once, no rest after the regen pulse. Each level is a pulse set of the NoChargeRelaxation form, followed by its
// SOC step; online, the set is complete once the SOC step has lasted longer than a pulse can (before, it may be
// the next pulse of a drive cycle), with the rows an offline run finds.
TEST(Segment, UsabcPulseSetsEndWithTheRegenPulseAndAreCompleteWhenTheSocStepBegins) {
    std::vector<Step> prog;
    for (int level = 0; level < 3; ++level) {
        prog.push_back({700, 0, "Rest"});
        prog.push_back({30, -9.0, "CC DChg"});
        prog.push_back({40, 0, "Rest"});
        prog.push_back({10, 4.5, "CC Chg"});
        prog.push_back({300, -4.5, "CC DChg"});
    }
    prog.push_back({700, 0, "Rest"});
    const auto full = test::synthesize(prog, {.voltage_noise_v = 3e-4, .current_noise_a = 5e-3, .seed = 5});
    const auto seg = segment_recording(full);
    ASSERT_EQ(seg.pulse_sets.size(), 3u);
    ASSERT_EQ(seg.soc_steps.size(), 3u);
    for (const auto& ps : seg.pulse_sets) {
        EXPECT_EQ(ps.form, PulseSetForm::NoChargeRelaxation);
        EXPECT_TRUE(ps.has_charge_pulse());
        EXPECT_EQ(ps.charge_end, ps.end);
        EXPECT_NEAR(ps.discharge_duration_s, 30.0, 0.2);
        EXPECT_NEAR(ps.charge_duration_s, 10.0, 0.2);
        EXPECT_EQ(ps.charge_relaxation_s, 0.0);
    }
    for (const auto& s : seg.soc_steps) EXPECT_TRUE(s.followed_by_long_rest);

    const auto& target = seg.pulse_sets[1];
    const std::size_t w0 = target.rest_begin;
    // Mid charge pulse, at its last row (it may go on), 30 s into the SOC step (it may be a pulse): not complete.
    for (std::size_t end : {target.charge_begin + 50, target.charge_end, target.charge_end + 300}) {
        EXPECT_FALSE(last_complete_pulse_set(full.slice(w0, end))) << "window end " << end;
    }
    for (std::size_t extra : {605u, 2000u}) {
        const auto ps = last_complete_pulse_set(full.slice(w0, target.charge_end + extra));
        ASSERT_TRUE(ps) << extra;
        EXPECT_EQ(ps->form, PulseSetForm::NoChargeRelaxation);
        EXPECT_EQ(ps->pulse_begin + w0, target.pulse_begin);
        EXPECT_EQ(ps->charge_begin + w0, target.charge_begin);
        EXPECT_EQ(ps->end + w0, target.end);
        EXPECT_EQ(ps->next_window_begin + w0, target.end);
    }
}

// Discharge pulses alone, two currents per level (the Panasonic 18650PF's kind): every pulse after a long rest is
// a DischargeOnly pulse set. A rest after a discharge pulse may still be followed by a charge pulse, so online the
// set is complete only when the next phase has begun; when that rest is long it is also the next set's rest, and
// the window after the first set starts there and finds the second set with the offline rows.
TEST(Segment, DischargeOnlyPulseSetsWaitForWhatFollowsTheirRestAndShareALongRest) {
    std::vector<Step> prog;
    for (int level = 0; level < 2; ++level) {
        prog.push_back({700, 0, "Rest"});
        prog.push_back({10, -4.5, "CC DChg"});
        prog.push_back({700, 0, "Rest"});
        prog.push_back({10, -9.0, "CC DChg"});
        prog.push_back({120, 0, "Rest"});
        prog.push_back({300, -4.5, "CC DChg"});
    }
    prog.push_back({700, 0, "Rest"});
    const auto full = test::synthesize(prog, {.voltage_noise_v = 3e-4, .current_noise_a = 5e-3, .seed = 7});
    const auto seg = segment_recording(full);
    ASSERT_EQ(seg.pulse_sets.size(), 4u);
    for (const auto& ps : seg.pulse_sets) {
        EXPECT_EQ(ps.form, PulseSetForm::DischargeOnly);
        EXPECT_FALSE(ps.has_charge_pulse());
        EXPECT_EQ(ps.charge_begin, ps.end);
        EXPECT_EQ(ps.charge_end, ps.end);
    }
    EXPECT_NEAR(seg.pulse_sets[0].discharge_current_a, -4.5, 0.05);
    EXPECT_NEAR(seg.pulse_sets[1].discharge_current_a, -9.0, 0.05);
    // The first set's rest is the second set's long rest; the second is followed by its SOC step.
    EXPECT_EQ(seg.pulse_sets[0].next_window_begin, seg.pulse_sets[0].discharge_end);
    EXPECT_EQ(seg.pulse_sets[1].rest_begin, seg.pulse_sets[0].discharge_end);
    EXPECT_EQ(seg.pulse_sets[1].next_window_begin, seg.pulse_sets[1].end);
    ASSERT_EQ(seg.soc_steps.size(), 2u);
    EXPECT_EQ(seg.soc_steps[0].pulse_set_index, 1u);

    const auto& first = seg.pulse_sets[0];
    const std::size_t w0 = first.rest_begin;
    // 60 s and the whole 700 s into the rest after the pulse, nothing after it yet: not complete.
    for (std::size_t end : {first.discharge_end + 600, first.end}) {
        EXPECT_FALSE(last_complete_pulse_set(full.slice(w0, end))) << "window end " << end;
    }
    const auto ps = last_complete_pulse_set(full.slice(w0, first.end + 5));
    ASSERT_TRUE(ps);
    EXPECT_EQ(ps->pulse_begin + w0, first.pulse_begin);
    EXPECT_EQ(ps->end + w0, first.end);
    // The daemon's next window starts where the first set says, and holds the second set.
    const std::size_t w1 = w0 + ps->next_window_begin;
    const auto second = last_complete_pulse_set(full.slice(w1, seg.pulse_sets[1].end + 700));
    ASSERT_TRUE(second);
    EXPECT_EQ(second->pulse_begin + w1, seg.pulse_sets[1].pulse_begin);
    EXPECT_EQ(second->end + w1, seg.pulse_sets[1].end);
    EXPECT_DOUBLE_EQ(second->ocv_v, seg.pulse_sets[1].ocv_v);
}

// Any other order after the long rest (PulseSetForm::Other): a charge pulse first and a discharge pulse straight
// after it (no rest between) is a pulse set once the SOC step has begun; the step between the two pulses is no R0
// step of either direction. A drive-cycle-like run of more pulses before the next long phase is no pulse set.
TEST(Segment, PulsesInAnyOrderUpToTheNextLongPhaseAreAPulseSetButADriveCycleIsNot) {
    std::vector<Step> prog;
    for (int level = 0; level < 2; ++level) {
        prog.push_back({700, 0, "Rest"});
        prog.push_back({2, 2.25, "CC Chg"});
        prog.push_back({30, -4.5, "CC DChg"});
        prog.push_back({40, 0, "Rest"});
        prog.push_back({300, -4.5, "CC DChg"});
    }
    prog.push_back({700, 0, "Rest"});
    for (int k = 0; k < 6; ++k) {  // a drive cycle's accelerations and decelerations
        prog.push_back({8, k % 2 ? 3.0 : -6.0, k % 2 ? "CC Chg" : "CC DChg"});
        prog.push_back({5, 0, "Rest"});
    }
    prog.push_back({300, -4.5, "CC DChg"});
    prog.push_back({700, 0, "Rest"});
    const auto full = test::synthesize(prog, {.voltage_noise_v = 3e-4, .current_noise_a = 5e-3, .seed = 9});
    const auto seg = segment_recording(full);
    ASSERT_EQ(seg.pulse_sets.size(), 2u);
    ASSERT_EQ(seg.soc_steps.size(), 2u);
    for (const auto& ps : seg.pulse_sets) {
        EXPECT_EQ(ps.form, PulseSetForm::Other);
        EXPECT_TRUE(ps.has_charge_pulse());
        EXPECT_EQ(ps.pulse_begin, ps.charge_begin);       // the charge pulse comes first
        EXPECT_EQ(ps.charge_end, ps.discharge_begin);     // and the discharge pulse at once
        EXPECT_TRUE(ps.rest_before_charge);
        EXPECT_FALSE(ps.rest_after_charge);
        EXPECT_FALSE(ps.rest_before_discharge);
        EXPECT_TRUE(ps.rest_after_discharge);
        EXPECT_NEAR(ps.discharge_relaxation_s, 40.0, 0.2);
        EXPECT_EQ(ps.pulses_end, ps.discharge_end);
    }
    // Online: complete once the SOC step has begun, with the offline rows.
    const auto& target = seg.pulse_sets[1];
    const std::size_t w0 = target.rest_begin;
    EXPECT_FALSE(last_complete_pulse_set(full.slice(w0, target.end + 5)));  // the SOC step may be a pulse yet
    const auto ps = last_complete_pulse_set(full.slice(w0, target.end + 700));
    ASSERT_TRUE(ps);
    EXPECT_EQ(ps->form, PulseSetForm::Other);
    EXPECT_EQ(ps->pulse_begin + w0, target.pulse_begin);
    EXPECT_EQ(ps->end + w0, target.end);
}
