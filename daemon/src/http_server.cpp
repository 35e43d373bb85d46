// The HTTP server's transport: one session per connection (read a request, answer it, repeat while
// keep-alive; limits, timeouts and streamed exports), the listener with its connection caps, and the
// socket-free entry point of http_handler.hpp. Routing and handlers: http_router.cpp and the handler files.
#include "http_internal.hpp"
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
#include <spdlog/spdlog.h>

namespace cellbench::daemon {

using namespace http_detail;

namespace {

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

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// One connection: read a request, answer it, repeat while keep-alive. Everything runs on the socket's
// strand, so the session needs no locks.


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
