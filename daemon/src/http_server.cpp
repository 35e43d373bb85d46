#include "cellbench/daemon/http_server.hpp"
#include "cellbench/daemon/http_handler.hpp"
#include "cellbench/daemon/openapi.hpp"
#include "cellbench/daemon/web_assets.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <unordered_map>
#include <utility>
#include <vector>

#include <boost/asio/dispatch.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/asio/write.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <spdlog/spdlog.h>
#include "cellbench/protocol/json_input.hpp"

namespace cellbench::daemon {

namespace beast = boost::beast;
namespace http = beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;
namespace fs = std::filesystem;

namespace {

using Request = http::request<http::string_body>;
using StringResponse = http::response<http::string_body>;

constexpr const char* kServerName = "cellbenchd";
constexpr std::string_view kApiPrefix = "/api/v1";
constexpr const char* kJson = "application/json";
constexpr std::size_t kMaxBodyDepth = 32;  // request bodies are flat objects; deeper is an attack, not a request
// After an early error response (413, 400) the client may still be sending; read and drop at most this
// much (for at most kDrainTime) before closing, so the kernel does not answer with a reset that can make
// the client lose our response.
constexpr std::size_t kDrainLimit = 4 * 1024 * 1024;
constexpr std::chrono::seconds kDrainTime{2};

std::string dump(const nlohmann::json& j) {
    // Backend strings may carry invalid UTF-8 (instrument text); replace rather than fail the response.
    return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

bool iequals(std::string_view a, std::string_view b) {
    return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), [](char x, char y) {
               return std::tolower(static_cast<unsigned char>(x)) == std::tolower(static_cast<unsigned char>(y));
           });
}

int hex_value(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

// Percent-decoding; `plus_is_space` for query strings. nullopt for a malformed escape.
std::optional<std::string> percent_decode(std::string_view s, bool plus_is_space) {
    std::string out;
    out.reserve(s.size());
    for (std::size_t i = 0; i < s.size(); ++i) {
        if (s[i] == '%') {
            if (i + 2 >= s.size()) return std::nullopt;
            const int hi = hex_value(s[i + 1]), lo = hex_value(s[i + 2]);
            if (hi < 0 || lo < 0) return std::nullopt;
            out.push_back(static_cast<char>(hi * 16 + lo));
            i += 2;
        } else if (plus_is_space && s[i] == '+') {
            out.push_back(' ');
        } else {
            out.push_back(s[i]);
        }
    }
    return out;
}

std::vector<std::string_view> split(std::string_view s, char sep) {
    std::vector<std::string_view> parts;
    std::size_t start = 0;
    while (true) {
        const auto pos = s.find(sep, start);
        parts.push_back(s.substr(start, pos == std::string_view::npos ? std::string_view::npos : pos - start));
        if (pos == std::string_view::npos) break;
        start = pos + 1;
    }
    return parts;
}

const char* mime_type(const fs::path& p) {
    static const std::unordered_map<std::string, const char*> types = {
        {".html", "text/html; charset=utf-8"},
        {".htm", "text/html; charset=utf-8"},
        {".js", "text/javascript; charset=utf-8"},
        {".mjs", "text/javascript; charset=utf-8"},
        {".css", "text/css; charset=utf-8"},
        {".json", "application/json"},
        {".map", "application/json"},
        {".webmanifest", "application/manifest+json"},
        {".svg", "image/svg+xml"},
        {".png", "image/png"},
        {".jpg", "image/jpeg"},
        {".jpeg", "image/jpeg"},
        {".gif", "image/gif"},
        {".webp", "image/webp"},
        {".ico", "image/vnd.microsoft.icon"},
        {".woff", "font/woff"},
        {".woff2", "font/woff2"},
        {".ttf", "font/ttf"},
        {".wasm", "application/wasm"},
        {".txt", "text/plain; charset=utf-8"},
        {".csv", "text/csv; charset=utf-8"},
    };
    std::string ext = p.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    const auto it = types.find(ext);
    return it == types.end() ? "application/octet-stream" : it->second;
}

// True when `p` is `root` or lies below it (both canonical).
bool is_within(const fs::path& root, const fs::path& p) {
    const auto [r, q] = std::mismatch(root.begin(), root.end(), p.begin(), p.end());
    return r == root.end();
}

// A program or cell name from POST /runs: a file name under config/, never a path.
bool valid_name(std::string_view s) {
    if (s.empty() || s.size() > 128 || s.front() == '.') return false;
    return std::all_of(s.begin(), s.end(), [](unsigned char c) {
        return std::isalnum(c) || c == '_' || c == '-' || c == '.';
    });
}

std::optional<RunId> parse_run_id(std::string_view s) {
    RunId id = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), id);
    if (ec != std::errc() || p != s.data() + s.size() || id <= 0) return std::nullopt;
    return id;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Free helpers declared in the header.

ListenAddress parse_listen_address(std::string_view text) {
    const std::string expected = "expected HOST:PORT (e.g. 127.0.0.1:8750, [::1]:8750 or :8750), got \"" +
                                 std::string(text) + "\"";
    ListenAddress out;
    std::string_view port_text;
    if (!text.empty() && text.front() == '[') {
        const auto close = text.find(']');
        if (close == std::string_view::npos || close + 1 >= text.size() || text[close + 1] != ':')
            throw std::invalid_argument(expected);
        out.host = std::string(text.substr(1, close - 1));
        port_text = text.substr(close + 2);
    } else {
        const auto colon = text.rfind(':');
        if (colon == std::string_view::npos) throw std::invalid_argument(expected);
        out.host = std::string(text.substr(0, colon));
        if (out.host.find(':') != std::string::npos) throw std::invalid_argument(expected);  // bare IPv6
        port_text = text.substr(colon + 1);
    }
    if (out.host.empty()) out.host = "127.0.0.1";
    unsigned port = 0;
    const auto [p, ec] = std::from_chars(port_text.data(), port_text.data() + port_text.size(), port);
    if (port_text.empty() || ec != std::errc() || p != port_text.data() + port_text.size() || port > 65535)
        throw std::invalid_argument(expected);
    out.port = static_cast<std::uint16_t>(port);
    return out;
}

bool token_equals(std::string_view expected, std::string_view given) {
    // Fold every byte of `expected` in; bytes of `given` beyond its length read as 0 and the length
    // difference is folded in too. No early exit, so timing reveals at most the expected length.
    unsigned diff = static_cast<unsigned>(expected.size() != given.size());
    for (std::size_t i = 0; i < expected.size(); ++i) {
        const unsigned char g = i < given.size() ? static_cast<unsigned char>(given[i]) : 0;
        diff |= static_cast<unsigned>(static_cast<unsigned char>(expected[i]) ^ g);
    }
    // Keep the compiler from turning the loop into an early-exit comparison.
    asm volatile("" : "+r"(diff));
    return diff == 0;
}

// ---------------------------------------------------------------------------------------------------------

class Session;

struct HttpServer::State : std::enable_shared_from_this<HttpServer::State> {
    State(net::io_context& c, ApiBackend& b, HttpServerOptions o)
        : ioc(c), backend(b), opt(std::move(o)), acceptor(net::make_strand(c)), retry_timer(acceptor.get_executor()) {}

    net::io_context& ioc;
    ApiBackend& backend;
    HttpServerOptions opt;
    fs::path static_root;  // canonical, empty = none
    tcp::acceptor acceptor;
    net::steady_timer retry_timer;  // backs off accept() when out of file descriptors
    tcp::endpoint bound;

    std::atomic<bool> stopping{false};
    std::mutex sessions_mutex;
    std::unordered_map<const Session*, std::weak_ptr<Session>> sessions;

    // Counters for /metrics.
    std::atomic<std::uint64_t> open_connections{0};
    std::atomic<std::uint64_t> refused_connections{0};
    std::atomic<std::uint64_t> evicted_connections{0};  // slow header-pending sessions closed for a new one
    std::atomic<std::size_t> sample_reads{0};           // GET samples being served now
    std::atomic<std::uint64_t> client_limited{0};       // requests answered 429: a client over its cap

    // Per client (remote address): open connections and record reads in flight (see HttpServerOptions).
    struct ClientUse {
        std::size_t connections = 0;
        std::size_t record_reads = 0;
    };
    std::mutex clients_mutex;
    std::unordered_map<std::string, ClientUse> clients;
    std::size_t record_reads_total = 0;  // over all clients (under clients_mutex)
    // A new connection of `client`; false when it is over max_connections_per_client (it is counted anyway:
    // release_connection() balances it).
    bool add_connection(const std::string& client) {
        std::lock_guard lock(clients_mutex);
        const std::size_t n = ++clients[client].connections;
        return opt.max_connections_per_client == 0 || n <= opt.max_connections_per_client;
    }
    void release_connection(const std::string& client) {
        std::lock_guard lock(clients_mutex);
        const auto it = clients.find(client);
        if (it == clients.end()) return;
        if (it->second.connections > 0) --it->second.connections;
        if (it->second.connections == 0 && it->second.record_reads == 0) clients.erase(it);
    }
    // A record read of `client` may start unless it already has max_record_reads_per_client in flight while
    // another client's reads are in flight or queued too (alone, a client may use the whole pool).
    bool begin_record_read(const std::string& client) {
        std::lock_guard lock(clients_mutex);
        auto& u = clients[client];
        if (opt.max_record_reads_per_client != 0 && u.record_reads >= opt.max_record_reads_per_client &&
            record_reads_total > u.record_reads)
            return false;
        ++u.record_reads;
        ++record_reads_total;
        return true;
    }
    void end_record_read(const std::string& client) {
        std::lock_guard lock(clients_mutex);
        const auto it = clients.find(client);
        if (it == clients.end()) return;
        if (it->second.record_reads > 0) --it->second.record_reads, --record_reads_total;
        if (it->second.connections == 0 && it->second.record_reads == 0) clients.erase(it);
    }
    // Reads of the run records (SQLite) are routed here, off the io threads, so the cheap requests (health,
    // status) never queue behind them.
    // Created by HttpServer::start(), stopped and joined by stop() (never from one of its own threads).
    std::unique_ptr<net::thread_pool> read_pool;
    ~State() {
        if (read_pool) {
            read_pool->stop();
            read_pool->join();
        }
    }

    // At the connection limit: closes the session that has waited longest for its request header. Returns
    // whether there was one.
    bool evict_slowest_pending();
    std::array<std::atomic<std::uint64_t>, 6> responses_by_class{};  // index = status / 100

    void count(unsigned status) { responses_by_class[std::min(status / 100, 5u)].fetch_add(1, std::memory_order_relaxed); }

    // Registers a session unless the server is stopping (then the caller drops the connection).
    bool add(const std::shared_ptr<Session>& s);
    void remove(const Session* s) {
        std::lock_guard lock(sessions_mutex);
        sessions.erase(s);
    }

    void do_accept();
    void on_accept(beast::error_code ec, tcp::socket socket);
};

namespace {

// ---------------------------------------------------------------------------------------------------------
// Routing: a request in, a Reply out. Pure with respect to the connection, so every route is one function.

struct Reply {
    StringResponse res;                                   // the response (or, for an export, its header)
    std::optional<http::response<http::file_body>> file;  // static file
    std::unique_ptr<ExportCursor> cursor;                 // set: stream res' header, then the cursor
};

class Router {
public:
    Router(HttpServer::State& st, const Request& req) : st_(st), req_(req) {}

    Reply route() {
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
    static bool is_upload(const Request& req) {
        if (req.method() != http::verb::post) return false;
        std::string_view path(req.target().data(), req.target().size());
        path = path.substr(0, path.find('?'));
        if (path.size() > 1 && path.back() == '/') path.remove_suffix(1);
        return path == "/api/v1/diagnose";
    }

    // The token check of an upload, on its header (Session::on_header).
    std::optional<Reply> check_upload_token() const { return check_token(); }

    static Reply error(http::status status, const std::string& message) {
        Reply r;
        r.res.result(status);
        r.res.set(http::field::content_type, kJson);
        r.res.body() = dump({{"error", message}});
        return r;
    }

private:
    bool is_get() const { return req_.method() == http::verb::get || req_.method() == http::verb::head; }
    bool is_post() const { return req_.method() == http::verb::post; }
    std::string method_text() const { return std::string(req_.method_string()); }

    static Reply json(http::status status, const nlohmann::json& body) {
        Reply r;
        r.res.result(status);
        r.res.set(http::field::content_type, kJson);
        r.res.body() = dump(body);
        return r;
    }

    Reply method_not_allowed(std::string_view allow) const {
        Reply r = error(http::status::method_not_allowed,
                        "method " + method_text() + " not allowed here; allowed: " + std::string(allow));
        r.res.set(http::field::allow, beast::string_view(allow.data(), allow.size()));
        return r;
    }

    // Runs a backend call, mapping its typed errors to statuses. Anything else is a 500 whose details
    // stay in the log (they may name files or SQL).
    template <class F>
    Reply call(F&& f) {
        try {
            return f();
        } catch (const ApiError& e) {
            return error(static_cast<http::status>(e.status()), e.what());
        } catch (const std::exception& e) {
            spdlog::error("http: {} {}: {}", method_text(), std::string(req_.target()), e.what());
            return error(http::status::internal_server_error, "internal error (details in the cellbenchd log)");
        }
    }

    // Mutating endpoints: refused outright without a configured token, else Bearer TOKEN required.
    std::optional<Reply> check_token() const {
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

    Reply api(std::string_view rest, std::string_view query) {
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

    Reply not_found() const {
        return error(http::status::not_found,
                     "no such endpoint: " + method_text() + " " + std::string(req_.target().substr(0, 200)) +
                         " (the API is under /api/v1: health, status, cells, runs, runs/{id}[/samples|events|fits|"
                         "steps|export.bdf.csv|stop|pause|resume|diagnose], diagnose, diagnoses[/{job}])");
    }

    // A diagnosis job's reply: 202 Accepted with the job and where to poll it.
    static Reply accepted_job(const nlohmann::json& job) {
        Reply r = json(http::status::accepted, job);
        if (job.is_object() && job.contains("id") && job["id"].is_number_integer())
            r.res.set(http::field::location,
                      std::string(kApiPrefix) + "/diagnoses/" + std::to_string(job["id"].get<std::int64_t>()));
        return r;
    }

    // "params" (a plain name or "run") and "effects" (strings) of a diagnosis request; an error reply if bad.
    static std::optional<Reply> check_diagnose_request(const DiagnoseRequest& dr) {
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

    // The request body as a JSON object into `body`, else the 400 reply saying what was expected (`example`).
    std::optional<Reply> json_object_body(const std::string& example, nlohmann::json& body) {
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

    // POST /runs/{id}/diagnose {"params": NAME, "effects": [...]?}
    Reply diagnose_run(RunId id) {
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
        if (auto bad = check_diagnose_request(dr)) return std::move(*bad);
        dr.body = std::move(body);
        return call([&] { return accepted_job(st_.backend.diagnose_run(id, dr)); });
    }

    // POST /diagnose?params=NAME[&effects=a,b] with a BDF CSV recording as the body.
    Reply diagnose_upload(std::string_view query) {
        DiagnoseRequest dr;
        dr.body = nlohmann::json::object();
        for (const auto part : split(query, '&')) {
            if (part.empty()) continue;
            const auto eq = part.find('=');
            const auto key = percent_decode(part.substr(0, eq), true);
            const auto value = percent_decode(eq == std::string_view::npos ? "" : part.substr(eq + 1), true);
            if (!key || !value) return error(http::status::bad_request, "malformed query string");
            if (*key == "params") {
                dr.params = *value;
            } else if (*key == "effects") {
                for (const auto e : split(*value, ','))
                    if (!e.empty()) dr.effects.emplace_back(e);
            } else if (*key == "name") {
                dr.body["name"] = value->substr(0, 200);  // the file's name, for the job's description
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

    Reply start_run() {
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

    Reply samples(RunId id, std::string_view query) {
        SampleQuery sq;
        sq.max_points = kDefaultSamplePoints;
        if (!query.empty()) {
            for (const auto part : split(query, '&')) {
                if (part.empty()) continue;
                const auto eq = part.find('=');
                const auto key = percent_decode(part.substr(0, eq), true);
                const auto value = percent_decode(eq == std::string_view::npos ? "" : part.substr(eq + 1), true);
                if (!key || !value) return error(http::status::bad_request, "malformed query string");
                if (*key == "from" || *key == "to") {
                    double v = 0;
                    const auto [p, ec] = std::from_chars(value->data(), value->data() + value->size(), v);
                    if (value->empty() || ec != std::errc() || p != value->data() + value->size() || !std::isfinite(v))
                        return error(http::status::bad_request,
                                     "\"" + *key + "\": expected a number of seconds of test time, got \"" + *value + "\"");
                    (*key == "from" ? sq.from_s : sq.to_s) = v;
                } else if (*key == "max_points") {
                    std::size_t v = 0;
                    const auto [p, ec] = std::from_chars(value->data(), value->data() + value->size(), v);
                    if (value->empty() || ec != std::errc() || p != value->data() + value->size() || v < 1 ||
                        v > kMaxSamplePoints)
                        return error(http::status::bad_request, "\"max_points\": expected an integer from 1 to " +
                                                                    std::to_string(kMaxSamplePoints) + ", got \"" +
                                                                    *value + "\"");
                    sq.max_points = v;
                }
                // Other parameters are ignored (room for later options).
            }
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
        return call([&] { return json(http::status::ok, st_.backend.samples(id, sq)); });
    }

    Reply export_csv(RunId id) {
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

    Reply metrics() {
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

    // The dashboard compiled into the daemon (web_assets.hpp). Only the exact embedded names exist (no file
    // system behind them, so nothing to traverse); "/" is index.html. Strong ETag with 304 on If-None-Match;
    // content-hashed names are cached for a year, index.html is revalidated; gzip when the client takes it.
    Reply embedded_file(std::string_view path) {
        const auto assets = web_assets();
        if (assets.empty()) {
            if (path != "/" && path != "/index.html") return not_found();
            Reply r;
            r.res.result(http::status::not_found);
            r.res.set(http::field::content_type, "text/html; charset=utf-8");
            r.res.body() =
                "<!doctype html><meta charset=utf-8><title>cellbenchd: no dashboard</title>"
                "<h1>This cellbenchd was built without its dashboard</h1>"
                "<p>The dashboard is bundled from <code>web/</code> with node and npm when cellbenchd is built. "
                "Install them (<code>make deps</code> installs the Debian packages <code>nodejs npm</code>) and "
                "rebuild (<code>make</code>, or <code>cmake --build build</code>), or serve a built bundle with "
                "<code>cellbenchd --web-root DIR</code>.</p><p>The REST API is under <a href=\"/api/v1/status\">"
                "/api/v1</a>.</p>";
            return r;
        }
        if (!is_get()) return method_not_allowed("GET, HEAD");
        if (path == "/") path = "/index.html";
        const auto it = std::find_if(assets.begin(), assets.end(), [&](const WebAsset& a) { return a.path == path; });
        if (it == assets.end()) return error(http::status::not_found, "not found");
        Reply r;
        // The gzip representation has its own validator ("HASH-gz"); either names the same file content.
        const bool gzip = accepts_gzip();
        const std::string_view hash = it->etag.substr(1, it->etag.size() - 2);  // without the quotes
        r.res.set(http::field::etag, "\"" + std::string(hash) + (gzip ? "-gz\"" : "\""));
        r.res.set(http::field::cache_control, it->immutable ? "public, max-age=31536000, immutable" : "no-cache");
        r.res.set(http::field::vary, "Accept-Encoding");
        r.res.set("X-Content-Type-Options", "nosniff");
        const auto inm = req_[http::field::if_none_match];
        if (!hash.empty() && std::string_view(inm.data(), inm.size()).find(hash) != std::string_view::npos) {
            r.res.result(http::status::not_modified);
            return r;
        }
        r.res.result(http::status::ok);
        r.res.set(http::field::content_type, beast::string_view(it->content_type.data(), it->content_type.size()));
        if (gzip) {
            r.res.set(http::field::content_encoding, "gzip");
            r.res.body().assign(it->gzip);
        } else {
            r.res.body().assign(it->body);
        }
        return r;
    }

    // Accept-Encoding names gzip (or *) without q=0.
    bool accepts_gzip() const {
        const auto field = req_[http::field::accept_encoding];
        for (auto item : split(std::string_view(field.data(), field.size()), ',')) {
            while (!item.empty() && (item.front() == ' ' || item.front() == '\t')) item.remove_prefix(1);
            const auto semi = item.find(';');
            std::string_view name = item.substr(0, semi), params = semi == std::string_view::npos ? "" : item.substr(semi);
            while (!name.empty() && (name.back() == ' ' || name.back() == '\t')) name.remove_suffix(1);
            if (!iequals(name, "gzip") && name != "*") continue;
            const auto q = params.find("q=");
            if (q == std::string_view::npos) return true;
            double v = 1.0;
            std::from_chars(params.data() + q + 2, params.data() + params.size(), v);
            return v > 0.0;
        }
        return false;
    }

    Reply static_file(std::string_view path) {
        if (st_.static_root.empty()) return embedded_file(path);
        if (!is_get()) return method_not_allowed("GET, HEAD");
        // Decode first: "%2e%2e" must be seen as "..". Then refuse any dot segment, hidden name, backslash
        // or NUL, and finally check the canonical result is inside the root (symlinks cannot lead out).
        const auto decoded = percent_decode(path, false);
        const auto refuse = [&] { return error(http::status::not_found, "not found"); };
        if (!decoded || decoded->find('\0') != std::string::npos || decoded->find('\\') != std::string::npos)
            return refuse();
        fs::path rel;
        for (const auto part : split(*decoded, '/')) {
            if (part.empty()) continue;
            if (part.front() == '.') return refuse();  // ".", "..", ".git", ...
            rel /= std::string(part);
        }
        fs::path file = st_.static_root / rel;
        std::error_code ec;
        if (fs::is_directory(file, ec)) file /= "index.html";
        const fs::path canonical = fs::canonical(file, ec);
        if (ec || !is_within(st_.static_root, canonical) || !fs::is_regular_file(canonical, ec)) return refuse();

        http::file_body::value_type body;
        beast::error_code bec;
        body.open(canonical.c_str(), beast::file_mode::scan, bec);
        if (bec) return refuse();
        Reply r;
        r.file.emplace(std::piecewise_construct, std::make_tuple(std::move(body)),
                       std::make_tuple(http::status::ok, req_.version()));
        r.file->set(http::field::content_type, mime_type(canonical));
        // Dashboard files change with a build and carry no content hash in their names: revalidate.
        r.file->set(http::field::cache_control, "no-cache");
        r.file->set("X-Content-Type-Options", "nosniff");
        return r;
    }

    HttpServer::State& st_;
    const Request& req_;
};

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// One connection: read a request, answer it, repeat while keep-alive. Everything runs on the socket's
// strand, so the session needs no locks.

// The handler boundary: whatever a request makes the router or a backend throw becomes a 500 for that
// request; it never unwinds into the io_context threads (which would end the process and the run with it).
Reply route_guarded(HttpServer::State& st, const HttpRequest& request) {
    try {
        return Router(st, request).route();
    } catch (const std::exception& e) {
        spdlog::error("http: {} {}: unhandled: {}", std::string(request.method_string()),
                      std::string(request.target().substr(0, 200)), e.what());
    } catch (...) {
        spdlog::error("http: {} {}: unhandled non-standard exception", std::string(request.method_string()),
                      std::string(request.target().substr(0, 200)));
    }
    return Router::error(http::status::internal_server_error, "internal error (details in the cellbenchd log)");
}

class Session : public std::enable_shared_from_this<Session> {
public:
    Session(tcp::socket&& socket, std::shared_ptr<HttpServer::State> st)
        : stream_(std::move(socket)), st_(std::move(st)) {
        st_->open_connections.fetch_add(1);
        beast::error_code ec;
        auto addr = stream_.socket().remote_endpoint(ec).address();
        if (addr.is_v6() && addr.to_v6().is_v4_mapped()) addr = net::ip::make_address_v4(net::ip::v4_mapped, addr.to_v6());
        client_ = ec ? std::string("?") : addr.to_string();
        over_cap_ = !st_->add_connection(client_);
    }
    ~Session() {
        st_->release_connection(client_);
        st_->open_connections.fetch_sub(1);
        st_->remove(this);
    }

    void run() { net::dispatch(stream_.get_executor(), beast::bind_front_handler(&Session::do_read, shared_from_this())); }

    // Taken out of the eviction candidates at once (its close is posted to its strand).
    void mark_evicted() { header_pending_since_.store(0); }

    // Since when the session waits for a request header (steady clock ns), 0 when it is not waiting.
    [[nodiscard]] std::int64_t header_pending_since() const { return header_pending_since_.load(); }

    // From HttpServer::stop(): cut the connection; pending operations complete with an error.
    void shutdown() {
        net::post(stream_.get_executor(), [self = shared_from_this()] {
            beast::error_code ec;
            self->stream_.socket().shutdown(tcp::socket::shutdown_both, ec);
            self->stream_.close();
        });
    }

private:
    void do_read() {
        if (st_->stopping) return;
        parser_.emplace();
        parser_->header_limit(static_cast<std::uint32_t>(st_->opt.max_header_bytes));
        // The header is parsed against the larger limit (Beast checks Content-Length there); on_header applies
        // the limit of the endpoint.
        body_limit_ = std::max(st_->opt.max_body_bytes, st_->opt.max_upload_bytes);
        parser_->body_limit(body_limit_);
        // The header (and the keep-alive idle time) has a short deadline; the body gets the request's.
        stream_.expires_after(std::min(st_->opt.header_timeout, st_->opt.request_timeout));
        header_pending_since_.store(std::max<std::int64_t>(1, std::chrono::steady_clock::now().time_since_epoch().count()));
        http::async_read_header(stream_, buffer_, *parser_,
                                beast::bind_front_handler(&Session::on_header, shared_from_this()));
    }

    void on_header(beast::error_code ec, std::size_t) {
        header_pending_since_.store(0);
        if (ec) return on_read_error(ec);
        if (over_cap_) {
            // This client already holds max_connections_per_client connections: answer, close, serve others.
            st_->client_limited.fetch_add(1, std::memory_order_relaxed);
            started_ = std::chrono::steady_clock::now();
            return reply_and_close(too_many(std::to_string(st_->opt.max_connections_per_client) +
                                            " connections from " + client_ + " are open (the per-client limit)"));
        }
        started_ = std::chrono::steady_clock::now();
        stream_.expires_after(st_->opt.request_timeout);
        {
            // Only an upload of a recording (POST /api/v1/diagnose) may carry a large body, and only with the
            // token: refuse before reading megabytes from a client that may not send them.
            const auto& req = parser_->get();
            const bool upload = Router::is_upload(req);
            body_limit_ = upload ? st_->opt.max_upload_bytes : st_->opt.max_body_bytes;
            if (const auto len = parser_->content_length(); len && *len > body_limit_)
                return on_read_error(http::error::body_limit);
            parser_->body_limit(body_limit_);  // chunked bodies
            if (upload && !parser_->is_done())
                if (auto denied = Router(*st_, req).check_upload_token()) return reply_and_close(std::move(*denied));
        }
        if (parser_->is_done()) return handle_request();
        // curl and others wait for "100 Continue" before sending a larger body.
        const auto expect = parser_->get()[http::field::expect];
        if (iequals(std::string_view(expect.data(), expect.size()), "100-continue")) {
            auto cont = std::make_shared<http::response<http::empty_body>>(http::status::continue_, parser_->get().version());
            http::async_write(stream_, *cont, [self = shared_from_this(), cont](beast::error_code ec2, std::size_t) {
                if (ec2) return self->close_now();
                self->read_body();
            });
            return;
        }
        read_body();
    }

    void read_body() {
        http::async_read(stream_, buffer_, *parser_, beast::bind_front_handler(&Session::on_body, shared_from_this()));
    }

    void on_body(beast::error_code ec, std::size_t) {
        if (ec) return on_read_error(ec);
        handle_request();
    }

    void on_read_error(beast::error_code ec) {
        // Parse errors of the request itself get an answer; a clean end between requests, a client gone
        // mid-request, the idle timeout, a reset or the server stopping just close.
        static const auto& http_category = make_error_code(http::error::bad_method).category();
        if (ec.category() != http_category || ec == http::error::end_of_stream || ec == http::error::partial_message)
            return close_now();
        Reply r;
        if (ec == http::error::body_limit)
            r = Router::error(http::status::payload_too_large,
                              "request body too large (limit " + std::to_string(body_limit_) + " bytes)");
        else if (ec == http::error::header_limit)
            r = Router::error(http::status::request_header_fields_too_large,
                              "request header too large (limit " + std::to_string(st_->opt.max_header_bytes) + " bytes)");
        else
            r = Router::error(http::status::bad_request, "malformed HTTP request: " + ec.message());
        started_ = std::chrono::steady_clock::now();
        reply_and_close(std::move(r));
    }

    // An answer before the request's body was read: the rest of the request is unread, so answer, then close
    // (draining what the client still sends).
    void reply_and_close(Reply&& r) {
        r.res.version(11);
        r.res.keep_alive(false);
        finish_headers(r.res, false);
        log_line("-", "-", r.res.result_int());
        send(std::move(r.res));
    }

    // Requests that read run records from the database: routed on the read pool.
    static bool reads_records(const Request& req) {
        const std::string_view target(req.target().data(), req.target().size());
        return target.rfind("/api/v1/runs", 0) == 0 || target.rfind("/api/v1/diagnos", 0) == 0;
    }

    void handle_request() {
        request_ = parser_->release();
        if (st_->stopping) return send_reply(Router::error(http::status::service_unavailable, "cellbenchd is shutting down"));
        if (st_->read_pool && reads_records(request_)) {
            if (!st_->begin_record_read(client_)) {
                st_->client_limited.fetch_add(1, std::memory_order_relaxed);
                return send_reply(too_many(std::to_string(st_->opt.max_record_reads_per_client) +
                                           " record reads from " + client_ +
                                           " are in progress while other clients wait (the per-client limit)"));
            }
            net::post(*st_->read_pool, [self = shared_from_this()] {
                struct Done {
                    Session& s;
                    ~Done() { s.st_->end_record_read(s.client_); }
                } done{*self};
                auto r = std::make_shared<Reply>(route_guarded(*self->st_, self->request_));
                net::post(self->stream_.get_executor(), [self, r] { self->send_reply(std::move(*r)); });
            });
            return;
        }
        send_reply(route_guarded(*st_, request_));
    }

    // 429 for a client over one of its caps; Retry-After says when to come back.
    static Reply too_many(const std::string& why) {
        Reply r = Router::error(http::status::too_many_requests, "too many requests: " + why + "; retry in a second");
        r.res.set(http::field::retry_after, "1");
        return r;
    }

    void send_reply(Reply&& reply) {
        Reply r = std::move(reply);
        const bool keep = request_.keep_alive() && !st_->stopping;
        const bool head = request_.method() == http::verb::head;
        if (r.file) {
            auto& f = *r.file;
            f.version(request_.version());
            f.keep_alive(keep);
            f.set(http::field::server, kServerName);
            f.prepare_payload();
            log_line(request_.method_string(), request_.target(), f.result_int());
            if (head) {  // same header, no body
                StringResponse h{f.result(), f.version()};
                for (const auto& field : f) h.set(field.name_string(), field.value());
                return send(std::move(h));
            }
            return send(std::move(f));
        }
        r.res.version(request_.version());
        r.res.keep_alive(keep);
        log_line(request_.method_string(), request_.target(), r.res.result_int());
        if (r.cursor) {
            if (!head) return start_export(std::move(r));
            // HEAD of an export: the length is unknown until streamed; say nothing and close after.
            r.cursor.reset();
            r.res.set(http::field::server, kServerName);
            r.res.keep_alive(false);
            return send(std::move(r.res));
        }
        finish_headers(r.res, head);
        send(std::move(r.res));
    }

    // Server, caching and length headers; for HEAD the length of the body that GET would send.
    static void finish_headers(StringResponse& res, bool head) {
        res.set(http::field::server, kServerName);
        if (!res.count(http::field::cache_control)) res.set(http::field::cache_control, "no-store");
        if (head) {
            res.content_length(res.body().size());
            res.body().clear();
        } else {
            res.prepare_payload();
        }
    }

    template <class Body>
    void send(http::response<Body>&& res) {
        auto sp = std::make_shared<http::response<Body>>(std::move(res));
        const bool close = sp->need_eof() || !sp->keep_alive();
        stream_.expires_after(st_->opt.write_timeout);
        // The lambda holds the message alive until the write completes.
        http::async_write(stream_, *sp, [self = shared_from_this(), sp, close](beast::error_code ec, std::size_t) {
            if (ec) return self->close_now();
            if (close) return self->close_gracefully();
            self->do_read();
        });
    }

    // --- export: chunked transfer (HTTP/1.1) or close-delimited (HTTP/1.0), one cursor piece at a time.
    void start_export(Reply&& r) {
        cursor_ = std::move(r.cursor);
        chunked_ = request_.version() >= 11;
        export_keep_alive_ = chunked_ && r.res.keep_alive();
        export_header_.emplace(r.res.result(), r.res.version());
        for (const auto& field : r.res) export_header_->set(field.name_string(), field.value());
        export_header_->set(http::field::server, kServerName);
        export_header_->set(http::field::cache_control, "no-store");
        if (chunked_) {
            export_header_->chunked(true);
        } else {
            export_header_->keep_alive(false);
        }
        export_serializer_.emplace(*export_header_);
        stream_.expires_after(st_->opt.write_timeout);
        http::async_write_header(stream_, *export_serializer_,
                                 [self = shared_from_this()](beast::error_code ec, std::size_t) {
                                     if (ec) return self->close_now();
                                     self->export_next();
                                 });
    }

    void export_next() {
        std::optional<std::string> piece;
        try {
            do {
                piece = cursor_->next();
            } while (piece && piece->empty());
        } catch (const std::exception& e) {
            // Headers are out: the only honest signal left is to cut the transfer before its last chunk.
            spdlog::error("http: export {} aborted: {}", std::string(request_.target()), e.what());
            return close_now();
        }
        stream_.expires_after(st_->opt.write_timeout);
        auto self = shared_from_this();
        if (!piece) {
            cursor_.reset();
            if (!chunked_) return close_gracefully();
            net::async_write(stream_, http::make_chunk_last(), [self](beast::error_code ec, std::size_t) {
                self->export_serializer_.reset();
                self->export_header_.reset();
                if (ec) return self->close_now();
                if (!self->export_keep_alive_) return self->close_gracefully();
                self->do_read();
            });
            return;
        }
        chunk_ = std::move(*piece);
        const auto done = [self](beast::error_code ec, std::size_t) {
            if (ec) return self->close_now();
            self->export_next();
        };
        if (chunked_)
            net::async_write(stream_, http::make_chunk(net::buffer(chunk_)), done);
        else
            net::async_write(stream_, net::buffer(chunk_), done);
    }

    // --- closing
    void close_now() {
        beast::error_code ec;
        stream_.socket().shutdown(tcp::socket::shutdown_both, ec);
        stream_.close();
    }

    // Send FIN, then read and drop what the client still sends (bounded), so unread request bytes do not
    // turn our close into a reset that could destroy the response in flight.
    void close_gracefully() {
        beast::error_code ec;
        stream_.socket().shutdown(tcp::socket::shutdown_send, ec);
        if (ec) return close_now();
        drained_ = 0;
        stream_.expires_after(kDrainTime);
        drain();
    }
    void drain() {
        stream_.async_read_some(net::buffer(drain_buf_), [self = shared_from_this()](beast::error_code ec, std::size_t n) {
            self->drained_ += n;
            if (ec || self->drained_ > kDrainLimit) return self->close_now();
            self->drain();
        });
    }

    void log_line(beast::string_view method, beast::string_view target, unsigned status) {
        st_->count(status);
        if (!spdlog::should_log(spdlog::level::debug)) return;
        const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - started_).count();
        spdlog::debug("http: {} {} {} {:.2f} ms", std::string(method), std::string(target.substr(0, 200)), status, ms);
    }

    beast::tcp_stream stream_;
    beast::flat_buffer buffer_;
    std::shared_ptr<HttpServer::State> st_;
    std::optional<http::request_parser<http::string_body>> parser_;
    Request request_;
    std::chrono::steady_clock::time_point started_{};

    std::unique_ptr<ExportCursor> cursor_;
    std::optional<http::response<http::empty_body>> export_header_;
    std::optional<http::response_serializer<http::empty_body>> export_serializer_;
    std::string chunk_;
    bool chunked_ = true;
    bool export_keep_alive_ = false;

    std::array<char, 8192> drain_buf_{};
    std::size_t drained_ = 0;
    std::size_t body_limit_ = 0;  // of the request being read
    std::atomic<std::int64_t> header_pending_since_{0};
    std::string client_;     // remote address: the unit of the per-client caps
    bool over_cap_ = false;  // opened beyond max_connections_per_client: answered 429 and closed
};

// ---------------------------------------------------------------------------------------------------------
// Listener.

bool HttpServer::State::add(const std::shared_ptr<Session>& s) {
    std::lock_guard lock(sessions_mutex);
    if (stopping) return false;
    sessions.emplace(s.get(), s);
    return true;
}

bool HttpServer::State::evict_slowest_pending() {
    std::shared_ptr<Session> oldest;
    std::int64_t oldest_since = 0;
    {
        std::lock_guard lock(sessions_mutex);
        for (auto& [ptr, weak] : sessions) {
            const std::int64_t since = ptr->header_pending_since();
            if (since == 0 || (oldest && since >= oldest_since)) continue;
            if (auto s = weak.lock()) {
                oldest = std::move(s);
                oldest_since = since;
            }
        }
    }
    if (!oldest) return false;
    oldest->mark_evicted();
    oldest->shutdown();
    return true;
}

void HttpServer::State::do_accept() {
    // Each connection gets its own strand: its handlers never run concurrently, different connections do.
    acceptor.async_accept(net::make_strand(ioc), [self = shared_from_this()](beast::error_code ec, tcp::socket socket) {
        self->on_accept(ec, std::move(socket));
    });
}

HttpServer::HttpServer(net::io_context& ioc, ApiBackend& backend, HttpServerOptions options)
    : state_(std::make_shared<State>(ioc, backend, std::move(options))) {}

HttpServer::~HttpServer() { stop(); }

void HttpServer::start() {
    auto& st = *state_;
    const std::string where = st.opt.host + ":" + std::to_string(st.opt.port);
    const auto fail = [&](const std::string& why) { throw std::runtime_error("cannot listen on " + where + ": " + why); };

    if (!st.opt.static_dir.empty()) {
        std::error_code ec;
        st.static_root = fs::canonical(st.opt.static_dir, ec);
        if (ec || !fs::is_directory(st.static_root)) {
            spdlog::warn("http: dashboard folder {} not found; serving the {}", st.opt.static_dir.string(),
                         web_assets().empty() ? "API only" : "built-in dashboard");
            st.static_root.clear();
        }
    }

    beast::error_code ec;
    tcp::resolver resolver(st.ioc);
    const auto results = resolver.resolve(st.opt.host, std::to_string(st.opt.port),
                                          tcp::resolver::passive | tcp::resolver::numeric_service, ec);
    if (ec || results.empty()) fail(ec ? ec.message() : "no address");
    const tcp::endpoint ep = results.begin()->endpoint();

    st.acceptor.open(ep.protocol(), ec);
    if (ec) fail(ec.message());
    st.acceptor.set_option(net::socket_base::reuse_address(true), ec);
    st.acceptor.bind(ep, ec);
    if (ec) fail(ec.message());
    st.acceptor.listen(net::socket_base::max_listen_connections, ec);
    if (ec) fail(ec.message());
    st.bound = st.acceptor.local_endpoint(ec);

    const std::string bound = (st.bound.address().is_v6() ? "[" + st.bound.address().to_string() + "]"
                                                           : st.bound.address().to_string()) +
                              ":" + std::to_string(st.bound.port());
    spdlog::info("http: listening on http://{}{}", bound,
                 !st.static_root.empty() ? " (dashboard at / from " + st.static_root.string() + ")"
                 : !web_assets().empty() ? std::string(" (dashboard at /)")
                                         : std::string(" (built without the dashboard)"));
    if (!st.bound.address().is_loopback())
        spdlog::warn("http: listening on {}, beyond loopback, without TLS: the bearer token and bench data travel "
                     "in clear text; put a TLS-terminating reverse proxy in front or listen on 127.0.0.1",
                     bound);
    if (st.opt.token.empty())
        spdlog::info("http: no API token configured: starting, stopping, pausing and resuming runs over the API "
                     "is refused (set --token or CELLBENCH_TOKEN)");

    st.read_pool = std::make_unique<net::thread_pool>(2);
    net::dispatch(st.acceptor.get_executor(), [s = state_] { s->do_accept(); });
}

void HttpServer::State::on_accept(beast::error_code ec, tcp::socket socket) {
    if (stopping || ec == net::error::operation_aborted) return;  // acceptor closed by stop()
    if (ec) {
        // Typically out of file descriptors: back off briefly instead of spinning on the error.
        spdlog::warn("http: accept failed: {}", ec.message());
        retry_timer.expires_after(std::chrono::milliseconds(100));
        retry_timer.async_wait([self = shared_from_this()](beast::error_code e) {
            if (!e && !self->stopping) self->do_accept();
        });
        return;
    }
    if (open_connections.load() >= opt.max_connections && evict_slowest_pending()) {
        // The slow client's session closes on its own strand; the new connection is served meanwhile.
        if (evicted_connections.fetch_add(1) % 1000 == 0)
            spdlog::warn("http: {} connections open (the limit); closing the ones waiting longest for their "
                         "request header to serve new ones",
                         opt.max_connections);
        beast::error_code ignored;
        socket.set_option(tcp::no_delay(true), ignored);
        auto session = std::make_shared<Session>(std::move(socket), shared_from_this());
        if (add(session)) session->run();
    } else if (open_connections.load() >= opt.max_connections) {
        if (refused_connections.fetch_add(1) % 1000 == 0)
            spdlog::warn("http: {} connections open (the limit); closing new ones", opt.max_connections);
        beast::error_code ignored;
        socket.close(ignored);
    } else {
        // Responses go out in one write, but an export is several; don't let Nagle hold back its tail.
        beast::error_code ignored;
        socket.set_option(tcp::no_delay(true), ignored);
        auto session = std::make_shared<Session>(std::move(socket), shared_from_this());
        if (add(session)) session->run();
    }
    do_accept();
}

void HttpServer::stop() {
    const auto st = state_;
    {
        std::lock_guard lock(st->sessions_mutex);
        if (st->stopping.exchange(true)) return;
    }
    net::post(st->acceptor.get_executor(), [st] {
        beast::error_code ec;
        st->acceptor.close(ec);
        st->retry_timer.cancel();
    });
    std::vector<std::shared_ptr<Session>> live;
    {
        std::lock_guard lock(st->sessions_mutex);
        for (auto& [ptr, weak] : st->sessions)
            if (auto s = weak.lock()) live.push_back(std::move(s));
    }
    for (auto& s : live) s->shutdown();
    if (st->read_pool) {  // a read in progress finishes (bounded); queued ones are dropped with their sessions
        st->read_pool->stop();
        st->read_pool->join();
    }
    if (st->bound.port() != 0) spdlog::info("http: stopped ({} connections closed)", live.size());
}

tcp::endpoint HttpServer::local_endpoint() const { return state_->bound; }

// ---------------------------------------------------------------------------------------------------------
// Socket-free handling (http_handler.hpp): the sessions' router on a State that never listens.

HttpResponse handle_http_request(const HttpRequest& request, ApiBackend& backend, const HttpServerOptions& options) {
    // The State wants an executor for its acceptor and timer; they are never opened or run here.
    static net::io_context unused_ioc;
    HttpServer::State st(unused_ioc, backend, options);
    if (!options.static_dir.empty()) {
        std::error_code ec;
        st.static_root = fs::canonical(options.static_dir, ec);
        if (ec || !fs::is_directory(st.static_root)) st.static_root.clear();
    }
    Reply r = route_guarded(st, request);
    const bool head = request.method() == http::verb::head;
    StringResponse res;
    if (r.file) {
        auto& f = *r.file;
        res.result(f.result());
        for (const auto& field : f) res.set(field.name_string(), field.value());
        std::string body(static_cast<std::size_t>(f.body().size()), '\0');
        beast::error_code ec;
        std::size_t got = 0;
        while (got < body.size() && !ec) {
            const std::size_t n = f.body().file().read(body.data() + got, body.size() - got, ec);
            if (n == 0) break;
            got += n;
        }
        body.resize(got);
        res.body() = std::move(body);
    } else if (r.cursor) {
        res = std::move(r.res);
        if (!head)
            while (auto piece = r.cursor->next()) res.body() += *piece;
    } else {
        res = std::move(r.res);
    }
    res.version(request.version());
    res.keep_alive(request.keep_alive());
    res.set(http::field::server, kServerName);
    if (!res.count(http::field::cache_control)) res.set(http::field::cache_control, "no-store");
    if (head && r.cursor) {
        res.keep_alive(false);  // the server does not know the length of an export: it closes after HEAD
    } else if (head) {
        res.content_length(res.body().size());
        res.body().clear();
    } else {
        res.prepare_payload();
    }
    return res;
}

}  // namespace cellbench::daemon
