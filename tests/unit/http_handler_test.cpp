// The socket-free request handling (http_handler.hpp) that the HTTP fuzz target drives: the same router as
// the server, so the same statuses, JSON errors and headers, without a connection.
#include "cellbench/daemon/http_handler.hpp"

#include <gtest/gtest.h>

#include "unit/api_test_support.hpp"

using namespace cellbench::testing;
using cellbench::daemon::handle_http_request;
using cellbench::daemon::HttpRequest;
using cellbench::daemon::HttpResponse;
using cellbench::daemon::HttpServerOptions;
using http::verb;

namespace {

const std::string kToken = "handler-token";

HttpRequest req(verb method, const std::string& target, const std::string& body = "", bool auth = false) {
    return handler_request(method, target, body, auth ? kToken : "");
}

HttpServerOptions opts() {
    HttpServerOptions o;
    o.token = kToken;
    return o;
}

std::string error_of(const HttpResponse& r) {
    const auto j = json::parse(r.body(), nullptr, false);
    return j.is_object() && j.contains("error") && j["error"].is_string() ? j["error"].get<std::string>() : "";
}

}  // namespace

TEST(HttpHandler, AnswersLikeTheServer) {
    FakeBackend be;
    auto r = handle_http_request(req(verb::get, "/api/v1/health"), be, opts());
    EXPECT_EQ(r.result_int(), 200u);
    EXPECT_EQ(r[http::field::content_type], "application/json");
    EXPECT_EQ(json::parse(r.body())["status"], "ok");
    EXPECT_EQ(r[http::field::content_length], std::to_string(r.body().size()));
    EXPECT_EQ(r[http::field::server], "cellbenchd");

    r = handle_http_request(req(verb::get, "/api/v1/runs/42"), be, opts());
    EXPECT_EQ(r.result_int(), 404u);
    EXPECT_NE(error_of(r).find("42"), std::string::npos) << r.body();

    // Unknown ids everywhere, including ones that do not fit a 64-bit integer (http_api_test covers the rest).
    for (const char* target : {"/api/v1/runs/42/samples?from=0&to=1", "/api/v1/runs/99999999999999999999999",
                               "/api/v1/runs/0/fits", "/api/v1/runs/1%00/events"}) {
        r = handle_http_request(req(verb::get, target), be, opts());
        EXPECT_EQ(r.result_int(), 404u) << target;
        EXPECT_FALSE(error_of(r).empty()) << target;
    }

    r = handle_http_request(req(verb::put, "/api/v1/runs/1"), be, opts());
    EXPECT_EQ(r.result_int(), 405u);
    EXPECT_EQ(r[http::field::allow], "GET, HEAD");
    EXPECT_FALSE(error_of(r).empty());
}

TEST(HttpHandler, MutatingRequestsNeedTheTokenAndValidBodies) {
    FakeBackend be;
    const std::string body = R"({"program": "hppc", "cell": "p45b"})";
    EXPECT_EQ(handle_http_request(req(verb::post, "/api/v1/runs", body), be, opts()).result_int(), 401u);
    HttpServerOptions no_token;
    EXPECT_EQ(handle_http_request(req(verb::post, "/api/v1/runs", body, true), be, no_token).result_int(), 403u);
    auto r = handle_http_request(req(verb::post, "/api/v1/runs", "{\"program\": ", true), be, opts());
    EXPECT_EQ(r.result_int(), 400u);
    EXPECT_NE(error_of(r).find("invalid JSON"), std::string::npos) << r.body();
    EXPECT_EQ(be.start_calls, 0);
    r = handle_http_request(req(verb::post, "/api/v1/runs", body, true), be, opts());
    EXPECT_EQ(r.result_int(), 201u) << r.body();
    EXPECT_EQ(be.start_calls, 1);
    EXPECT_FALSE(r[http::field::location].empty());
}

TEST(HttpHandler, ExportIsCollectedAndHeadHasNoBody) {
    FakeBackend be;
    be.export_rows = 5000;  // several cursor pieces
    const auto full = handle_http_request(req(verb::get, "/api/v1/runs/1/export.bdf.csv"), be, opts());
    ASSERT_EQ(full.result_int(), 200u);
    EXPECT_GT(full.body().size(), 64u * 1024u);
    EXPECT_TRUE(full.body() == be.export_text()) << "the export, every piece in order";

    const auto get = handle_http_request(req(verb::get, "/api/v1/runs/1"), be, opts());
    const auto head = handle_http_request(req(verb::head, "/api/v1/runs/1"), be, opts());
    EXPECT_EQ(head.result_int(), 200u);
    EXPECT_TRUE(head.body().empty());
    EXPECT_EQ(head[http::field::content_length], std::to_string(get.body().size()));
}
