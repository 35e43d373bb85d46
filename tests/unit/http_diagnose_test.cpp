// The diagnosis endpoints of the HTTP layer (POST /runs/{id}/diagnose, POST /diagnose, GET /diagnoses/{job},
// GET /cells): authentication, request validation and JSON errors, through the socket-free handler and, for the
// upload's size limit and its early token check, over a real socket. The backend is a fake: what the daemon
// does with a valid request is tested in tests/hil/daemon_diagnose_test.cpp.
#include <gtest/gtest.h>

#include "cellbench/daemon/http_handler.hpp"
#include "unit/api_test_support.hpp"

using namespace cellbench::testing;
using cellbench::daemon::DiagnoseRequest;
using cellbench::daemon::handle_http_request;
using cellbench::daemon::HttpRequest;
using cellbench::daemon::HttpResponse;
using cellbench::daemon::HttpServerOptions;
using http::verb;

namespace {

const std::string kToken = "diag-token";
const std::string kCsv = "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7,0\n";

// Run 1 exists and has ended; job 7 exists. Everything else is unknown.
class DiagnoseBackend : public FakeBackend {
public:
    int run_calls = 0, upload_calls = 0;
    std::optional<DiagnoseRequest> last;
    std::string last_csv;

    json diagnose_run(RunId id, const DiagnoseRequest& r) override {
        ++run_calls;
        if (id != 1) throw cellbench::daemon::NotFound("no run " + std::to_string(id));
        if (r.params != "p45b-thesis" && r.params != "run")
            throw cellbench::daemon::BadRequest("\"params\": no parameter set \"" + r.params + "\"");
        last = r;
        return {{"id", 7}, {"state", "running"}, {"progress", 0.0}};
    }
    json diagnose_recording(const DiagnoseRequest& r, std::string csv) override {
        ++upload_calls;
        last = r;
        last_csv = std::move(csv);
        return {{"id", 8}, {"state", "running"}, {"progress", 0.0}};
    }
    json diagnosis(std::int64_t job) override {
        if (job != 7) throw cellbench::daemon::NotFound("no diagnosis job " + std::to_string(job));
        return {{"id", 7}, {"state", "done"}, {"progress", 1.0}};
    }
};

HttpRequest req(verb method, const std::string& target, const std::string& body = "", bool auth = false,
                const char* type = "application/json") {
    return handler_request(method, target, body, auth ? kToken : "", type);
}

HttpServerOptions opts() {
    HttpServerOptions o;
    o.token = kToken;
    return o;
}


}  // namespace

TEST(HttpDiagnose, RunDiagnosisNeedsTheToken) {
    DiagnoseBackend be;
    const std::string body = R"({"params": "p45b-thesis"})";
    auto r = handle_http_request(req(verb::post, "/api/v1/runs/1/diagnose", body), be, opts());
    EXPECT_TRUE(is_json_error(r, 401));
    EXPECT_FALSE(r[http::field::www_authenticate].empty());
    HttpRequest wrong = req(verb::post, "/api/v1/runs/1/diagnose", body);
    wrong.set(http::field::authorization, "Bearer not-the-token");
    EXPECT_TRUE(is_json_error(handle_http_request(wrong, be, opts()), 401));
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::post, "/api/v1/runs/1/diagnose", body, true), be, HttpServerOptions{}), 403));
    EXPECT_EQ(be.run_calls, 0);

    r = handle_http_request(req(verb::post, "/api/v1/runs/1/diagnose", body, true), be, opts());
    ASSERT_EQ(r.result_int(), 202u) << r.body();
    EXPECT_EQ(json::parse(r.body())["id"], 7);
    EXPECT_EQ(r[http::field::location], "/api/v1/diagnoses/7");
    ASSERT_TRUE(be.last);
    EXPECT_EQ(be.last->params, "p45b-thesis");
    EXPECT_TRUE(be.last->effects.empty());
    // GET is not the way to start one.
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::get, "/api/v1/runs/1/diagnose"), be, opts()), 405));
}

TEST(HttpDiagnose, RunDiagnosisValidatesTheRunAndTheBody) {
    DiagnoseBackend be;
    const auto post = [&](const std::string& target, const std::string& body) {
        return handle_http_request(req(verb::post, target, body, true), be, opts());
    };
    EXPECT_TRUE(is_json_error(post("/api/v1/runs/99/diagnose", R"({"params": "p45b-thesis"})"), 404));
    EXPECT_TRUE(is_json_error(post("/api/v1/runs/abc/diagnose", R"({"params": "p45b-thesis"})"), 404));
    EXPECT_TRUE(is_json_error(post("/api/v1/runs/1/diagnose", R"({"params": "nope"})"), 400));
    const int calls = be.run_calls;
    for (const std::string& bad : {std::string(""), std::string("{"), std::string("[1]"), std::string("{}"),
                                  std::string(R"({"params": 3})"), std::string(R"({"params": ""})"),
                                  std::string(R"({"params": "../etc/passwd"})"), std::string(R"({"params": ".hidden"})"),
                                  std::string(R"({"params": "p45b-thesis", "effects": "ocv_hysteresis"})"),
                                  std::string(R"({"params": "p45b-thesis", "effects": [1]})"),
                                  std::string(R"({"params": "p45b-thesis", "effects": ["a/b"]})"),
                                  std::string(R"({"params": "p45b-thesis", "confirm_runs": 2})"),
                                  std::string(R"({"params": "p45b-thesis", "confirm_runs": ["2"]})"),
                                  std::string(R"({"params": "p45b-thesis", "confirm_runs": [0]})"),
                                  std::string(R"({"params": "p45b-thesis", "confirm_runs": [2.5]})"),
                                  std::string(R"({"params": "p45b-thesis", "confirm_runs": [1,2,3,4,5,6,7,8,9]})")})
        EXPECT_TRUE(is_json_error(post("/api/v1/runs/1/diagnose", bad), 400)) << bad;
    EXPECT_EQ(be.run_calls, calls) << "malformed bodies never reach the backend";

    const auto r = post("/api/v1/runs/1/diagnose", R"({"params": "run", "effects": ["ocv_hysteresis", "extra_rc"]})");
    ASSERT_EQ(r.result_int(), 202u) << r.body();
    ASSERT_TRUE(be.last);
    EXPECT_EQ(be.last->params, "run");
    EXPECT_EQ(be.last->effects, (std::vector<std::string>{"ocv_hysteresis", "extra_rc"}));
    EXPECT_TRUE(be.last->confirm_runs.empty());

    const auto c = post("/api/v1/runs/1/diagnose", R"({"params": "p45b-thesis", "confirm_runs": [2, 5]})");
    ASSERT_EQ(c.result_int(), 202u) << c.body();
    EXPECT_EQ(be.last->confirm_runs, (std::vector<std::int64_t>{2, 5}));
}

TEST(HttpDiagnose, UploadValidatesTokenParamsAndBody) {
    DiagnoseBackend be;
    const auto post = [&](const std::string& target, const std::string& body, bool auth = true) {
        return handle_http_request(req(verb::post, target, body, auth, "text/csv"), be, opts());
    };
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose?params=p45b-thesis", kCsv, false), 401));
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose", kCsv), 400)) << "params missing";
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose?params=", kCsv), 400));
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose?params=..%2Fx", kCsv), 400));
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose?params=run", kCsv), 400)) << "an upload has no fitted set";
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose?params=%zz", kCsv), 400));
    EXPECT_TRUE(is_json_error(post("/api/v1/diagnose?params=p45b-thesis", ""), 400)) << "empty body";
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::get, "/api/v1/diagnose"), be, opts()), 405));
    HttpServerOptions small = opts();
    small.max_upload_bytes = 16;
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::post, "/api/v1/diagnose?params=p45b-thesis", kCsv, true, "text/csv"), be, small), 413));
    EXPECT_EQ(be.upload_calls, 0);

    const auto r = post("/api/v1/diagnose?params=p45b-thesis&effects=extra_rc,ocv_hysteresis&name=drive.bdf.csv", kCsv);
    ASSERT_EQ(r.result_int(), 202u) << r.body();
    EXPECT_EQ(r[http::field::location], "/api/v1/diagnoses/8");
    EXPECT_EQ(be.last_csv, kCsv);
    ASSERT_TRUE(be.last);
    EXPECT_EQ(be.last->params, "p45b-thesis");
    EXPECT_EQ(be.last->effects, (std::vector<std::string>{"extra_rc", "ocv_hysteresis"}));
    EXPECT_EQ(be.last->body.value("name", ""), "drive.bdf.csv");
}

TEST(HttpDiagnose, JobsAndCellsAreReadsWithoutToken) {
    DiagnoseBackend be;
    auto r = handle_http_request(req(verb::get, "/api/v1/diagnoses/7"), be, opts());
    ASSERT_EQ(r.result_int(), 200u) << r.body();
    EXPECT_EQ(json::parse(r.body())["state"], "done");
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::get, "/api/v1/diagnoses/8"), be, opts()), 404));
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::get, "/api/v1/diagnoses/x"), be, opts()), 404));
    EXPECT_TRUE(is_json_error(handle_http_request(req(verb::post, "/api/v1/diagnoses/7", "{}", true), be, opts()), 405));
    r = handle_http_request(req(verb::get, "/api/v1/diagnoses"), be, opts());
    ASSERT_EQ(r.result_int(), 200u);
    EXPECT_TRUE(json::parse(r.body())["diagnoses"].is_array());
    r = handle_http_request(req(verb::get, "/api/v1/cells"), be, opts());
    ASSERT_EQ(r.result_int(), 200u);
    EXPECT_TRUE(json::parse(r.body())["parameter_sets"].is_array());
}

// Over a socket: the upload may exceed the API's small body limit up to its own, is refused by Content-Length
// before the body is read, and an upload without the token is refused on its header.
TEST(HttpDiagnose, UploadLimitsOverASocket) {
    DiagnoseBackend be;
    HttpServerOptions o = opts();
    o.max_body_bytes = 1024;
    o.max_upload_bytes = 256 * 1024;
    TestServer server(be, o);
    const Headers auth = {{"Authorization", "Bearer " + kToken}, {"Content-Type", "text/csv"}};

    std::string csv = "Test Time / s,Voltage / V,Current / A\n";
    for (int k = 0; csv.size() < 100 * 1024; ++k) csv += std::to_string(k) + ",3.7,0\n";
    auto r = request(server.port(), verb::post, "/api/v1/diagnose?params=p45b-thesis", csv, auth);
    ASSERT_EQ(r.result_int(), 202u) << r.body();
    EXPECT_EQ(be.last_csv.size(), csv.size());
    // The same size elsewhere is over the API's limit.
    r = request(server.port(), verb::post, "/api/v1/runs/1/diagnose", std::string(2048, ' '), auth);
    EXPECT_EQ(r.result_int(), 413u) << r.body();

    // Over the upload limit: 413 JSON, from the header alone (the body is never sent here).
    {
        Connection c(server.port());
        c.send("POST /api/v1/diagnose?params=p45b-thesis HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + kToken +
               "\r\nContent-Type: text/csv\r\nContent-Length: 1000000\r\n\r\n");
        const auto resp = c.read();
        ASSERT_TRUE(resp);
        EXPECT_EQ(resp->result_int(), 413u);
        EXPECT_NE(json::parse(resp->body())["error"].get<std::string>().find("262144"), std::string::npos) << resp->body();
    }
    // No token: 401 on the header, before any of the body.
    {
        Connection c(server.port());
        c.send("POST /api/v1/diagnose?params=p45b-thesis HTTP/1.1\r\nHost: x\r\nContent-Type: text/csv\r\n"
               "Content-Length: 200000\r\n\r\n");
        const auto resp = c.read();
        ASSERT_TRUE(resp);
        EXPECT_EQ(resp->result_int(), 401u);
        EXPECT_TRUE(json::parse(resp->body())["error"].is_string());
    }
    EXPECT_EQ(be.upload_calls, 1);
    // The server carries on.
    EXPECT_EQ(request(server.port(), verb::get, "/api/v1/health").result_int(), 200u);
}
