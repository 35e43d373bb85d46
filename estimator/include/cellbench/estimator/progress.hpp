#pragma once
// Progress of a long estimator computation (fit, diagnose), for the caller to show. The estimator does no
// I/O: it only calls this.
#include <functional>
#include <mutex>
#include <string_view>
#include <utility>

namespace cellbench::estimator {

// (fraction done 0..1, what it is doing now in a few words). May be empty. The estimator calls it from one
// thread at a time (worker threads serialise through ProgressReporter), never with a decreasing fraction,
// and with 1.0 exactly once, at the end.
using Progress = std::function<void(double fraction, std::string_view stage)>;

// Serialises the calls of several worker threads and keeps the fraction from going backwards.
class ProgressReporter {
public:
    explicit ProgressReporter(const Progress& progress) : progress_(progress) {}
    void operator()(double fraction, std::string_view stage) {
        if (!progress_) return;
        std::lock_guard lock(m_);
        if (fraction < last_) fraction = last_;
        if (fraction > 1.0) fraction = 1.0;
        last_ = fraction;
        progress_(fraction, stage);
    }

private:
    const Progress& progress_;
    std::mutex m_;
    double last_ = 0.0;
};

}  // namespace cellbench::estimator
