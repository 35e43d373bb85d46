// GET /status and GET /metrics: one snapshot of the instruments, the active run and the store.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>

#include "cellbench/daemon/metrics.hpp"

namespace cellbench::daemon {

json BenchDaemon::status() {
    auto& d = *impl_;
    json j = {{"version", kVersion},
              {"uptime_s", std::chrono::duration<double>(SteadyClock::now() - d.started_at).count()},
              {"bench_time_s", d.now_s()},
              {"time_scale", d.scale},
              {"time_scale_achieved", d.clock->achieved_scale()},
              {"bench_time_paced", d.clock->paced()}};
    auto c = d.active();
    double t_rel = kNaN;
    {
        std::lock_guard l(d.live_m);
        // Paced bench time slowed down until this instrument's readings catch up (sim::PaceGate), else null.
        j["bench_time_waiting_for"] = d.pace_waiting_for.empty() ? json(nullptr) : json(d.pace_waiting_for);
        // Every registered instrument, in registry order. Data age: wall seconds since the instrument's newest
        // reading (null before the first).
        const double now_unix = unix_now_s();
        j["instruments"] = json::array();
        for (const auto& inst : d.instruments) {
            const auto st = inst->status(now_unix);
            j["instruments"].push_back({{"name", st.name},
                                        {"kind", st.kind},
                                        {"state", instruments::to_string(st.state)},
                                        {"address", st.address},
                                        {"detail", st.detail},
                                        {"mode", st.simulated ? "simulated" : "real"},
                                        {"data_age_s", st.data_age_s ? json(*st.data_age_s) : json(nullptr)}});
            // The cycler: the tester channels wired in parallel as it, each as it reported itself.
            if (st.kind == "cycler") {
                json members = json::array();
                for (const auto& m : st.members)
                    members.push_back({{"channel", m.channel}, {"voltage_v", nullable(m.voltage_v)},
                                       {"current_a", nullable(m.current_a)}, {"status", m.status}});
                j["instruments"].back()["members"] = std::move(members);
            }
        }
        json live = {{"time_unix_s", unix_now_s()}, {"test_time_s", nullptr}, {"voltage_v", nullptr},
                     {"current_a", nullptr}, {"soc", nullptr}, {"surface_c", nullptr}, {"ambient_c", nullptr},
                     {"t1_c", nullptr}, {"t2_c", nullptr}, {"heat_flux_w_per_m2", nullptr}};
        if (d.live_cycler) {
            live["voltage_v"] = nullable(d.live_cycler->voltage_v);
            live["current_a"] = nullable(d.live_cycler->current_a);
            live["time_unix_s"] = d.live_cycler->unix_s;
            if (c) {
                t_rel = c->rel(d.live_cycler->t_s);
                live["test_time_s"] = t_rel;
                live["soc"] = nullable(d.live_soc);
            }
        }
        if (d.live_daq) {
            live["surface_c"] = nullable(d.live_daq->surface_c);
            live["t1_c"] = nullable(d.live_daq->t1_c);
            live["t2_c"] = nullable(d.live_daq->t2_c);
            live["heat_flux_w_per_m2"] = nullable(d.live_daq->heat_flux_w_per_m2);
        }
        if (d.live_chamber) {
            live["ambient_c"] = nullable(d.live_chamber->ambient_c);
            live["setpoint_c"] = nullable(d.live_chamber->setpoint_c);
        }
        j["live"] = std::move(live);
    }
    j["run"] = c ? d.run_json(c->id) : json(nullptr);
    // Progress by expected time: test time over the program's expected duration (an estimate: the fraction
    // stays below 1 until the run ends).
    if (c && std::isfinite(c->expected_s) && c->expected_s > 0 && std::isfinite(t_rel))
        j["progress"] = {{"elapsed_s", t_rel},
                         {"expected_duration_s", c->expected_s},
                         {"fraction", std::clamp(t_rel / c->expected_s, 0.0, 0.99)}};
    else
        j["progress"] = nullptr;
    if (c) j["sequencer"] = c->seq->status();
    // Whether the last run's fits (its pulse sets', then its end fit after it ended) are still computing: a
    // script waiting for a run's parameter set, or measuring the daemon at rest, waits for false.
    const auto last = d.current();
    j["fits_running"] = last && last->seq->fits_running();
    return j;
}

// ---- lab integration (issue 7): GET /metrics gathers a snapshot here, metrics.cpp formats it; post() is the
// ---- watchdog's liveness probe of the io_context (cellbenchd's sd_notify WATCHDOG=1 pings).
std::string BenchDaemon::metrics_text() {
    auto& d = *impl_;
    metrics::BenchSnapshot s;
    s.uptime_s = std::chrono::duration<double>(SteadyClock::now() - d.started_at).count();
    s.version = cellbench::version();
    s.git = cellbench::git_describe();
    const bool run_active = d.active() != nullptr;
    {
        std::lock_guard l(d.live_m);
        if (d.live_cycler) s.voltage_v = d.live_cycler->voltage_v, s.current_a = d.live_cycler->current_a;
        if (d.live_daq) s.surface_c = d.live_daq->surface_c;
        if (d.live_chamber) s.ambient_c = d.live_chamber->ambient_c;
        if (run_active) s.soc = d.live_soc;
    }
    for (const auto& inst : d.instruments) {
        const auto st = inst->status(unix_now_s());
        s.instruments.push_back({st.name, st.kind, std::string(instruments::to_string(st.state)), st.simulated,
                                 st.sim_requests, st.faults, st.reconnects, st.lost_frames});
    }
    if (d.dewe) s.daq_stream = d.dewe->health().stats;
    if (d.store) s.store = d.store->stats();
    if (auto c = d.current()) {
        metrics::RunSnapshot r;
        r.id = c->id;
        r.active = c->live;
        try {
            const json j = d.run_json(c->id);
            r.state = j.value("state", "");
            if (j.contains("step") && j["step"].is_object()) {
                if (j["step"].contains("index") && j["step"]["index"].is_number_integer()) r.step_index = j["step"]["index"].get<int>();
                if (j["step"].contains("count") && j["step"]["count"].is_number_integer()) r.step_count = j["step"]["count"].get<int>();
            }
        } catch (const std::exception& e) {
            spdlog::debug("metrics: run {}: {}", c->id, e.what());
        }
        s.run = std::move(r);
    }
    return metrics::format_bench_metrics(s);
}

}  // namespace cellbench::daemon
