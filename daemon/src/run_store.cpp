// SQLite run store: see run_store.hpp for the threading, durability and failure model. The store is split by
// responsibility:
//   run_store.cpp          enumerations, records and their JSON (this file)
//   run_store_sql.*        thin sqlite3 wrappers shared by the pieces (internal)
//   run_store_schema.cpp   tables, indexes, rollups, the file's identity (the schema is documented there)
//   run_store_impl.hpp     RunStore::Impl: writer queue and thread, reader pool (internal)
//   run_store_writer.cpp   the writer thread, open/close and the calls that queue writes
//   run_store_queries.cpp  read queries (runs, steps, events, fits, sample windows and rows)
//   run_store_export.cpp   a run as a Recording (BDF export, fit replay)
#include "cellbench/daemon/run_store.hpp"

#include "cellbench/estimator/plausibility.hpp"

#include <cmath>

namespace cellbench::daemon {

using nlohmann::json;

namespace {

json nullable(double v) { return std::isfinite(v) ? json(v) : json(nullptr); }

json rc_json(const estimator::RcValues& v) {
    if (!std::isfinite(v.r0_ohm) && !std::isfinite(v.r1_ohm) && !std::isfinite(v.r2_ohm)) return nullptr;
    return {{"r0_ohm", v.r0_ohm}, {"r1_ohm", v.r1_ohm}, {"c1_f", v.c1_f}, {"r2_ohm", v.r2_ohm}, {"c2_f", v.c2_f}};
}

json sd_json(const estimator::RcValues& s) {
    return {{"r0_ohm", nullable(s.r0_ohm)}, {"r1_ohm", nullable(s.r1_ohm)}, {"c1_f", nullable(s.c1_f)},
            {"r2_ohm", nullable(s.r2_ohm)}, {"c2_f", nullable(s.c2_f)}};
}

estimator::RcValues sd_from_json(const json& j) {
    auto get = [&](const char* k) { return j.is_object() && j.contains(k) && j[k].is_number() ? j[k].get<double>() : kNaN; };
    return {get("r0_ohm"), get("r1_ohm"), get("c1_f"), get("r2_ohm"), get("c2_f")};
}

// A direction of GET /runs/{id}/fits: the values, "<name>_sd" for each and "flags" for those that are
// implausible, uncertain or at a bound (estimator/plausibility.hpp), so nothing flagged reads as fine.
json rc_json(const estimator::RcValues& v, const estimator::RcValues& sd, bool tau_at_bound) {
    json j = rc_json(v);
    if (j.is_null()) return j;
    const json s = sd_json(sd);
    for (const auto& [k, x] : s.items()) j[k + "_sd"] = x;
    json flags = json::object();
    for (auto& [name, f] : estimator::rc_flags(v, sd, tau_at_bound)) flags[name] = std::move(f);
    j["flags"] = std::move(flags);
    return j;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Enumerations

std::string_view to_string(RunState state) {
    switch (state) {
        case RunState::starting: return "starting";
        case RunState::running: return "running";
        case RunState::paused: return "paused";
        case RunState::completed: return "completed";
        case RunState::stopped: return "stopped";
        case RunState::aborted: return "aborted";
        case RunState::interrupted: return "interrupted";
    }
    return "running";
}

std::optional<RunState> run_state_from_string(std::string_view text) {
    for (auto s : {RunState::starting, RunState::running, RunState::paused, RunState::completed, RunState::stopped,
                   RunState::aborted, RunState::interrupted})
        if (text == to_string(s)) return s;
    return std::nullopt;
}

bool is_terminal(RunState state) {
    return state == RunState::completed || state == RunState::stopped || state == RunState::aborted ||
           state == RunState::interrupted;
}

std::string_view to_string(EventLevel level) {
    switch (level) {
        case EventLevel::info: return "info";
        case EventLevel::warning: return "warning";
        case EventLevel::error: return "error";
    }
    return "info";
}

std::optional<EventLevel> event_level_from_string(std::string_view text) {
    for (auto l : {EventLevel::info, EventLevel::warning, EventLevel::error})
        if (text == to_string(l)) return l;
    return std::nullopt;
}

std::string_view to_string(StoreFaultKind kind) {
    switch (kind) {
        case StoreFaultKind::disk_full: return "disk_full";
        case StoreFaultKind::busy: return "busy";
        case StoreFaultKind::readonly: return "readonly";
        case StoreFaultKind::io_error: return "io_error";
        case StoreFaultKind::corrupt: return "corrupt";
        case StoreFaultKind::overflow: return "overflow";
        case StoreFaultKind::closed: return "closed";
        case StoreFaultKind::other: return "other";
    }
    return "other";
}

std::size_t SourceWindow::channel(std::string_view name) const {
    for (std::size_t i = 0; i < channels.size(); ++i)
        if (channels[i] == name) return i;
    return static_cast<std::size_t>(-1);
}

const SourceWindow* SampleWindow::source(std::string_view name) const {
    for (const auto& s : sources)
        if (s.source == name) return &s;
    return nullptr;
}

PulseFitRecord pulse_fit_record(RunId run_id, int pulse_set, double t_s, double unix_s, const estimator::PulseSetFit& fit) {
    PulseFitRecord r;
    r.run_id = run_id;
    r.pulse_set = pulse_set;
    r.t_s = t_s;
    r.unix_s = unix_s;
    r.soc = fit.soc;
    r.ocv_v = fit.ocv_v;
    r.temperature_c = fit.temperature_c;
    r.discharge = estimator::to_rc_values(fit.chosen_discharge());
    r.charge = estimator::to_rc_values(fit.chosen_charge());
    r.method = estimator::to_string(fit.chosen);
    const bool joint = fit.chosen == estimator::PulseSetFit::Method::Joint;
    r.rms_v = joint ? fit.joint_rms_v : fit.thesis_rms_v;
    // The per-segment thesis fits give no covariance: their values carry no sigma (null), never a made-up one.
    if (joint) {
        r.discharge_sd = estimator::rc_sigma(fit.joint_discharge, fit.joint_discharge_sigma);
        r.charge_sd = estimator::rc_sigma(fit.joint_charge, fit.joint_charge_sigma);
    }
    r.tau_at_bound = joint ? fit.joint_at_bound : fit.thesis_at_bound;
    auto method_json = [](const estimator::Rc2Params<double>& d, const estimator::Rc2Params<double>& c, double rms, bool at_bound) {
        return json{{"discharge", rc_json(estimator::to_rc_values(d))},
                    {"charge", rc_json(estimator::to_rc_values(c))},
                    {"rms_v", nullable(rms)},
                    {"at_bound", at_bound}};
    };
    r.detail = {
        {"thesis", method_json(fit.thesis_discharge, fit.thesis_charge, fit.thesis_rms_v, fit.thesis_at_bound)},
        {"joint", method_json(fit.joint_discharge, fit.joint_charge, fit.joint_rms_v, fit.joint_at_bound)},
        {"joint_fit_rms_v", nullable(fit.joint_fit_rms_v)},
        {"joint_converged", fit.joint_converged},
        {"joint_ocv_offset_v", nullable(fit.joint_ocv_offset_v)},
        {"r0_steps", {{"ab_ohm", nullable(fit.r0.ab_ohm)}, {"cd_ohm", nullable(fit.r0.cd_ohm)},
                      {"ef_ohm", nullable(fit.r0.ef_ohm)}, {"gh_ohm", nullable(fit.r0.gh_ohm)},
                      {"discharge_sampling_corrected_ohm", nullable(fit.r0.discharge_corrected_ohm)},
                      {"charge_sampling_corrected_ohm", nullable(fit.r0.charge_corrected_ohm)}}},
        {"rows", {fit.begin, fit.end}},
        {"form", estimator::to_string(fit.pulse_set.form)},
        {"warnings", fit.warnings},
        {"chosen_sd", {{"discharge", sd_json(r.discharge_sd)}, {"charge", sd_json(r.charge_sd)}}},
    };
    return r;
}

void PulseFitRecord::restore_from_detail() {
    if (!detail.is_object()) return;
    if (const auto it = detail.find("chosen_sd"); it != detail.end() && it->is_object()) {
        discharge_sd = sd_from_json(it->value("discharge", json()));
        charge_sd = sd_from_json(it->value("charge", json()));
    }
    if (const auto it = detail.find(method); it != detail.end() && it->is_object())
        tau_at_bound = it->value("at_bound", false);
}

// ---------------------------------------------------------------------------------------------------------
// JSON

json to_json(const RunInfo& r) {
    json j = {{"id", r.id},
              {"program", r.program},
              {"cell", r.cell},
              {"state", std::string(to_string(r.state))},
              {"created_unix_s", r.created_unix_s},
              {"started_unix_s", r.started_unix_s ? json(*r.started_unix_s) : json(nullptr)},
              {"ended_unix_s", r.ended_unix_s ? json(*r.ended_unix_s) : json(nullptr)},
              {"reason", r.reason.empty() ? json(nullptr) : json(r.reason)},
              {"samples", r.cycler_samples + r.daq_samples + r.chamber_samples},
              {"samples_by_source", {{"cycler", r.cycler_samples}, {"daq", r.daq_samples}, {"chamber", r.chamber_samples}}}};
    if (!r.config.is_null()) j["config"] = r.config;
    return j;
}

json to_json(const EventRecord& e) {
    return {{"id", e.id},
            {"run_id", e.run_id ? json(*e.run_id) : json(nullptr)},
            {"time_unix_s", e.unix_s},
            {"test_time_s", e.t_s ? json(*e.t_s) : json(nullptr)},
            {"level", std::string(to_string(e.level))},
            {"kind", e.kind},
            {"step", e.step ? json(*e.step) : json(nullptr)},
            {"message", e.message},
            {"detail", e.detail}};
}

json to_json(const PulseFitRecord& f) {
    return {{"pulse_set", f.pulse_set},
            {"test_time_s", nullable(f.t_s)},
            {"time_unix_s", nullable(f.unix_s)},
            {"soc", nullable(f.soc)},
            {"ocv_v", nullable(f.ocv_v)},
            {"temperature_c", nullable(f.temperature_c)},
            {"discharge", rc_json(f.discharge, f.discharge_sd, f.tau_at_bound)},
            {"charge", rc_json(f.charge, f.charge_sd, f.tau_at_bound)},
            {"method", f.method},
            {"rms_v", nullable(f.rms_v)}};
}

json to_json(const SampleWindow& w) {
    json sources = json::object();
    for (const auto& s : w.sources) {
        json series = json::object();
        for (std::size_t c = 0; c < s.channels.size(); ++c) {
            auto arr = [](const std::vector<double>& v) {
                json a = json::array();
                for (double x : v) a.push_back(nullable(x));
                return a;
            };
            if (w.decimated) series[s.channels[c]] = {{"min", arr(s.min[c])}, {"max", arr(s.max[c])}};
            else series[s.channels[c]] = arr(s.min[c]);
        }
        json o = {{"time_s", s.time_s}, {"series", std::move(series)}};
        if (w.decimated) {
            o["bucket"] = s.bucket;
            o["count"] = s.count;
        }
        sources[s.source] = std::move(o);
    }
    return {{"run_id", w.run_id},
            {"from_s", nullable(w.from_s)},
            {"to_s", nullable(w.to_s)},
            {"max_points", w.max_points},
            {"decimated", w.decimated},
            {"bucket_s", w.decimated ? json(w.bucket_s) : json(nullptr)},
            {"sources", std::move(sources)}};
}

}  // namespace cellbench::daemon