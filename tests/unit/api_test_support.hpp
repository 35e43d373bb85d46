#pragma once
// Test support for the HTTP API: a fake ApiBackend with a tiny in-memory bench, a server running it on
// loopback threads, and a blocking HTTP client on plain sockets (every read has a timeout, so a server bug
// fails a test instead of hanging it). Shared by http_api_test, cli_client_test and bench/api_bench.
#include <sys/socket.h>
#include <sys/time.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <arpa/inet.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <nlohmann/json.hpp>

#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/http_server.hpp"

namespace cellbench::testing {

namespace http = boost::beast::http;
using nlohmann::json;
using daemon::RunId;

// A bench with runs in memory. Runs finish on their own after `polls_until_done` GET /status calls, so a
// client following a run terminates.
class FakeBackend : public daemon::ApiBackend {
public:
    // Knobs (set before the server runs, or under `mu`).
    int polls_until_done = 3;
    std::string final_state = "completed";  // what a run becomes when it finishes on its own
    std::atomic<bool> unavailable{false};   // start_run -> 503
    std::atomic<bool> explode{false};       // status -> std::runtime_error (a bug) -> 500
    std::size_t export_rows = 6000;         // > 64 KiB of CSV: several chunks
    int export_fail_after_chunks = -1;      // >= 0: the cursor throws after this many chunks

    // Observations.
    std::mutex mu;
    std::atomic<int> start_calls{0}, status_calls{0};
    std::optional<daemon::SampleQuery> last_query;
    std::optional<daemon::StartRequest> last_start;

    FakeBackend() {
        // Run 1: a finished run with data, so reads work before anything is started.
        runs_[1] = make_run(1, "hppc", "p45b", "completed");
        runs_[1]["ended_unix_s"] = 1.7e9 + 3600;
        runs_[1]["samples"] = static_cast<long long>(export_rows);
    }

    json health() override { return {{"status", "ok"}, {"version", "test"}, {"uptime_s", 12.5}}; }

    json status() override {
        ++status_calls;
        if (explode) throw std::runtime_error("secret internal detail");
        std::lock_guard lock(mu);
        json run = nullptr;
        if (active_) {
            auto& r = runs_[active_];
            if (r["state"] == "running") {
                r["step"]["index"] = r["step"]["index"].get<int>() + 1;
                r["step"]["elapsed_s"] = 1.5;
                if (--polls_left_ <= 0) finish(active_, final_state);
            }
            if (active_) run = runs_[active_];
        }
        return {{"version", "test"},
                {"uptime_s", 7384.0},
                {"instruments",
                 json::array({{{"name", "neware"}, {"kind", "cycler"}, {"state", "connected"},
                               {"address", "127.0.0.1:15020"}, {"detail", ""}},
                              {{"name", "chamber"}, {"kind", "chamber"}, {"state", "offline"},
                               {"address", "127.0.0.1:15021"}, {"detail", "connection refused"}}})},
                {"run", run},
                {"live",
                 {{"time_unix_s", 1.7e9}, {"test_time_s", 812.4}, {"voltage_v", 3.712}, {"current_a", -3.82},
                  {"soc", 0.621}, {"surface_c", 30.4}, {"ambient_c", 30.0}, {"t1_c", 30.9}, {"t2_c", 30.7},
                  {"heat_flux_w_per_m2", 41.2}}}};
    }

    json list_runs() override {
        std::lock_guard lock(mu);
        json list = json::array();
        for (auto it = runs_.rbegin(); it != runs_.rend(); ++it) list.push_back(it->second);
        return {{"runs", list}};
    }

    json get_run(RunId id) override {
        std::lock_guard lock(mu);
        return run_or_throw(id);
    }

    json samples(RunId id, const daemon::SampleQuery& q) override {
        std::lock_guard lock(mu);
        run_or_throw(id);
        last_query = q;
        return {{"run_id", id},
                {"from_s", q.from_s ? json(*q.from_s) : json(nullptr)},
                {"to_s", q.to_s ? json(*q.to_s) : json(nullptr)},
                {"max_points", q.max_points},
                {"decimated", false},
                {"time_s", {0.0, 0.1}},
                {"series", {{"voltage_v", {3.7, 3.69}}, {"current_a", {0.0, -3.82}}}}};
    }

    json events(RunId id) override {
        std::lock_guard lock(mu);
        run_or_throw(id);
        return {{"run_id", id},
                {"events", json::array({{{"time_unix_s", 1.7e9}, {"test_time_s", 0.0}, {"level", "info"},
                                          {"kind", "step_started"}, {"step", 1}, {"message", "Rest 1 h"}}})}};
    }

    json fits(RunId id) override {
        std::lock_guard lock(mu);
        run_or_throw(id);
        const json rc = {{"r0_ohm", 0.012}, {"r1_ohm", 0.004}, {"c1_f", 900.0}, {"r2_ohm", 0.006}, {"c2_f", 12000.0}};
        return {{"run_id", id},
                {"fits", json::array({{{"pulse_set", 1}, {"test_time_s", 4200.0}, {"soc", 0.9}, {"ocv_v", 4.05},
                                       {"discharge", rc}, {"charge", rc}}})}};
    }

    // The CSV the export of any run streams (deterministic, so tests can compare byte for byte).
    std::string export_text() const {
        std::string s = "Test Time / s,Voltage / V,Current / A\n";
        for (std::size_t i = 0; i < export_rows; ++i)
            s += std::to_string(i) + ".0," + std::to_string(3.7 - static_cast<double>(i) * 1e-5) + ",-3.82\n";
        return s;
    }

    std::unique_ptr<daemon::ExportCursor> export_bdf_csv(RunId id) override {
        {
            std::lock_guard lock(mu);
            run_or_throw(id);
        }
        struct Cursor : daemon::ExportCursor {
            std::string text;
            std::size_t pos = 0;
            int chunks = 0, fail_after = -1;
            std::optional<std::string> next() override {
                if (fail_after >= 0 && chunks >= fail_after) throw std::runtime_error("database went away");
                if (pos >= text.size()) return std::nullopt;
                const std::size_t n = std::min<std::size_t>(7000, text.size() - pos);  // odd size: many chunks
                ++chunks;
                auto piece = text.substr(pos, n);
                pos += n;
                return piece;
            }
        };
        auto c = std::make_unique<Cursor>();
        c->text = export_text();
        c->fail_after = export_fail_after_chunks;
        return c;
    }

    json start_run(const daemon::StartRequest& req) override {
        ++start_calls;
        std::lock_guard lock(mu);
        last_start = req;
        if (unavailable) throw daemon::Unavailable("instruments not ready: chamber offline");
        if (active_) throw daemon::Conflict("a run is already active (run " + std::to_string(active_) + ")");
        if (req.program != "hppc" && req.program != "cc")
            throw daemon::BadRequest("no step program \"" + req.program + "\" under config/programs/");
        const RunId id = runs_.rbegin()->first + 1;
        runs_[id] = make_run(id, req.program, req.cell, "running");
        runs_[id]["step"] = {{"index", 0}, {"count", 140}, {"type", "CC discharge"}, {"elapsed_s", 0.0}};
        active_ = id;
        polls_left_ = polls_until_done;
        return runs_[id];
    }

    json stop_run(RunId id) override { return control(id, "stopped"); }
    json pause_run(RunId id) override { return control(id, "paused"); }
    json resume_run(RunId id) override { return control(id, "running"); }

    std::string metrics_text() override {
        return "# HELP cellbench_cell_voltage_volts Cell voltage.\n# TYPE cellbench_cell_voltage_volts gauge\n"
               "cellbench_cell_voltage_volts 3.712\n";
    }

    RunId active() {
        std::lock_guard lock(mu);
        return active_;
    }

private:
    static json make_run(RunId id, const std::string& program, const std::string& cell, const std::string& state) {
        return {{"id", id},           {"program", program},      {"cell", cell},
                {"state", state},     {"created_unix_s", 1.7e9}, {"started_unix_s", 1.7e9},
                {"ended_unix_s", nullptr}, {"samples", 0},       {"step", nullptr},
                {"error", nullptr}};
    }
    json& run_or_throw(RunId id) {
        const auto it = runs_.find(id);
        if (it == runs_.end()) throw daemon::NotFound("no run " + std::to_string(id));
        return it->second;
    }
    void finish(RunId id, const std::string& state) {
        auto& r = runs_[id];
        r["state"] = state;
        r["step"] = nullptr;
        r["ended_unix_s"] = 1.7e9 + 60;
        if (state == "aborted") r["error"] = r["reason"] = "cycler reported over-voltage";
        if (active_ == id) active_ = 0;
    }
    json control(RunId id, const std::string& to) {
        std::lock_guard lock(mu);
        auto& r = run_or_throw(id);
        const std::string state = r["state"];
        if (state == "completed" || state == "stopped" || state == "aborted" || state == "interrupted")
            throw daemon::Conflict("run " + std::to_string(id) + " is already " + state);
        if (to == "running" && state != "paused") throw daemon::Conflict("run " + std::to_string(id) + " is not paused");
        if (to == "paused" && state != "running") throw daemon::Conflict("run " + std::to_string(id) + " is not running");
        if (to == "stopped")
            finish(id, "stopped");
        else
            r["state"] = to;
        return r;
    }

    std::map<RunId, json> runs_;
    RunId active_ = 0;
    int polls_left_ = 0;
};

// The server on an ephemeral loopback port, run by `threads` io threads; stopped and joined on destruction.
class TestServer {
public:
    explicit TestServer(daemon::ApiBackend& backend, daemon::HttpServerOptions opt = {}, int threads = 2)
        : guard_(boost::asio::make_work_guard(ioc_)) {
        opt.host = "127.0.0.1";
        opt.port = 0;
        server_ = std::make_unique<daemon::HttpServer>(ioc_, backend, std::move(opt));
        server_->start();
        for (int i = 0; i < threads; ++i) threads_.emplace_back([this] { ioc_.run(); });
    }
    ~TestServer() { shutdown(); }

    // stop() and wait until every io thread has returned from run(): nothing may be left running.
    void shutdown() {
        if (threads_.empty()) return;
        server_->stop();
        guard_.reset();
        for (auto& t : threads_) t.join();
        threads_.clear();
    }
    std::uint16_t port() const { return server_->local_endpoint().port(); }
    daemon::HttpServer& server() { return *server_; }

private:
    boost::asio::io_context ioc_;
    boost::asio::executor_work_guard<boost::asio::io_context::executor_type> guard_;
    std::unique_ptr<daemon::HttpServer> server_;
    std::vector<std::thread> threads_;
};

using Response = http::response<http::string_body>;
using Headers = std::vector<std::pair<std::string, std::string>>;

inline std::string make_request(http::verb method, const std::string& target, const std::string& body = {},
                                const Headers& headers = {}, unsigned version = 11) {
    http::request<http::string_body> req{method, target, version};
    req.set(http::field::host, "127.0.0.1");
    for (const auto& [k, v] : headers) req.set(k, v);
    if (!body.empty() || method == http::verb::post) req.body() = body;
    req.prepare_payload();
    std::ostringstream ss;
    ss << req;
    return ss.str();
}

// A blocking HTTP/1.1 connection on a plain socket; every receive times out after 10 s.
class Connection {
public:
    // `from`: the local (source) address, e.g. "127.0.0.2" to be another client on loopback; null = any.
    explicit Connection(std::uint16_t port, const char* from = nullptr) {
        fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
        if (fd_ < 0) throw std::runtime_error("socket failed");
        if (from) {
            sockaddr_in src{};
            src.sin_family = AF_INET;
            src.sin_port = 0;
            if (::inet_pton(AF_INET, from, &src.sin_addr) != 1 ||
                ::bind(fd_, reinterpret_cast<sockaddr*>(&src), sizeof src) != 0) {
                ::close(fd_);
                throw std::runtime_error(std::string("cannot bind the client to ") + from);
            }
        }
        timeval tv{10, 0};
        ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
        int one = 1;
        ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        sockaddr_in addr{};
        addr.sin_family = AF_INET;
        addr.sin_port = htons(port);
        addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        if (::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
            ::close(fd_);
            throw std::runtime_error("connect failed");
        }
    }
    ~Connection() { ::close(fd_); }
    Connection(const Connection&) = delete;
    Connection& operator=(const Connection&) = delete;

    void send(std::string_view bytes) {
        while (!bytes.empty()) {
            const auto n = ::send(fd_, bytes.data(), bytes.size(), MSG_NOSIGNAL);
            if (n <= 0) throw std::runtime_error("send failed");
            bytes.remove_prefix(static_cast<std::size_t>(n));
        }
    }

    // The next response; nullopt when the connection ends (or times out) before a whole one arrived, e.g.
    // a chunked transfer cut before its last chunk.
    std::optional<Response> read(bool head = false) {
        http::response_parser<http::string_body> p;
        p.eager(true);
        p.body_limit(std::numeric_limits<std::uint64_t>::max());
        if (head) p.skip(true);
        for (;;) {
            boost::beast::error_code ec;
            if (!pending_.empty()) {
                const auto used = p.put(boost::asio::buffer(pending_), ec);
                pending_.erase(0, used);
                if (p.is_done()) return p.release();
                if (ec && ec != http::error::need_more) return std::nullopt;
                if (used > 0 && !pending_.empty()) continue;
            }
            char buf[16384];
            const auto n = ::recv(fd_, buf, sizeof buf, 0);
            if (n <= 0) {
                if (n == 0 && p.is_header_done()) {
                    p.put_eof(ec);
                    if (!ec && p.is_done()) return p.release();
                }
                return std::nullopt;
            }
            pending_.append(buf, static_cast<std::size_t>(n));
        }
    }

    Response request(http::verb method, const std::string& target, const std::string& body = {},
                     const Headers& headers = {}) {
        send(make_request(method, target, body, headers));
        auto r = read(method == http::verb::head);
        if (!r) throw std::runtime_error("no response to " + target);
        return std::move(*r);
    }

    // True when the server closes the connection (EOF) with nothing more to read.
    bool closed_by_peer() {
        if (!pending_.empty()) return false;
        char c;
        const auto n = ::recv(fd_, &c, 1, 0);
        return n == 0 || (n < 0 && errno == ECONNRESET);
    }

private:
    int fd_ = -1;
    std::string pending_;
};

// One request on a fresh connection.
inline Response request(std::uint16_t port, http::verb method, const std::string& target, const std::string& body = {},
                        const Headers& headers = {}) {
    Connection c(port);
    return c.request(method, target, body, headers);
}

inline json body_json(const Response& r) { return json::parse(r.body()); }

// A request as a client sends it, for the socket-free handler (http_handler.hpp): host, the bearer token
// when one is given, the body with its content type.
inline http::request<http::string_body> handler_request(http::verb method, const std::string& target,
                                                        const std::string& body = "", const std::string& token = "",
                                                        const char* content_type = "application/json") {
    http::request<http::string_body> r{method, target, 11};
    r.set(http::field::host, "127.0.0.1");
    if (!token.empty()) r.set(http::field::authorization, "Bearer " + token);
    if (!body.empty()) {
        r.set(http::field::content_type, content_type);
        r.body() = body;
    }
    r.prepare_payload();
    return r;
}

// Every error is JSON {"error": "..."} with a non-empty message, with this status.
inline ::testing::AssertionResult is_json_error(const Response& r, unsigned status) {
    if (r.result_int() != status)
        return ::testing::AssertionFailure() << "status " << r.result_int() << ", expected " << status << ": " << r.body();
    if (r[http::field::content_type] != "application/json")
        return ::testing::AssertionFailure() << "content type " << r[http::field::content_type];
    const auto j = json::parse(r.body(), nullptr, false);
    if (j.is_discarded()) return ::testing::AssertionFailure() << "not JSON: " << r.body();
    if (!j.is_object() || !j.contains("error") || !j["error"].is_string() || j["error"].get<std::string>().empty())
        return ::testing::AssertionFailure() << "no error message: " << r.body();
    return ::testing::AssertionSuccess();
}

}  // namespace cellbench::testing
