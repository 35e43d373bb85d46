// The REST API's answers (ApiBackend): health, runs and their records, diagnosis jobs, cells. GET /status
// and GET /metrics: bench_daemon_status.cpp.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>
#include <fstream>
#include <sstream>

#include "cellbench/estimator/diagnose.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

namespace cellbench::daemon {

json BenchDaemon::health() {
    std::lock_guard l(impl_->live_m);
    const bool db_ok = impl_->db_writable_again();
    const bool ok = impl_->instruments.all_connected() && db_ok;
    json j = {{"status", ok ? "ok" : "degraded"},
              {"version", kVersion},
              {"uptime_s", std::chrono::duration<double>(SteadyClock::now() - impl_->started_at).count()},
              {"database", {{"writable", db_ok}}}};
    if (!db_ok) j["database"]["detail"] = impl_->db_fault;
    return j;
}

json BenchDaemon::list_runs() {
    json runs = json::array();
    for (const auto& r : impl_->store->list_runs()) runs.push_back(impl_->run_json(r));
    return {{"runs", std::move(runs)}};
}

json BenchDaemon::get_run(RunId id) { return impl_->run_json(id); }

namespace {
json samples_answer(RunStore& store, RunId id, std::optional<double> from_s, std::optional<double> to_s,
                    std::size_t max_points);

// The query as the store reads it: a range in order, max_points within the API's bounds.
std::size_t checked_max_points(const SampleQuery& q) {
    if (q.from_s && q.to_s && *q.from_s > *q.to_s) throw BadRequest("from must not be after to");
    return std::clamp<std::size_t>(q.max_points, 2, kMaxSamplePoints);
}
}  // namespace

json BenchDaemon::samples(RunId id, const SampleQuery& q) {
    return samples_answer(*impl_->store, id, q.from_s, q.to_s, checked_max_points(q));
}

std::shared_ptr<const std::string> BenchDaemon::samples_body(RunId id, const SampleQuery& q) {
    const std::size_t max_points = checked_max_points(q);
    const SampleAnswerCache::Key key{id, q.from_s, q.to_s, max_points};
    const std::uint64_t version = impl_->store->commit_count();  // before the reads
    if (auto hit = impl_->sample_answers.find(key, version)) return hit;
    auto body = std::make_shared<const std::string>(
        api_json_text(samples_answer(*impl_->store, id, q.from_s, q.to_s, max_points)));
    impl_->sample_answers.put(key, version, body);
    return body;
}

namespace {
json samples_answer(RunStore& store, RunId id, std::optional<double> from_s, std::optional<double> to_s,
                    std::size_t max_points) {
    existing_run(store, id);
    const auto w = store.samples(id, from_s, to_s, max_points);
    // The API's shape: one time base (the cycler's, or the bucket grid) with every series on it; DAQ and
    // chamber values are the latest at or before each point (raw), or the bucket's min/max (decimated).
    json j = {{"run_id", id}, {"from_s", nullable(w.from_s)}, {"to_s", nullable(w.to_s)},
              {"max_points", max_points}, {"decimated", w.decimated}};
    const SourceWindow* base = w.source("cycler");
    if (!base && !w.sources.empty()) base = &w.sources.front();
    json series = json::object();
    std::vector<double> time_s = base ? base->time_s : std::vector<double>{};
    struct Map {
        const char* source;
        const char* channel;
        const char* api;
    };
    static const Map maps[] = {{"cycler", "voltage_v", "voltage_v"}, {"cycler", "current_a", "current_a"},
                               {"cycler", "soc", "soc"},             {"daq", "surface_c", "surface_c"},
                               {"chamber", "ambient_c", "ambient_c"}, {"daq", "t1_c", "t1_c"},
                               {"daq", "t2_c", "t2_c"},              {"daq", "heat_flux_w_per_m2", "heat_flux_w_per_m2"}};
    if (w.decimated) {
        j["bucket_s"] = w.bucket_s;
        // Buckets of the base source; other sources looked up by bucket index.
        for (const auto& m : maps) {
            const SourceWindow* s = w.source(m.source);
            if (!s || !base) continue;
            const std::size_t ch = s->channel(m.channel);
            if (ch == std::string::npos) continue;
            std::map<std::int64_t, std::size_t> at;
            for (std::size_t k = 0; k < s->bucket.size(); ++k) at[s->bucket[k]] = k;
            json mn = json::array(), mx = json::array();
            for (std::size_t k = 0; k < base->bucket.size(); ++k) {
                const auto it = at.find(base->bucket[k]);
                mn.push_back(it == at.end() ? json(nullptr) : nullable(s->min[ch][it->second]));
                mx.push_back(it == at.end() ? json(nullptr) : nullable(s->max[ch][it->second]));
            }
            series[m.api] = {{"min", std::move(mn)}, {"max", std::move(mx)}};
        }
    } else {
        // Each point carries the source's sample in (previous point, this point] that departs most from the
        // value shown before, so a DAQ spike between two cycler rows survives (the DAQ may sample faster).
        for (const auto& m : maps) {
            const SourceWindow* s = w.source(m.source);
            if (!s || !base) continue;
            const std::size_t ch = s->channel(m.channel);
            if (ch == std::string::npos) continue;
            const auto& values = s->min[ch];
            json v = json::array();
            std::size_t k = 0;  // next source sample not yet consumed
            double shown = kNaN;
            for (double t : time_s) {
                std::optional<std::size_t> pick;
                for (; k < s->time_s.size() && s->time_s[k] <= t + 1e-9; ++k) {
                    if (!std::isfinite(values[k])) continue;
                    if (!pick || !std::isfinite(shown) ||
                        std::abs(values[k] - shown) > std::abs(values[*pick] - shown))
                        pick = k;
                }
                if (!pick && k > 0 && std::isfinite(values[k - 1])) pick = k - 1;  // slower source: latest sample
                if (pick) shown = values[*pick];
                v.push_back(pick ? nullable(values[*pick]) : json(nullptr));
            }
            series[m.api] = std::move(v);
        }
    }
    j["time_s"] = time_s;
    j["series"] = std::move(series);
    return j;
}
}  // namespace

json BenchDaemon::events(RunId id) {
    existing_run(*impl_->store, id);
    json ev = json::array();
    for (const auto& e : impl_->store->events(id)) {
        json x = to_json(e);
        // The API's levels are info/warning/error.
        ev.push_back(std::move(x));
    }
    return {{"run_id", id}, {"events", std::move(ev)}};
}

json BenchDaemon::steps(RunId id) {
    existing_run(*impl_->store, id);
    json out = json::array();
    for (const auto& s : impl_->store->steps(id)) {
        auto opt = [](const std::optional<double>& v) { return v && std::isfinite(*v) ? json(*v) : json(nullptr); };
        out.push_back({{"index", s.index}, {"segment", s.segment}, {"step_id", s.step_id}, {"cycle", s.cycle},
                       {"type", s.type}, {"started_s", s.started_t_s}, {"ended_s", opt(s.ended_t_s)},
                       {"capacity_ah", opt(s.capacity_ah)}, {"energy_wh", opt(s.energy_wh)},
                       {"end_reason", s.end_reason}});
    }
    return {{"run_id", id}, {"steps", std::move(out)}};
}

json BenchDaemon::fits(RunId id) {
    existing_run(*impl_->store, id);
    json f = json::array();
    for (const auto& r : impl_->store->pulse_fits(id)) f.push_back(to_json(r));
    return {{"run_id", id}, {"fits", std::move(f)}};
}

std::unique_ptr<ExportCursor> BenchDaemon::export_bdf_csv(RunId id) {
    existing_run(*impl_->store, id);
    const Recording rec = impl_->store->export_recording(id);
    std::ostringstream out;
    protocol::write_bdf_csv(out, rec);
    return std::make_unique<StringExportCursor>(out.str());
}

// ---- diagnosis jobs (api.hpp "Diagnosis jobs"; the work is in diagnose_jobs.cpp and the estimator).
namespace {

json read_json(const std::filesystem::path& path) {
    std::ifstream in(path);
    if (!in) throw InputError(path.string() + ": cannot read");
    std::stringstream text;
    text << in.rdbuf();
    return protocol::parse_json_input(text.str(), path.string());
}

// A parameter set as the diagnosis requests name it: config/cells/NAME.json, a cellbench.params/1 file, or a
// cell (cellbench.cell/1) standing for the parameter set its "params" names. Returns it and the file's stem.
std::pair<estimator::ParameterSet, std::string> load_named_params(const std::filesystem::path& config_dir,
                                                                  const std::string& name) {
    const auto where = (config_dir / "cells").string();
    try {
        const auto file = cell_file(config_dir, name);
        std::error_code ec;
        if (!std::filesystem::is_regular_file(file, ec))
            throw BadRequest("\"params\": no parameter set \"" + name + "\" in " + where +
                             " (GET /api/v1/cells lists them)");
        const json j = read_json(file);
        if (j.is_object() && j.contains("schema") && j["schema"] == "cellbench.cell/1") {
            const CellConfig cell = load_cell_config(file);
            if (!cell.params_path)
                throw BadRequest("\"params\": cell \"" + name + "\" names no parameter set (its \"params\"); name one in " +
                                 where);
            return {load_param_file(*cell.params_path), cell.params_path->stem().string()};
        }
        return {estimator::ParameterSet::from_json(j, file.string()), file.stem().string()};
    } catch (const InputError& e) {
        throw BadRequest(std::string("\"params\": ") + e.what());
    }
}

void check_effects(const std::vector<std::string>& effects) {
    const auto& cat = estimator::effect_catalogue();
    for (const auto& e : effects)
        if (std::find(cat.begin(), cat.end(), e) == cat.end()) {
            std::string list;
            for (const auto& c : cat) list += (list.empty() ? "" : ", ") + c;
            throw BadRequest("\"effects\": unknown effect id \"" + e + "\" (known: " + list + ")");
        }
}

}  // namespace

json BenchDaemon::diagnose_run(RunId id, const DiagnoseRequest& request) {
    auto& d = *impl_;
    const json run = d.run_json(id);  // NotFound
    if (run["outcome"].is_null())  // not ended: any live state
        throw Conflict("run " + std::to_string(id) + " is still " + run.value("state", "live") +
                       "; diagnose it once it has ended");
    check_effects(request.effects);
    estimator::ParameterSet params;
    std::string used;
    if (request.params == "run") {
        const auto fitted = d.store->latest_parameter_set(id);
        if (!fitted)
            throw BadRequest("\"params\": \"run\": run " + std::to_string(id) +
                             " has no fitted parameter set (the daemon fits one when an HPPC with enough pulse sets "
                             "ends); name a parameter set under " + (d.cfg.config_dir / "cells").string() + " instead");
        try {
            params = estimator::ParameterSet::from_json(fitted->params, "run " + std::to_string(id) + " parameter set");
        } catch (const InputError& e) {
            throw BadRequest(std::string("\"params\": \"run\": ") + e.what());
        }
        used = "run " + std::to_string(id);
    } else {
        std::tie(params, used) = load_named_params(d.cfg.config_dir, request.params);
    }
    // The runs to confirm the findings on: other ended runs (a body reference, so an unknown one is a bad request).
    std::vector<RunId> confirm;
    for (const RunId c : request.confirm_runs) {
        if (c == id)
            throw BadRequest("\"confirm_runs\": run " + std::to_string(c) +
                             " is the run diagnosed; name other runs of the cell to confirm its findings on");
        if (std::find(confirm.begin(), confirm.end(), c) != confirm.end()) continue;
        json other;
        try {
            other = d.run_json(c);
        } catch (const NotFound&) {
            throw BadRequest("\"confirm_runs\": no run " + std::to_string(c));
        }
        if (other["outcome"].is_null())
            throw Conflict("\"confirm_runs\": run " + std::to_string(c) + " is still " + other.value("state", "live") +
                           "; confirm on it once it has ended");
        confirm.push_back(c);
    }
    json info = {{"source", {{"kind", "run"}, {"run_id", id}, {"program", run.value("program", "")},
                             {"cell", run.value("cell", "")}}},
                 {"params", request.params},
                 {"params_used", used}};
    if (!confirm.empty()) info["confirm_runs"] = confirm;
    RunStore* store = d.store.get();
    return d.diagnoses->submit(std::move(info), request.effects,
                               [store, id, confirm, params = std::move(params)](const std::function<void(std::string_view)>& stage) {
                                   stage("reading run " + std::to_string(id) + " from the database");
                                   DiagnoseInput in{params, store->export_recording(id), {}};
                                   in.recording.source = "run " + std::to_string(id);
                                   for (const RunId c : confirm) {
                                       stage("reading run " + std::to_string(c) + " (to confirm on) from the database");
                                       in.confirm.push_back(store->export_recording(c));
                                       in.confirm.back().source = "run " + std::to_string(c);
                                   }
                                   return in;
                               });
}

json BenchDaemon::diagnose_recording(const DiagnoseRequest& request, std::string csv) {
    auto& d = *impl_;
    if (request.params == "run")
        throw BadRequest("\"params\": \"run\" names a run's fitted parameter set; name a parameter set under " +
                         (d.cfg.config_dir / "cells").string());
    check_effects(request.effects);
    auto [params, used] = load_named_params(d.cfg.config_dir, request.params);
    std::string name = request.body.is_object() ? request.body.value("name", std::string{}) : std::string{};
    const std::string source = name.empty() ? std::string("uploaded recording") : name;
    // The header and the first rows now, for a clear 400; the whole file on the worker (it may be large).
    {
        std::size_t end = 0;
        for (int lines = 0; lines < 200 && end != std::string::npos; ++lines) {
            end = csv.find('\n', end);
            if (end != std::string::npos) ++end;
        }
        const std::string_view head = end == std::string::npos ? std::string_view(csv) : std::string_view(csv).substr(0, end);
        try {
            (void)protocol::parse_bdf_csv(head, source);
        } catch (const InputError& e) {
            throw BadRequest(std::string("not a BDF CSV recording: ") + e.what());
        }
    }
    json info = {{"source", {{"kind", "upload"}, {"bytes", csv.size()}, {"name", name}}},
                 {"params", request.params},
                 {"params_used", used}};
    return d.diagnoses->submit(
        std::move(info), request.effects,
        [csv = std::move(csv), params = std::move(params), source](const std::function<void(std::string_view)>& stage) {
            stage("parsing the recording");
            protocol::BdfReadReport report;
            DiagnoseInput in{params, protocol::parse_bdf_csv(csv, source, &report), {}};
            for (const auto& m : protocol::describe(report, source)) {
                if (m.warning)
                    spdlog::warn("diagnosis: {}", m.text);
                else
                    spdlog::info("diagnosis: {}", m.text);
            }
            if (in.recording.take_t1_as_surface())
                spdlog::info("diagnosis: {}: no Surface Temperature column: the cell temperature is read from T1", source);
            return in;
        });
}

json BenchDaemon::diagnosis(std::int64_t job) { return impl_->diagnoses->get(job); }
json BenchDaemon::list_diagnoses() { return impl_->diagnoses->list(); }

json BenchDaemon::cells() {
    const auto& dir = impl_->cfg.config_dir;
    json cells = json::array(), sets = json::array();
    for (const auto& name : list_cells(dir)) {
        json c = {{"name", name}, {"params", nullptr}};
        try {
            const CellConfig cell = load_cell_config(cell_file(dir, name));
            c["description"] = cell.name;
            if (cell.params_path) c["params"] = cell.params_path->stem().string();
        } catch (const std::exception& e) {
            c["error"] = e.what();
        }
        cells.push_back(std::move(c));
    }
    std::error_code ec;
    std::vector<std::filesystem::path> files;
    if (std::filesystem::is_directory(dir / "cells", ec))
        for (const auto& e : std::filesystem::directory_iterator(dir / "cells", ec))
            if (e.is_regular_file() && e.path().extension() == ".json") files.push_back(e.path());
    std::sort(files.begin(), files.end());
    for (const auto& f : files) {
        try {
            const json j = read_json(f);
            if (!j.is_object() || j.value("schema", "") != "cellbench.params/1") continue;
            sets.push_back({{"name", f.stem().string()}, {"cell", j.value("cell", "")},
                            {"capacity_ah", j.contains("capacity_ah") ? j["capacity_ah"] : json(nullptr)}});
        } catch (const std::exception&) {
        }
    }
    return {{"cells", std::move(cells)}, {"parameter_sets", std::move(sets)}, {"programs", list_programs(dir)}};
}

json BenchDaemon::start_run(const StartRequest& request) { return impl_->start_run(request); }
json BenchDaemon::stop_run(RunId id) { return impl_->stop_run(id); }
json BenchDaemon::pause_run(RunId id) { return impl_->pause_run(id); }
json BenchDaemon::resume_run(RunId id) { return impl_->resume_run(id); }

}  // namespace cellbench::daemon
