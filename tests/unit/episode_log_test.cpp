// A failing instrument logs one warning per kind of fault in an episode, not one per poll (drivers/episode_log.hpp).
#include <gtest/gtest.h>

#include <memory>
#include <sstream>

#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "cellbench/drivers/episode_log.hpp"

namespace {

using cellbench::drivers::EpisodeLog;
using spdlog::level::debug;
using spdlog::level::warn;

TEST(EpisodeLog, RepeatsOfAKindGoToDebugUntilAGoodAnswerEndsTheEpisode) {
    EpisodeLog log;
    EXPECT_EQ(log.level("timeout", warn), warn);
    for (int k = 0; k < 100; ++k) EXPECT_EQ(log.level("timeout", warn), debug);
    EXPECT_EQ(log.level("protocol_error", warn), warn) << "another kind of fault is news";
    EXPECT_EQ(log.level("protocol_error", warn), debug);
    EXPECT_EQ(log.level("timeout", warn), debug) << "interleaved kinds (a poll and a write failing) stay one line each";
    // The good answer ends the episode and says how many were kept at debug.
    std::ostringstream out;
    auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(out);
    auto previous = spdlog::default_logger();
    spdlog::set_default_logger(std::make_shared<spdlog::logger>("episode", sink));
    log.end("chamber 127.0.0.1:502");
    log.end("chamber 127.0.0.1:502");  // no episode open: nothing
    spdlog::set_default_logger(previous);
    EXPECT_NE(out.str().find("chamber 127.0.0.1:502: answering again (102 more faults"), std::string::npos) << out.str();
    EXPECT_EQ(out.str().find("answering again", out.str().find("answering again") + 1), std::string::npos) << out.str();
    EXPECT_EQ(log.level("timeout", warn), warn) << "a new episode starts with a warning";
}

}  // namespace
