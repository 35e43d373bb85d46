// Handlers of the runs resource: POST /runs, GET /runs/{id}/samples and the streamed BDF export.
#include "http_internal.hpp"

#include <charconv>
#include <cmath>
#include <stdexcept>

#include "cellbench/protocol/json_input.hpp"

namespace cellbench::daemon::http_detail {

// The request body as a JSON object into `body`, else the 400 reply saying what was expected (`example`).
std::optional<Reply> Router::json_object_body(const std::string& example, nlohmann::json& body) {
    if (req_.body().empty()) return error(http::status::bad_request, "empty request body: " + example);
    // Bounded nesting; a number beyond a double (1e999, which nlohmann reports as out_of_range, not as a
    // parse error) is a 400 like any other bad JSON.
    if (protocol::json_nesting_depth(req_.body(), kMaxBodyDepth) > kMaxBodyDepth)
        return error(http::status::bad_request, "request body nested deeper than " +
                                                    std::to_string(kMaxBodyDepth) + " levels: " + example);
    try {
        body = nlohmann::json::parse(req_.body());
    } catch (const nlohmann::json::parse_error& e) {
        return error(http::status::bad_request, "invalid JSON at byte " + std::to_string(e.byte) + ": " + example);
    } catch (const nlohmann::json::exception& e) {
        std::string what = e.what();
        if (const auto p = what.find("] "); p != std::string::npos) what = what.substr(p + 2);
        return error(http::status::bad_request, "invalid JSON (" + what.substr(0, 120) + "): " + example);
    }
    if (!body.is_object()) return error(http::status::bad_request, "request body: " + example);
    return std::nullopt;
}

Reply Router::start_run() {
    const std::string example = R"(expected a JSON object like {"program": "hppc", "cell": "p45b"})";
    nlohmann::json body;
    if (auto bad = json_object_body(example, body)) return std::move(*bad);
    StartRequest sr;
    for (const auto& [key, out] : {std::pair<const char*, std::string*>{"program", &sr.program},
                                   std::pair<const char*, std::string*>{"cell", &sr.cell}}) {
        const auto it = body.find(key);
        if (it == body.end() || !it->is_string() || it->get_ref<const std::string&>().empty())
            return error(http::status::bad_request,
                         std::string("\"") + key + "\": expected a non-empty string (a file name under config/)");
        *out = it->get<std::string>();
        if (!valid_name(*out))
            return error(http::status::bad_request,
                         std::string("\"") + key + "\": \"" + *out +
                             "\" is not a plain name (letters, digits, '.', '_', '-'; no paths)");
    }
    if (const auto it = body.find("parameters"); it != body.end() && !it->is_null()) {
        if (!it->is_object())
            return error(http::status::bad_request,
                         "\"parameters\": expected an object of overrides of the program's declared parameters, "
                         "like {\"c_rate\": 2}");
        for (const auto& [k, v] : it->items()) sr.parameters[k] = v;
    }
    sr.body = std::move(body);
    return call([&] {
        auto run = st_.backend.start_run(sr);
        Reply r = json(http::status::created, run);
        if (run.is_object() && run.contains("id") && run["id"].is_number_integer())
            r.res.set(http::field::location,
                      std::string(kApiPrefix) + "/runs/" + std::to_string(run["id"].get<RunId>()));
        return r;
    });
}

Reply Router::samples(RunId id, std::string_view query) {
    SampleQuery sq;
    sq.max_points = kDefaultSamplePoints;
    const auto params = query_params(query);
    if (!params) return error(http::status::bad_request, "malformed query string");
    for (const auto& [key, value] : *params) {
        if (key == "from" || key == "to") {
            double v = 0;
            const auto [p, ec] = std::from_chars(value.data(), value.data() + value.size(), v);
            if (value.empty() || ec != std::errc() || p != value.data() + value.size() || !std::isfinite(v))
                return error(http::status::bad_request,
                             "\"" + key + "\": expected a number of seconds of test time, got \"" + value + "\"");
            (key == "from" ? sq.from_s : sq.to_s) = v;
        } else if (key == "max_points") {
            std::size_t v = 0;
            const auto [p, ec] = std::from_chars(value.data(), value.data() + value.size(), v);
            if (value.empty() || ec != std::errc() || p != value.data() + value.size() || v < 1 || v > kMaxSamplePoints)
                return error(http::status::bad_request, "\"max_points\": expected an integer from 1 to " +
                                                            std::to_string(kMaxSamplePoints) + ", got \"" + value + "\"");
            sq.max_points = v;
        }
        // Other parameters are ignored (room for later options).
    }
    if (sq.from_s && sq.to_s && *sq.from_s > *sq.to_s)
        return error(http::status::bad_request, "\"from\" is after \"to\"");
    // A bounded number at once: more readers would only queue on the database's reader pool.
    struct Slot {
        std::atomic<std::size_t>& n;
        bool held;
        ~Slot() {
            if (held) n.fetch_sub(1);
        }
    } slot{st_.sample_reads, st_.sample_reads.fetch_add(1) < st_.opt.max_concurrent_sample_reads};
    if (!slot.held) {
        st_.sample_reads.fetch_sub(1);
        Reply r = error(http::status::service_unavailable,
                        "busy: " + std::to_string(st_.opt.max_concurrent_sample_reads) +
                            " sample reads are being served; retry in a second");
        r.res.set(http::field::retry_after, "1");
        return r;
    }
    return call([&] { return json_text(http::status::ok, *st_.backend.samples_body(id, sq)); });
}

Reply Router::export_csv(RunId id) {
    return call([&] {
        Reply r;
        r.cursor = st_.backend.export_bdf_csv(id);
        if (!r.cursor) throw std::runtime_error("backend returned no export cursor");
        r.res.result(http::status::ok);
        r.res.set(http::field::content_type, "text/csv; charset=utf-8");
        r.res.set(http::field::content_disposition,
                  "attachment; filename=\"run-" + std::to_string(id) + ".bdf.csv\"");
        return r;
    });
}

}  // namespace cellbench::daemon::http_detail
