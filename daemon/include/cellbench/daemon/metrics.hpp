#pragma once
// GET /metrics: the Prometheus text exposition format, version 0.0.4
// (https://prometheus.io/docs/instrumenting/exposition_formats/), written by hand (no client library).
//
//   Exposition  writes metric families: one "# HELP" and one "# TYPE" line per family, then its samples
//               `name{label="value",...} value`. Help text and label values are escaped (\\, \n, and \" in
//               label values); names are checked; a family may appear only once; counters end in _total.
//   RateMeter   a per-second rate of a cumulative count over a sliding window (samples/s ingested).
//   BenchSnapshot / format_bench_metrics   what cellbenchd exposes about its bench, gathered by the backend
//               (BenchDaemon::metrics_text) under its own locks and formatted here, so the format is
//               testable without a bench.
#include <cstdint>
#include <deque>
#include <initializer_list>
#include <limits>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "cellbench/daemon/run_store.hpp"
#include "cellbench/protocol/dewe_can.hpp"

namespace cellbench::daemon::metrics {

enum class MetricType { counter, gauge };

// `name="value"` pairs of one sample, in the order given.
using Labels = std::initializer_list<std::pair<std::string_view, std::string_view>>;

[[nodiscard]] bool valid_metric_name(std::string_view name);  // [a-zA-Z_:][a-zA-Z0-9_:]*
[[nodiscard]] bool valid_label_name(std::string_view name);   // [a-zA-Z_][a-zA-Z0-9_]*, not starting "__"
[[nodiscard]] std::string escape_help(std::string_view text);          // \ -> \\, LF -> \n
[[nodiscard]] std::string escape_label_value(std::string_view text);   // \ -> \\, " -> \", LF -> \n
// Shortest text that reads back as the same double; "NaN", "+Inf", "-Inf".
[[nodiscard]] std::string format_value(double value);

class Exposition {
public:
    // Starts a family. Throws std::invalid_argument for an invalid name, a counter whose name does not end
    // in "_total", or a name already used in this exposition.
    Exposition& family(std::string_view name, MetricType type, std::string_view help);
    // A sample of the current family (std::logic_error before any family). Counters must be finite and
    // >= 0 (std::invalid_argument); label names are checked (std::invalid_argument).
    Exposition& sample(double value, Labels labels = {});
    Exposition& sample(std::uint64_t value, Labels labels = {});
    // Shorthands: a family with one unlabelled sample.
    Exposition& gauge(std::string_view name, std::string_view help, double value);
    Exposition& counter(std::string_view name, std::string_view help, std::uint64_t value);

    [[nodiscard]] const std::string& text() const { return text_; }

private:
    void write_sample(std::string_view value, Labels labels);
    std::string text_;
    std::string current_;
    MetricType current_type_ = MetricType::gauge;
    std::set<std::string, std::less<>> families_;
};

// Rate of a cumulative count, per second, over roughly the last `window_s` seconds. Not thread-safe (its
// owner locks). Times are any monotonic seconds.
class RateMeter {
public:
    RateMeter() = default;  // 10 s window
    explicit RateMeter(double window_s) : window_s_(window_s) {}
    // Records the cumulative count at time t (keeps at most one point per window/20).
    void observe(double t_s, double count);
    // (count_now - count at the reference point) / elapsed time, the reference being the newest recorded
    // point at least one window old (or the oldest one); 0 without history or less than 0.5 s of it.
    [[nodiscard]] double rate(double t_now_s, double count_now) const;

private:
    double window_s_ = 10.0;
    std::deque<std::pair<double, double>> points_;  // (t, count), ascending t
};

// -------------------------------------------------------------------------------------------------------

struct InstrumentSnapshot {
    std::string name;   // "neware", "chamber", "dewe"
    std::string kind;   // "cycler", "chamber", "daq"
    std::string state;  // "connected" | "connecting" | "offline" | "error"
    bool simulated = false;
    // Requests answered by the simulated instrument (its server side), when simulated.
    std::optional<std::uint64_t> sim_requests;
    std::uint64_t faults = 0;      // fault occurrences since start (every report, not only episode openings)
    std::uint64_t reconnects = 0;  // returns to "connected" after having been connected
    // Frames lost on the way: DAQ CAN frame counter gaps; cycler answers lost (timeouts) or malformed.
    std::optional<std::uint64_t> lost_frames;
};

struct RunSnapshot {
    std::int64_t id = 0;
    std::string state;  // the API's run state (kRunStates)
    bool active = false;
    std::optional<int> step_index, step_count;
};

struct BenchSnapshot {
    std::string version, git;  // cellbench_build_info labels (core/version.hpp)
    double uptime_s = 0.0;
    std::vector<InstrumentSnapshot> instruments;
    std::optional<protocol::DeweStreamStats> daq_stream;  // the DEWE-43A CAN decoder's counters
    std::optional<StoreStats> store;
    std::optional<RunSnapshot> run;  // the latest run this daemon started (active or finished)
    // Latest readings (NaN = none).
    double voltage_v = std::numeric_limits<double>::quiet_NaN();
    double current_a = std::numeric_limits<double>::quiet_NaN();
    double surface_c = std::numeric_limits<double>::quiet_NaN();
    double ambient_c = std::numeric_limits<double>::quiet_NaN();
    double soc = std::numeric_limits<double>::quiet_NaN();
};

// The API's run states, in the order they are exposed as cellbench_run_state{state=...}.
inline constexpr std::string_view kRunStates[] = {"starting", "waiting_equilibrium", "running", "paused", "stopping",
                                                   "completed", "stopped", "aborted", "interrupted"};
// The API's instrument states, exposed as cellbench_instrument_state{state=...}.
inline constexpr std::string_view kInstrumentStates[] = {"connected", "connecting", "offline", "error"};

// Every family of the bench (names documented in README "Metrics").
void write_bench_metrics(Exposition& out, const BenchSnapshot& snapshot);
[[nodiscard]] std::string format_bench_metrics(const BenchSnapshot& snapshot);

}  // namespace cellbench::daemon::metrics
