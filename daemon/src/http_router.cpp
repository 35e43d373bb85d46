// Routing of the REST API: every path and method of /api/v1 (openapi.json describes the same set, and
// tests/unit/openapi_test.cpp checks this file against it), the bearer-token check of mutating endpoints,
// and /metrics.
#include "http_internal.hpp"

#include "cellbench/daemon/openapi.hpp"

namespace cellbench::daemon::http_detail {

Reply Router::route() {
    const std::string_view target(req_.target().data(), req_.target().size());
    if (target.empty() || target.front() != '/')
        return error(http::status::bad_request, "request target must be a path starting with /");
    const auto q = target.find('?');
    const std::string_view path = target.substr(0, q);
    const std::string_view query = q == std::string_view::npos ? std::string_view{} : target.substr(q + 1);

    if (path == kApiPrefix || path.starts_with("/api/v1/"))
        return api(path.substr(kApiPrefix.size()), query);
    if (path == "/metrics") {
        if (!is_get()) return method_not_allowed("GET, HEAD");
        return metrics();
    }
    return static_file(path);
}

// POST /api/v1/diagnose (the one request with a large body), judged on the header alone.
bool Router::is_upload(const Request& req) {
    if (req.method() != http::verb::post) return false;
    std::string_view path(req.target().data(), req.target().size());
    path = path.substr(0, path.find('?'));
    if (path.size() > 1 && path.back() == '/') path.remove_suffix(1);
    return path == "/api/v1/diagnose";
}

Reply Router::method_not_allowed(std::string_view allow) const {
    Reply r = error(http::status::method_not_allowed,
                    "method " + method_text() + " not allowed here; allowed: " + std::string(allow));
    r.res.set(http::field::allow, beast::string_view(allow.data(), allow.size()));
    return r;
}

// Mutating endpoints: refused outright without a configured token, else Bearer TOKEN required.
std::optional<Reply> Router::check_token() const {
    if (st_.opt.token.empty())
        return error(http::status::forbidden,
                     "mutating endpoints are disabled: no API token is configured (start cellbenchd with "
                     "--token TOKEN or set CELLBENCH_TOKEN in its environment)");
    const auto header = req_[http::field::authorization];
    const std::string_view h(header.data(), header.size());
    std::string_view given;
    bool has_bearer = false;
    if (h.size() > 7 && iequals(h.substr(0, 6), "Bearer") && h[6] == ' ') {
        given = h.substr(7);
        while (!given.empty() && given.front() == ' ') given.remove_prefix(1);
        while (!given.empty() && (given.back() == ' ' || given.back() == '\t')) given.remove_suffix(1);
        has_bearer = !given.empty();
    }
    if (!has_bearer) {
        Reply r = error(http::status::unauthorized,
                        "missing bearer token: send \"Authorization: Bearer TOKEN\" (cellbench --token TOKEN "
                        "or CELLBENCH_TOKEN)");
        r.res.set(http::field::www_authenticate, "Bearer realm=\"cellbench\"");
        return r;
    }
    if (!token_equals(st_.opt.token, given)) {
        Reply r = error(http::status::unauthorized, "invalid bearer token");
        r.res.set(http::field::www_authenticate, "Bearer realm=\"cellbench\", error=\"invalid_token\"");
        return r;
    }
    return std::nullopt;
}

Reply Router::api(std::string_view rest, std::string_view query) {
    // rest is "" or "/..." ; one trailing slash is tolerated.
    if (rest.size() > 1 && rest.back() == '/') rest.remove_suffix(1);
    if (!rest.empty()) rest.remove_prefix(1);
    const auto seg = split(rest, '/');
    const auto n = seg.size();
    auto& be = st_.backend;

    if (n == 1 && (seg[0] == "health" || seg[0] == "status")) {
        if (!is_get()) return method_not_allowed("GET, HEAD");
        if (seg[0] == "health") return call([&] { return json(http::status::ok, be.health()); });
        return call([&] { return json(http::status::ok, be.status()); });
    }
    if (n == 1 && seg[0] == "runs") {
        if (is_get()) return call([&] { return json(http::status::ok, be.list_runs()); });
        if (is_post()) {
            if (auto denied = check_token()) return std::move(*denied);
            return start_run();
        }
        return method_not_allowed("GET, HEAD, POST");
    }
    if (n == 1 && seg[0] == "openapi.json") {  // daemon/src/openapi.json (openapi.hpp)
        if (!is_get()) return method_not_allowed("GET, HEAD");
        Reply r;
        r.res.set(http::field::content_type, kJson);
        r.res.body() = std::string(openapi_json());
        return r;
    }
    if (n == 1 && seg[0] == "cells") {
        if (!is_get()) return method_not_allowed("GET, HEAD");
        return call([&] { return json(http::status::ok, be.cells()); });
    }
    if (n == 1 && seg[0] == "diagnose") {
        if (!is_post()) return method_not_allowed("POST");
        if (auto denied = check_token()) return std::move(*denied);
        return diagnose_upload(query);
    }
    if (n == 1 && seg[0] == "diagnoses") {
        if (!is_get()) return method_not_allowed("GET, HEAD");
        return call([&] { return json(http::status::ok, be.list_diagnoses()); });
    }
    if (n == 2 && seg[0] == "diagnoses") {
        if (!is_get()) return method_not_allowed("GET, HEAD");
        const auto job = parse_run_id(seg[1]);
        if (!job)
            return error(http::status::not_found,
                         "no diagnosis job \"" + std::string(seg[1].substr(0, 100)) + "\" (job ids are positive integers)");
        return call([&] { return json(http::status::ok, be.diagnosis(*job)); });
    }
    if (n >= 2 && n <= 3 && seg[0] == "runs") {
        const std::string_view action = n == 3 ? seg[2] : std::string_view{};
        const bool reads = n == 2 || action == "samples" || action == "events" || action == "fits" ||
                           action == "steps" || action == "export.bdf.csv";
        const bool mutates = action == "stop" || action == "pause" || action == "resume" || action == "diagnose";
        if (!reads && !mutates) return not_found();
        if (reads && !is_get()) return method_not_allowed("GET, HEAD");
        if (mutates && !is_post()) return method_not_allowed("POST");
        if (mutates)
            if (auto denied = check_token()) return std::move(*denied);
        const auto id = parse_run_id(seg[1]);
        if (!id) return error(http::status::not_found, "no run \"" + std::string(seg[1]) + "\" (run ids are positive integers)");
        if (n == 2) return call([&] { return json(http::status::ok, be.get_run(*id)); });
        if (action == "samples") return samples(*id, query);
        if (action == "events") return call([&] { return json(http::status::ok, be.events(*id)); });
        if (action == "fits") return call([&] { return json(http::status::ok, be.fits(*id)); });
        if (action == "steps") return call([&] { return json(http::status::ok, be.steps(*id)); });
        if (action == "export.bdf.csv") return export_csv(*id);
        if (action == "stop") return call([&] { return json(http::status::ok, be.stop_run(*id)); });
        if (action == "pause") return call([&] { return json(http::status::ok, be.pause_run(*id)); });
        if (action == "diagnose") return diagnose_run(*id);
        return call([&] { return json(http::status::ok, be.resume_run(*id)); });
    }
    return not_found();
}

Reply Router::not_found() const {
    return error(http::status::not_found,
                 "no such endpoint: " + method_text() + " " + std::string(req_.target().substr(0, 200)) +
                     " (the API is under /api/v1: health, status, cells, runs, runs/{id}[/samples|events|fits|"
                     "steps|export.bdf.csv|stop|pause|resume|diagnose], diagnose, diagnoses[/{job}])");
}

Reply Router::metrics() {
    return call([&] {
        std::string text = st_.backend.metrics_text();
        if (!text.empty() && text.back() != '\n') text.push_back('\n');
        text += "# HELP cellbench_http_responses_total HTTP responses sent by cellbenchd, by status class.\n"
                "# TYPE cellbench_http_responses_total counter\n";
        for (unsigned c = 1; c <= 5; ++c)
            text += "cellbench_http_responses_total{code=\"" + std::to_string(c) + "xx\"} " +
                    std::to_string(st_.responses_by_class[c].load(std::memory_order_relaxed)) + "\n";
        text += "# HELP cellbench_http_connections_open Open HTTP connections.\n"
                "# TYPE cellbench_http_connections_open gauge\n"
                "cellbench_http_connections_open " +
                std::to_string(st_.open_connections.load()) + "\n";
        text += "# HELP cellbench_http_connections_refused_total Connections closed at once (over the limit).\n"
                "# TYPE cellbench_http_connections_refused_total counter\n"
                "cellbench_http_connections_refused_total " +
                std::to_string(st_.refused_connections.load()) + "\n";
        text += "# HELP cellbench_http_client_limited_total Requests answered 429 (a client over its per-client "
                "connection or record-read limit).\n"
                "# TYPE cellbench_http_client_limited_total counter\n"
                "cellbench_http_client_limited_total " +
                std::to_string(st_.client_limited.load()) + "\n";
        Reply r;
        r.res.result(http::status::ok);
        r.res.set(http::field::content_type, "text/plain; version=0.0.4; charset=utf-8");
        r.res.body() = std::move(text);
        return r;
    });
}

}  // namespace cellbench::daemon::http_detail
