#pragma once
// One run (internal to daemon/src): the sequencer, the sink that writes what it reports to the store, and the
// step bookkeeping. Also the small helpers the daemon's pieces share (bench_detail).
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <future>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/core/version.hpp"
#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/daemon/run_store.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/json_input.hpp"
#include "cellbench/sequencer/sequencer.hpp"
#include "sequencer_program.hpp"

namespace cellbench::daemon {

namespace asio = boost::asio;
using nlohmann::json;
using SteadyClock = std::chrono::steady_clock;

namespace bench_detail {

inline const char* const kVersion = cellbench::version();  // CMake project version (core/version.hpp)

inline double unix_now_s() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}
// Wall (UTC) time of a steady_clock instant in the recent past.
inline double unix_at(SteadyClock::time_point t) {
    return unix_now_s() - std::chrono::duration<double>(SteadyClock::now() - t).count();
}
inline json nullable(double x) { return std::isfinite(x) ? json(x) : json(nullptr); }

// Paced bench time: the pacer runs every kPacePeriod; a call more than kPaceMaxStepWallS after the previous
// one (the host starved the daemon) adds only kPaceMaxStepWallS x scale bench seconds.
constexpr auto kPacePeriod = std::chrono::milliseconds(10);
constexpr double kPaceMaxStepWallS = 0.1;
constexpr double kPaceGatedScale = 10.0;  // bench s per wall s while waiting for an instrument's readings

// A bench-time period as a wall timer period (the simulation runs time_scale bench s per wall s), >= 1 ms.
inline std::chrono::milliseconds wall_period(double bench_ms, double scale, double min_ms = 1.0) {
    return std::chrono::milliseconds(static_cast<std::int64_t>(std::max(min_ms, std::round(bench_ms / scale))));
}

inline estimator::ParameterSet load_param_file(const std::filesystem::path& path) {
    std::ifstream in(path);
    if (!in) throw InputError(path.string() + ": cannot read the parameter set");
    std::stringstream text;
    text << in.rdbuf();
    auto p = estimator::ParameterSet::from_json(protocol::parse_json_input(text.str(), path.string()), path.string());
    for (const auto& id : p.extensions.unknown_ids())
        spdlog::warn("{}: extension \"{}\" is not an effect this cellbench models: left out of the model",
                     path.string(), id);
    return p;
}

inline RunState store_state(sequencer::RunState s) {
    switch (s) {
        case sequencer::RunState::Running: return RunState::running;
        case sequencer::RunState::Paused: return RunState::paused;
        case sequencer::RunState::Completed: return RunState::completed;
        case sequencer::RunState::Aborted: return RunState::aborted;
        case sequencer::RunState::Stopped: return RunState::stopped;
        case sequencer::RunState::Idle: break;
    }
    return RunState::starting;
}

inline EventLevel event_level(const std::string& severity) {
    if (severity == "info") return EventLevel::info;
    if (severity == "warning") return EventLevel::warning;
    return EventLevel::error;  // "alarm", "error"
}

// The API's run state (INTERFACES.md): the store's word, except that a live run waiting for the cell and
// chamber to reach equilibrium says so.
inline std::string api_state(RunState s, bool waiting_equilibrium) {
    if (s == RunState::running && waiting_equilibrium) return "waiting_equilibrium";
    return std::string(to_string(s));
}

// A run's summary from the store (never its stored config), NotFound when there is no such run: where an API call
// on /runs/{id} starts.
inline RunInfo existing_run(const RunStore& store, RunId id) {
    auto r = store.get_run(id, RunStore::RunRead::summary);
    if (!r) throw NotFound("no run " + std::to_string(id));
    return std::move(*r);
}

inline bool live_state(RunState s) { return s == RunState::starting || s == RunState::running || s == RunState::paused; }

inline std::string safe_name(std::string s) {
    for (char& c : s)
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') c = '_';
    return s;
}

}  // namespace bench_detail

using namespace bench_detail;

// ---------------------------------------------------------------------------------------------------------
// One run: the sequencer, the sink that writes what it reports to the store, and the step bookkeeping.

struct RunContext final : sequencer::RunSink {
    RunStore& store;
    RunId id;
    double start_bench_s;            // bench time at which the run started (t_s = bench - this)
    std::string cell_name;
    std::vector<int> steps_per_segment;
    std::unique_ptr<sequencer::Sequencer> seq;

    std::atomic<bool> live{true};
    // After the run ended and its fits were delivered, the tick gives memory back in two steps: the store's page
    // caches (1), then, once the writer has freed its cache (store_released ready), the freed heap to the system
    // (2). Trimming before the writer's release left its whole page cache (up to 16 MiB) resident as free heap.
    // Touched by the tick only.
    int memory_returned = 0;
    std::future<void> store_released;
    std::atomic<int> seq_state{static_cast<int>(sequencer::RunState::Running)};

    // Leaf lock: sink callbacks (under the sequencer's lock) and sample handlers.
    mutable std::mutex m;
    int step_index = 0;
    std::string end_reason;  // why the run ended (terminal state), as the sequencer said
    std::optional<StepRecord> open_step;
    int pulse_sets = 0;
    double last_cycler_t_s = kNaN;  // run time of the latest stored cycler row
    double capacity_ah = 4.5;
    // The open step's totals as the sequencer reported them at its end (on_step_end); else the live reading's.
    std::optional<std::pair<double, double>> step_totals;
    double last_capacity_ah = kNaN, last_energy_wh = kNaN;
    double expected_s = kNaN;  // the program's expected duration (estimate_duration), for progress by time

    RunContext(RunStore& s, RunId run, double start, std::string cell)
        : store(s), id(run), start_bench_s(start), cell_name(std::move(cell)) {}

    double rel(double t_bench) const { return t_bench - start_bench_s; }

    void on_state(sequencer::RunState state, const std::string& reason) override {
        seq_state = static_cast<int>(state);
        const RunState st = store_state(state);
        if (is_terminal(st)) {
            live = false;
            std::lock_guard lock(m);
            end_reason = reason;  // the API shows it even while the store cannot commit it (disk full, locked)
            close_step_locked(unix_now_s(), last_cycler_t_s, state == sequencer::RunState::Completed ? "end" : "stopped");
        }
        store.set_run_state(id, st, reason);
        spdlog::info("run {}: {} ({})", id, sequencer::to_string(state), reason);
    }

    void close_step_locked(double unix_s, double t_s, const std::string& why) {
        if (!open_step) return;
        open_step->ended_t_s = std::isfinite(t_s) ? t_s : open_step->started_t_s;
        open_step->ended_unix_s = unix_s;
        if (std::isfinite(last_capacity_ah)) open_step->capacity_ah = std::abs(last_capacity_ah);
        if (std::isfinite(last_energy_wh)) open_step->energy_wh = std::abs(last_energy_wh);
        open_step->end_reason = why;
        if (step_totals) {
            open_step->capacity_ah = step_totals->first;
            open_step->energy_wh = step_totals->second;
        }
        store.record_step(id, *open_step);
        open_step.reset();
        step_totals.reset();
    }

    void on_step_end(double, double capacity_ah, double energy_wh) override {
        std::lock_guard lock(m);
        step_totals = std::make_pair(capacity_ah, energy_wh);
    }

    void on_step(double t_mono_s, int segment, int step_id, int cycle_id, const std::string& step_type) override {
        std::lock_guard lock(m);
        const double t = rel(t_mono_s), u = unix_now_s();
        close_step_locked(u, t, "next step");
        StepRecord r;
        r.index = ++step_index;
        r.segment = segment;
        r.step_id = step_id;
        r.cycle = cycle_id;
        r.type = step_type;
        r.started_t_s = t;
        r.started_unix_s = u;
        store.record_step(id, r);
        open_step = r;
    }

    void on_event(double t_mono_s, const std::string& severity, const std::string& kind,
                  const std::string& message) override {
        EventRecord e;
        e.run_id = id;
        e.unix_s = unix_now_s();
        e.t_s = rel(t_mono_s);
        e.level = event_level(severity);
        e.kind = kind;
        {
            std::lock_guard lock(m);
            if (open_step) e.step = open_step->index;
        }
        e.message = message;
        store.record_event(e);
        if (e.level == EventLevel::error) spdlog::warn("run {}: {}: {}", id, kind, message);
    }

    void on_pulse_fit(const estimator::PulseSetFit& fit, double t_mono_s) override {
        // SOC and start time as the sequencer (SOC's one owner) gave them.
        int n = 0;
        {
            std::lock_guard lock(m);
            n = ++pulse_sets;
        }
        store.record_pulse_fit(pulse_fit_record(id, n, rel(t_mono_s), kNaN, fit));
        const auto d = fit.chosen_discharge();
        spdlog::info("run {}: pulse set {} fitted: SOC {:.3f}, R0 discharge {:.3f} mOhm", id, n, fit.soc,
                     d.r0_ohm * 1e3);
    }

    void on_parameter_set(const estimator::ParameterSet& params, const json& summary) override {
        ParameterSetRecord r;
        r.run_id = id;
        r.created_unix_s = unix_now_s();
        r.cell = cell_name;
        r.params = params.to_json();
        store.record_parameter_set(r);
        EventRecord e;
        e.run_id = id;
        e.unix_s = r.created_unix_s;
        e.kind = "fit";
        e.message = "parameter set fitted from the run";
        e.detail = summary;
        store.record_event(e);
    }

    json step_json(double t_s) const {
        std::lock_guard lock(m);
        if (!open_step) return nullptr;
        const auto seg = static_cast<std::size_t>(open_step->segment);
        return {{"index", open_step->step_id},
                {"count", seg < steps_per_segment.size() ? steps_per_segment[seg] : 0},
                {"type", open_step->type},
                {"run_step", open_step->index},
                {"elapsed_s", std::isfinite(t_s) ? std::max(0.0, t_s - open_step->started_t_s) : 0.0}};
    }
};

}  // namespace cellbench::daemon
