// Bench events (no run) and instrument fault episodes (issue 6): one episode per fault key, the configured
// policy (reconnect within a grace or abort now), the events a run and the bench log get.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>

namespace cellbench::daemon {

void BenchDaemon::Impl::bench_event(EventLevel level, const std::string& kind, const std::string& message, json detail,
                 std::optional<RunId> run) {
    if (!store) return;
    store_event(event_record(run, level, kind, message, std::move(detail)));
}

EventRecord BenchDaemon::Impl::event_record(std::optional<RunId> run, EventLevel level, const std::string& kind,
                                const std::string& message, json detail) {
    EventRecord e;
    e.run_id = run;
    e.unix_s = unix_now_s();
    e.level = level;
    e.kind = kind;
    e.message = message;
    e.detail = std::move(detail);
    return e;
}

// An event the store refuses (full, locked) is logged, never thrown into the caller's path.
void BenchDaemon::Impl::store_event(const EventRecord& e) {
    try {
        store->record_event(e);
    } catch (const std::exception& ex) {
        spdlog::warn("cannot record event: {}", ex.what());
    }
}

// Grace in bench time, never below what the host can promise in wall time (min_grace_s).
double BenchDaemon::Impl::grace_for(const std::string& instrument) const {
    const auto& f = cfg.faults;
    const double g = instrument == "neware" ? f.cycler.grace_s : instrument == "dewe" ? f.daq.grace_s : f.chamber.grace_s;
    return std::max(g, min_grace_s());
}

void BenchDaemon::Impl::record_run_event(std::optional<RunId> run, EventLevel level, const std::string& kind, const std::string& message,
                      json detail) {
    if (!store) return;
    EventRecord e = event_record(run, level, kind, message, std::move(detail));
    if (run) {
        if (auto c = current(); c && c->id == *run) {
            e.t_s = c->rel(now_s());
            std::lock_guard l(c->m);
            if (c->open_step) e.step = c->open_step->index;
        }
    }
    store_event(e);
}

void BenchDaemon::Impl::fault(const std::string& key, const std::string& kind, const std::string& message, bool fatal, json extra) {
    const double now = now_s();
    const std::string instrument = instrument_of(key);
    auto c = active();
    bool first = false;
    std::optional<RunId> run;
    {
        std::lock_guard l(fault_m);
        auto& ep = episodes[key];
        if (!ep.open) {
            ep = FaultEpisode{};
            ep.open = first = true;
            ep.since_s = now;
            ep.fault = kind;
            if (c) ep.run = c->id;
        } else if (c && ep.run != c->id) {
            ep.run = c->id;  // a fault still going on when a run started: that run records it too
            first = true;
        }
        ++ep.occurrences;
        if (auto* i = instruments.find(instrument)) i->count_fault(kind == "timeout" || kind == "protocol_error");
        ep.last_s = now;
        ep.message = message;
        run = c ? std::optional<RunId>(c->id) : ep.run;
    }
    if (first || fatal) {
        json detail = {{"instrument", instrument}, {"fault", kind}, {"message", message},
                       {"action", fatal ? "abort" : "reconnect"}};
        if (!fatal) detail["grace_s"] = grace_for(instrument);
        if (extra.is_object())
            for (const auto& [k, v] : extra.items()) detail[k] = v;
        spdlog::warn("{}: {} fault: {}{}", instrument, kind, message, fatal ? " (fatal: the run aborts)" : "");
        record_run_event(run, fatal ? EventLevel::error : EventLevel::warning, "fault", instrument + ": " + message,
                         std::move(detail));
    }
    if (fatal && c) c->seq->abort(instrument + ": " + message + " (" + kind + ", immediately fatal)", now);
}

// A valid reading: closes the key's episode (after settle_s bench seconds without a new fault).
void BenchDaemon::Impl::recovered(const std::string& key, double settle_s) {
    const double now = now_s();
    FaultEpisode ep;
    {
        std::lock_guard l(fault_m);
        const auto it = episodes.find(key);
        if (it == episodes.end() || !it->second.open || now - it->second.last_s < settle_s) return;
        ep = it->second;
        it->second.open = false;
    }
    const std::string instrument = instrument_of(key);
    const double down_s = std::max(0.0, now - ep.since_s);
    spdlog::info("{}: recovered from {} after {:.1f} s ({} occurrences)", instrument, ep.fault, down_s, ep.occurrences);
    auto c = active();
    const auto run = ep.run ? ep.run : (c ? std::optional<RunId>(c->id) : std::nullopt);
    char text[64];
    std::snprintf(text, sizeof text, " cleared after %.1f s", down_s);
    record_run_event(run, EventLevel::info, "recovery", instrument + ": " + ep.fault + text,
                     {{"instrument", instrument}, {"fault", ep.fault}, {"down_s", down_s},
                      {"occurrences", ep.occurrences}, {"last_message", ep.message}});
}

// Faults reported outside the drivers' own fault streams (commands not taken, set point writes).
void BenchDaemon::Impl::instrument_fault(const std::string& instrument, const std::string& message, bool safety_data_lost) {
    fault(instrument + ":command", "command", message, safety_data_lost);
}

}  // namespace cellbench::daemon
