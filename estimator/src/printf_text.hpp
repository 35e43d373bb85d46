#pragma once
// Internal to the estimator: numbers put into the messages and explanations the fits and the diagnosis write.

#include <cstdio>
#include <string>

namespace cellbench::estimator {

// printf_text("%.2f mOhm", r_ohm * 1e3): the printf format applied to the numbers (and strings), whatever the
// length (a file's path in a message is as long as the user's folders make it).
template <class... Numbers>
std::string printf_text(const char* format, Numbers... numbers) {
    const int n = std::snprintf(nullptr, 0, format, numbers...);
    if (n <= 0) return {};
    std::string out(static_cast<std::size_t>(n), '\0');
    std::snprintf(out.data(), out.size() + 1, format, numbers...);
    return out;
}

}  // namespace cellbench::estimator
