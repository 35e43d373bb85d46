// Segmentation and pulse-set fits on the real HPPC of the reference thesis (Molicel P45B, 30 degC, 0.1 s),
// compared with the thesis' Table 3.2. Reads the shared data in place (never copied into the repo).
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <tuple>
#include <utility>

#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/pulse_fit.hpp"
#include "cellbench/estimator/segment.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

using namespace cellbench;
using namespace cellbench::estimator;

namespace {

const std::filesystem::path kHppc =
    std::filesystem::path(CELLBENCH_SHARED_DIR) / "data" / "p45b" / "hppc_1c_30degC.bdf.csv";

// Thesis Table 3.2, 90 % ... 20 % SOC (the 10 % column is not asserted).
constexpr double kSoc[] = {0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2};
constexpr double kR0DaMilliohm[] = {7.50, 7.39, 7.36, 7.38, 7.34, 7.30, 7.28, 7.37};
constexpr double kR1DrMilliohm[] = {1.59, 1.57, 1.53, 1.42, 1.41, 1.37, 1.44, 1.63};
constexpr double kC1DFarad[] = {1360, 1100, 927, 1470, 1450, 1410, 1680, 1730};
constexpr double kR2DMilliohm[] = {9.93, 12.0, 8.12, 9.45, 11.1, 11.3, 8.73, 29.2};

// Thesis OCV table (thesis_ocv_by_soc.csv): the caller's local OCV slope per Ah.
constexpr double kOcvSoc[] = {0.10419, 0.20376, 0.30334, 0.40291, 0.50248, 0.60206, 0.70134, 0.80091, 0.90049, 1.0};
constexpr double kOcvV[] = {3.2899, 3.4568, 3.5318, 3.631, 3.716, 3.7923, 3.8721, 3.958, 4.05, 4.0975};
constexpr double kCapacityAh = 3.816;  // pilot discharge of this test (README)

double docv_dah(double soc) {
    std::size_t j = 0;
    while (j + 2 < std::size(kOcvSoc) && kOcvSoc[j + 1] < soc) ++j;
    return (kOcvV[j + 1] - kOcvV[j]) / (kOcvSoc[j + 1] - kOcvSoc[j]) / kCapacityAh;
}

class RealHppc : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        if (!std::filesystem::exists(kHppc)) return;
        std::ifstream in(kHppc, std::ios::binary);
        std::stringstream ss;
        ss << in.rdbuf();
        rec_ = new Recording(protocol::parse_bdf_csv(ss.str(), kHppc.string()));
        seg_ = new RecordingSegments(segment_recording(*rec_));
    }
    static void TearDownTestSuite() {
        delete rec_;
        delete seg_;
        rec_ = nullptr;
        seg_ = nullptr;
    }
    void SetUp() override {
        if (!rec_) GTEST_SKIP() << "shared data not found: " << kHppc << " (set CELLBENCH_SHARED_DIR)";
    }
    // SOC at A of a pulse set: the recording starts fully charged (the 1 h rest after the CCCV charge).
    static double soc_at(std::size_t row) {
        double q = 0;
        for (std::size_t k = 1; k <= row; ++k)
            q += rec_->current_a[k] * (rec_->time_s[k] - rec_->time_s[k - 1]) / 3600.0;
        return 1.0 + q / kCapacityAh;
    }
    static Recording* rec_;
    static RecordingSegments* seg_;
};
Recording* RealHppc::rec_ = nullptr;
RecordingSegments* RealHppc::seg_ = nullptr;

}  // namespace

// The HPPC file on its own (no pilot discharge, no CC discharge beside it) runs from full charge to the 2.9 V
// cut-off: its throughput is the capacity. Its last discharge ends at 5.0x the rested voltage's slope per Ah, a
// knee the first rule (5x) refused: `fit` of this file alone and `make bench` failed with "no recording measures
// the capacity".
TEST_F(RealHppc, AloneItMeasuresItsCapacityFromFullChargeToTheCutOff) {
    const auto c = characterize({*rec_});
    EXPECT_EQ(c.capacity.method, "throughput from full charge to the cut-off");
    EXPECT_NEAR(c.params.capacity_ah, kCapacityAh, 0.03 * kCapacityAh);  // the pilot discharge's 3.816 Ah
}

TEST_F(RealHppc, Segmentation) {
    const auto& seg = *seg_;
    // 100 % ... 10 % (the thesis' 0 % pulse set is missing from the test, section 3.2).
    ASSERT_EQ(seg.pulse_sets.size(), 10u);
    EXPECT_EQ(seg.soc_steps.size(), 10u);  // nine 10 % steps and the final discharge to 2.9 V
    EXPECT_EQ(seg.long_rests.size(), 11u);
    EXPECT_EQ(seg.cc_discharges.size(), 10u);
    EXPECT_FALSE(seg.pilot_discharge);  // not part of this file (README)
    for (std::size_t j = 0; j < seg.pulse_sets.size(); ++j) {
        const auto& ps = seg.pulse_sets[j];
        SCOPED_TRACE("pulse set " + std::to_string(j));
        EXPECT_NEAR(ps.discharge_current_a, -4.5, 0.01);
        EXPECT_NEAR(ps.discharge_duration_s, 30.4, 0.5);
        EXPECT_NEAR(ps.discharge_relaxation_s, 40.0, 0.1);
        EXPECT_NEAR(ps.charge_duration_s, 10.0, 0.1);
        EXPECT_NEAR(ps.charge_relaxation_s, 40.0, 0.1);
        EXPECT_GE(ps.rest_duration_s, 3599.0);
        EXPECT_EQ(ps.charge_cv, j == 0);  // 100 %: the charge pulse hits 4.1 V and turns CV
        EXPECT_FALSE(ps.discharge_cv);
        // The step log agrees with the current-based boundaries.
        EXPECT_EQ(rec_->step_type[ps.pulse_begin], "CCCV DChg");
        EXPECT_EQ(rec_->step_type[ps.pulse_begin - 1], "Rest");
        EXPECT_EQ(rec_->step_type[ps.charge_begin], "CCCV Chg");
        EXPECT_EQ(rec_->step_type[ps.charge_end], "Rest");
        if (j > 0) {
            EXPECT_NEAR(soc_at(ps.pulse_begin - 1), 1.0 - 0.1 * static_cast<double>(j), 0.01);
        }
    }
    // The same pulse set comes back from an online window ending right after its relaxation.
    const auto& target = seg.pulse_sets[4];
    const auto window = rec_->slice(target.rest_begin, target.end);
    const auto online = last_complete_pulse_set(window);
    ASSERT_TRUE(online);
    EXPECT_EQ(online->pulse_begin + target.rest_begin, target.pulse_begin);
    EXPECT_EQ(online->end + target.rest_begin, target.end);
    // ... and fits to the same numbers (what `fit --db` replay relies on).
    PulseFitOptions po;
    po.docv_dah_v_per_ah = 0.22;
    const auto a = fit_pulse_set(*rec_, target, po);
    const auto b = fit_pulse_set(window, *online, po);
    EXPECT_DOUBLE_EQ(a.r0.discharge_ohm, b.r0.discharge_ohm);
    EXPECT_DOUBLE_EQ(a.thesis_discharge.r2_ohm, b.thesis_discharge.r2_ohm);
    EXPECT_DOUBLE_EQ(a.joint_discharge.r1_ohm, b.joint_discharge.r1_ohm);
    EXPECT_DOUBLE_EQ(a.joint_charge.tau2_s, b.joint_charge.tau2_s);
    EXPECT_DOUBLE_EQ(a.joint_rms_v, b.joint_rms_v);
}

TEST_F(RealHppc, PulseFitsAgainstThesisTable32) {
    const auto& seg = *seg_;
    ASSERT_EQ(seg.pulse_sets.size(), 10u);
    double total_ms = 0;
    std::printf("  SOC   method  R0 mOhm  R1 mOhm  C1 F   R2 mOhm  C2 F    | dir | RMS mV\n");
    for (std::size_t j = 0; j < seg.pulse_sets.size(); ++j) {
        const auto& ps = seg.pulse_sets[j];
        const double soc = soc_at(ps.pulse_begin - 1);
        PulseFitOptions po;
        po.docv_dah_v_per_ah = docv_dah(soc);
        const auto t0 = std::chrono::steady_clock::now();
        auto fit = fit_pulse_set(*rec_, ps, po);
        total_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        fit.soc = soc;
        for (const auto& [name, d, c, rms] :
             {std::tuple{"thesis", fit.thesis_discharge, fit.thesis_charge, fit.thesis_rms_v},
              std::tuple{"joint", fit.joint_discharge, fit.joint_charge, fit.joint_rms_v}}) {
            for (const auto& [dir, p] : {std::pair{"D", d}, std::pair{"C", c}}) {
                const auto v = to_rc_values(p);
                std::printf("  %4.0f%% %-7s %7.3f  %7.3f  %6.0f  %7.3f  %7.0f | %s | %.2f%s\n", 100 * soc, name,
                            1e3 * v.r0_ohm, 1e3 * v.r1_ohm, v.c1_f, 1e3 * v.r2_ohm, v.c2_f, dir, 1e3 * rms,
                            to_string(fit.chosen) == std::string(name) ? " (chosen)" : "");
            }
        }
        SCOPED_TRACE("pulse set " + std::to_string(j));
        EXPECT_NEAR(fit.temperature_c, 29.6, 0.5);
        if (j == 0) {
            EXPECT_TRUE(std::any_of(fit.warnings.begin(), fit.warnings.end(), [](const std::string& w) {
                return w.find("turned CV") != std::string::npos;
            }));
            continue;
        }
        // The joint fit describes the whole pulse set to within a millivolt and predicts it better than the
        // thesis' segment parameters.
        EXPECT_LT(fit.joint_fit_rms_v, 1e-3);
        EXPECT_LT(fit.joint_rms_v, fit.thesis_rms_v);
        if (j > 8) continue;  // 10 %: not asserted against the table
        const std::size_t s = j - 1;
        ASSERT_NEAR(soc, kSoc[s], 0.01);
        // R0 "DA" (eq. 3.2, mean of AB and CD) within 5 % of Table 3.2 (it reproduces it to its rounding).
        EXPECT_NEAR(fit.r0.discharge_ohm * 1e3, kR0DaMilliohm[s], 0.05 * kR0DaMilliohm[s]);
        EXPECT_NEAR(fit.r0.discharge_ohm * 1e3, kR0DaMilliohm[s], 0.0051);
        // The discharge R0 of the chosen result, too.
        EXPECT_NEAR(fit.chosen_discharge().r0_ohm * 1e3, kR0DaMilliohm[s], 0.05 * kR0DaMilliohm[s]);
        // The thesis' discharge segment fits reproduce Table 3.2 (the charge-pulse fits do not: there the
        // thesis' MATLAB fits stopped short of the least-squares optimum, see the report).
        EXPECT_NEAR(fit.thesis.discharge_relaxation.r1_ohm * 1e3, kR1DrMilliohm[s], 0.05 * kR1DrMilliohm[s]);
        EXPECT_NEAR(fit.thesis.discharge.c1_f, kC1DFarad[s], 0.08 * kC1DFarad[s]);
        if (j < 8) {
            EXPECT_NEAR(fit.thesis.discharge.r2_ohm * 1e3, kR2DMilliohm[s], 0.10 * kR2DMilliohm[s]);
        }
    }
    std::printf("fit_pulse_set: %.1f ms per pulse set (wall clock, both methods)\n", total_ms / 10.0);
}

// A drive cycle or a constant-current discharge is no HPPC: the pulse-set forms of segment.hpp (a long rest, a
// discharge pulse, a rest, a charge pulse or none) must find nothing in them, else `fit` would take a drive cycle
// for a characterization test and the daemon would fit its accelerations as pulse sets.
TEST(RealDriveCycles, HoldNoPulseSet) {
    const auto dir = std::filesystem::path(CELLBENCH_SHARED_DIR) / "data";
    std::size_t read = 0;
    for (const char* name : {"panasonic-18650pf/us06_25degC.bdf.csv", "panasonic-18650pf/hwfet_a_25degC.bdf.csv",
                             "panasonic-18650pf/hwfet_b_25degC.bdf.csv", "panasonic-18650pf/la92_25degC.bdf.csv",
                             "panasonic-18650pf/nn_25degC.bdf.csv", "panasonic-18650pf/us06_0degC.bdf.csv",
                             "panasonic-18650pf/hwfet_0degC.bdf.csv", "panasonic-18650pf/la92_0degC.bdf.csv",
                             "p45b/cc_4c_30degC.bdf.csv"}) {
        const auto path = dir / name;
        if (!std::filesystem::exists(path)) continue;
        std::ifstream in(path, std::ios::binary);
        std::stringstream ss;
        ss << in.rdbuf();
        const Recording rec = protocol::parse_bdf_csv(ss.str(), path.string());
        const auto seg = segment_recording(rec);
        std::size_t pulses = 0;
        for (const auto& ph : seg.phases) pulses += ph.is_pulse();
        std::printf("%s: %zu phases, %zu pulses, %zu long rests, %zu pulse sets\n", name, seg.phases.size(), pulses,
                    seg.long_rests.size(), seg.pulse_sets.size());
        EXPECT_TRUE(seg.pulse_sets.empty()) << name;
        ++read;
    }
    if (read == 0) GTEST_SKIP() << "shared data not found in " << dir;
}
