#pragma once
// Internal to the estimator: numbers put into the messages and explanations the fits and the diagnosis write.

#include <cstdio>
#include <string>

namespace cellbench::estimator {

// printf_text("%.2f mOhm", r_ohm * 1e3): the printf format applied to the numbers (at most 255 characters).
template <class... Numbers>
std::string printf_text(const char* format, Numbers... numbers) {
    char buf[256];
    std::snprintf(buf, sizeof buf, format, numbers...);
    return buf;
}

}  // namespace cellbench::estimator
