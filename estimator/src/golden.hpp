#pragma once
// Internal to the estimator: golden-section search of a unimodal function on an interval.

#include <cmath>

namespace cellbench::estimator {

// The midpoint of the bracket left after `iterations` golden-section steps of f on [a, b] (ties keep the upper
// part). Each step shrinks the bracket by 0.618.
template <typename F>
double golden_section(F&& f, double a, double b, int iterations) {
    const double g = (std::sqrt(5.0) - 1) / 2;
    double c = b - g * (b - a), d = a + g * (b - a);
    double fc = f(c), fd = f(d);
    for (int i = 0; i < iterations; ++i) {
        if (fc < fd) {
            b = d, d = c, fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c, c = d, fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    return 0.5 * (a + b);
}

// Golden-section steps enough to shrink a bracket of `width` to at most `tolerance`.
inline int golden_section_steps(double width, double tolerance) {
    if (!(width > tolerance) || !(tolerance > 0)) return 0;
    return static_cast<int>(std::ceil(std::log(tolerance / width) / std::log((std::sqrt(5.0) - 1) / 2)));
}

}  // namespace cellbench::estimator
