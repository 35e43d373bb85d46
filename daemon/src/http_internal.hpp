#pragma once
// The HTTP server's pieces (internal to daemon/src), after Boost.Beast's advanced server: a pure router
// (request in, Reply out) with one handler per resource, and the sessions and listener that own the sockets.
//   http_server.cpp            sessions (limits, timeouts, streaming), the listener, socket-free handling
//   http_router.cpp            routing, the token check, /metrics
//   http_handlers_runs.cpp     POST /runs, samples, the BDF export
//   http_handlers_diagnose.cpp diagnosis jobs
//   http_static.cpp            the dashboard (embedded or --web-root)
//   http_util.cpp              parsing helpers
#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/http_handler.hpp"
#include "cellbench/daemon/http_server.hpp"

namespace cellbench::daemon {

namespace beast = boost::beast;
namespace http = beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;
namespace fs = std::filesystem;

namespace http_detail {

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

// Serialized JSON; backend strings may carry invalid UTF-8 (instrument text): replaced rather than failing.
std::string dump(const nlohmann::json& j);
// ASCII case-insensitive equality.
bool iequals(std::string_view a, std::string_view b);
// Percent-decoding; `plus_is_space` for query strings. nullopt for a malformed escape.
std::optional<std::string> percent_decode(std::string_view s, bool plus_is_space);
std::vector<std::string_view> split(std::string_view s, char sep);
// A query string's parameters, decoded, in order ("a=1&b" gives a = "1", b = ""); nullopt when one is malformed.
std::optional<std::vector<std::pair<std::string, std::string>>> query_params(std::string_view query);
// Content-Type of a static file by its extension.
const char* mime_type(const fs::path& p);
// True when `p` is `root` or lies below it (both canonical).
bool is_within(const fs::path& root, const fs::path& p);
// A program or cell name from POST /runs: a file name under config/, never a path.
bool valid_name(std::string_view s);
// A positive integer id from a path segment.
std::optional<RunId> parse_run_id(std::string_view s);

}  // namespace http_detail

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

namespace http_detail {

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

    Reply route();
    // POST /api/v1/diagnose (the one request with a large body), judged on the header alone.
    static bool is_upload(const Request& req);

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

    static Reply json(http::status status, const nlohmann::json& body) { return json_text(status, dump(body)); }
    static Reply json_text(http::status status, std::string body) {
        Reply r;
        r.res.result(status);
        r.res.set(http::field::content_type, kJson);
        r.res.body() = std::move(body);
        return r;
    }

    Reply method_not_allowed(std::string_view allow) const;

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
    std::optional<Reply> check_token() const;
    Reply api(std::string_view rest, std::string_view query);
    Reply not_found() const;

    // -- runs (http_handlers_runs.cpp) ----------------------------------------------------------------------
    // The request body as a JSON object into `body`, else the 400 reply saying what was expected (`example`).
    std::optional<Reply> json_object_body(const std::string& example, nlohmann::json& body);
    Reply start_run();
    Reply samples(RunId id, std::string_view query);
    Reply export_csv(RunId id);

    // -- diagnosis jobs (http_handlers_diagnose.cpp) --------------------------------------------------------
    // A diagnosis job's reply: 202 Accepted with the job and where to poll it.
    static Reply accepted_job(const nlohmann::json& job);
    // "params" (a plain name or "run") and "effects" (strings) of a diagnosis request; an error reply if bad.
    static std::optional<Reply> check_diagnose_request(const DiagnoseRequest& dr);
    // POST /runs/{id}/diagnose {"params": NAME, "effects": [...]?}
    Reply diagnose_run(RunId id);
    // POST /diagnose?params=NAME[&effects=a,b] with a BDF CSV recording as the body.
    Reply diagnose_upload(std::string_view query);

    // -- /metrics (http_router.cpp) -------------------------------------------------------------------------
    Reply metrics();

    // -- the dashboard (http_static.cpp) --------------------------------------------------------------------
    // The dashboard compiled into the daemon (web_assets.hpp). Only the exact embedded names exist (no file
    // system behind them, so nothing to traverse); "/" is index.html. Strong ETag with 304 on If-None-Match;
    // content-hashed names are cached for a year, index.html is revalidated; gzip when the client takes it.
    Reply embedded_file(std::string_view path);
    // Accept-Encoding names gzip (or *) without q=0.
    bool accepts_gzip() const;
    Reply static_file(std::string_view path);

    HttpServer::State& st_;
    const Request& req_;
};

}  // namespace http_detail

}  // namespace cellbench::daemon
