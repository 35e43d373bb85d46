#pragma once
// Internal to the estimator: ceres::Solve from a start where the cost can be evaluated.
#include <cmath>
#include <limits>

#include <ceres/ceres.h>

namespace cellbench::estimator {

// ceres::Solve, except from a start where the cost is not finite (a pulse of too few rows, a time constant the
// data cannot hold): Ceres 2.1 then stops at once and logs "Terminating: Residual and Jacobian evaluation failed"
// at ERROR level on stderr whatever logging_type says (its trust-region minimizer's RETURN_IF_ERROR_AND_LOG),
// outside the command's own log. Such a start is reported as Ceres reports it, a FAILURE with no finite cost,
// without the stray line.
inline void solve_from_finite_start(const ceres::Solver::Options& options, ceres::Problem* problem,
                                    ceres::Solver::Summary* summary) {
    double cost = 0;
    if (!problem->Evaluate(ceres::Problem::EvaluateOptions(), &cost, nullptr, nullptr, nullptr) || !std::isfinite(cost)) {
        *summary = ceres::Solver::Summary();
        summary->termination_type = ceres::FAILURE;
        summary->message = "the cost is not finite at the start";
        summary->initial_cost = summary->final_cost = std::numeric_limits<double>::infinity();
        return;
    }
    ceres::Solve(options, problem, summary);
}

}  // namespace cellbench::estimator
