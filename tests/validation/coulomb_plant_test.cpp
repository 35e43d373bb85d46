// Coulomb counting (estimator/coulomb.hpp) on recordings this project's model did not make: the independent
// validation plant's HPPCs (tests/plant: a cycler that writes a step's first row the moment the step begins, rests
// logged at 1 s, pulses at 0.1-1 s by seed), in every layout. The counted charge must follow the plant cell's own
// SOC to within 0.05 % of its capacity over the whole test: the fit's SOC axis, its rests' OCV points and the
// capacity rest on it (held each row's current over the interval before it, the count drifted by up to 0.64 %,
// 3-8 mV of OCV at the low levels).
//
// Seeds: CELLBENCH_VALIDATION_SEEDS per layout (default 3), from CELLBENCH_VALIDATION_FIRST_SEED (default 1).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/plant/plant.hpp"

namespace {

namespace est = cellbench::estimator;
namespace plant = cellbench::plant;

int env_int(const char* name, int fallback) {
    const char* e = std::getenv(name);
    return e ? std::max(1, std::atoi(e)) : fallback;
}

}  // namespace

TEST(CoulombOnIndependentPlant, TheCountedChargeFollowsTheCellsOwnSocInEveryLayout) {
    const int first = env_int("CELLBENCH_VALIDATION_FIRST_SEED", 1), seeds = env_int("CELLBENCH_VALIDATION_SEEDS", 3);
    for (plant::Layout layout : {plant::Layout::thesis, plant::Layout::usabc, plant::Layout::random}) {
        for (int seed = first; seed < first + seeds; ++seed) {
            plant::PlantOptions o;
            o.seed = static_cast<std::uint64_t>(seed);
            o.layout = layout;
            const auto cell = plant::make_cell(o);
            const auto r = plant::generate_hppc(cell, o);
            const double c = cell.capacity_ah;
            EXPECT_EQ(est::step_logging(r.time_s, r.current_a), est::StepLogging::at_step_start)
                << plant::layout_name(layout) << " seed " << seed;
            const auto q = est::cumulative_charge_ah(r.time_s, r.current_a);
            double worst = 0, worst_hold = 0, hold = 0;
            for (std::size_t k = 1; k < q.size(); ++k) {
                hold += r.current_a[k] * (r.time_s[k] - r.time_s[k - 1]) / 3600.0;  // the model's ZOH count
                const double truth = r.true_soc[k] - r.true_soc[0];
                worst = std::max(worst, std::abs(q[k] / c - truth));
                worst_hold = std::max(worst_hold, std::abs(hold / c - truth));
            }
            std::printf("%-6s seed %2d (sample %.1f s): worst SOC error %.4f %% (ZOH count %.4f %%)\n",
                        std::string(plant::layout_name(layout)).c_str(), seed, cell.measurement.sample_s,
                        100 * worst, 100 * worst_hold);
            EXPECT_LT(worst, 5e-4) << plant::layout_name(layout) << " seed " << seed;
        }
    }
}
