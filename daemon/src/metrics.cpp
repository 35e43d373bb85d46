#include "cellbench/daemon/metrics.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <stdexcept>

namespace cellbench::daemon::metrics {

namespace {

bool name_char(char c, bool first, bool colon) {
    const bool alpha = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '_' || (colon && c == ':');
    return first ? alpha : alpha || (c >= '0' && c <= '9');
}

}  // namespace

bool valid_metric_name(std::string_view name) {
    if (name.empty()) return false;
    for (std::size_t i = 0; i < name.size(); ++i)
        if (!name_char(name[i], i == 0, true)) return false;
    return true;
}

bool valid_label_name(std::string_view name) {
    if (name.empty() || name.starts_with("__")) return false;
    for (std::size_t i = 0; i < name.size(); ++i)
        if (!name_char(name[i], i == 0, false)) return false;
    return true;
}

std::string escape_help(std::string_view text) {
    std::string out;
    out.reserve(text.size());
    for (char c : text) {
        if (c == '\\') out += "\\\\";
        else if (c == '\n') out += "\\n";
        else out += c;
    }
    return out;
}

std::string escape_label_value(std::string_view text) {
    std::string out;
    out.reserve(text.size());
    for (char c : text) {
        if (c == '\\') out += "\\\\";
        else if (c == '"') out += "\\\"";
        else if (c == '\n') out += "\\n";
        else out += c;
    }
    return out;
}

std::string format_value(double value) {
    if (std::isnan(value)) return "NaN";
    if (std::isinf(value)) return value > 0 ? "+Inf" : "-Inf";
    char buf[32];
    const auto r = std::to_chars(buf, buf + sizeof buf, value);  // shortest round-trip form
    return std::string(buf, r.ptr);
}

Exposition& Exposition::family(std::string_view name, MetricType type, std::string_view help) {
    if (!valid_metric_name(name)) throw std::invalid_argument("metrics: invalid metric name \"" + std::string(name) + "\"");
    if (type == MetricType::counter && !name.ends_with("_total"))
        throw std::invalid_argument("metrics: counter \"" + std::string(name) + "\" must end in _total");
    if (!families_.emplace(name).second)
        throw std::invalid_argument("metrics: family \"" + std::string(name) + "\" declared twice");
    current_ = std::string(name);
    current_type_ = type;
    text_ += "# HELP ";
    text_ += name;
    text_ += ' ';
    text_ += escape_help(help);
    text_ += "\n# TYPE ";
    text_ += name;
    text_ += type == MetricType::counter ? " counter\n" : " gauge\n";
    return *this;
}

void Exposition::write_sample(std::string_view value, Labels labels) {
    if (current_.empty()) throw std::logic_error("metrics: sample before any family");
    text_ += current_;
    if (labels.size() > 0) {
        text_ += '{';
        bool first = true;
        for (const auto& [k, v] : labels) {
            if (!valid_label_name(k)) throw std::invalid_argument("metrics: invalid label name \"" + std::string(k) + "\"");
            if (!first) text_ += ',';
            first = false;
            text_ += k;
            text_ += "=\"";
            text_ += escape_label_value(v);
            text_ += '"';
        }
        text_ += '}';
    }
    text_ += ' ';
    text_ += value;
    text_ += '\n';
}

Exposition& Exposition::sample(double value, Labels labels) {
    if (current_type_ == MetricType::counter && !(std::isfinite(value) && value >= 0))
        throw std::invalid_argument("metrics: counter \"" + current_ + "\" must be finite and >= 0");
    write_sample(format_value(value), labels);
    return *this;
}

Exposition& Exposition::sample(std::uint64_t value, Labels labels) {
    write_sample(std::to_string(value), labels);
    return *this;
}

Exposition& Exposition::gauge(std::string_view name, std::string_view help, double value) {
    return family(name, MetricType::gauge, help).sample(value);
}

Exposition& Exposition::counter(std::string_view name, std::string_view help, std::uint64_t value) {
    return family(name, MetricType::counter, help).sample(value);
}

// -------------------------------------------------------------------------------------------------------

void RateMeter::observe(double t_s, double count) {
    if (!points_.empty() && t_s - points_.back().first < window_s_ / 20.0) return;
    points_.emplace_back(t_s, count);
    // Keep one point at least a window old as the reference; drop the older ones.
    while (points_.size() >= 2 && points_[1].first <= t_s - window_s_) points_.pop_front();
}

double RateMeter::rate(double t_now_s, double count_now) const {
    if (points_.empty()) return 0.0;
    auto ref = points_.front();
    for (const auto& p : points_) {
        if (p.first > t_now_s - window_s_) break;
        ref = p;
    }
    const double dt = t_now_s - ref.first;
    if (!(dt >= 0.5)) return 0.0;
    return std::max(0.0, count_now - ref.second) / dt;
}

// -------------------------------------------------------------------------------------------------------

void write_bench_metrics(Exposition& out, const BenchSnapshot& s) {
    out.family("cellbench_build_info", MetricType::gauge, "Always 1; the labels say which cellbenchd this is.");
    out.sample(1.0, {{"version", s.version}, {"git", s.git}});
    out.gauge("cellbench_uptime_seconds", "Seconds since cellbenchd started.", s.uptime_s);

    // Instruments.
    out.family("cellbench_instrument_connected", MetricType::gauge,
               "1 when the instrument is connected and delivering readings, else 0.");
    for (const auto& i : s.instruments)
        out.sample(i.state == "connected" ? 1.0 : 0.0,
                   {{"instrument", i.name}, {"kind", i.kind}, {"mode", i.simulated ? "simulated" : "real"}});
    out.family("cellbench_instrument_state", MetricType::gauge,
               "Instrument state: 1 for the current state (connected, connecting, offline, error), 0 for the others.");
    for (const auto& i : s.instruments)
        for (auto st : kInstrumentStates) out.sample(i.state == st ? 1.0 : 0.0, {{"instrument", i.name}, {"state", st}});
    out.family("cellbench_instrument_faults_total", MetricType::counter,
               "Faults reported by or about the instrument (lost connection, timeout, malformed frame, alarm, ...).");
    for (const auto& i : s.instruments) out.sample(i.faults, {{"instrument", i.name}});
    out.family("cellbench_instrument_reconnects_total", MetricType::counter,
               "Times the instrument came back (connected again after having been connected).");
    for (const auto& i : s.instruments) out.sample(i.reconnects, {{"instrument", i.name}});
    out.family("cellbench_instrument_lost_frames_total", MetricType::counter,
               "Frames lost: DAQ CAN frame counter gaps; cycler answers that never came or did not parse.");
    for (const auto& i : s.instruments)
        if (i.lost_frames) out.sample(*i.lost_frames, {{"instrument", i.name}});
    bool any_sim = false;
    for (const auto& i : s.instruments) any_sim = any_sim || i.sim_requests.has_value();
    if (any_sim) {
        out.family("cellbench_sim_requests_total", MetricType::counter,
                   "Requests answered by the simulated instruments hosted by cellbenchd (server side).");
        for (const auto& i : s.instruments)
            if (i.sim_requests) out.sample(*i.sim_requests, {{"instrument", i.name}});
    }

    // DAQ CAN stream.
    if (s.daq_stream) {
        const auto& d = *s.daq_stream;
        out.counter("cellbench_daq_can_frames_total", "CAN frames of the DEWE-43A layout accepted.", d.frames);
        out.counter("cellbench_daq_can_lost_frames_total", "CAN frames lost (gaps in the per-frame counters).",
                    d.lost_frames);
        out.counter("cellbench_daq_can_duplicate_frames_total", "CAN frames repeating their previous counter.",
                    d.duplicates);
        out.counter("cellbench_daq_can_garbage_frames_total",
                    "Records that are not frames of the layout (wrong size or length, unknown id, remote/error).",
                    d.garbage);
        out.counter("cellbench_daq_can_resyncs_total", "Counter restarts of the DAQ stream (DAQ restarted).", d.resyncs);
        out.counter("cellbench_daq_samples_total", "Complete DAQ samples decoded.", d.samples);
        out.counter("cellbench_daq_lost_samples_total", "DAQ samples lost (counter gaps and incomplete samples).",
                    d.lost_samples);
    }

    // Run store: ingestion and the writer.
    if (s.store) {
        const auto& st = *s.store;
        out.family("cellbench_samples_ingested_total", MetricType::counter,
                   "Samples of the active run accepted into the run store's writer queue, by source.");
        out.sample(st.cycler_samples_accepted, {{"source", "cycler"}});
        out.sample(st.daq_samples_accepted, {{"source", "daq"}});
        out.sample(st.chamber_samples_accepted, {{"source", "chamber"}});
        out.family("cellbench_samples_ingested_per_second", MetricType::gauge,
                   "Samples per second accepted into the run store over the last ~10 s, by source.");
        out.sample(st.cycler_samples_per_s, {{"source", "cycler"}});
        out.sample(st.daq_samples_per_s, {{"source", "daq"}});
        out.sample(st.chamber_samples_per_s, {{"source", "chamber"}});
        out.gauge("cellbench_store_queue_samples", "Samples waiting in the writer queue or being written now.",
                  static_cast<double>(st.samples_queued));
        out.family("cellbench_store_batches_total", MetricType::counter, "Writer transactions, by result.");
        out.sample(st.batches, {{"result", "committed"}});
        out.sample(st.failed_batches, {{"result", "failed"}});
        out.gauge("cellbench_store_last_batch_seconds", "Duration of the writer's last commit.", st.last_batch_ms / 1e3);
        out.counter("cellbench_store_samples_written_total", "Samples committed to the database.", st.samples_written);
        out.counter("cellbench_store_samples_dropped_total", "Samples refused (writer queue full or no time stamp).",
                    st.samples_dropped);
        out.counter("cellbench_store_samples_lost_total", "Samples of failed transactions.", st.samples_lost);
    }

    // The run.
    out.gauge("cellbench_run_active", "1 while a run is active (running or paused).", s.run && s.run->active ? 1.0 : 0.0);
    if (s.run) {
        const auto& r = *s.run;
        const std::string id = std::to_string(r.id);
        out.family("cellbench_run_state", MetricType::gauge,
                   "State of the latest run: 1 for its state (the API's run states), 0 for the others.");
        for (auto st : kRunStates) out.sample(r.state == st ? 1.0 : 0.0, {{"run", id}, {"state", st}});
        out.gauge("cellbench_run_id", "Id of the latest run.", static_cast<double>(r.id));
        if (r.step_index) out.gauge("cellbench_run_step", "1-based index of the active run's current step.", *r.step_index);
        if (r.step_count) out.gauge("cellbench_run_steps", "Number of steps of the active run's program.", *r.step_count);
    }

    // Latest readings (absent until an instrument has delivered one).
    auto live = [&](std::string_view name, std::string_view help, double v) {
        if (std::isfinite(v)) out.gauge(name, help, v);
    };
    live("cellbench_cell_voltage_volts", "Cell terminal voltage.", s.voltage_v);
    live("cellbench_cell_current_amperes", "Cell current, positive when charging.", s.current_a);
    live("cellbench_cell_surface_celsius", "Cell surface temperature.", s.surface_c);
    live("cellbench_chamber_air_celsius", "Chamber air temperature.", s.ambient_c);
    live("cellbench_cell_soc_ratio", "State of charge of the active run (Coulomb count, 0..1).", s.soc);
}

std::string format_bench_metrics(const BenchSnapshot& snapshot) {
    Exposition out;
    write_bench_metrics(out, snapshot);
    return out.text();
}

}  // namespace cellbench::daemon::metrics
