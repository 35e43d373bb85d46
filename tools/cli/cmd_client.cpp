// `cellbench status | runs | start | stop | pause | resume | export`: the command-line client of cellbenchd's
// REST/JSON API (INTERFACES.md, "Daemon"; JSON shapes in daemon/include/cellbench/daemon/api.hpp).
//
// One short HTTP/1.1 connection per request (Beast). The calls block like Beast's synchronous client, but
// each is run as an asynchronous operation to completion on a private io_context so that every step
// (connect, write, read) has a deadline: a wedged daemon must not hang an unattended script.
#include <sys/ioctl.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <limits>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <boost/asio/connect.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <nlohmann/json.hpp>
#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

#include "cellbench/core/recording.hpp"
#include "cellbench/daemon/config.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

namespace beast = boost::beast;
namespace http = beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;
using nlohmann::json;

struct ClientCommands {
    std::string server = "http://127.0.0.1:8750";
    std::string token;
    double timeout_s = 10.0;
    bool json_output = false;
    // start
    std::string program, cell;
    std::vector<std::string> params;  // --param K=V (repeatable)
    bool follow = false;
    double interval_s = 1.0;
    // stop / pause / resume / export
    long long run_id = 0;
    std::string output;

    CLI::App* status = nullptr;
    CLI::App* runs = nullptr;
    CLI::App* start = nullptr;
    CLI::App* stop = nullptr;
    CLI::App* pause = nullptr;
    CLI::App* resume = nullptr;
    CLI::App* exporter = nullptr;
};

namespace {

constexpr const char* kApi = "/api/v1";

// --------------------------------------------------------------------------------------------------------
// HTTP client

struct Url {
    std::string host, port, prefix;  // prefix: path the daemon is mounted under (reverse proxy), may be ""
};

Url parse_server(const std::string& text) {
    std::string rest = text;
    const auto scheme = rest.find("://");
    if (scheme != std::string::npos) {
        const std::string s = rest.substr(0, scheme);
        if (s == "https")
            throw InputError("--server " + text +
                             ": https is not supported by cellbench; reach the daemon over loopback or an SSH tunnel");
        if (s != "http") throw InputError("--server " + text + ": expected http://HOST:PORT");
        rest = rest.substr(scheme + 3);
    }
    Url u;
    const auto slash = rest.find('/');
    if (slash != std::string::npos) {
        u.prefix = rest.substr(slash);
        while (!u.prefix.empty() && u.prefix.back() == '/') u.prefix.pop_back();
        rest = rest.substr(0, slash);
    }
    std::string hostport = rest;
    if (!hostport.empty() && hostport.front() == '[') {  // [v6]:port
        const auto close = hostport.find(']');
        if (close == std::string::npos) throw InputError("--server " + text + ": expected http://HOST:PORT");
        u.host = hostport.substr(1, close - 1);
        u.port = close + 1 < hostport.size() && hostport[close + 1] == ':' ? hostport.substr(close + 2) : "80";
    } else {
        const auto colon = hostport.rfind(':');
        u.host = hostport.substr(0, colon);
        u.port = colon == std::string::npos ? "80" : hostport.substr(colon + 1);
    }
    if (u.host.empty() || u.port.empty() || u.port.find_first_not_of("0123456789") != std::string::npos)
        throw InputError("--server " + text + ": expected http://HOST:PORT (e.g. http://127.0.0.1:8750)");
    return u;
}

struct Response {
    unsigned status = 0;
    std::string reason;
    std::string body;
};

class Client {
public:
    explicit Client(const ClientCommands& o)
        : url_(parse_server(o.server)), display_(o.server), token_(o.token),
          timeout_(std::chrono::milliseconds(static_cast<long long>(o.timeout_s * 1000))) {}

    const std::string& display() const { return display_; }

    // One request and its whole answer (JSON-sized).
    Response request(http::verb method, const std::string& path, const std::optional<json>& body = std::nullopt) {
        Exchange x(*this);
        x.send(method, path, body);
        http::response_parser<http::string_body> parser;
        parser.body_limit(256 * 1024 * 1024);
        x.read(parser, method, path, /*header_only=*/false);
        auto res = parser.release();
        return {res.result_int(), std::string(res.reason()), std::move(res.body())};
    }

    json get(const std::string& path) { return expect_json(http::verb::get, path, request(http::verb::get, path)); }
    json post(const std::string& path, const json& body) {
        return expect_json(http::verb::post, path, request(http::verb::post, path, body));
    }

    // Streams a 200 answer's body into `out` (any transfer encoding); returns the bytes written. An
    // error status throws before `out` sees anything; a cut transfer throws afterwards.
    template <class OpenSink>
    std::size_t download(const std::string& path, OpenSink&& open_sink) {
        Exchange x(*this);
        x.send(http::verb::get, path, std::nullopt);
        http::response_parser<http::buffer_body> parser;
        parser.body_limit(std::numeric_limits<std::uint64_t>::max());
        x.read(parser, http::verb::get, path, /*header_only=*/true);
        std::string error_body;
        const bool ok = parser.get().result_int() == 200;
        std::size_t total = 0;
        const auto pump = [&](const std::function<void(const char*, std::size_t)>& sink) {
            std::array<char, 64 * 1024> buf;
            while (!parser.is_done()) {
                parser.get().body().data = buf.data();
                parser.get().body().size = buf.size();
                x.read(parser, http::verb::get, path, false);
                const std::size_t n = buf.size() - parser.get().body().size;
                if (n) sink(buf.data(), n);
                total += n;
            }
        };
        if (!ok) {
            pump([&](const char* p, std::size_t n) {
                if (error_body.size() < 64 * 1024) error_body.append(p, n);
            });
            throw InputError(describe(http::verb::get, path,
                                      {parser.get().result_int(), std::string(parser.get().reason()), error_body}));
        }
        open_sink([&](const std::function<void(const char*, std::size_t)>& sink) { pump(sink); });
        return total;
    }

    // "cellbenchd: GET /api/v1/runs/9 -> 404 Not Found: no run 9"
    std::string describe(http::verb method, const std::string& path, const Response& r) const {
        std::string message;
        try {
            const auto j = json::parse(r.body);
            if (j.is_object() && j.contains("error") && j["error"].is_string()) message = j["error"].get<std::string>();
        } catch (const json::exception&) {
        }
        if (message.empty()) message = r.body.substr(0, 200);
        std::string out = "cellbenchd at " + display_ + ": " + std::string(http::to_string(method)) + " " + path +
                          " -> " + std::to_string(r.status) + " " + r.reason;
        if (!message.empty()) out += ": " + message;
        return out;
    }

private:
    json expect_json(http::verb method, const std::string& path, const Response& r) const {
        if (r.status < 200 || r.status >= 300) throw InputError(describe(method, path, r));
        try {
            return json::parse(r.body);
        } catch (const json::parse_error& e) {
            throw InputError("cellbenchd at " + display_ + ": " + std::string(http::to_string(method)) + " " + path +
                             ": the answer is not JSON (" + e.what() + "); is --server pointing at cellbenchd?");
        }
    }

    // One connection: each step runs to completion on a private io_context, under the deadline.
    class Exchange {
    public:
        explicit Exchange(Client& c) : c_(c), stream_(ioc_) {
            tcp::resolver resolver(ioc_);
            beast::error_code ec;
            const auto endpoints = resolver.resolve(c_.url_.host, c_.url_.port, ec);
            if (ec)
                throw InputError("cannot reach cellbenchd at " + c_.display_ + ": cannot resolve " + c_.url_.host + ": " +
                                 ec.message());
            stream_.expires_after(c_.timeout_);
            ec = run([&](auto h) { stream_.async_connect(endpoints, h); });
            if (ec) fail("connect", ec);
        }
        ~Exchange() {
            beast::error_code ec;
            stream_.socket().shutdown(tcp::socket::shutdown_both, ec);
        }

        void send(http::verb method, const std::string& path, const std::optional<json>& body) {
            http::request<http::string_body> req{method, c_.url_.prefix + path, 11};
            req.set(http::field::host, c_.url_.host + ":" + c_.url_.port);
            req.set(http::field::user_agent, "cellbench");
            req.set(http::field::accept, "application/json, text/csv");
            req.keep_alive(false);
            if (!c_.token_.empty()) req.set(http::field::authorization, "Bearer " + c_.token_);
            if (body) {
                req.set(http::field::content_type, "application/json");
                req.body() = body->dump();
            }
            req.prepare_payload();
            stream_.expires_after(c_.timeout_);
            const auto ec = run([&](auto h) { http::async_write(stream_, req, h); });
            if (ec) fail(std::string(http::to_string(method)) + " " + path, ec);
        }

        template <class Parser>
        void read(Parser& parser, http::verb method, const std::string& path, bool header_only) {
            stream_.expires_after(c_.timeout_);  // per read: a long export keeps going while data flows
            const auto ec = run([&](auto h) {
                if (header_only)
                    http::async_read_header(stream_, buffer_, parser, h);
                else
                    http::async_read(stream_, buffer_, parser, h);
            });
            if (ec && ec != http::error::need_buffer) fail(std::string(http::to_string(method)) + " " + path, ec);
        }

    private:
        template <class Start>
        beast::error_code run(Start&& start) {
            beast::error_code result = net::error::would_block;
            start([&result](beast::error_code ec, auto&&...) { result = ec; });
            ioc_.restart();
            ioc_.run();
            return result;
        }

        [[noreturn]] void fail(const std::string& what, beast::error_code ec) const {
            if (ec == beast::error::timeout)
                throw InputError("cellbenchd at " + c_.display_ + " did not answer within " +
                                 fmt::format("{:g}", c_.timeout_.count() / 1000.0) + " s (" + what + ")");
            if (ec == net::error::connection_refused)
                throw InputError("cannot connect to cellbenchd at " + c_.display_ +
                                 ": connection refused (is cellbenchd running? --server or CELLBENCH_SERVER selects "
                                 "the address)");
            if (what == "connect")
                throw InputError("cannot connect to cellbenchd at " + c_.display_ + ": " + ec.message());
            throw InputError("cellbenchd at " + c_.display_ + ": " + what + ": " + ec.message());
        }

        Client& c_;
        net::io_context ioc_;
        beast::tcp_stream stream_;
        beast::flat_buffer buffer_;
    };

    Url url_;
    std::string display_;
    std::string token_;
    std::chrono::milliseconds timeout_;
};

// --------------------------------------------------------------------------------------------------------
// Formatting

std::optional<double> num(const json& j, const char* key) {
    if (!j.is_object()) return std::nullopt;
    const auto it = j.find(key);
    if (it == j.end() || !it->is_number()) return std::nullopt;
    return it->get<double>();
}

std::string str(const json& j, const char* key, const std::string& fallback = "-") {
    if (!j.is_object()) return fallback;
    const auto it = j.find(key);
    if (it == j.end() || it->is_null()) return fallback;
    if (it->is_string()) return it->get<std::string>();
    return it->dump();
}

std::string duration(double s) {
    if (!(s >= 0)) return "-";
    const auto t = static_cast<long long>(s);
    if (t < 60) return fmt::format("{} s", t);
    if (t < 3600) return fmt::format("{} min {:02} s", t / 60, t % 60);
    if (t < 86400) return fmt::format("{} h {:02} min", t / 3600, t % 3600 / 60);
    return fmt::format("{} d {:02} h", t / 86400, t % 86400 / 3600);
}

std::string local_time(const json& j, const char* key) {
    const auto s = num(j, key);
    if (!s) return "-";
    const std::time_t t = static_cast<std::time_t>(*s);
    std::tm tm{};
    localtime_r(&t, &tm);
    char buf[32];
    std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", &tm);
    return buf;
}

// "step 12/140 CC discharge"
std::string step_text(const json& run) {
    const json step = run.is_object() && run.contains("step") ? run["step"] : json();
    if (!step.is_object()) return {};
    std::string s = "step " + (num(step, "index") ? fmt::format("{:.0f}", *num(step, "index")) : std::string("?"));
    if (const auto n = num(step, "count")) s += fmt::format("/{:.0f}", *n);
    if (const auto type = str(step, "type", ""); !type.empty()) s += " " + type;
    return s;
}

// "SOC 62.1 %  3.712 V  -3.820 A  30.4 degC" (what the progress line shows); unmeasured values left out.
std::string live_text(const json& live, bool all) {
    std::string s;
    const auto add = [&](const std::string& part) { s += (s.empty() ? "" : "  ") + part; };
    if (const auto v = num(live, "soc")) add(fmt::format("SOC {:.1f} %", *v * 100));
    if (const auto v = num(live, "voltage_v")) add(fmt::format("{:.3f} V", *v));
    if (const auto v = num(live, "current_a")) add(fmt::format("{:+.3f} A", *v));
    if (!all) {
        auto t = num(live, "surface_c");
        if (!t) t = num(live, "t1_c");
        if (t) add(fmt::format("{:.1f} degC", *t));
        return s;
    }
    if (const auto v = num(live, "surface_c")) add(fmt::format("surface {:.1f} degC", *v));
    if (const auto v = num(live, "ambient_c")) add(fmt::format("ambient {:.1f} degC", *v));
    if (const auto v = num(live, "t1_c")) add(fmt::format("T1 {:.1f} degC", *v));
    if (const auto v = num(live, "t2_c")) add(fmt::format("T2 {:.1f} degC", *v));
    if (const auto v = num(live, "heat_flux_w_per_m2")) add(fmt::format("heat flux {:.1f} W/m^2", *v));
    return s;
}

std::string run_summary(const json& run) {
    std::string s = fmt::format("run {}: {} on {}, {}", str(run, "id"), str(run, "program"), str(run, "cell"),
                                str(run, "state"));
    if (const auto o = str(run, "outcome", ""); !o.empty() && o != str(run, "state", "")) s += " (" + o + ")";
    if (const auto st = step_text(run); !st.empty()) {
        s += ", " + st;
        if (const auto e = num(run["step"], "elapsed_s")) s += " for " + duration(*e);
    }
    if (const auto err = str(run, "error", ""); !err.empty()) s += " (" + err + ")";
    return s;
}

void print_json(const json& j) { std::printf("%s\n", j.dump(2).c_str()); }

bool terminal_state(const std::string& state) {
    // "failed": what daemons before the run-state vocabulary of INTERFACES.md answered for aborted/interrupted.
    return state == "completed" || state == "stopped" || state == "aborted" || state == "interrupted" || state == "failed";
}

// --------------------------------------------------------------------------------------------------------
// Commands

int cmd_status(const ClientCommands& o) {
    Client c(o);
    const json st = c.get(std::string(kApi) + "/status");
    if (o.json_output) {
        print_json(st);
        return 0;
    }
    std::string head = "cellbenchd";
    if (const auto v = str(st, "version", ""); !v.empty()) head += " " + v;
    head += " at " + c.display();
    if (const auto up = num(st, "uptime_s")) head += ", up " + duration(*up);
    std::printf("%s\n", head.c_str());
    const json instruments = st.value("instruments", json::array());
    if (instruments.is_array() && !instruments.empty()) {
        std::printf("%-12s %-9s %-11s %-22s %s\n", "INSTRUMENT", "KIND", "STATE", "ADDRESS", "DETAIL");
        for (const auto& i : instruments)
            std::printf("%-12s %-9s %-11s %-22s %s\n", str(i, "name").c_str(), str(i, "kind").c_str(),
                        str(i, "state").c_str(), str(i, "address").c_str(), str(i, "detail", "").c_str());
    }
    const json run = st.value("run", json());
    std::printf("%s\n", run.is_object() ? run_summary(run).c_str() : "no active run");
    if (const auto live = live_text(st.value("live", json()), true); !live.empty()) std::printf("%s\n", live.c_str());
    return 0;
}

int cmd_runs(const ClientCommands& o) {
    Client c(o);
    const json r = c.get(std::string(kApi) + "/runs");
    if (o.json_output) {
        print_json(r);
        return 0;
    }
    const json runs = r.value("runs", json::array());
    if (!runs.is_array() || runs.empty()) {
        std::printf("no runs\n");
        return 0;
    }
    std::printf("%6s  %-14s %-14s %-10s %-19s  %-19s  %9s\n", "ID", "PROGRAM", "CELL", "STATE", "STARTED", "ENDED",
                "SAMPLES");
    for (const auto& run : runs) {
        const auto samples = num(run, "samples");
        std::printf("%6s  %-14s %-14s %-10s %-19s  %-19s  %9s\n", str(run, "id").c_str(), str(run, "program").c_str(),
                    str(run, "cell").c_str(), str(run, "state").c_str(), local_time(run, "started_unix_s").c_str(),
                    local_time(run, "ended_unix_s").c_str(),
                    samples ? fmt::format("{:.0f}", *samples).c_str() : "-");
    }
    return 0;
}

// The progress line fits the terminal so that "\r" rewrites it in place instead of wrapping.
void show_progress(const std::string& line) {
    winsize ws{};
    std::size_t width = 100;
    if (::ioctl(STDERR_FILENO, TIOCGWINSZ, &ws) == 0 && ws.ws_col > 10) width = ws.ws_col - 1;
    const std::string shown = line.size() > width ? line.substr(0, width) : line;
    std::fprintf(stderr, "\r\033[K%s", shown.c_str());
    std::fflush(stderr);
}

// Polls /status until the run reaches a terminal state; exit 0 only when it completed.
int follow_run(Client& c, long long id, const ClientCommands& o) {
    const bool tty = stderr_is_terminal();
    const auto interval = std::chrono::milliseconds(static_cast<long long>(std::max(0.01, o.interval_s) * 1000));
    const std::string run_path = std::string(kApi) + "/runs/" + std::to_string(id);
    int failures = 0;
    bool shown = false;
    json final_run;
    for (bool first = true;; first = false) {
        if (!first) std::this_thread::sleep_for(interval);
        try {
            const json st = c.get(std::string(kApi) + "/status");
            const json run = st.value("run", json());
            if (run.is_object() && run.value("id", json()) == json(id) && !terminal_state(str(run, "state", ""))) {
                if (tty) {
                    std::string line = fmt::format("run {} {}", id, str(run, "state", ""));
                    if (const auto s = step_text(run); !s.empty()) line += "  " + s;
                    if (const auto l = live_text(st.value("live", json()), false); !l.empty()) line += "  " + l;
                    show_progress(line);
                    shown = true;
                }
            } else {
                const json r = c.get(run_path);  // not the active run any more (or not yet): ask about it
                if (terminal_state(str(r, "state", ""))) {
                    final_run = r;
                    break;
                }
            }
            failures = 0;
        } catch (const InputError& e) {
            // Ride out a daemon restart or a busy moment; give up after ~10 polls in a row.
            if (++failures >= 10)
                throw InputError(std::string(e.what()) + " (stopped following run " + std::to_string(id) +
                                 "; it may still be going: cellbench status)");
        }
    }
    if (shown) std::fprintf(stderr, "\r\033[K");
    if (o.json_output)
        print_json(final_run);
    else
        std::printf("%s\n", run_summary(final_run).c_str());
    return str(final_run, "state", "") == "completed" ? 0 : 1;
}

}  // namespace

// `--param K=V`... as the "parameters" object of POST /runs (values typed by parse_override_argument; the
// daemon's program loader validates them). Every malformed argument at once.
json overrides_json(const std::vector<std::string>& params) {
    json out = json::object();
    std::string problems;
    for (const auto& p : params) {
        try {
            auto [k, v] = daemon::parse_override_argument(p);
            if (out.contains(k)) problems += "\n  --param " + k + ": given more than once";
            out[k] = std::move(v);
        } catch (const InputError& e) {
            problems += "\n  --param: " + std::string(e.what());
        }
    }
    if (!problems.empty()) throw InputError("bad --param arguments:" + problems);
    return out;
}

namespace {

int cmd_start(const ClientCommands& o) {
    json body = {{"program", o.program}, {"cell", o.cell}};
    if (!o.params.empty()) body["parameters"] = overrides_json(o.params);
    Client c(o);
    const json run = c.post(std::string(kApi) + "/runs", body);
    if (!run.is_object() || !run.contains("id") || !run["id"].is_number_integer())
        throw InputError("cellbenchd at " + c.display() + ": POST /api/v1/runs: the answer has no run \"id\"");
    const long long id = run["id"].get<long long>();
    if (!o.follow) {
        if (o.json_output)
            print_json(run);
        else
            std::printf("run %lld started: program %s, cell %s\n", id, str(run, "program", o.program).c_str(),
                        str(run, "cell", o.cell).c_str());
        return 0;
    }
    if (!o.json_output)
        std::printf("run %lld started: program %s, cell %s\n", id, str(run, "program", o.program).c_str(),
                    str(run, "cell", o.cell).c_str());
    std::fflush(stdout);
    return follow_run(c, id, o);
}

// stop / pause / resume: the given run, else the active one.
int cmd_control(const ClientCommands& o, const char* action) {
    Client c(o);
    long long id = o.run_id;
    if (id <= 0) {
        const json st = c.get(std::string(kApi) + "/status");
        const json run = st.value("run", json());
        if (!run.is_object() || !run.contains("id") || !run["id"].is_number_integer())
            throw InputError(std::string("cellbench ") + action + ": no active run on cellbenchd at " + c.display() +
                             " (give a RUN_ID)");
        id = run["id"].get<long long>();
    }
    const json run = c.post(std::string(kApi) + "/runs/" + std::to_string(id) + "/" + action, json::object());
    if (o.json_output)
        print_json(run);
    else
        std::printf("%s\n", run_summary(run).c_str());
    return 0;
}

int cmd_export(const ClientCommands& o) {
    Client c(o);
    std::size_t lines = 0;
    const std::string path = std::string(kApi) + "/runs/" + std::to_string(o.run_id) + "/export.bdf.csv";
    const auto bytes = c.download(path, [&](const auto& pump) {
        write_file_atomic(o.output, [&](std::ostream& out) {
            pump([&](const char* p, std::size_t n) {
                out.write(p, static_cast<std::streamsize>(n));
                lines += static_cast<std::size_t>(std::count(p, p + n, '\n'));
            });
            if (!out) throw InputError(o.output + ": write failed (disk full?)");
        });
    });
    spdlog::info("wrote run {} to {}: {} rows, {} bytes", o.run_id, o.output, lines > 0 ? lines - 1 : 0, bytes);
    return 0;
}

}  // namespace

std::shared_ptr<ClientCommands> add_client_commands(CLI::App& app) {
    auto o = std::make_shared<ClientCommands>();
    const auto common = [&](CLI::App* cmd, bool json_flag) {
        cmd->add_option("--server", o->server, "cellbenchd address, http://HOST:PORT")
            ->envname("CELLBENCH_SERVER")
            ->capture_default_str();
        cmd->add_option("--token", o->token, "API token for starting/stopping runs (default: $CELLBENCH_TOKEN)")
            ->envname("CELLBENCH_TOKEN");
        cmd->add_option("--timeout", o->timeout_s, "Seconds to wait for each answer of the daemon")
            ->check(CLI::PositiveNumber)
            ->capture_default_str();
        if (json_flag) cmd->add_flag("--json", o->json_output, "Print the daemon's JSON answer instead of a table");
        return cmd;
    };
    o->status = common(app.add_subcommand("status", "Show cellbenchd's instruments, active run and live values"), true);
    o->runs = common(app.add_subcommand("runs", "List the runs stored by cellbenchd"), true);

    o->start = common(app.add_subcommand("start", "Start a run on cellbenchd (needs the API token)"), true);
    o->start->add_option("--program", o->program, "Step program name (a file under config/), e.g. hppc")->required();
    o->start->add_option("--cell", o->cell, "Cell name (a file under config/), e.g. p45b")->required();
    o->start->add_option("--param", o->params,
                         "Override a declared program parameter, K=V (repeatable), e.g. --param c_rate=2; validated "
                         "by the daemon like the program (unknown, wrong type or out of range: nothing starts)");
    o->start->add_flag("--follow", o->follow,
                       "Stay until the run ends, with a live progress line on a terminal; exit 0 only if it "
                       "completed (Ctrl-C stops following, not the run)");
    o->start->add_option("--interval", o->interval_s, "Seconds between progress updates with --follow")
        ->check(CLI::PositiveNumber)
        ->capture_default_str();

    for (auto [slot, name, what] : {std::tuple{&o->stop, "stop", "Stop a run (default: the active one)"},
                                    std::tuple{&o->pause, "pause", "Pause a run (default: the active one)"},
                                    std::tuple{&o->resume, "resume", "Resume a paused run (default: the active one)"}}) {
        *slot = common(app.add_subcommand(name, std::string(what) + " (needs the API token)"), true);
        (*slot)->add_option("run_id", o->run_id, "Run id (see cellbench runs)")->check(CLI::PositiveNumber);
    }

    o->exporter = common(app.add_subcommand("export", "Download a run as a BDF CSV recording"), false);
    o->exporter->add_option("run_id", o->run_id, "Run id (see cellbench runs)")->required()->check(CLI::PositiveNumber);
    o->exporter->add_option("-o,--output", o->output, "Output BDF CSV (written atomically)")->required();
    return o;
}

std::optional<int> run_client_command(const ClientCommands& o) {
    if (*o.status) return cmd_status(o);
    if (*o.runs) return cmd_runs(o);
    if (*o.start) return cmd_start(o);
    if (*o.stop) return cmd_control(o, "stop");
    if (*o.pause) return cmd_control(o, "pause");
    if (*o.resume) return cmd_control(o, "resume");
    if (*o.exporter) return cmd_export(o);
    return std::nullopt;
}

}  // namespace cellbench::cli
