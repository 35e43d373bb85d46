// Handlers of diagnosis jobs: POST /runs/{id}/diagnose (a stored run) and POST /diagnose (an uploaded
// recording); both answer 202 with the job to poll under /diagnoses/{job}.
#include "http_internal.hpp"

namespace cellbench::daemon::http_detail {

// A diagnosis job's reply: 202 Accepted with the job and where to poll it.
Reply Router::accepted_job(const nlohmann::json& job) {
    Reply r = json(http::status::accepted, job);
    if (job.is_object() && job.contains("id") && job["id"].is_number_integer())
        r.res.set(http::field::location,
                  std::string(kApiPrefix) + "/diagnoses/" + std::to_string(job["id"].get<std::int64_t>()));
    return r;
}

// "params" (a plain name or "run") and "effects" (strings) of a diagnosis request; an error reply if bad.
std::optional<Reply> Router::check_diagnose_request(const DiagnoseRequest& dr) {
    if (dr.params.empty())
        return error(http::status::bad_request,
                     "\"params\": expected a non-empty string: a parameter set under config/cells/ (e.g. "
                     "\"p45b-thesis\") or \"run\" (the run's own fitted parameter set)");
    if (!valid_name(dr.params))
        return error(http::status::bad_request,
                     "\"params\": \"" + dr.params.substr(0, 100) +
                         "\" is not a plain name (letters, digits, '.', '_', '-'; no paths)");
    if (dr.effects.size() > 64) return error(http::status::bad_request, "\"effects\": too many entries");
    for (const auto& e : dr.effects)
        if (!valid_name(e))
            return error(http::status::bad_request,
                         "\"effects\": \"" + e.substr(0, 100) + "\" is not an effect id (see INTERFACES.md)");
    return std::nullopt;
}

// POST /runs/{id}/diagnose {"params": NAME, "effects": [...]?, "confirm_runs": [run ids]?}
Reply Router::diagnose_run(RunId id) {
    const std::string example = R"(expected a JSON object like {"params": "p45b-thesis"} or {"params": "run"})";
    nlohmann::json body;
    if (auto bad = json_object_body(example, body)) return std::move(*bad);
    DiagnoseRequest dr;
    const auto p = body.find("params");
    if (p == body.end() || !p->is_string())
        return error(http::status::bad_request, "\"params\": expected a string: " + example);
    dr.params = p->get<std::string>();
    if (const auto e = body.find("effects"); e != body.end() && !e->is_null()) {
        if (!e->is_array())
            return error(http::status::bad_request, "\"effects\": expected an array of effect ids (strings)");
        for (const auto& x : *e) {
            if (!x.is_string())
                return error(http::status::bad_request, "\"effects\": expected an array of effect ids (strings)");
            dr.effects.push_back(x.get<std::string>());
        }
    }
    if (const auto c = body.find("confirm_runs"); c != body.end() && !c->is_null()) {
        const std::string expected = "\"confirm_runs\": expected an array of at most " + std::to_string(kMaxConfirmRuns) +
                                     " run ids (positive integers)";
        if (!c->is_array() || c->size() > kMaxConfirmRuns) return error(http::status::bad_request, expected);
        for (const auto& x : *c) {
            if (!x.is_number_integer() || x.get<std::int64_t>() <= 0) return error(http::status::bad_request, expected);
            dr.confirm_runs.push_back(x.get<std::int64_t>());
        }
    }
    if (auto bad = check_diagnose_request(dr)) return std::move(*bad);
    dr.body = std::move(body);
    return call([&] { return accepted_job(st_.backend.diagnose_run(id, dr)); });
}

// POST /diagnose?params=NAME[&effects=a,b] with a BDF CSV recording as the body.
Reply Router::diagnose_upload(std::string_view query) {
    DiagnoseRequest dr;
    dr.body = nlohmann::json::object();
    const auto params = query_params(query);
    if (!params) return error(http::status::bad_request, "malformed query string");
    for (const auto& [key, value] : *params) {
        if (key == "params") {
            dr.params = value;
        } else if (key == "effects") {
            for (const auto e : split(value, ','))
                if (!e.empty()) dr.effects.emplace_back(e);
        } else if (key == "name") {
            dr.body["name"] = value.substr(0, 200);  // the file's name, for the job's description
        }
    }
    if (dr.params.empty())
        return error(http::status::bad_request,
                     "missing ?params=NAME: the parameter set under config/cells/ to diagnose the recording with "
                     "(e.g. /api/v1/diagnose?params=p45b-thesis)");
    if (dr.params == "run")
        return error(http::status::bad_request,
                     "\"params\": \"run\" names a run's own fitted parameter set; an uploaded recording needs "
                     "a parameter set under config/cells/");
    if (auto bad = check_diagnose_request(dr)) return std::move(*bad);
    if (req_.body().size() > st_.opt.max_upload_bytes)
        return error(http::status::payload_too_large, "recording too large (limit " +
                                                          std::to_string(st_.opt.max_upload_bytes) + " bytes)");
    if (req_.body().empty())
        return error(http::status::bad_request,
                     "empty request body: expected a BDF CSV recording (header row with \"Test Time / s\", "
                     "\"Voltage / V\", \"Current / A\")");
    return call([&] { return accepted_job(st_.backend.diagnose_recording(dr, req_.body())); });
}

}  // namespace cellbench::daemon::http_detail
