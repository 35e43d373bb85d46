// Coulomb counting (estimator/coulomb.hpp) on a real logger that does not write a row when a step begins: the
// Panasonic 18650PF HPPCs (../shared/data/panasonic-18650pf, README: "the first row of each discharge is logged
// about 60 s after it starts", the rests after the SOC steps every 300 s). The counted discharge of the whole test
// must be the source's own Ah counter (README: 2.833 Ah at 25 degC, 2.503 Ah at 0 degC); holding the last row's
// current over the 300 s gap after every SOC step gave 3.62 and 3.16 Ah. The P45B's cycler export (Neware: a row
// at every step start) must count its pilot discharge as the cycler's own capacity column (3.7975 Ah).
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <string>
#include <utility>

#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/estimator/segment.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/neware_export.hpp"
#include "support/command.hpp"

namespace {

namespace fs = std::filesystem;
using namespace cellbench;
const fs::path kShared = fs::path(CELLBENCH_SHARED_DIR) / "data";

Recording read(const fs::path& p) { return protocol::parse_bdf_csv(test::slurp(p), p.filename().string()); }

}  // namespace

TEST(CoulombOnRealLoggers, ThePanasonicHppcDischargesWhatItsOwnAhCounterSays) {
    for (const auto& [file, source_ah] : {std::pair{"hppc_5pulse_25degC.bdf.csv", 2.833}, std::pair{"hppc_5pulse_0degC.bdf.csv", 2.503}}) {
        const auto path = kShared / "panasonic-18650pf" / file;
        if (!fs::exists(path)) GTEST_SKIP() << "no Panasonic data in " << path.parent_path();
        const auto rec = read(path);
        EXPECT_EQ(estimator::step_logging(rec.time_s, rec.current_a), estimator::StepLogging::one_interval_after) << file;
        const auto q = estimator::cumulative_charge_ah(rec);
        const double discharged = *std::max_element(q.begin(), q.end()) - q.back();
        EXPECT_NEAR(discharged, source_ah, 0.003 * source_ah) << file;
    }
}

TEST(CoulombOnRealLoggers, TheNewareExportsPilotDischargeIsTheCyclersOwnCapacity) {
    const auto path = kShared / "p45b" / "hppc_1c_30degC_neware.csv";
    if (!fs::exists(path)) GTEST_SKIP() << "no P45B data in " << path.parent_path();
    const auto rec = protocol::parse_neware_export(test::slurp(path), path.filename().string());
    EXPECT_EQ(estimator::step_logging(rec.time_s, rec.current_a), estimator::StepLogging::at_step_start);
    const auto seg = estimator::segment_recording(rec);
    ASSERT_TRUE(seg.pilot_discharge.has_value());
    EXPECT_NEAR(-seg.pilot_discharge->charge_ah, 3.7975, 0.0005);  // the cycler's Capacity(Ah) column
    // The merged 0.1 s BDF recording of the pulses alone has no step that tells: the ZOH count.
    const auto merged = read(kShared / "p45b" / "hppc_1c_30degC.bdf.csv");
    EXPECT_EQ(estimator::step_logging(merged.time_s, merged.current_a), estimator::StepLogging::unknown);
}
