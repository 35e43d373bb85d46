// GET /api/v1/openapi.json (INTERFACES.md): an OpenAPI 3.1 document that describes every route cellbenchd
// answers, and no route it does not. The routes are probed through the server's own router
// (handle_http_request): every path built from the words the router compares path segments with (read from
// daemon/src/http_router.cpp, so a new route cannot hide from this test), with every method. A route "is
// answered" unless the router says there is no such endpoint (404 "no such endpoint") or refuses the method
// (405).
#include <gtest/gtest.h>

#include <fstream>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <utility>

#include "cellbench/daemon/http_handler.hpp"
#include "cellbench/daemon/openapi.hpp"
#include "unit/api_test_support.hpp"

using namespace cellbench::testing;
using cellbench::daemon::handle_http_request;
using cellbench::daemon::HttpServerOptions;
using http::verb;

namespace {

const std::string kToken = "openapi-token";

using Route = std::pair<std::string, std::string>;  // (METHOD, path with ids filled in)

std::set<std::string> words_compared_with(const std::string& source, const std::string& lhs) {
    std::set<std::string> words;
    const std::regex re(lhs + R"( == "([^"]+)\")");
    for (auto it = std::sregex_iterator(source.begin(), source.end(), re); it != std::sregex_iterator(); ++it)
        words.insert((*it)[1].str());
    return words;
}

std::string fill_ids(std::string path) {
    for (const char* p : {"{id}", "{job}"})
        for (auto at = path.find(p); at != std::string::npos; at = path.find(p)) path.replace(at, std::string(p).size(), "1");
    return path;
}

bool answered(verb method, const std::string& path) {
    FakeBackend be;
    HttpServerOptions o;
    o.token = kToken;
    std::string target = path, body;
    const char* type = "application/json";
    if (method == verb::post) {
        body = R"({"program": "hppc", "cell": "p45b", "params": "p45b-thesis"})";
        if (path == "/api/v1/diagnose") {
            target += "?params=p45b-thesis";
            body = "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7,0\n";
            type = "text/csv";
        }
    }
    const auto r = handle_http_request(handler_request(method, target, body, kToken, type), be, o);
    if (r.result_int() == 405) return false;
    if (r.result_int() == 404) {
        const auto j = json::parse(r.body(), nullptr, false);
        if (j.is_object() && j.value("error", "").starts_with("no such endpoint")) return false;
    }
    return true;
}

}  // namespace

TEST(OpenApi, IsAnOpenApi31DocumentServedAsJson) {
    const auto doc = json::parse(cellbench::daemon::openapi_json());
    EXPECT_TRUE(doc["openapi"].get<std::string>().starts_with("3.1")) << doc["openapi"];
    EXPECT_TRUE(doc["info"].contains("title"));
    EXPECT_TRUE(doc["info"].contains("version"));
    FakeBackend be;
    HttpServerOptions o;
    const auto r = handle_http_request(handler_request(verb::get, "/api/v1/openapi.json"), be, o);
    EXPECT_EQ(r.result_int(), 200u);
    EXPECT_EQ(r[http::field::content_type], "application/json");
    EXPECT_EQ(json::parse(r.body()), doc);
    // Every operation says what it answers; the POST ones need the bearer token.
    for (const auto& [path, item] : doc["paths"].items())
        for (const auto& [method, op] : item.items()) {
            if (method == "parameters") continue;
            EXPECT_TRUE(op.contains("responses") && !op["responses"].empty()) << method << " " << path;
            EXPECT_TRUE(op.contains("summary")) << method << " " << path;
            if (method == "post") {
                EXPECT_TRUE(op.contains("security")) << method << " " << path;
            }
        }
}

TEST(OpenApi, DescribesEveryRouteTheServerAnswersAndNoOther) {
    const auto doc = json::parse(cellbench::daemon::openapi_json());
    std::set<Route> documented;
    for (const auto& [path, item] : doc["paths"].items())
        for (const auto& [method, op] : item.items()) {
            if (method == "parameters") continue;
            std::string m = method;
            for (auto& c : m) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
            documented.emplace(m, fill_ids(path));
        }

    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/daemon/src/http_router.cpp");
    ASSERT_TRUE(in) << "daemon/src/http_router.cpp";
    std::stringstream ss;
    ss << in.rdbuf();
    const auto firsts = words_compared_with(ss.str(), R"(seg\[0\])");
    const auto actions = words_compared_with(ss.str(), "action");
    ASSERT_TRUE(firsts.contains("runs") && firsts.contains("openapi.json")) << "router words not found";
    ASSERT_TRUE(actions.contains("samples") && actions.contains("stop"));

    std::set<std::string> paths = {"/metrics", "/api/v1", "/api/v1/runs/1/nonsense", "/api/v1/nonsense"};
    for (const auto& w : firsts) {
        paths.insert("/api/v1/" + w);
        paths.insert("/api/v1/" + w + "/1");
        for (const auto& a : actions) paths.insert("/api/v1/" + w + "/1/" + a);
    }
    for (const auto& [m, p] : documented) EXPECT_TRUE(paths.contains(p)) << "documented but never probed: " << m << " " << p;

    std::set<Route> served;
    for (const auto& p : paths)
        for (const auto& [method, name] : {std::pair{verb::get, "GET"}, {verb::post, "POST"}, {verb::put, "PUT"},
                                           {verb::delete_, "DELETE"}, {verb::patch, "PATCH"}})
            if (answered(method, p)) served.emplace(name, p);

    for (const auto& r : served) EXPECT_TRUE(documented.contains(r)) << "answered but not in openapi.json: " << r.first << " " << r.second;
    for (const auto& r : documented) EXPECT_TRUE(served.contains(r)) << "in openapi.json but not answered: " << r.first << " " << r.second;
}
