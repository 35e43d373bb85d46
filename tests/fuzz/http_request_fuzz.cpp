// libFuzzer target: the daemon's HTTP request handling. Raw bytes from a client go through Beast's request
// parser with the server's header and body limits, then every complete request (pipelined ones too) through
// handle_http_request (the server's router, http_handler.hpp) with a fake backend. Any input must give
// well-formed answers, never a crash, hang or sanitizer report, and:
//   - every error (4xx/5xx) is JSON {"error": "non-empty message"} (no body for HEAD);
//   - the backend's mutating calls (start/stop/pause/resume) happen only with the configured bearer token;
//   - the backend only sees validated input (run ids > 0, plain program/cell names, sample ranges in order);
//   - no static file outside the dashboard folder is ever served.
//   - errors are JSON, except the HTML page at / that says the daemon was built without its dashboard.
// Mode: the first byte (bit 0: a dashboard folder is configured, bit 1: no token is configured, bit 2: no
// dashboard compiled in).
#include <unistd.h>

#include <cctype>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <string_view>
#include <utility>

#include <boost/asio/buffer.hpp>
#include <boost/beast/http.hpp>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/http_handler.hpp"

using namespace cellbench::daemon;
namespace http = boost::beast::http;
namespace fs = std::filesystem;
using nlohmann::json;

namespace cellbench::fuzz {
extern bool web_assets_enabled;  // web_assets_stub.cpp
}

namespace {

constexpr const char* kToken = "fuzz-token-0123";
constexpr const char* kSecret = "SECRET-OUTSIDE-THE-DASHBOARD";

void check(bool condition) {
    if (!condition) __builtin_trap();
}

bool plain_name(const std::string& s) {
    if (s.empty() || s.front() == '.') return false;
    for (const unsigned char c : s)
        if (!(std::isalnum(c) || c == '_' || c == '-' || c == '.')) return false;
    return true;
}

class FakeBackend final : public ApiBackend {
public:
    int mutations = 0;

    json health() override { return {{"status", "ok"}, {"version", "0.1.0"}, {"uptime_s", 1.5}}; }
    json status() override { return {{"version", "0.1.0"}, {"run", nullptr}, {"instruments", json::array()}}; }
    json list_runs() override { return {{"runs", {run(2), run(1)}}}; }
    json get_run(RunId id) override { return run(id); }
    json samples(RunId id, const SampleQuery& q) override {
        known(id);
        check(q.max_points >= 1 && q.max_points <= kMaxSamplePoints);
        if (q.from_s && q.to_s) check(*q.from_s <= *q.to_s);
        return {{"run_id", id}, {"decimated", false}, {"time_s", {0.0, 1.0}}, {"series", {{"voltage_v", {3.7, 3.69}}}}};
    }
    json events(RunId id) override {
        known(id);
        return {{"run_id", id}, {"events", json::array()}};
    }
    json fits(RunId id) override {
        known(id);
        return {{"run_id", id}, {"fits", json::array()}};
    }
    std::unique_ptr<ExportCursor> export_bdf_csv(RunId id) override {
        known(id);
        return std::make_unique<StringExportCursor>("Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.69,-1\n");
    }
    json start_run(const StartRequest& r) override {
        ++mutations;
        check(plain_name(r.program) && plain_name(r.cell) && r.body.is_object());
        if (r.program == "busy") throw Conflict("a run is already active");
        if (r.program == "nope") throw BadRequest("no program \"nope\"");
        if (r.program == "bug") throw std::runtime_error("a bug");
        return run(3);
    }
    json stop_run(RunId id) override { return mutate(id); }
    json pause_run(RunId id) override { return mutate(id); }
    json resume_run(RunId id) override { return mutate(id); }
    std::string metrics_text() override { return "# TYPE cellbench_up gauge\ncellbench_up 1"; }

private:
    static void known(RunId id) {
        check(id > 0);
        if (id > 3) throw NotFound("no run " + std::to_string(id));
    }
    static json run(RunId id) {
        known(id);
        return {{"id", id}, {"program", "hppc"}, {"cell", "p45b"}, {"state", "completed"}, {"samples", 2},
                {"step", nullptr}, {"error", nullptr}};
    }
    json mutate(RunId id) {
        ++mutations;
        known(id);
        if (id == 2) throw Conflict("run 2 has ended");
        return run(id);
    }
};

// A dashboard folder with two files, beside a file that must never be served.
const fs::path& dashboard() {
    static const fs::path dir = [] {
        const fs::path root = fs::temp_directory_path() / ("cellbench-http-fuzz-" + std::to_string(::getpid()));
        fs::create_directories(root / "web" / "js");
        std::ofstream(root / "web" / "index.html") << "<!doctype html><title>cellbench</title>";
        std::ofstream(root / "web" / "js" / "app.js") << "console.log('cellbench');";
        std::ofstream(root / "secret.txt") << kSecret;
        std::atexit([] {
            std::error_code ec;
            fs::remove_all(fs::temp_directory_path() / ("cellbench-http-fuzz-" + std::to_string(::getpid())), ec);
        });
        return root / "web";
    }();
    return dir;
}

void check_response(std::string_view raw, const HttpRequest& req, const HttpResponse& res, bool token_configured,
                    int mutations_before, int mutations_after) {
    const unsigned status = res.result_int();
    check(status >= 200 && status <= 599);
    const bool head = req.method() == http::verb::head;
    const auto target = std::string_view(req.target().data(), req.target().size());
    const auto path = target.substr(0, target.find('?'));
    const bool no_dashboard_page = status == 404 && res[http::field::content_type] == "text/html; charset=utf-8" &&
                                   !cellbench::fuzz::web_assets_enabled && (path == "/" || path == "/index.html");
    if (status >= 400 && !no_dashboard_page) {
        check(res[http::field::content_type] == "application/json");
        if (!head) {
            const json j = json::parse(res.body(), nullptr, false);
            check(j.is_object() && j.contains("error") && j["error"].is_string() &&
                  !j["error"].get<std::string>().empty());
        }
    } else if (res[http::field::content_type] == "application/json" && !head) {
        check(!json::parse(res.body(), nullptr, false).is_discarded());
    }
    // (Error messages echo the method and target, so the request itself may carry the text.)
    if (raw.find(kSecret) == std::string_view::npos) check(res.body().find(kSecret) == std::string::npos);
    if (mutations_after != mutations_before) {
        check(token_configured);
        const auto auth = req[http::field::authorization];
        check(std::string_view(auth.data(), auth.size()).find(kToken) != std::string_view::npos);
    }
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
    spdlog::set_level(spdlog::level::off);  // the 500 path logs; keep the fuzzer's output readable
    return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0) return 0;
    const unsigned mode = data[0];
    HttpServerOptions opt;
    opt.token = mode & 2 ? "" : kToken;
    if (mode & 1) opt.static_dir = dashboard();
    cellbench::fuzz::web_assets_enabled = !(mode & 4);
    opt.max_header_bytes = 2048;
    opt.max_body_bytes = 4096;
    FakeBackend backend;

    const std::string_view raw(reinterpret_cast<const char*>(data) + 1, size - 1);
    std::string_view rest = raw;
    // Up to 8 pipelined requests, as a keep-alive connection would read them.
    for (int n = 0; n < 8 && !rest.empty(); ++n) {
        http::request_parser<http::string_body> parser;
        parser.header_limit(static_cast<std::uint32_t>(opt.max_header_bytes));
        parser.body_limit(opt.max_body_bytes);
        parser.eager(true);
        boost::beast::error_code ec;
        while (!rest.empty() && !parser.is_done()) {
            const std::size_t used = parser.put(boost::asio::buffer(rest.data(), rest.size()), ec);
            rest.remove_prefix(used);
            if (ec == http::error::need_more) {
                if (used == 0) break;  // the rest is an incomplete request: the connection would wait
                ec = {};
                continue;
            }
            if (ec) break;
        }
        if (!parser.is_done()) return 0;  // incomplete or malformed: the server answers 400/413/431 and closes
        const HttpRequest req = parser.release();
        const int before = backend.mutations;
        const HttpResponse res = handle_http_request(req, backend, opt);
        check_response(raw, req, res, !opt.token.empty(), before, backend.mutations);
        if (!req.keep_alive()) break;
    }
    return 0;
}
