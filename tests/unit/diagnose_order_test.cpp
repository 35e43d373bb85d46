// Which candidate one round of `diagnose` accepts (estimator::accepted_in_round): the strongest significant
// finding, with the Occam rule between a base correction (parameters_wrong) and physics that explain nearly as
// much. The figures are the ones the independent plant produced (make prove, docs/diagnose.md).
#include <gtest/gtest.h>

#include "cellbench/estimator/diagnose.hpp"

using cellbench::estimator::accepted_in_round;
using cellbench::estimator::Finding;

namespace {

Finding finding(std::string effect, std::string kind, double score, double delta_bic, bool significant = true) {
    Finding f;
    f.effect = std::move(effect);
    f.kind = std::move(kind);
    f.score = score;
    f.delta_bic = delta_bic;
    f.significant = significant;
    return f;
}

}  // namespace

TEST(DiagnoseOrder, NothingSignificantAcceptsNothing) {
    const std::vector<Finding> round = {finding("extra_rc", "physics_missing", 0.2, -50, false),
                                        finding("capacity_error", "parameters_wrong", 0.1, -20, false)};
    EXPECT_EQ(accepted_in_round(round), round.size());
    EXPECT_EQ(accepted_in_round({}), 0u);
}

TEST(DiagnoseOrder, TheStrongestPlausibleFindingGoesFirst) {
    std::vector<Finding> round = {finding("ambient_drift", "physics_missing", 0.4, -100),
                                  finding("heat_flux_sensor_gain", "physics_missing", 0.7, -300),
                                  finding("ocv_offset", "parameters_wrong", 0.3, -90)};
    EXPECT_EQ(accepted_in_round(round), 1u);
    // A correction on its plausible limit ranks after every plausible one, however well it scores.
    round[1].implausible = true;
    EXPECT_EQ(accepted_in_round(round), 0u);
}

TEST(DiagnoseOrder, ABaseCorrectionThatExplainsAsMuchForFewerParametersGoesFirst) {
    // Plant seed 2, a slow RC hidden: extra_rc (4 parameters) 0.549 held out, BIC -343.9; capacity_error (1)
    // 0.531, BIC -349.2. Nearly the same evidence, and BIC prefers the single parameter.
    const std::vector<Finding> round = {finding("extra_rc", "physics_missing", 0.549, -343.9),
                                        finding("capacity_error", "parameters_wrong", 0.531, -349.2)};
    EXPECT_EQ(round[accepted_in_round(round)].effect, "capacity_error");
}

TEST(DiagnoseOrder, PhysicsThatFitsBetterThanItsExtraParametersCostIsNotSetAside) {
    // Plant seed 5, a slow RC hidden: extra_rc 0.618, BIC -429.0; capacity_error 0.525 (85 % of it), BIC -333.7.
    // Before, any base correction within 80 % of the score went first, and on top of the capacity error the
    // slow pair was no longer significant: the capacity was named, the RC pair missed.
    const std::vector<Finding> round = {finding("extra_rc", "physics_missing", 0.618, -429.0),
                                        finding("capacity_error", "parameters_wrong", 0.525, -333.7)};
    EXPECT_EQ(round[accepted_in_round(round)].effect, "extra_rc");
}

TEST(DiagnoseOrder, ABaseCorrectionFarBehindThePhysicsDoesNotCount) {
    // Below 80 % of the physics' score the base correction is not a rival, whatever its BIC.
    const std::vector<Finding> round = {finding("thermal_second_order", "physics_missing", 0.60, -150),
                                        finding("thermal_parameters", "parameters_wrong", 0.40, -400)};
    EXPECT_EQ(round[accepted_in_round(round)].effect, "thermal_second_order");
}
