#pragma once
// The daemon's HTTP/1.1 server (Boost.Beast): REST/JSON under /api/v1 (INTERFACES.md, "Daemon"), the
// Prometheus text at /metrics, and static dashboard files at / . Modelled on Beast's "advanced server":
// one listener, one session per connection on its own strand, asynchronous reads and writes with
// timeouts, keep-alive; the io_context may be run by several threads.
//
// Security model: listens on loopback unless configured otherwise (a warning is logged beyond loopback:
// there is no TLS here, put a TLS proxy in front). Reads are open to whoever can connect; mutating
// endpoints (POST) need `Authorization: Bearer TOKEN`, compared in constant time, and are refused (403)
// when no token is configured rather than left open.
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <string_view>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>

#include "cellbench/daemon/api.hpp"

namespace cellbench::daemon {

struct HttpServerOptions {
    std::string host = "127.0.0.1";  // an address or a name; 0.0.0.0 / :: listen beyond loopback
    std::uint16_t port = 8750;       // 0 = any free port (tests; see HttpServer::local_endpoint)
    std::string token;               // bearer token for the mutating endpoints; empty = refuse them (403)
    // Dashboard files served at / from this folder (e.g. BUILD/web/dist, `cellbenchd --web-root`); empty = the
    // bundle compiled into the daemon (web_assets.hpp).
    std::filesystem::path static_dir;

    std::size_t max_header_bytes = 8 * 1024;   // larger request headers -> 431
    std::size_t max_body_bytes = 64 * 1024;    // larger request bodies -> 413 (API bodies are tiny)
    // POST /api/v1/diagnose carries a whole recording: its own limit (larger -> 413). Its bearer token is
    // checked on the header, before the body is read.
    std::size_t max_upload_bytes = kMaxUploadBytes;
    // Beyond this many open connections, a new one takes the place of the connection that has waited longest
    // for its request header (a slow or idle client); only when none is waiting is the new one closed. So
    // slow clients cannot lock out a client that sends its request at once (GET /health keeps answering).
    std::size_t max_connections = 512;
    // Per client (remote address): beyond this many open connections, a new one from the same address is
    // answered 429 with Retry-After and closed, while other clients are served as usual. 0 = no limit. A
    // browser opens at most 6 per host; this stops one host from holding the whole max_connections.
    std::size_t max_connections_per_client = 64;
    // Per client: requests that read run records (queued on the small read pool: /runs/..., /diagnoses) in
    // flight at once while other clients' record reads are in flight or queued too; one more is answered 429
    // with Retry-After (the connection stays open). A client alone may use the whole pool (behind a reverse
    // proxy every client is one address). 0 = no limit.
    std::size_t max_record_reads_per_client = 8;
    // The request header must arrive within this time after the connection opens or the previous response
    // (the keep-alive idle limit too): a few seconds, so slow-header ("slowloris") clients are dropped early.
    std::chrono::milliseconds header_timeout{5'000};
    // The whole request (header and body) must arrive within this time.
    std::chrono::milliseconds request_timeout{30'000};
    // Expensive reads (GET /runs/{id}/samples) served at once; beyond, 503 with Retry-After, so readers
    // cannot pile up on the database while a run records.
    std::size_t max_concurrent_sample_reads = 4;
    std::chrono::milliseconds write_timeout{60'000};  // per response or export chunk
};

// "HOST:PORT", "[v6addr]:PORT" or ":PORT" (loopback) as given to `cellbenchd --listen`.
// Throws std::invalid_argument with a message saying what was expected.
struct ListenAddress {
    std::string host;
    std::uint16_t port = 8750;
};
ListenAddress parse_listen_address(std::string_view text);

// True when `given` equals `expected`. The time taken depends only on expected.size(), never on where
// the strings differ, so the token cannot be guessed byte by byte from response times.
bool token_equals(std::string_view expected, std::string_view given);

class HttpServer {
public:
    // The backend must outlive every session: stop() the server and let io_context::run() return (or
    // destroy the io_context) before destroying the backend.
    HttpServer(boost::asio::io_context& ioc, ApiBackend& backend, HttpServerOptions options);
    ~HttpServer();  // stop()s
    HttpServer(const HttpServer&) = delete;
    HttpServer& operator=(const HttpServer&) = delete;

    // Binds, listens and starts accepting on the io_context. Throws std::runtime_error
    // ("cannot listen on HOST:PORT: reason") when the address cannot be used.
    void start();

    // Closes the acceptor and every open connection (in-flight responses are cut). Idempotent and
    // thread-safe; returns at once, the io_context runs the closing handlers. Once the rest of the daemon
    // has stopped too, io_context::run() returns.
    void stop();

    // The bound address (after start()); with port 0 this tells the port chosen.
    [[nodiscard]] boost::asio::ip::tcp::endpoint local_endpoint() const;

    struct State;  // shared with the sessions (defined in http_server.cpp)

private:
    std::shared_ptr<State> state_;
};

}  // namespace cellbench::daemon
