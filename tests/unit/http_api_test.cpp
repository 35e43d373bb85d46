// The daemon's HTTP API over real loopback sockets, with a fake backend: routes, JSON errors with fitting
// statuses, limits, the bearer token, keep-alive, the export stream, static files and clean stopping.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <filesystem>
#include <fstream>
#include <thread>

#include "cellbench/daemon/web_assets.hpp"
#include "unit/api_test_support.hpp"

namespace fs = std::filesystem;
using namespace cellbench::testing;
using cellbench::daemon::HttpServerOptions;
using http::verb;

namespace {

const std::string kToken = "0123456789abcdef-token";
const Headers kAuth = {{"Authorization", "Bearer " + kToken}};

HttpServerOptions with_token() {
    HttpServerOptions o;
    o.token = kToken;
    return o;
}

std::string error_of(const Response& r) { return body_json(r).at("error").get<std::string>(); }

}  // namespace

TEST(HttpApi, ReadEndpointsReturnTheBackendsJson) {
    FakeBackend be;
    TestServer srv(be);
    const auto port = srv.port();

    auto r = request(port, verb::get, "/api/v1/health");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(r[http::field::content_type], "application/json");
    EXPECT_EQ(body_json(r)["status"], "ok");

    r = request(port, verb::get, "/api/v1/status");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(body_json(r)["instruments"][0]["name"], "neware");
    EXPECT_DOUBLE_EQ(body_json(r)["live"]["voltage_v"].get<double>(), 3.712);

    r = request(port, verb::get, "/api/v1/runs");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(body_json(r)["runs"][0]["id"], 1);

    r = request(port, verb::get, "/api/v1/runs/1");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(body_json(r)["program"], "hppc");

    r = request(port, verb::get, "/api/v1/runs/1/events");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(body_json(r)["events"][0]["kind"], "step_started");

    r = request(port, verb::get, "/api/v1/runs/1/fits");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_DOUBLE_EQ(body_json(r)["fits"][0]["discharge"]["r0_ohm"].get<double>(), 0.012);

    // A trailing slash is tolerated.
    EXPECT_EQ(request(port, verb::get, "/api/v1/runs/").result_int(), 200);
}

TEST(HttpApi, SamplesQueryIsParsedAndValidated) {
    FakeBackend be;
    TestServer srv(be);
    const auto port = srv.port();

    auto r = request(port, verb::get, "/api/v1/runs/1/samples?from=10.5&to=3600&max_points=500");
    ASSERT_EQ(r.result_int(), 200) << r.body();
    ASSERT_TRUE(be.last_query);
    EXPECT_DOUBLE_EQ(*be.last_query->from_s, 10.5);
    EXPECT_DOUBLE_EQ(*be.last_query->to_s, 3600.0);
    EXPECT_EQ(be.last_query->max_points, 500u);

    r = request(port, verb::get, "/api/v1/runs/1/samples");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_FALSE(be.last_query->from_s);
    EXPECT_FALSE(be.last_query->to_s);
    EXPECT_EQ(be.last_query->max_points, cellbench::daemon::kDefaultSamplePoints);

    r = request(port, verb::get, "/api/v1/runs/1/samples?from=%31e2");  // percent-encoded "1e2"
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_DOUBLE_EQ(*be.last_query->from_s, 100.0);

    for (const char* bad : {"?from=abc", "?to=", "?from=nan", "?max_points=0", "?max_points=-3", "?max_points=2.5",
                            "?max_points=100000000", "?from=50&to=10", "?from=%zz"}) {
        r = request(port, verb::get, std::string("/api/v1/runs/1/samples") + bad);
        EXPECT_TRUE(is_json_error(r, 400)) << bad;
    }
    EXPECT_TRUE(is_json_error(request(port, verb::get, "/api/v1/runs/77/samples"), 404));
}

TEST(HttpApi, UnknownRunsAndPathsAre404Json) {
    FakeBackend be;
    TestServer srv(be);
    const auto port = srv.port();
    for (const char* path : {"/api/v1/runs/42", "/api/v1/runs/42/events", "/api/v1/runs/42/fits",
                             "/api/v1/runs/42/export.bdf.csv", "/api/v1/runs/abc", "/api/v1/runs/-1",
                             "/api/v1/runs/1/nothing", "/api/v1/nothing", "/api/v1", "/api/v2/status", "/nothing"}) {
        const auto r = request(port, verb::get, path);
        EXPECT_TRUE(is_json_error(r, 404)) << path;
    }
    EXPECT_NE(error_of(request(port, verb::get, "/api/v1/runs/42")).find("42"), std::string::npos);
}

TEST(HttpApi, WrongMethodsAre405WithAllow) {
    FakeBackend be;
    TestServer srv(be, with_token());
    const auto port = srv.port();
    struct Case {
        verb method;
        const char* path;
        const char* allow;
    };
    for (const auto& c : {Case{verb::post, "/api/v1/status", "GET, HEAD"}, Case{verb::delete_, "/api/v1/runs", "GET, HEAD, POST"},
                          Case{verb::put, "/api/v1/runs/1", "GET, HEAD"}, Case{verb::get, "/api/v1/runs/1/stop", "POST"},
                          Case{verb::delete_, "/api/v1/runs/1/pause", "POST"}, Case{verb::post, "/metrics", "GET, HEAD"}}) {
        const auto r = request(port, c.method, c.path, "", kAuth);
        EXPECT_TRUE(is_json_error(r, 405)) << c.path;
        EXPECT_EQ(r[http::field::allow], c.allow) << c.path;
    }
    EXPECT_EQ(be.start_calls, 0);
}

TEST(HttpApi, MutatingEndpointsNeedTheBearerToken) {
    FakeBackend be;
    TestServer srv(be, with_token());
    const auto port = srv.port();
    const std::string body = R"({"program": "hppc", "cell": "p45b"})";

    auto r = request(port, verb::post, "/api/v1/runs", body);
    EXPECT_TRUE(is_json_error(r, 401));
    EXPECT_NE(r[http::field::www_authenticate].find("Bearer"), std::string::npos);

    for (const std::string& wrong : {std::string("Bearer wrong"), "Bearer " + kToken.substr(0, kToken.size() - 1),
                                     "Bearer " + kToken + "x", "Bearer " + kToken.substr(1), "Basic " + kToken,
                                     kToken, std::string("Bearer "), "Bearer X" + kToken.substr(1)}) {
        r = request(port, verb::post, "/api/v1/runs", body, {{"Authorization", wrong}});
        EXPECT_TRUE(is_json_error(r, 401)) << wrong;
    }
    for (const char* path : {"/api/v1/runs/1/stop", "/api/v1/runs/1/pause", "/api/v1/runs/1/resume"})
        EXPECT_TRUE(is_json_error(request(port, verb::post, path, "", {{"Authorization", "Bearer nope"}}), 401)) << path;
    EXPECT_EQ(be.start_calls, 0) << "the backend must not be reached without the token";

    // The right token (scheme case-insensitive) starts a run: 201 with its location.
    r = request(port, verb::post, "/api/v1/runs", body, {{"Authorization", "bearer " + kToken}});
    ASSERT_EQ(r.result_int(), 201) << r.body();
    const auto run = body_json(r);
    EXPECT_EQ(run["state"], "running");
    EXPECT_EQ(r[http::field::location], "/api/v1/runs/" + std::to_string(run["id"].get<long long>()));
    ASSERT_TRUE(be.last_start);
    EXPECT_EQ(be.last_start->program, "hppc");
    EXPECT_EQ(be.last_start->cell, "p45b");

    const std::string id = std::to_string(run["id"].get<long long>());
    r = request(port, verb::post, "/api/v1/runs/" + id + "/pause", "", kAuth);
    ASSERT_EQ(r.result_int(), 200) << r.body();
    EXPECT_EQ(body_json(r)["state"], "paused");
    r = request(port, verb::post, "/api/v1/runs/" + id + "/resume", "", kAuth);
    EXPECT_EQ(body_json(r)["state"], "running");
    r = request(port, verb::post, "/api/v1/runs/" + id + "/stop", "{}", kAuth);
    EXPECT_EQ(body_json(r)["state"], "stopped");

    // Reads stay open without a token.
    EXPECT_EQ(request(port, verb::get, "/api/v1/runs/" + id).result_int(), 200);
}

TEST(HttpApi, WithoutAConfiguredTokenMutatingEndpointsAreRefused) {
    FakeBackend be;
    TestServer srv(be);  // no token
    const auto port = srv.port();
    for (const Headers& h : {Headers{}, Headers{{"Authorization", "Bearer "}}, Headers{{"Authorization", "Bearer anything"}}}) {
        const auto r = request(port, verb::post, "/api/v1/runs", R"({"program": "hppc", "cell": "p45b"})", h);
        EXPECT_TRUE(is_json_error(r, 403));
        EXPECT_NE(error_of(r).find("--token"), std::string::npos) << error_of(r);
        EXPECT_NE(error_of(r).find("CELLBENCH_TOKEN"), std::string::npos) << error_of(r);
    }
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs/1/stop"), 403));
    EXPECT_EQ(be.start_calls, 0);
    EXPECT_EQ(request(port, verb::get, "/api/v1/status").result_int(), 200);
}

TEST(HttpApi, BadStartBodiesAre400AndBackendErrorsMapToStatuses) {
    FakeBackend be;
    TestServer srv(be, with_token());
    const auto port = srv.port();
    for (const char* body : {"", "{", "not json", "[1,2]", R"({"program": "hppc"})", R"({"program": 3, "cell": "p45b"})",
                             R"({"program": "", "cell": "p45b"})", R"({"program": "../../etc/passwd", "cell": "p45b"})",
                             R"({"program": "hppc", "cell": "a/b"})", R"({"program": ".hidden", "cell": "p45b"})"}) {
        EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs", body, kAuth), 400)) << body;
    }
    EXPECT_EQ(be.start_calls, 0);

    // Backend errors: BadRequest 400, Conflict 409, Unavailable 503, NotFound 404, anything else 500.
    auto r = request(port, verb::post, "/api/v1/runs", R"({"program": "nope", "cell": "p45b"})", kAuth);
    EXPECT_TRUE(is_json_error(r, 400));
    EXPECT_NE(error_of(r).find("nope"), std::string::npos);
    ASSERT_EQ(request(port, verb::post, "/api/v1/runs", R"({"program": "hppc", "cell": "p45b"})", kAuth).result_int(), 201);
    r = request(port, verb::post, "/api/v1/runs", R"({"program": "cc", "cell": "p45b"})", kAuth);
    EXPECT_TRUE(is_json_error(r, 409));
    EXPECT_NE(error_of(r).find("already active"), std::string::npos);
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs/1/stop", "", kAuth), 409));
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs/99/stop", "", kAuth), 404));
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs/abc/stop", "", kAuth), 404));
    be.unavailable = true;
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs", R"({"program": "cc", "cell": "p45b"})", kAuth), 503));
    be.explode = true;
    r = request(port, verb::get, "/api/v1/status");
    EXPECT_TRUE(is_json_error(r, 500));
    EXPECT_EQ(r.body().find("secret internal detail"), std::string::npos) << "internals stay in the log";
}

TEST(HttpApi, StartParametersReachTheBackendAndAMalformedObjectIs400) {
    FakeBackend be;
    TestServer srv(be, with_token());
    const auto port = srv.port();
    for (const char* body : {R"({"program": "hppc", "cell": "p45b", "parameters": [1]})",
                             R"({"program": "hppc", "cell": "p45b", "parameters": "c_rate=2"})",
                             R"({"program": "hppc", "cell": "p45b", "parameters": 2})"}) {
        const auto r = request(port, verb::post, "/api/v1/runs", body, kAuth);
        EXPECT_TRUE(is_json_error(r, 400)) << body;
        EXPECT_NE(error_of(r).find("\"parameters\""), std::string::npos) << error_of(r);
    }
    EXPECT_EQ(be.start_calls, 0);
    // Values go to the backend as sent (the program loader is the one validator of names, types and ranges).
    const auto r = request(port, verb::post, "/api/v1/runs",
                           R"({"program": "hppc", "cell": "p45b", "parameters": {"c_rate": 2, "soc_step": "x"}})", kAuth);
    ASSERT_EQ(r.result_int(), 201) << r.body();
    ASSERT_TRUE(be.last_start);
    ASSERT_EQ(be.last_start->parameters.size(), 2u);
    EXPECT_EQ(be.last_start->parameters.at("c_rate"), json(2));
    EXPECT_EQ(be.last_start->parameters.at("soc_step"), json("x"));
}

namespace {
// Polls f for up to 20 s (no timing assertion: only that it happens).
bool poll_until(const std::function<bool()>& f) {
    for (int i = 0; i < 2000; ++i) {
        if (f()) return true;
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return false;
}
// Record reads block until released: the read pool fills up.
struct GatedBackend : FakeBackend {
    std::mutex gate_m;
    std::condition_variable gate_cv;
    bool open = false;
    std::atomic<int> waiting{0};
    json get_run(RunId id) override {
        ++waiting;
        std::unique_lock lock(gate_m);
        gate_cv.wait(lock, [&] { return open; });
        return FakeBackend::get_run(id);
    }
    void release() {
        std::lock_guard lock(gate_m);
        open = true;
        gate_cv.notify_all();
    }
};
}  // namespace

TEST(HttpApi, AClientOverItsConnectionCapGets429WhileOthersAreServed) {
    FakeBackend be;
    HttpServerOptions opt;
    opt.max_connections_per_client = 3;
    TestServer srv(be, opt);
    const auto port = srv.port();
    // Client A (127.0.0.1) holds 3 idle connections: its 4th is answered 429 with Retry-After and closed.
    std::vector<std::unique_ptr<Connection>> idle;
    for (int i = 0; i < 3; ++i) idle.push_back(std::make_unique<Connection>(port, "127.0.0.1"));
    {
        Connection over(port, "127.0.0.1");
        const auto r = over.request(verb::get, "/api/v1/health");
        EXPECT_TRUE(is_json_error(r, 429)) << r.body();
        EXPECT_EQ(r[http::field::retry_after], "1");
        EXPECT_NE(error_of(r).find("127.0.0.1"), std::string::npos) << error_of(r);
        EXPECT_TRUE(over.closed_by_peer());
    }
    // Client B (127.0.0.2, another host as far as the server can tell) is served as usual.
    {
        Connection other(port, "127.0.0.2");
        EXPECT_EQ(other.request(verb::get, "/api/v1/health").result_int(), 200);
    }
    // A closes one: its next connection is served again (the server sees the close asynchronously).
    idle.pop_back();
    EXPECT_TRUE(poll_until([&] {
        Connection again(port, "127.0.0.1");
        return again.request(verb::get, "/api/v1/health").result_int() == 200;
    }));
    // From another client: A's last probe may still count until the server sees its close.
    Connection reader(port, "127.0.0.2");
    const auto m = reader.request(verb::get, "/metrics").body();
    // At least the refusal above (the probes of the poll may add theirs while the close is in flight).
    const std::string key = "\ncellbench_http_client_limited_total ";
    const auto at = m.find(key);
    ASSERT_NE(at, std::string::npos) << m;
    EXPECT_GE(std::stoul(m.substr(at + key.size())), 1u) << m;
}


TEST(HttpApi, AClientOverItsRecordReadCapGets429WhileOthersWaitAndKeepsItsConnection) {
    GatedBackend be;
    HttpServerOptions opt;
    opt.max_record_reads_per_client = 1;
    TestServer srv(be, opt);
    const auto port = srv.port();
    // A client alone may use the whole read pool: two reads of A at once are both taken.
    std::atomic<int> served{0};
    std::vector<std::thread> readers;
    auto read_from = [&](const char* from) {
        readers.emplace_back([&, from] {
            Connection c(port, from);
            if (c.request(verb::get, "/api/v1/runs/1").result_int() == 200) ++served;
        });
    };
    read_from("127.0.0.1");
    ASSERT_TRUE(poll_until([&] { return be.waiting.load() == 1; }));
    read_from("127.0.0.2");  // B's read: in the backend too (the pool has two threads)
    ASSERT_TRUE(poll_until([&] { return be.waiting.load() == 2; }));
    // Now A (one read in flight, the cap) and B compete: A's next record read is refused at once, with
    // Retry-After, and its connection stays usable.
    Connection a(port, "127.0.0.1");
    const auto r = a.request(verb::get, "/api/v1/runs/1/events");
    EXPECT_TRUE(is_json_error(r, 429)) << r.body();
    EXPECT_EQ(r[http::field::retry_after], "1");
    EXPECT_NE(error_of(r).find("127.0.0.1"), std::string::npos) << error_of(r);
    EXPECT_EQ(a.request(verb::get, "/api/v1/health").result_int(), 200);
    // A third client is not refused: its read queues and is answered once the pool frees up.
    read_from("127.0.0.3");
    be.release();
    for (auto& t : readers) t.join();
    EXPECT_EQ(served.load(), 3);
    // The slots are returned: A may read again.
    EXPECT_EQ(a.request(verb::get, "/api/v1/runs/1").result_int(), 200);
}

TEST(HttpApi, OversizedBodiesAre413AndTheServerCarriesOn) {
    FakeBackend be;
    HttpServerOptions opt = with_token();
    opt.max_body_bytes = 1024;
    TestServer srv(be, opt);
    const auto port = srv.port();

    // Declared by Content-Length, and sent in full.
    const std::string big(200 * 1024, 'x');
    {
        Connection c(port);
        c.send(make_request(verb::post, "/api/v1/runs", big, kAuth));
        const auto r = c.read();
        ASSERT_TRUE(r);
        EXPECT_TRUE(is_json_error(*r, 413));
        EXPECT_NE(error_of(*r).find("1024"), std::string::npos);
        EXPECT_TRUE(c.closed_by_peer());
    }
    // Chunked, with no length up front: cut off once the limit is passed.
    {
        Connection c(port);
        std::string req = "POST /api/v1/runs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + kToken +
                          "\r\nTransfer-Encoding: chunked\r\n\r\n";
        for (int i = 0; i < 8; ++i) req += "200\r\n" + std::string(512, 'y') + "\r\n";
        req += "0\r\n\r\n";
        c.send(req);
        const auto r = c.read();
        ASSERT_TRUE(r);
        EXPECT_TRUE(is_json_error(*r, 413));
    }
    // Also on routes that take no body, and before authentication.
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/api/v1/runs/1/stop", big), 413));
    // Oversized headers: 431.
    EXPECT_TRUE(is_json_error(request(port, verb::get, "/api/v1/status", "", {{"X-Filler", std::string(20000, 'h')}}), 431));
    EXPECT_EQ(be.start_calls, 0);
    EXPECT_EQ(request(port, verb::get, "/api/v1/health").result_int(), 200);
}

TEST(HttpApi, MalformedRequestsAre400Json) {
    FakeBackend be;
    TestServer srv(be);
    for (const char* raw : {"GET /api/v1/health HTTX/1.1\r\n\r\n", "GARBAGE\r\n\r\n",
                            "GET /api/v1/health HTTP/1.1\r\nContent-Length: zz\r\n\r\n",
                            "GET api/v1/health HTTP/1.1\r\nHost: x\r\n\r\n"}) {
        Connection c(srv.port());
        c.send(raw);
        const auto r = c.read();
        ASSERT_TRUE(r) << raw;
        EXPECT_TRUE(is_json_error(*r, 400)) << raw;
    }
}

TEST(HttpApi, KeepAlivePipeliningAndConnectionClose) {
    FakeBackend be;
    TestServer srv(be);
    Connection c(srv.port());
    for (int i = 0; i < 20; ++i) {
        const auto r = c.request(verb::get, i % 2 ? "/api/v1/status" : "/api/v1/runs/1");
        ASSERT_EQ(r.result_int(), 200);
        EXPECT_TRUE(r.keep_alive());
    }
    // Errors keep the connection too.
    EXPECT_EQ(c.request(verb::get, "/api/v1/runs/99").result_int(), 404);
    // Two requests in one write: two answers, in order.
    c.send(make_request(verb::get, "/api/v1/health") + make_request(verb::get, "/api/v1/runs/1"));
    auto a = c.read(), b = c.read();
    ASSERT_TRUE(a && b);
    EXPECT_EQ(body_json(*a)["status"], "ok");
    EXPECT_EQ(body_json(*b)["id"], 1);
    // Connection: close is honoured.
    auto r = c.request(verb::get, "/api/v1/health", "", {{"Connection", "close"}});
    EXPECT_EQ(r.result_int(), 200);
    EXPECT_FALSE(r.keep_alive());
    EXPECT_TRUE(c.closed_by_peer());

    // HTTP/1.0 without keep-alive: one answer, then close.
    Connection old(srv.port());
    old.send(make_request(verb::get, "/api/v1/health", "", {}, 10));
    ASSERT_TRUE(old.read());
    EXPECT_TRUE(old.closed_by_peer());
}

TEST(HttpApi, HeadAnswersWithoutBodyAndExpectContinueWorks) {
    FakeBackend be;
    TestServer srv(be, with_token());
    Connection c(srv.port());
    const auto get = c.request(verb::get, "/api/v1/runs/1");
    const auto head = c.request(verb::head, "/api/v1/runs/1");
    EXPECT_EQ(head.result_int(), 200);
    EXPECT_TRUE(head.body().empty());
    EXPECT_EQ(head[http::field::content_length], std::to_string(get.body().size()));
    EXPECT_EQ(c.request(verb::get, "/api/v1/health").result_int(), 200);  // connection still in step

    // curl's "Expect: 100-continue": interim 100, then the answer to the body.
    Connection d(srv.port());
    const std::string body = R"({"program": "hppc", "cell": "p45b"})";
    std::string req = make_request(verb::post, "/api/v1/runs", body, {{"Authorization", "Bearer " + kToken}, {"Expect", "100-continue"}});
    const auto split = req.find("\r\n\r\n") + 4;
    d.send(req.substr(0, split));
    auto interim = d.read();
    ASSERT_TRUE(interim);
    EXPECT_EQ(interim->result_int(), 100);
    d.send(req.substr(split));
    auto r = d.read();
    ASSERT_TRUE(r);
    EXPECT_EQ(r->result_int(), 201) << r->body();
}

TEST(HttpApi, ExportStreamsTheWholeCsv) {
    FakeBackend be;
    TestServer srv(be);
    Connection c(srv.port());
    auto r = c.request(verb::get, "/api/v1/runs/1/export.bdf.csv");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(r[http::field::content_type], "text/csv; charset=utf-8");
    EXPECT_NE(r[http::field::content_disposition].find("run-1.bdf.csv"), std::string::npos);
    EXPECT_TRUE(r.chunked());
    EXPECT_GT(r.body().size(), 100u * 1024);
    EXPECT_EQ(r.body(), be.export_text());
    // The connection stays usable after a streamed answer.
    EXPECT_EQ(c.request(verb::get, "/api/v1/health").result_int(), 200);

    // HTTP/1.0: no chunked encoding, the end of the body is the end of the connection.
    Connection old(srv.port());
    old.send(make_request(verb::get, "/api/v1/runs/1/export.bdf.csv", "", {}, 10));
    auto r10 = old.read();
    ASSERT_TRUE(r10);
    EXPECT_EQ(r10->body(), be.export_text());

    EXPECT_TRUE(is_json_error(request(srv.port(), verb::get, "/api/v1/runs/5/export.bdf.csv"), 404));
}

TEST(HttpApi, ExportFailingMidwayIsCutNotShortened) {
    FakeBackend be;
    be.export_fail_after_chunks = 3;
    TestServer srv(be);
    Connection c(srv.port());
    c.send(make_request(verb::get, "/api/v1/runs/1/export.bdf.csv"));
    // The status line is out already; the client must see an incomplete transfer, never a short "complete" file.
    EXPECT_FALSE(c.read());
}

TEST(HttpApi, MetricsPassThroughWithServerCounters) {
    FakeBackend be;
    TestServer srv(be);
    request(srv.port(), verb::get, "/api/v1/health");
    const auto r = request(srv.port(), verb::get, "/metrics");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(r[http::field::content_type].substr(0, 10), "text/plain");
    EXPECT_NE(r.body().find("cellbench_cell_voltage_volts 3.712\n"), std::string::npos);
    EXPECT_NE(r.body().find("cellbench_http_responses_total{code=\"2xx\"}"), std::string::npos);
    EXPECT_NE(r.body().find("# TYPE cellbench_http_connections_open gauge"), std::string::npos);
}

class StaticFiles : public ::testing::Test {
protected:
    void SetUp() override {
        base_ = fs::temp_directory_path() / ("cellbench-static-" + std::to_string(::getpid()));
        fs::remove_all(base_);
        fs::create_directories(base_ / "www/assets");
        fs::create_directories(base_ / "www/docs");
        std::ofstream(base_ / "www/index.html") << "<!doctype html><title>cellbench</title>";
        std::ofstream(base_ / "www/assets/app.js") << "console.log('hi')";
        std::ofstream(base_ / "www/assets/style.css") << "body{}";
        std::ofstream(base_ / "www/assets/logo.svg") << "<svg/>";
        std::ofstream(base_ / "www/docs/index.html") << "docs";
        std::ofstream(base_ / "www/.env") << "HIDDEN";
        std::ofstream(base_ / "secret.txt") << "TOP-SECRET";
        fs::create_symlink(base_ / "secret.txt", base_ / "www/assets/link.txt");
        fs::create_directory_symlink(base_, base_ / "www/up");
    }
    void TearDown() override { fs::remove_all(base_); }
    fs::path base_;
};

TEST_F(StaticFiles, ServesTheDashboardWithContentTypes) {
    FakeBackend be;
    HttpServerOptions opt;
    opt.static_dir = base_ / "www";
    TestServer srv(be, opt);
    const auto port = srv.port();
    auto r = request(port, verb::get, "/");
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(r.body(), "<!doctype html><title>cellbench</title>");
    EXPECT_EQ(r[http::field::content_type], "text/html; charset=utf-8");
    r = request(port, verb::get, "/assets/app.js");
    EXPECT_EQ(r.body(), "console.log('hi')");
    EXPECT_EQ(r[http::field::content_type], "text/javascript; charset=utf-8");
    EXPECT_EQ(request(port, verb::get, "/assets/style.css")[http::field::content_type], "text/css; charset=utf-8");
    EXPECT_EQ(request(port, verb::get, "/assets/logo.svg")[http::field::content_type], "image/svg+xml");
    EXPECT_EQ(request(port, verb::get, "/docs/").body(), "docs");
    EXPECT_EQ(request(port, verb::get, "/assets/app.js?v=3").body(), "console.log('hi')");
    r = request(port, verb::head, "/assets/app.js");
    EXPECT_EQ(r.result_int(), 200);
    EXPECT_EQ(r[http::field::content_length], "17");
    EXPECT_TRUE(is_json_error(request(port, verb::get, "/missing.js"), 404));
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/index.html"), 405));
    // The API still answers beside the files.
    EXPECT_EQ(request(port, verb::get, "/api/v1/health").result_int(), 200);
}

TEST(HttpApi, BuiltInDashboardIsServedWithValidatorsAndGzip) {
    FakeBackend be;
    TestServer srv(be);
    const auto port = srv.port();
    const auto assets = cellbench::daemon::web_assets();
    auto r = request(port, verb::get, "/");
    if (assets.empty()) {  // built without node/npm: / says how to get the dashboard
        EXPECT_EQ(r.result_int(), 404);
        EXPECT_NE(r.body().find("built without its dashboard"), std::string::npos) << r.body();
        return;
    }
    ASSERT_EQ(r.result_int(), 200);
    EXPECT_EQ(r[http::field::content_type], "text/html; charset=utf-8");
    EXPECT_EQ(r[http::field::cache_control], "no-cache");
    const std::string etag(r[http::field::etag]);
    ASSERT_FALSE(etag.empty());
    EXPECT_NE(r.body().find("<title>cellbench</title>"), std::string::npos);
    // Every embedded file is served under its name with its type; hashed names are cacheable for a year.
    for (const auto& a : assets) {
        r = request(port, verb::get, std::string(a.path));
        ASSERT_EQ(r.result_int(), 200) << a.path;
        EXPECT_EQ(r.body(), a.body) << a.path;
        EXPECT_EQ(std::string(r[http::field::content_type]), std::string(a.content_type)) << a.path;
        if (a.immutable) {
            EXPECT_NE(r[http::field::cache_control].find("immutable"), std::string::npos) << a.path;
        }
        if (a.path.ends_with(".js") || a.path.ends_with(".css")) {  // index.html names every bundle file
            EXPECT_NE(request(port, verb::get, "/").body().find(std::string(a.path.substr(1))), std::string::npos) << a.path;
        }
    }
    // Revalidation: the same ETag gives 304 without a body.
    r = request(port, verb::get, "/", {}, {{"If-None-Match", etag}});
    EXPECT_EQ(r.result_int(), 304);
    EXPECT_TRUE(r.body().empty());
    // gzip when accepted (not when refused with q=0); the compressed body is the embedded one.
    r = request(port, verb::get, "/index.html", {}, {{"Accept-Encoding", "br, gzip;q=0.8"}});
    EXPECT_EQ(r[http::field::content_encoding], "gzip");
    EXPECT_EQ(r[http::field::vary], "Accept-Encoding");
    const auto index = std::find_if(assets.begin(), assets.end(), [](const auto& a) { return a.path == "/index.html"; });
    ASSERT_NE(index, assets.end());
    EXPECT_EQ(r.body(), index->gzip);
    EXPECT_EQ(request(port, verb::get, "/", {}, {{"Accept-Encoding", "gzip;q=0"}})[http::field::content_encoding], "");
    // Only the embedded names exist: no file system behind them, API routing unchanged.
    for (const char* path : {"/nothing.js", "/../CMakeLists.txt", "/%2e%2e/CMakeLists.txt", "/index.html/.."})
        EXPECT_TRUE(is_json_error(request(port, verb::get, path), 404)) << path;
    EXPECT_TRUE(is_json_error(request(port, verb::post, "/"), 405));
    EXPECT_EQ(request(port, verb::get, "/api/v1/health").result_int(), 200);
}

TEST_F(StaticFiles, PathTraversalIsRefused) {
    FakeBackend be;
    HttpServerOptions opt;
    opt.static_dir = base_ / "www";
    TestServer srv(be, opt);
    for (const char* path : {"/../secret.txt", "/assets/../../secret.txt", "/%2e%2e/secret.txt", "/%2E%2E%2Fsecret.txt",
                             "/assets/..%2f..%2fsecret.txt", "/..%5csecret.txt", "/assets/%2e%2e/%2e%2e/secret.txt",
                             "/assets/link.txt", "/up/secret.txt", "/.env", "/%2eenv", "/index.html%00.js", "/%zz"}) {
        Connection c(srv.port());
        c.send(std::string("GET ") + path + " HTTP/1.1\r\nHost: x\r\n\r\n");
        const auto r = c.read();
        ASSERT_TRUE(r) << path;
        EXPECT_TRUE(r->result_int() == 404 || r->result_int() == 400) << path << " -> " << r->result_int();
        EXPECT_EQ(r->body().find("TOP-SECRET"), std::string::npos) << path;
        EXPECT_EQ(r->body().find("HIDDEN"), std::string::npos) << path;
    }
}

TEST(HttpApi, ManyConcurrentClients) {
    FakeBackend be;
    TestServer srv(be, {}, 4);
    constexpr int kClients = 50, kRequests = 20;
    std::atomic<int> ok{0};
    std::vector<std::thread> clients;
    for (int i = 0; i < kClients; ++i)
        clients.emplace_back([&, i] {
            try {
                Connection c(srv.port());
                for (int k = 0; k < kRequests; ++k) {
                    const auto r = c.request(verb::get, (i + k) % 3 ? "/api/v1/status" : "/api/v1/runs/1");
                    const auto j = body_json(r);
                    if (r.result_int() == 200 && (j.contains("instruments") || j.value("id", 0) == 1)) ++ok;
                }
            } catch (const std::exception&) {
            }
        });
    for (auto& t : clients) t.join();
    EXPECT_EQ(ok, kClients * kRequests);
}

TEST(HttpApi, StopClosesOpenConnectionsAndReturnsTheThreads) {
    FakeBackend be;
    TestServer srv(be);
    const auto port = srv.port();
    Connection idle(port);
    ASSERT_EQ(idle.request(verb::get, "/api/v1/health").result_int(), 200);
    Connection half(port);
    half.send("GET /api/v1/status HTTP/1.1\r\n");  // an unfinished request
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    srv.shutdown();  // returns only once every io thread has left run(): nothing left hanging
    EXPECT_TRUE(idle.closed_by_peer());
    EXPECT_TRUE(half.closed_by_peer());
    EXPECT_THROW(Connection{port}, std::runtime_error);  // the listener is gone
}

TEST(HttpApi, ListeningOnABusyPortFailsClearly) {
    FakeBackend be;
    TestServer first(be);
    boost::asio::io_context ioc;
    HttpServerOptions opt;
    opt.port = first.port();
    cellbench::daemon::HttpServer second(ioc, be, opt);
    try {
        second.start();
        FAIL() << "expected an error";
    } catch (const std::runtime_error& e) {
        EXPECT_NE(std::string(e.what()).find("cannot listen on 127.0.0.1:" + std::to_string(first.port())),
                  std::string::npos)
            << e.what();
    }
}

TEST(HttpApi, TokenComparison) {
    using cellbench::daemon::token_equals;
    EXPECT_TRUE(token_equals("abc", "abc"));
    EXPECT_FALSE(token_equals("abc", "abd"));
    EXPECT_FALSE(token_equals("abc", "ab"));
    EXPECT_FALSE(token_equals("abc", "abcd"));
    EXPECT_FALSE(token_equals("abc", ""));
    EXPECT_FALSE(token_equals("abc", std::string("abc\0", 4)));
    EXPECT_FALSE(token_equals("", "x"));
}

TEST(HttpApi, ListenAddressParsing) {
    using cellbench::daemon::parse_listen_address;
    auto a = parse_listen_address("127.0.0.1:8750");
    EXPECT_EQ(a.host, "127.0.0.1");
    EXPECT_EQ(a.port, 8750);
    a = parse_listen_address("[::1]:9000");
    EXPECT_EQ(a.host, "::1");
    EXPECT_EQ(a.port, 9000);
    a = parse_listen_address(":8751");
    EXPECT_EQ(a.host, "127.0.0.1");
    a = parse_listen_address("0.0.0.0:0");
    EXPECT_EQ(a.port, 0);
    for (const char* bad : {"", "8750", "host:", "host:99999", "host:12ab", "::1:8750", "[::1]8750"})
        EXPECT_THROW(parse_listen_address(bad), std::invalid_argument) << bad;
}
