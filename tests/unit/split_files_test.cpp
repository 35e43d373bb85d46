// A test split into files (a cycler's export cut into parts, a test logged day by day) is one test. Before, each
// part was a characterization of its own anchored at SOC 1 at its first row: the P45B HPPC cut in two at a rest
// and handed in as its two halves fitted a capacity of 1.89 Ah instead of 3.79 and predicted the Random Walk at
// 1369 mV RMS, with no error. Parts that continue one another are now joined; a later part handed in without
// its start is refused where another recording shows it does not start full, and the assumption is stated where
// nothing can tell.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/merge.hpp"
#include "unit/hppc_synthetic.hpp"

namespace {

namespace est = cellbench::estimator;
using cellbench::Recording;
using cellbench::test::kCapacityAh;

constexpr double kUnixStart = 1.7e9;

// Four pulse sets from full charge at 1 s, with a Unix clock.
Recording hppc() {
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    so.voltage_noise_v = 2e-4;
    auto rec = cellbench::test::synthesize(cellbench::test::hppc_program(4, 1800.0, 4.5), so);
    rec.source = "hppc";
    rec.unix_time_s.clear();
    for (double t : rec.time_s) rec.unix_time_s.push_back(kUnixStart + t);
    return rec;
}

// The row in the middle of the long rest nearest the middle of the recording.
std::size_t split_row(const Recording& r) {
    for (std::size_t k = r.size() / 2; k + 600 < r.size(); ++k) {
        bool rest = true;
        for (std::size_t j = k - 600; j <= k + 600 && rest; ++j) rest = r.current_a[j] == 0.0;
        if (rest) return k;
    }
    return 0;
}

// The parts as a cycler writes them: each file's test time starts at 0.
std::pair<Recording, Recording> split(const Recording& r) {
    const std::size_t k = split_row(r);
    EXPECT_GT(k, 0u);
    auto a = r.slice(0, k), b = r.slice(k, r.size());
    a.source = "part1", b.source = "part2";
    const double t0 = b.time_s.front();
    for (double& t : b.time_s) t -= t0;
    return {a, b};
}

bool has_note(const std::vector<std::string>& notes, const std::string& text) {
    for (const auto& n : notes)
        if (n.find(text) != std::string::npos) return true;
    return false;
}

TEST(SplitFiles, PartsThatContinueOneAnotherAreJoinedInEitherOrderWithOrWithoutAClock) {
    const auto whole = hppc();
    for (bool clock : {true, false}) {
        auto [a, b] = split(whole);
        if (!clock) a.unix_time_s.clear(), b.unix_time_s.clear();
        std::vector<std::string> notes;
        const auto joined = est::join_continued_recordings({b, a}, notes);  // handed in the wrong order
        ASSERT_EQ(joined.size(), 1u) << (clock ? "with" : "without") << " Unix time";
        EXPECT_TRUE(has_note(notes, "part2 continues part1")) << notes.size();
        const auto& j = joined.front();
        ASSERT_EQ(j.size(), whole.size());
        for (std::size_t k = 0; k < whole.size(); ++k) {
            ASSERT_NEAR(j.time_s[k], whole.time_s[k], 1e-6) << "row " << k;
            ASSERT_EQ(j.current_a[k], whole.current_a[k]) << "row " << k;
            ASSERT_EQ(j.voltage_v[k], whole.voltage_v[k]) << "row " << k;
        }
    }
}

TEST(SplitFiles, RecordingsThatDoNotContinueOneAnotherStayApart) {
    const auto whole = hppc();
    auto no_join = [](std::vector<Recording> recs) {
        std::vector<std::string> notes;
        const std::size_t n = recs.size();
        return est::join_continued_recordings(std::move(recs), notes).size() == n && notes.empty();
    };
    {  // the voltage jumps by 20 mV at the junction: another cell state, not the same rest
        auto [a, b] = split(whole);
        for (double& v : b.voltage_v) v += 0.02;
        EXPECT_TRUE(no_join({a, b}));
    }
    {  // the second file starts two hours after the first ends
        auto [a, b] = split(whole);
        for (double& t : b.unix_time_s) t += 7200.0;
        EXPECT_TRUE(no_join({a, b}));
    }
    {  // without a clock: a discharge that ran the cell to its lowest voltage ends the test, whatever starts at
       // the voltage it rests at afterwards
        cellbench::test::SyntheticOptions so;
        so.dt_s = 1.0;
        const double i = kCapacityAh / 2.0;
        auto empty = cellbench::test::synthesize({{600.0, 0.0, "Rest"}, {6480.0, -i, "CC DChg"}, {1800.0, 0.0, "Rest"}}, so);
        so.soc0 = 1.0 - 6480.0 * i / 3600.0 / kCapacityAh;
        auto next = cellbench::test::synthesize({{1800.0, 0.0, "Rest"}, {600.0, i, "CC Chg"}, {600.0, 0.0, "Rest"}}, so);
        ASSERT_NEAR(next.voltage_v.front(), empty.voltage_v.back(), 0.005);  // the case: the voltages agree
        EXPECT_TRUE(no_join({empty, next}));
    }
}

TEST(SplitFiles, TheJoinedPartsFitAsTheWholeTest) {
    const auto whole = hppc();
    auto [a, b] = split(whole);
    const auto o = cellbench::test::characterization_options();
    const auto from_whole = est::characterize({whole}, o);
    const auto from_parts = est::characterize({b, a}, o);
    EXPECT_EQ(from_parts.capacity.capacity_ah, from_whole.capacity.capacity_ah);
    ASSERT_EQ(from_parts.params.soc.size(), from_whole.params.soc.size());
    for (std::size_t k = 0; k < from_whole.params.soc.size(); ++k) {
        EXPECT_NEAR(from_parts.params.ocv_v[k], from_whole.params.ocv_v[k], 1e-6) << "knot " << k;
        EXPECT_NEAR(from_parts.params.discharge.r0_ohm[k], from_whole.params.discharge.r0_ohm[k],
                    1e-6 * from_whole.params.discharge.r0_ohm[k])
            << "knot " << k;
    }
}

TEST(SplitFiles, ALaterPartAloneIsRefusedWhereAnotherRecordingStartsFullAndStatedWhereNothingCanTell) {
    const auto whole = hppc();
    const auto [a, b] = split(whole);
    // A C/5 discharge that starts rested at full charge: the cell's full voltage, 0.2 V above the part's start.
    cellbench::test::SyntheticOptions so;
    so.dt_s = 1.0;
    auto full = cellbench::test::synthesize({{1800.0, 0.0, "Rest"}, {7200.0, -kCapacityAh / 5.0, "CC DChg"}, {1800.0, 0.0, "Rest"}}, so);
    full.source = "c5_from_full";
    const auto o = cellbench::test::characterization_options();
    try {
        (void)est::characterize({b, full}, o);
        ADD_FAILURE() << "a part that starts at 60 % SOC was taken as fully charged";
    } catch (const cellbench::InputError& e) {
        const std::string what = e.what();
        EXPECT_NE(what.find("part2 does not start fully charged"), std::string::npos) << what;
        EXPECT_NE(what.find("c5_from_full"), std::string::npos) << what;
    }
    // Alone, nothing tells: the fit runs and says what it assumed.
    const auto c = est::characterize({b}, o);
    EXPECT_TRUE(has_note(c.warnings, "part2: SOC 100 % taken at its first row")) << c.warnings.size();
    // The whole test with the discharge beside it confirms its start: no such note.
    const auto w = est::characterize({whole, full}, o);
    EXPECT_FALSE(has_note(w.warnings, "SOC 100 % taken at its first row"));
}

}  // namespace
