#pragma once
// One log line per kind of fault in an episode. An instrument that keeps failing the same way (a chamber
// answering every poll with an exception, a tester sending malformed frames) would otherwise write a warning per
// poll: 2 lines a second at 1 s polls, 57 000 over a night, hiding everything else. The first fault of a kind is
// logged at its own level, its repeats at debug and counted; the line that ends the episode (the first good
// answer) says how many there were. Not thread-safe: used on the driver's strand or worker.
#include <algorithm>
#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

#include <spdlog/spdlog.h>

namespace cellbench::drivers {

class EpisodeLog {
public:
    // The level to log a fault of `kind` at: `first` the first time in this episode, debug for a repeat.
    spdlog::level::level_enum level(std::string_view kind, spdlog::level::level_enum first) {
        if (std::find(kinds_.begin(), kinds_.end(), kind) != kinds_.end()) {
            ++repeats_;
            return spdlog::level::debug;
        }
        kinds_.emplace_back(kind);  // a handful per episode (an instrument fails in few ways at once)
        return first;
    }
    // Ends the episode on a good answer: logs (at info, with `who`) how many repeats were kept at debug.
    void end(std::string_view who) {
        if (kinds_.empty()) return;
        if (repeats_ > 0) spdlog::info("{}: answering again ({} more faults of the episode logged at debug)", who, repeats_);
        kinds_.clear();
        repeats_ = 0;
    }

private:
    std::vector<std::string> kinds_;  // the kinds logged in this episode
    std::size_t repeats_ = 0;
};

}  // namespace cellbench::drivers
