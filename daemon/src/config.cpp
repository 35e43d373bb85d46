// Configuration loading: see config.hpp. The readers below never stop at the first problem: each one records
// an issue (file, JSON path, what was expected) and returns a default, so one load reports everything.
#include "cellbench/daemon/config.hpp"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>

#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/chamber_modbus.hpp"
#include "cellbench/protocol/dewe_can.hpp"
#include "cellbench/protocol/json_input.hpp"

namespace cellbench::daemon {

using nlohmann::json;
namespace fs = std::filesystem;

// ---------------------------------------------------------------------------------------------------------
// Errors

std::string ConfigIssue::to_string() const {
    std::string s = file;
    if (!path.empty()) s += (s.empty() ? "" : ": ") + path;
    return s + (s.empty() ? "" : ": ") + message;
}

namespace {
std::string join_issues(const std::vector<ConfigIssue>& issues) {
    std::string s;
    for (const auto& i : issues) {
        if (!s.empty()) s += '\n';
        s += i.to_string();
    }
    return s.empty() ? std::string("invalid configuration") : s;
}
}  // namespace

ConfigError::ConfigError(std::vector<ConfigIssue> issues) : InputError(join_issues(issues)), issues_(std::move(issues)) {}

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

std::string format_number(double v) {
    char buf[64];
    const auto r = std::to_chars(buf, buf + sizeof buf, v);
    return std::string(buf, r.ptr);
}

// "got "abc"", "got -3", "got an array" — for messages.
std::string got(const json& j) {
    switch (j.type()) {
        case json::value_t::null: return "got null";
        case json::value_t::boolean: return std::string("got ") + (j.get<bool>() ? "true" : "false");
        case json::value_t::string: {
            std::string s = j.get<std::string>();
            if (s.size() > 40) s = s.substr(0, 37) + "...";
            return "got \"" + s + "\"";
        }
        case json::value_t::number_integer:
        case json::value_t::number_unsigned:
        case json::value_t::number_float: return "got " + j.dump();
        case json::value_t::array: return "got an array";
        case json::value_t::object: return "got an object";
        default: return std::string("got ") + j.type_name();
    }
}

struct Ctx {
    std::string file;
    std::vector<ConfigIssue> issues;

    void add(const std::string& path, const std::string& message) { issues.push_back({file, path, message}); }
    [[nodiscard]] std::size_t count() const { return issues.size(); }

    // Throws the collected issues (duplicates removed, order kept).
    void throw_if_any() {
        if (issues.empty()) return;
        std::vector<ConfigIssue> unique;
        for (auto& i : issues)
            if (std::find(unique.begin(), unique.end(), i) == unique.end()) unique.push_back(std::move(i));
        throw ConfigError(std::move(unique));
    }

    // An InputError thrown by another layer's parser called with source = `marker`: its message reads
    // "MARKER: PATH: what" (PATH with or without a leading "$"); re-root PATH under `base_path`.
    void add_nested(const std::string& base_path, const std::string& marker, const std::string& message) {
        const std::string prefix = marker + ": ";
        if (message.rfind(prefix, 0) == 0) {
            std::string rest = message.substr(prefix.size());
            const auto sep = rest.find(": ");
            if (sep != std::string::npos) {
                std::string sub = rest.substr(0, sep);
                std::string what = rest.substr(sep + 2);
                if (sub == "$" || sub == "(root)") sub.clear();
                else if (sub.rfind("$", 0) == 0) sub = sub.substr(1);
                else if (!sub.empty() && sub.front() != '[') sub = "." + sub;
                add(base_path + sub, what);
                return;
            }
            add(base_path, rest);
            return;
        }
        add(base_path, message);
    }
};

inline const std::string kNestedMarker = "\x01nested";

struct Range {
    double lo = -kInf, hi = kInf;
    bool lo_open = false, hi_open = false;

    static Range any() { return {}; }
    static Range positive() { return {0.0, kInf, true, false}; }
    static Range non_negative() { return {0.0, kInf, false, false}; }
    static Range closed(double a, double b) { return {a, b, false, false}; }

    [[nodiscard]] bool contains(double v) const {
        if (!std::isfinite(v)) return false;
        if (lo_open ? !(v > lo) : !(v >= lo)) return false;
        if (hi_open ? !(v < hi) : !(v <= hi)) return false;
        return true;
    }
    [[nodiscard]] std::string describe(const char* what = "a number") const {
        std::string s = what;
        if (lo == -kInf && hi == kInf) return s;
        if (hi == kInf) return s + (lo_open ? " > " : " >= ") + format_number(lo);
        if (lo == -kInf) return s + (hi_open ? " < " : " <= ") + format_number(hi);
        return s + " in " + (lo_open ? "(" : "[") + format_number(lo) + ", " + format_number(hi) + (hi_open ? ")" : "]");
    }
};

// Reads the members of one JSON object, recording problems; finish() reports members nobody asked for.
// Keys starting with "_" are comments and always allowed.
class Obj {
public:
    Obj(Ctx& ctx, const json* j, std::string path) : ctx_(ctx), path_(std::move(path)) {
        if (j == nullptr) return;
        if (!j->is_object()) {
            ctx_.add(path_, "expected an object, " + got(*j));
            return;
        }
        j_ = j;
    }

    [[nodiscard]] bool ok() const { return j_ != nullptr; }
    [[nodiscard]] const std::string& path() const { return path_; }
    [[nodiscard]] std::string child(std::string_view key) const { return path_ + "." + std::string(key); }
    Ctx& ctx() { return ctx_; }

    // The member, or nullptr (recording "missing" when required).
    const json* get(std::string_view key, bool required = false) {
        known_.insert(std::string(key));
        if (!j_) return nullptr;
        const auto it = j_->find(key);
        if (it == j_->end()) {
            if (required) ctx_.add(child(key), "missing (required)");
            return nullptr;
        }
        return &*it;
    }
    [[nodiscard]] bool has(std::string_view key) const { return j_ && j_->contains(key); }

    std::optional<double> number(std::string_view key, bool required, Range range = {}, const char* what = "a number") {
        const json* v = get(key, required);
        if (!v) return std::nullopt;
        if (!v->is_number() || !range.contains(v->get<double>())) {
            ctx_.add(child(key), "expected " + range.describe(what) + ", " + got(*v));
            return std::nullopt;
        }
        return v->get<double>();
    }
    double number_or(std::string_view key, double fallback, Range range = {}, const char* what = "a number") {
        return number(key, false, range, what).value_or(fallback);
    }

    std::optional<long long> integer(std::string_view key, bool required, long long lo, long long hi) {
        const json* v = get(key, required);
        if (!v) return std::nullopt;
        const bool integral = v->is_number_integer() ||
                              (v->is_number_float() && std::floor(v->get<double>()) == v->get<double>() &&
                               std::abs(v->get<double>()) < 9e15);
        const long long x = integral ? (v->is_number_float() ? static_cast<long long>(v->get<double>()) : v->get<long long>()) : 0;
        if (!integral || x < lo || x > hi) {
            ctx_.add(child(key), "expected an integer " + std::to_string(lo) + ".." + std::to_string(hi) + ", " + got(*v));
            return std::nullopt;
        }
        return x;
    }
    long long integer_or(std::string_view key, long long fallback, long long lo, long long hi) {
        return integer(key, false, lo, hi).value_or(fallback);
    }

    std::optional<std::string> string(std::string_view key, bool required, bool non_empty = true) {
        const json* v = get(key, required);
        if (!v) return std::nullopt;
        if (!v->is_string() || (non_empty && v->get<std::string>().empty())) {
            ctx_.add(child(key), std::string("expected ") + (non_empty ? "a non-empty string" : "a string") + ", " + got(*v));
            return std::nullopt;
        }
        return v->get<std::string>();
    }

    // One of `choices`; returns its index.
    std::optional<std::size_t> choice(std::string_view key, bool required, const std::vector<std::string>& choices) {
        const json* v = get(key, required);
        if (!v) return std::nullopt;
        if (v->is_string()) {
            const auto s = v->get<std::string>();
            for (std::size_t i = 0; i < choices.size(); ++i)
                if (s == choices[i]) return i;
        }
        std::string list;
        for (std::size_t i = 0; i < choices.size(); ++i)
            list += (i ? (i + 1 == choices.size() ? " or " : ", ") : "") + ("\"" + choices[i] + "\"");
        ctx_.add(child(key), "expected " + list + ", " + got(*v));
        return std::nullopt;
    }

    std::optional<bool> boolean(std::string_view key, bool required) {
        const json* v = get(key, required);
        if (!v) return std::nullopt;
        if (!v->is_boolean()) {
            ctx_.add(child(key), "expected true or false, " + got(*v));
            return std::nullopt;
        }
        return v->get<bool>();
    }

    // Reports members that were never asked for.
    void finish() {
        if (!j_) return;
        for (const auto& [key, value] : j_->items()) {
            if (key.rfind('_', 0) == 0 || known_.count(key)) continue;
            std::string list;
            for (const auto& k : known_) list += (list.empty() ? "" : ", ") + k;
            ctx_.add(child(key), "unknown field (expected one of: " + list + ")");
        }
    }

private:
    Ctx& ctx_;
    const json* j_ = nullptr;
    std::string path_;
    std::set<std::string> known_;
};

std::string read_text_file(const fs::path& file) {
    // Only regular files: a device or FIFO named by mistake (/dev/zero, a pipe) would never end.
    std::error_code ec;
    const auto status = fs::status(file, ec);
    if (fs::exists(status) && !fs::is_regular_file(status))
        throw InputError(file.string() + ": cannot read: not a regular file");
    // Every config, program and cell is a few kB; a huge file is a mistake, not something to read into memory.
    constexpr std::uintmax_t kMaxConfigBytes = 16u << 20;
    if (fs::is_regular_file(status) && fs::file_size(file, ec) > kMaxConfigBytes && !ec)
        throw InputError(file.string() + ": cannot read: larger than 16 MiB (not a cellbench JSON file)");
    std::ifstream in(file, std::ios::binary);
    if (!in) {
        const bool exists = fs::exists(file, ec);
        throw InputError(file.string() + ": cannot read: " + (exists ? "permission denied or not a file" : "no such file"));
    }
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

json parse_json_text(std::string_view text, const std::string& source) {
    // Nesting bounded, numbers that overflow a double (1e400) rejected: InputError naming the file.
    return protocol::parse_json_input(text, source);
}

json read_json_file(const fs::path& file) { return parse_json_text(read_text_file(file), file.string()); }

void check_schema(Obj& o, const char* expected) {
    const json* v = o.get("schema", true);
    if (!v) return;
    if (!v->is_string() || v->get<std::string>() != expected) {
        std::string hint;
        if (v->is_string() && v->get<std::string>() == estimator::kParamsSchema)
            hint = " (this file is a parameter set, not a " + std::string(expected) + " file)";
        o.ctx().add(o.child("schema"), std::string("expected \"") + expected + "\", " + got(*v) + hint);
    }
}

fs::path resolve(const fs::path& base_dir, const std::string& p) {
    fs::path path(p);
    return path.is_absolute() ? path : (base_dir / path).lexically_normal();
}

// A referenced parameter set must exist and be valid.
void check_params_file(Ctx& ctx, const std::string& json_path, const fs::path& file) {
    try {
        estimator::ParameterSet::from_json(read_json_file(file), file.string());
    } catch (const InputError& e) {
        ctx.add(json_path, std::string("parameter set does not load: ") + e.what());
    }
}

std::optional<Endpoint> endpoint_of(Obj& o, bool allow_port_zero) {
    const auto host = o.string("host", true);
    const auto port = o.integer("port", true, allow_port_zero ? 0 : 1, 65535);
    if (!host || !port) return std::nullopt;
    return Endpoint{*host, static_cast<int>(*port)};
}

bool valid_env_name(const std::string& s) {
    if (s.empty() || std::isdigit(static_cast<unsigned char>(s[0]))) return false;
    return std::all_of(s.begin(), s.end(), [](char c) { return std::isupper(static_cast<unsigned char>(c)) || std::isdigit(static_cast<unsigned char>(c)) || c == '_'; });
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Endpoint

std::string Endpoint::to_string() const { return host + ":" + std::to_string(port); }

std::optional<Endpoint> parse_endpoint(std::string_view text) {
    const auto colon = text.rfind(':');
    if (colon == std::string_view::npos || colon == 0 || colon + 1 >= text.size()) return std::nullopt;
    int port = 0;
    const auto digits = text.substr(colon + 1);
    const auto r = std::from_chars(digits.data(), digits.data() + digits.size(), port);
    if (r.ec != std::errc() || r.ptr != digits.data() + digits.size() || port < 0 || port > 65535) return std::nullopt;
    std::string host(text.substr(0, colon));
    if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
    if (host.empty() || host.find_first_of(" \t/") != std::string::npos) return std::nullopt;
    return Endpoint{host, port};
}

// ---------------------------------------------------------------------------------------------------------
// Bench

BenchConfig parse_bench_config(const json& j, const std::string& source, const fs::path& base_dir) {
    Ctx ctx{source, {}};
    BenchConfig b;
    b.source = source;
    b.config_dir = base_dir;
    b.document = j;

    Obj root(ctx, &j, "$");
    check_schema(root, kBenchSchema);
    b.name = root.string("name", false, false).value_or("");
    b.token_env = root.string("token_env", false).value_or(b.token_env);
    if (root.has("token_env") && !valid_env_name(b.token_env))
        ctx.add("$.token_env", "expected an environment variable name (A-Z, 0-9, _), got \"" + b.token_env + "\"");
    if (const auto listen = root.string("listen", false)) {
        const auto e = parse_endpoint(*listen);
        if (!e || e->port == 0) ctx.add("$.listen", "expected \"HOST:PORT\" with a port 1..65535, got \"" + *listen + "\"");
        else b.listen = *e;
    }

    Obj inst(ctx, root.get("instruments", true), "$.instruments");

    // Cycler.
    {
        Obj c(ctx, inst.get("cycler", true), "$.instruments.cycler");
        if (c.ok()) {
            auto& cy = b.cycler;
            cy.mode = c.choice("mode", true, {"simulated", "tcp"}).value_or(0) == 0 ? CyclerConfig::Mode::simulated
                                                                                  : CyclerConfig::Mode::tcp;
            if (auto e = endpoint_of(c, cy.mode == CyclerConfig::Mode::simulated)) cy.endpoint = *e;
            cy.poll_period_ms = static_cast<int>(c.integer_or("poll_period_ms", 100, 10, 60000));
            cy.response_timeout_ms = static_cast<int>(c.integer_or("response_timeout_ms", 2000, 50, 60000));
            cy.channel_max_current_a = c.number_or("channel_max_current_a", 20.0, Range::positive());
            const json* chans = c.get("channels", true);
            if (chans && (!chans->is_array() || chans->empty())) {
                ctx.add(c.child("channels"), "expected a non-empty array of channel addresses (the parallel group), " + got(*chans));
            } else if (chans) {
                for (std::size_t i = 0; i < chans->size(); ++i) {
                    Obj a(ctx, &(*chans)[i], c.child("channels") + "[" + std::to_string(i) + "]");
                    if (!a.ok()) continue;
                    protocol::neware::ChannelAddress addr;
                    addr.ip = a.string("ip", true).value_or("");
                    addr.devtype = static_cast<int>(a.integer("devtype", true, 0, 255).value_or(0));
                    addr.devid = static_cast<int>(a.integer("devid", true, 0, 65535).value_or(0));
                    addr.subdevid = static_cast<int>(a.integer("subdevid", true, 0, 65535).value_or(0));
                    addr.chlid = static_cast<int>(a.integer("chlid", true, 0, 65535).value_or(0));
                    a.finish();
                    for (const auto& other : cy.channels)
                        if (other == addr) ctx.add(a.path(), "duplicate channel (each member of the group once)");
                    cy.channels.push_back(addr);
                }
                if (cy.channels.size() > 4)
                    ctx.add(c.child("channels"), "expected at most 4 members (Neware parallels up to four channels), got " +
                                                    std::to_string(cy.channels.size()));
            }
            Obj g(ctx, c.get("group"), c.child("group"));
            auto& go = cy.group;
            go.voltage_tolerance_v = g.number_or("voltage_tolerance_v", go.voltage_tolerance_v, Range::positive());
            go.current_share_tolerance = g.number_or("current_share_tolerance", go.current_share_tolerance, Range{0, 1, true, false});
            go.current_share_tolerance_a = g.number_or("current_share_tolerance_a", go.current_share_tolerance_a, Range::non_negative());
            go.min_current_for_sharing_a = g.number_or("min_current_for_sharing_a", go.min_current_for_sharing_a, Range::non_negative());
            go.fault_after_samples = static_cast<int>(g.integer_or("fault_after_samples", go.fault_after_samples, 1, 100));
            g.finish();
        }
        c.finish();
    }

    // DAQ.
    {
        Obj d(ctx, inst.get("daq", true), "$.instruments.daq");
        if (d.ok()) {
            auto& dq = b.daq;
            dq.mode = d.choice("mode", true, {"simulated", "can"}).value_or(0) == 0 ? DaqConfig::Mode::simulated
                                                                                 : DaqConfig::Mode::can;
            dq.transport = d.choice("transport", true, {"can-dgram", "socketcan"}).value_or(0) == 0
                               ? DaqConfig::Transport::can_dgram
                               : DaqConfig::Transport::socketcan;
            if (dq.transport == DaqConfig::Transport::can_dgram) {
                dq.socket_path = d.string("socket_path", true).value_or("");
                if (dq.socket_path.size() >= 108)  // sizeof(sockaddr_un::sun_path)
                    ctx.add(d.child("socket_path"), "expected a path shorter than 108 bytes (Unix socket limit)");
                if (d.has("interface")) ctx.add(d.child("interface"), "only for transport \"socketcan\" (this one is \"can-dgram\")");
                d.get("interface");
            } else {
                dq.interface = d.string("interface", true).value_or("");
                if (dq.interface.size() >= 16)  // IFNAMSIZ
                    ctx.add(d.child("interface"), "expected an interface name shorter than 16 bytes");
                if (d.has("socket_path")) ctx.add(d.child("socket_path"), "only for transport \"can-dgram\" (this one is \"socketcan\")");
                d.get("socket_path");
            }
            if (const json* layout = d.get("layout")) {
                try {
                    dq.layout = protocol::DeweCanLayout::from_json(*layout, kNestedMarker).to_json();
                } catch (const InputError& e) {
                    ctx.add_nested(d.child("layout"), kNestedMarker, e.what());
                }
            } else {
                dq.layout = protocol::DeweCanLayout::bench_default().to_json();
            }
            // Sensitivity of a thermopile heat flux sensor: microvolts per W/m^2 (the thesis' FHF05: 17.39e-6).
            dq.sensitivity_v_per_w_per_m2 =
                d.number("sensitivity_v_per_w_per_m2", true, Range{0.0, 1e-3, true, false}).value_or(dq.sensitivity_v_per_w_per_m2);
            dq.sensor_area_m2 = d.number("sensor_area_m2", true, Range{0.0, 1.0, true, false}).value_or(dq.sensor_area_m2);
            dq.cell_area_m2 = d.number("cell_area_m2", true, Range{0.0, 1.0, true, false}).value_or(dq.cell_area_m2);
            dq.stale_after_s = d.number_or("stale_after_s", dq.stale_after_s, Range::positive());
        }
        d.finish();
    }

    // Chamber.
    {
        Obj c(ctx, inst.get("chamber", true), "$.instruments.chamber");
        if (c.ok()) {
            auto& ch = b.chamber;
            ch.mode = c.choice("mode", true, {"simulated", "modbus-tcp"}).value_or(0) == 0 ? ChamberConfig::Mode::simulated
                                                                                        : ChamberConfig::Mode::modbus_tcp;
            if (auto e = endpoint_of(c, ch.mode == ChamberConfig::Mode::simulated)) ch.endpoint = *e;
            ch.unit_id = static_cast<int>(c.integer_or("unit_id", 1, 0, 247));
            ch.poll_period_ms = static_cast<int>(c.integer_or("poll_period_ms", 1000, 50, 60000));
            bool map_ok = true;
            protocol::ChamberRegisterMap map = protocol::ChamberRegisterMap::bench_default();
            if (const json* rm = c.get("register_map")) {
                try {
                    map = protocol::ChamberRegisterMap::from_json(*rm, kNestedMarker);
                } catch (const InputError& e) {
                    ctx.add_nested(c.child("register_map"), kNestedMarker, e.what());
                    map_ok = false;
                }
            }
            ch.register_map = map.to_json();
            ch.setpoint_min_c = map.setpoint_min_c;
            ch.setpoint_max_c = map.setpoint_max_c;
            if (const auto safe = c.number("safe_setpoint_c", true)) {
                ch.safe_setpoint_c = *safe;
                if (map_ok && (*safe < ch.setpoint_min_c || *safe > ch.setpoint_max_c))
                    ctx.add(c.child("safe_setpoint_c"), "expected a set point the chamber accepts (" +
                                                            format_number(ch.setpoint_min_c) + ".." +
                                                            format_number(ch.setpoint_max_c) + " degC), got " + format_number(*safe));
            }
        }
        c.finish();
    }
    inst.finish();

    // Simulation (needed as soon as one instrument is simulated).
    if (const json* sj = root.get("simulation")) {
        Obj s(ctx, sj, "$.simulation");
        SimulationConfig sim;
        sim.time_scale = s.number_or("time_scale", 1.0, Range{0.0, 100000.0, true, false});
        sim.seed = static_cast<std::uint32_t>(s.integer_or("seed", 1, 0, 4294967295LL));
        if (const auto p = s.string("params", true)) {
            sim.params_path = resolve(base_dir, *p);
            check_params_file(ctx, s.child("params"), sim.params_path);
        }
        sim.initial_soc = s.number_or("initial_soc", 1.0, Range::closed(0.0, 1.0));
        sim.initial_temperature_c = s.number_or("initial_temperature_c", 25.0, Range::closed(-40.0, 80.0));
        if (const json* h = s.get("hidden")) {
            if (!h->is_object()) ctx.add(s.child("hidden"), "expected an object of hidden effects, " + got(*h));
            else sim.hidden = *h;
        }
        s.finish();
        b.simulation = sim;
    } else if (b.any_simulated()) {
        ctx.add("$.simulation", "missing (required when an instrument's mode is \"simulated\")");
    }

    // Safety limits.
    {
        Obj s(ctx, root.get("safety", true), "$.safety");
        auto& l = b.safety;
        const auto tmax = s.number("max_temperature_c", true, Range::closed(-40.0, 150.0));
        l.max_temperature_c = tmax.value_or(l.max_temperature_c);
        // Limits against each other: a run that ends or aborts sends the chamber to safe_setpoint_c, and the
        // simulated chamber starts at initial_temperature_c; either at or above the limit aborts every run at
        // once and heats the cell past its maximum on the way out.
        if (tmax && *tmax <= b.chamber.safe_setpoint_c)
            ctx.add("$.safety.max_temperature_c", "expected above the chamber's safe_setpoint_c (" +
                                                      format_number(b.chamber.safe_setpoint_c) + " degC), got " +
                                                      format_number(*tmax) + " degC");
        if (tmax && b.simulation && b.chamber.mode == ChamberConfig::Mode::simulated &&
            *tmax <= b.simulation->initial_temperature_c)
            ctx.add("$.safety.max_temperature_c", "expected above the simulated chamber's initial_temperature_c (" +
                                                      format_number(b.simulation->initial_temperature_c) + " degC), got " +
                                                      format_number(*tmax) + " degC");
        const auto vmin = s.number("min_voltage_v", true, Range{0.0, 10.0, false, false});
        const auto vmax = s.number("max_voltage_v", true, Range{0.0, 10.0, true, false});
        if (vmin) l.min_voltage_v = *vmin;
        if (vmax) l.max_voltage_v = *vmax;
        if (vmin && vmax && !(*vmin < *vmax))
            ctx.add("$.safety", "expected min_voltage_v < max_voltage_v, got " + format_number(*vmin) + " and " + format_number(*vmax));
        l.max_current_a = s.number("max_current_a", true, Range::positive()).value_or(l.max_current_a);
        l.chamber_deviation_c = s.number_or("chamber_deviation_c", l.chamber_deviation_c, Range::positive());
        l.instrument_loss_grace_s = s.number_or("instrument_loss_grace_s", l.instrument_loss_grace_s, Range::positive());
        s.finish();
        if (b.cycler.channels.size() > 0 && l.max_current_a > b.cycler.group_max_current_a() * 1.0000001)
            ctx.add("$.safety.max_current_a", "expected at most what the cycler group can carry (" +
                                                  format_number(b.cycler.group_max_current_a()) + " A = " +
                                                  std::to_string(b.cycler.channels.size()) + " x channel_max_current_a), got " +
                                                  format_number(l.max_current_a));
    }

    // Fault policy (optional): per instrument; every grace defaults to safety.instrument_loss_grace_s.
    {
        auto& fp = b.faults;
        const double grace = b.safety.instrument_loss_grace_s;
        fp.cycler.grace_s = fp.chamber.grace_s = fp.daq.grace_s = grace;
        Obj p(ctx, root.get("fault_policy"), "$.fault_policy");
        {
            Obj c(ctx, p.get("cycler"), "$.fault_policy.cycler");
            fp.cycler.grace_s = c.number_or("grace_s", grace, Range::positive());
            const auto lo = c.integer("reconnect_initial_ms", false, 1, 600000);
            const auto hi = c.integer("reconnect_max_ms", false, 1, 600000);
            if (lo) fp.cycler.reconnect_initial_ms = static_cast<int>(*lo);
            if (hi) fp.cycler.reconnect_max_ms = static_cast<int>(*hi);
            if (fp.cycler.reconnect_max_ms < fp.cycler.reconnect_initial_ms)
                ctx.add(c.path(), "expected reconnect_initial_ms <= reconnect_max_ms, got " +
                                      std::to_string(fp.cycler.reconnect_initial_ms) + " and " +
                                      std::to_string(fp.cycler.reconnect_max_ms));
            c.finish();
        }
        {
            Obj c(ctx, p.get("chamber"), "$.fault_policy.chamber");
            auto& ch = fp.chamber;
            ch.grace_s = c.number_or("grace_s", grace, Range::positive());
            ch.response_timeout_ms = static_cast<int>(c.integer_or("response_timeout_ms", ch.response_timeout_ms, 10, 60000));
            ch.retries = static_cast<int>(c.integer_or("retries", ch.retries, 0, 10));
            if (const auto a = c.choice("exception_response", false, {"reconnect", "abort"}))
                ch.exception_response = *a == 0 ? FaultAction::reconnect : FaultAction::abort;
            ch.setpoint_tolerance_c = c.number_or("setpoint_tolerance_c", ch.setpoint_tolerance_c, Range::positive());
            ch.setpoint_timeout_s = c.number_or("setpoint_timeout_s", ch.setpoint_timeout_s, Range::positive());
            if (const auto a = c.choice("setpoint_not_reached", false, {"event", "abort"}))
                ch.setpoint_not_reached = *a == 0 ? SetpointAction::event : SetpointAction::abort;
            c.finish();
        }
        {
            Obj d(ctx, p.get("daq"), "$.fault_policy.daq");
            fp.daq.grace_s = d.number_or("grace_s", grace, Range::positive());
            fp.daq.loss_event_interval_s = d.number_or("loss_event_interval_s", fp.daq.loss_event_interval_s, Range::positive());
            d.finish();
            // The stream is declared silent after stale_after_s; a grace shorter than that could never see it.
            if (b.daq.stale_after_s > fp.daq.grace_s)
                ctx.add("$.fault_policy.daq.grace_s", "expected at least instruments.daq.stale_after_s (" +
                                                          format_number(b.daq.stale_after_s) + " s), got " +
                                                          format_number(fp.daq.grace_s));
        }
        p.finish();
    }

    // Database.
    {
        Obj d(ctx, root.get("database", true), "$.database");
        if (const auto p = d.string("path", true)) b.database.path = *p;
        // The flush period bounds what kill -9 can lose; the reliability goal is at most 1 s.
        b.database.flush_period_ms = static_cast<int>(d.integer_or("flush_period_ms", 200, 10, 500));
        b.database.queue_capacity_samples =
            static_cast<std::size_t>(d.integer_or("queue_capacity_samples", 500000, 1000, 100000000));
        d.finish();
    }
    root.finish();

    ctx.throw_if_any();
    return b;
}

BenchConfig parse_bench_config_text(std::string_view text, const std::string& source, const fs::path& base_dir) {
    return parse_bench_config(parse_json_text(text, source), source, base_dir);
}

BenchConfig load_bench_config(const fs::path& file) {
    const std::string text = read_text_file(file);
    fs::path dir = file.parent_path();
    if (dir.empty()) dir = ".";
    return parse_bench_config_text(text, file.string(), dir);
}

// ---------------------------------------------------------------------------------------------------------
// Cell

json CellConfig::to_json() const { return document; }

std::map<std::string, double> CellConfig::constants() const {
    return {{"nominal_capacity_ah", nominal_capacity_ah},
            {"one_c_a", one_c_a()},
            {"min_voltage_v", min_voltage_v},
            {"max_voltage_v", max_voltage_v},
            {"max_charge_current_a", max_charge_current_a},
            {"max_discharge_current_a", max_discharge_current_a},
            {"min_temperature_c", min_temperature_c},
            {"max_temperature_c", max_temperature_c}};
}

CellConfig parse_cell_config(const json& j, const std::string& source, const fs::path& base_dir, std::string id) {
    Ctx ctx{source, {}};
    CellConfig c;
    c.id = std::move(id);
    c.document = j;
    Obj root(ctx, &j, "$");
    check_schema(root, kCellSchema);
    c.name = root.string("name", true).value_or("");
    c.nominal_capacity_ah = root.number("nominal_capacity_ah", true, Range{0.0, 10000.0, true, false}).value_or(0.0);
    const auto vmin = root.number("min_voltage_v", true, Range{0.0, 10.0, true, false});
    const auto vmax = root.number("max_voltage_v", true, Range{0.0, 10.0, true, false});
    if (vmin) c.min_voltage_v = *vmin;
    if (vmax) c.max_voltage_v = *vmax;
    if (vmin && vmax && !(*vmin < *vmax))
        ctx.add("$", "expected min_voltage_v < max_voltage_v, got " + format_number(*vmin) + " and " + format_number(*vmax));
    c.max_charge_current_a = root.number("max_charge_current_a", true, Range::positive()).value_or(0.0);
    c.max_discharge_current_a = root.number("max_discharge_current_a", true, Range::positive()).value_or(0.0);
    const auto tmin = root.number("min_temperature_c", false, Range::closed(-60.0, 150.0));
    const auto tmax = root.number("max_temperature_c", true, Range::closed(-60.0, 150.0));
    c.min_temperature_c = tmin.value_or(0.0);
    if (tmax) c.max_temperature_c = *tmax;
    if (tmax && !(c.min_temperature_c < *tmax))
        ctx.add("$", "expected min_temperature_c < max_temperature_c, got " + format_number(c.min_temperature_c) +
                         " and " + format_number(*tmax));
    c.surface_area_m2 = root.number_or("surface_area_m2", 0.0, Range::non_negative());
    if (const auto p = root.string("params", false)) {
        c.params_path = resolve(base_dir, *p);
        check_params_file(ctx, "$.params", *c.params_path);
    }
    root.get("description");
    root.finish();
    ctx.throw_if_any();
    return c;
}

CellConfig parse_cell_config_text(std::string_view text, const std::string& source, const fs::path& base_dir,
                                  std::string id) {
    return parse_cell_config(parse_json_text(text, source), source, base_dir, std::move(id));
}

CellConfig load_cell_config(const fs::path& file) {
    const std::string text = read_text_file(file);
    fs::path dir = file.parent_path();
    if (dir.empty()) dir = ".";
    return parse_cell_config_text(text, file.string(), dir, file.stem().string());
}

// ---------------------------------------------------------------------------------------------------------
// Expressions

namespace {

// constant + sum(factor * C[step]): the value of an expression, with the tester's step capacities symbolic.
struct Linear {
    double constant = 0.0;
    std::map<int, double> terms;  // step id -> factor
    [[nodiscard]] bool is_constant() const { return terms.empty(); }
};

class ExpressionParser {
public:
    ExpressionParser(std::string_view text, const std::map<std::string, double>& names, bool allow_capacity_refs)
        : text_(text), names_(names), allow_refs_(allow_capacity_refs) {}

    // Nesting of parentheses and unary signs (each one a recursion of factor()): deep enough for any real
    // expression, far from the stack's end (20 000 '(' used to overflow it).
    static constexpr int kMaxDepth = 64;
    static constexpr std::size_t kMaxLength = 4096;

    Linear parse() {
        if (text_.size() > kMaxLength)
            throw InputError("expression of " + std::to_string(text_.size()) + " characters: longer than " +
                             std::to_string(kMaxLength));
        skip_ws();
        if (pos_ >= text_.size()) fail("empty expression");
        Linear v = sum();
        skip_ws();
        if (pos_ < text_.size()) fail("unexpected '" + std::string(1, text_[pos_]) + "' at position " + std::to_string(pos_ + 1));
        if (!std::isfinite(v.constant)) fail("the result is not a finite number");
        for (const auto& [id, f] : v.terms)
            if (!std::isfinite(f)) fail("the result is not a finite number");
        return v;
    }
    [[nodiscard]] bool used_names() const { return used_names_; }

private:
    std::string_view text_;
    const std::map<std::string, double>& names_;
    bool allow_refs_;
    std::size_t pos_ = 0;
    bool used_names_ = false;
    int depth_ = 0;

    [[noreturn]] void fail(const std::string& what) const {
        const std::string shown = text_.size() > 80 ? std::string(text_.substr(0, 77)) + "..." : std::string(text_);
        throw InputError("expression \"" + shown + "\": " + what);
    }
    void skip_ws() {
        while (pos_ < text_.size() && std::isspace(static_cast<unsigned char>(text_[pos_]))) ++pos_;
    }
    bool eat(char c) {
        skip_ws();
        if (pos_ < text_.size() && text_[pos_] == c) {
            ++pos_;
            return true;
        }
        return false;
    }

    Linear sum() {
        Linear v = term();
        while (true) {
            if (eat('+')) add(v, term(), 1.0);
            else if (eat('-')) add(v, term(), -1.0);
            else return v;
        }
    }
    static void add(Linear& a, const Linear& b, double sign) {
        a.constant += sign * b.constant;
        for (const auto& [id, f] : b.terms) {
            a.terms[id] += sign * f;
            if (a.terms[id] == 0.0) a.terms.erase(id);
        }
    }
    Linear term() {
        Linear v = factor();
        while (true) {
            if (eat('*')) {
                Linear r = factor();
                if (!v.is_constant() && !r.is_constant())
                    fail("step capacities (C<n>) may only be multiplied by numbers");
                if (v.is_constant()) std::swap(v, r);  // v carries the terms (if any), r is the constant
                scale(v, r.constant);
            } else if (eat('/')) {
                Linear r = factor();
                if (!r.is_constant()) fail("cannot divide by a step capacity");
                if (r.constant == 0.0) fail("division by zero");
                scale(v, 1.0 / r.constant);
            } else {
                return v;
            }
        }
    }
    static void scale(Linear& v, double k) {
        v.constant *= k;
        for (auto it = v.terms.begin(); it != v.terms.end();) {
            it->second *= k;
            it = it->second == 0.0 ? v.terms.erase(it) : std::next(it);
        }
    }
    Linear factor() {
        struct Nest {
            int& d;
            ~Nest() { --d; }
        } nest{++depth_};
        if (depth_ > kMaxDepth)
            fail("nested deeper than " + std::to_string(kMaxDepth) + " levels (parentheses and signs) at position " +
                 std::to_string(pos_ + 1));
        skip_ws();
        if (eat('-')) {
            Linear v = factor();
            scale(v, -1.0);
            return v;
        }
        if (eat('+')) return factor();
        if (eat('(')) {
            Linear v = sum();
            if (!eat(')')) fail("expected ')' at position " + std::to_string(pos_ + 1));
            return v;
        }
        skip_ws();
        if (pos_ >= text_.size()) fail("unexpected end, expected a number, a name or '('");
        const char c = text_[pos_];
        if (std::isdigit(static_cast<unsigned char>(c)) || c == '.') {
            double x = 0.0;
            const auto r = std::from_chars(text_.data() + pos_, text_.data() + text_.size(), x);
            if (r.ec != std::errc()) fail("bad number at position " + std::to_string(pos_ + 1));
            pos_ = static_cast<std::size_t>(r.ptr - text_.data());
            return Linear{x, {}};
        }
        if (std::isalpha(static_cast<unsigned char>(c)) || c == '_') {
            const std::size_t start = pos_;
            while (pos_ < text_.size() && (std::isalnum(static_cast<unsigned char>(text_[pos_])) || text_[pos_] == '_')) ++pos_;
            const std::string name(text_.substr(start, pos_ - start));
            if (const auto it = names_.find(name); it != names_.end()) {
                used_names_ = true;
                return Linear{it->second, {}};
            }
            if (name.size() > 1 && name[0] == 'C' &&
                std::all_of(name.begin() + 1, name.end(), [](char d) { return std::isdigit(static_cast<unsigned char>(d)); })) {
                if (!allow_refs_) fail("step capacity " + name + " is only allowed in cutoff_capacity_ah");
                if (name.size() > 6) fail("step number out of range in " + name.substr(0, 20));
                const int id = std::atoi(name.c_str() + 1);
                if (id < 1) fail("expected a step number >= 1 in " + name);
                return Linear{0.0, {{id, 1.0}}};
            }
            std::string known;
            for (const auto& [n, v] : names_) known += (known.empty() ? "" : ", ") + n;
            fail("unknown name \"" + name + "\" (known: " + known + ")");
        }
        fail("unexpected '" + std::string(1, c) + "' at position " + std::to_string(pos_ + 1));
    }
};

// Capacity expression text in the tester's grammar, terms by step then the constant: "0.1*C4 - C8 + C10",
// "-C4 + C6 + 0.45" (CapacityExpression::parse reads them back to the same terms, in the same order).
std::string capacity_text(const Linear& v) {
    std::string out;
    auto append = [&](double f, const std::string& ref) {
        const double mag = std::abs(f);
        if (!out.empty()) out += f < 0 ? " - " : " + ";
        else if (f < 0) out += "-";
        if (ref.empty()) out += format_number(mag);
        else out += (mag == 1.0 ? std::string() : format_number(mag) + "*") + ref;
    };
    for (const auto& [id, f] : v.terms) {
        std::string ref(1, 'C');  // (not "C" + to_string: GCC 12 raises a false -Wrestrict on that)
        ref += std::to_string(id);
        append(f, ref);
    }
    if (v.constant != 0.0) append(v.constant, "");
    return out.empty() ? "0" : out;
}

}  // namespace

std::pair<std::string, json> parse_override_argument(std::string_view text) {
    const auto eq = text.find('=');
    if (eq == std::string_view::npos || eq == 0)
        throw InputError("expected NAME=VALUE (e.g. c_rate=2), got \"" + std::string(text) + "\"");
    std::string name(text.substr(0, eq));
    const std::string_view value = text.substr(eq + 1);
    if (value == "true" || value == "false") return {name, json(value == "true")};
    double x = 0.0;
    const auto [p, ec] = std::from_chars(value.data(), value.data() + value.size(), x);
    if (!value.empty() && ec == std::errc() && p == value.data() + value.size()) return {name, json(x)};
    return {name, json(std::string(value))};
}

double evaluate_expression(std::string_view text, const std::map<std::string, double>& names) {
    return ExpressionParser(text, names, false).parse().constant;
}

// ---------------------------------------------------------------------------------------------------------
// Programs

std::string_view segment_type(const Segment& segment) {
    switch (segment.index()) {
        case 0: return "cycler";
        case 1: return "chamber_setpoint";
        default: return "wait_equilibrium";
    }
}

double Program::max_current_a() const {
    double m = 0.0;
    for (const auto& s : segments)
        if (const auto* c = std::get_if<CyclerSegment>(&s)) m = std::max(m, c->program.max_current_a());
    return m;
}

json Program::to_json() const {
    json j = json::object();
    j["schema"] = kBenchProgramSchema;
    j["name"] = name;
    if (!description.empty()) j["description"] = description;
    j["parameters"] = json::object();
    for (const auto& [k, v] : parameters) {
        const auto spec = parameter_specs.find(k);
        if (spec == parameter_specs.end() || spec->second.plain()) {
            j["parameters"][k] = v;
            continue;
        }
        // The declaration form, with the value used as its default: parse_program reads it back unchanged.
        json d = {{"default", v}};
        if (spec->second.min) d["min"] = *spec->second.min;
        if (spec->second.max) d["max"] = *spec->second.max;
        if (spec->second.integer) d["integer"] = true;
        if (!spec->second.unit.empty()) d["unit"] = spec->second.unit;
        if (!spec->second.description.empty()) d["description"] = spec->second.description;
        j["parameters"][k] = std::move(d);
    }
    json segs = json::array();
    for (const auto& s : segments) {
        json o;
        if (const auto* c = std::get_if<CyclerSegment>(&s)) {
            o = c->program.to_json();
            o.erase("schema");
        } else if (const auto* sp = std::get_if<ChamberSetpointSegment>(&s)) {
            o["setpoint_c"] = sp->setpoint_c;
        } else if (const auto* w = std::get_if<WaitEquilibriumSegment>(&s)) {
            o["tolerance_c"] = w->tolerance_c;
            o["hold_s"] = w->hold_s;
            o["timeout_s"] = w->timeout_s;
            o["abort_on_timeout"] = w->abort_on_timeout;
        }
        o["type"] = std::string(segment_type(s));
        segs.push_back(std::move(o));
    }
    j["segments"] = std::move(segs);
    return j;
}

namespace {

bool valid_parameter_name(const std::string& n) {
    if (n.empty() || !(std::islower(static_cast<unsigned char>(n[0])) || n[0] == '_')) return false;
    return std::all_of(n.begin(), n.end(), [](char c) {
        return std::islower(static_cast<unsigned char>(c)) || std::isdigit(static_cast<unsigned char>(c)) || c == '_';
    });
}

// Step members that may hold expressions; integers must evaluate to whole numbers.
const std::set<std::string> kStepNumberKeys{"current_a", "voltage_v", "time_s", "cutoff_voltage_v", "cutoff_current_a"};
const std::set<std::string> kStepIntegerKeys{"start_step", "count", "id"};

// A number field of a chamber/wait segment that may be an expression.
std::optional<double> expr_number(Obj& o, std::string_view key, bool required, Range range,
                                  const std::map<std::string, double>& names) {
    const json* v = o.get(key, required);
    if (!v) return std::nullopt;
    double x = 0.0;
    if (v->is_number()) {
        x = v->get<double>();
    } else if (v->is_string()) {
        try {
            x = evaluate_expression(v->get<std::string>(), names);
        } catch (const InputError& e) {
            o.ctx().add(o.child(key), e.what());
            return std::nullopt;
        }
    } else {
        o.ctx().add(o.child(key), "expected " + range.describe() + " or an expression string, " + got(*v));
        return std::nullopt;
    }
    if (!range.contains(x)) {
        o.ctx().add(o.child(key), "expected " + range.describe() + ", got " + format_number(x) +
                                      (v->is_string() ? " (from \"" + v->get<std::string>() + "\")" : ""));
        return std::nullopt;
    }
    return x;
}

// Expands the expressions of one step object into plain numbers (in place). Returns false on a problem.
bool expand_step(Ctx& ctx, json& step, const std::string& path, const std::map<std::string, double>& names) {
    if (!step.is_object()) return true;  // StepProgram::from_json reports it
    bool ok = true;
    for (auto& [key, value] : step.items()) {
        if (!value.is_string()) continue;
        const std::string text = value.get<std::string>();
        const std::string p = path + "." + key;
        try {
            if (key == "cutoff_capacity_ah") {
                ExpressionParser parser(text, names, true);
                const Linear v = parser.parse();
                if (v.is_constant()) value = v.constant;
                else if (parser.used_names()) value = capacity_text(v);
                // else: only numbers and C<n>: keep the text as written (the tester's own form)
            } else if (kStepNumberKeys.count(key)) {
                value = evaluate_expression(text, names);
            } else if (kStepIntegerKeys.count(key)) {
                const double x = evaluate_expression(text, names);
                if (std::floor(x) != x || std::abs(x) > 1e9) {
                    ctx.add(p, "expected a whole number, got " + format_number(x) + " (from \"" + text + "\")");
                    ok = false;
                } else {
                    value = static_cast<long long>(x);
                }
            }
        } catch (const InputError& e) {
            ctx.add(p, e.what());
            ok = false;
        }
    }
    return ok;
}

struct ExpandedSegment {
    Segment segment;
    std::string path;  // of the segment in the file
};

std::optional<ExpandedSegment> parse_segment(Ctx& ctx, const json& sj, const std::string& path,
                                             const std::string& program_name,
                                             const std::map<std::string, double>& names) {
    Obj o(ctx, &sj, path);
    if (!o.ok()) return std::nullopt;
    const auto type = o.choice("type", true, {"cycler", "chamber_setpoint", "wait_equilibrium"});
    if (!type) return std::nullopt;
    if (*type == 0) {
        // Cycler: the StepProgram JSON form (name, description, steps) plus "type"; its own parser validates.
        json sp = sj;
        sp.erase("type");
        for (auto it = sp.begin(); it != sp.end();) {
            if (it.key().rfind('_', 0) == 0) it = sp.erase(it);
            else ++it;
        }
        if (!sp.contains("name")) sp["name"] = program_name;
        bool ok = true;
        if (auto steps = sp.find("steps"); steps != sp.end() && steps->is_array())
            for (std::size_t k = 0; k < steps->size(); ++k)
                ok = expand_step(ctx, (*steps)[k], path + ".steps[" + std::to_string(k) + "]", names) && ok;
        if (!ok) return std::nullopt;
        try {
            return ExpandedSegment{CyclerSegment{protocol::StepProgram::from_json(sp, kNestedMarker)}, path};
        } catch (const InputError& e) {
            ctx.add_nested(path, kNestedMarker, e.what());
            return std::nullopt;
        }
    }
    const std::size_t before = ctx.count();
    std::optional<ExpandedSegment> out;
    if (*type == 1) {
        const auto sp = expr_number(o, "setpoint_c", true, Range::closed(-100.0, 200.0), names);
        if (sp) out = ExpandedSegment{ChamberSetpointSegment{*sp}, path};
    } else {
        WaitEquilibriumSegment w;
        w.tolerance_c = expr_number(o, "tolerance_c", false, Range::positive(), names).value_or(w.tolerance_c);
        w.hold_s = expr_number(o, "hold_s", false, Range::non_negative(), names).value_or(w.hold_s);
        w.timeout_s = expr_number(o, "timeout_s", false, Range::positive(), names).value_or(w.timeout_s);
        w.abort_on_timeout = o.boolean("abort_on_timeout", false).value_or(true);
        if (w.timeout_s <= w.hold_s)
            ctx.add(path, "expected timeout_s > hold_s (equilibrium needs hold_s inside the timeout), got " +
                              format_number(w.timeout_s) + " and " + format_number(w.hold_s));
        out = ExpandedSegment{w, path};
    }
    o.get("description");
    o.finish();
    if (ctx.count() != before) return std::nullopt;
    return out;
}

// Every step and set point against the cell's limits and, when given, the bench's.
void check_limits(Ctx& ctx, const std::vector<ExpandedSegment>& segments, const CellConfig& cell, const BenchConfig* bench) {
    for (const auto& es : segments) {
        if (const auto* sp = std::get_if<ChamberSetpointSegment>(&es.segment)) {
            const std::string p = es.path + ".setpoint_c";
            const double t = sp->setpoint_c;
            if (t < cell.min_temperature_c || t > cell.max_temperature_c)
                ctx.add(p, "expected a set point inside the cell's temperature range " + format_number(cell.min_temperature_c) +
                               ".." + format_number(cell.max_temperature_c) + " degC, got " + format_number(t));
            if (bench) {
                if (t >= bench->safety.max_temperature_c)
                    ctx.add(p, "expected a set point below the bench's max_temperature_c (" +
                                   format_number(bench->safety.max_temperature_c) + " degC), got " + format_number(t));
                if (t < bench->chamber.setpoint_min_c || t > bench->chamber.setpoint_max_c)
                    ctx.add(p, "expected a set point the chamber accepts (" + format_number(bench->chamber.setpoint_min_c) +
                                   ".." + format_number(bench->chamber.setpoint_max_c) + " degC), got " + format_number(t));
            }
            continue;
        }
        const auto* cy = std::get_if<CyclerSegment>(&es.segment);
        if (!cy) continue;
        const auto& steps = cy->program.steps;
        for (std::size_t k = 0; k < steps.size(); ++k) {
            const auto& s = steps[k];
            const std::string p = es.path + ".steps[" + std::to_string(k) + "]";
            const int dir = protocol::step_direction(s.type);
            if (s.current_a) {
                const double i = *s.current_a;
                const double cell_max = dir > 0 ? cell.max_charge_current_a : cell.max_discharge_current_a;
                if (i > cell_max)
                    ctx.add(p + ".current_a", "expected at most the cell's max_" + std::string(dir > 0 ? "charge" : "discharge") +
                                                  "_current_a (" + format_number(cell_max) + " A), got " + format_number(i) + " A");
                if (bench && i > bench->safety.max_current_a)
                    ctx.add(p + ".current_a", "expected at most the bench's safety max_current_a (" +
                                                  format_number(bench->safety.max_current_a) + " A), got " + format_number(i) + " A");
                if (bench && !bench->cycler.channels.empty() && i > bench->cycler.group_max_current_a())
                    ctx.add(p + ".current_a", "expected at most what the cycler group carries (" +
                                                  format_number(bench->cycler.group_max_current_a()) + " A), got " + format_number(i) + " A");
            }
            const auto in_window = [&](const std::optional<double>& v, const char* key) {
                if (!v) return;
                if (*v < cell.min_voltage_v - 1e-9 || *v > cell.max_voltage_v + 1e-9)
                    ctx.add(p + "." + key, "expected a voltage inside the cell's test window " + format_number(cell.min_voltage_v) +
                                               ".." + format_number(cell.max_voltage_v) + " V, got " + format_number(*v) + " V");
                if (bench && (*v <= bench->safety.min_voltage_v || *v >= bench->safety.max_voltage_v))
                    ctx.add(p + "." + key, "expected a voltage inside the bench's safety window (" +
                                               format_number(bench->safety.min_voltage_v) + ".." +
                                               format_number(bench->safety.max_voltage_v) + " V), got " + format_number(*v) + " V");
            };
            in_window(s.voltage_v, "voltage_v");
            in_window(s.cutoff_voltage_v, "cutoff_voltage_v");
            // A constant-current step without a voltage limit can over-charge or over-discharge the cell.
            using protocol::StepType;
            if ((s.type == StepType::cc_charge || s.type == StepType::cc_discharge) && !s.cutoff_voltage_v)
                ctx.add(p, "expected cutoff_voltage_v: a constant-current step needs a voltage limit inside the cell's window");
        }
    }
}

// {"default": 1.0, "min": .., "max": .., "integer": bool, "unit": "..", "description": ".."}: the default and the
// declaration, or nullopt (problems recorded). The default must satisfy the declaration itself.
std::optional<std::pair<double, ProgramParameter>> parse_parameter_declaration(Ctx& ctx, const json& v, const std::string& path) {
    Obj o(ctx, &v, path);
    const std::size_t before = ctx.count();
    ProgramParameter spec;
    const auto def = o.number("default", true, Range::any());
    spec.min = o.number("min", false, Range::any());
    spec.max = o.number("max", false, Range::any());
    spec.integer = o.boolean("integer", false).value_or(false);
    spec.unit = o.string("unit", false, false).value_or("");
    spec.description = o.string("description", false, false).value_or("");
    o.finish();
    if (spec.min && spec.max && *spec.min > *spec.max)
        ctx.add(path, "min " + format_number(*spec.min) + " is above max " + format_number(*spec.max));
    if (def) {
        if ((spec.min && *def < *spec.min) || (spec.max && *def > *spec.max))
            ctx.add(o.child("default"), "default " + format_number(*def) + " is outside min..max");
        if (spec.integer && std::floor(*def) != *def)
            ctx.add(o.child("default"), "expected a whole number (\"integer\": true), got " + format_number(*def));
    }
    if (!def || ctx.count() != before) return std::nullopt;
    return std::make_pair(*def, std::move(spec));
}

Program parse_program_impl(Ctx& ctx, const json& j, const CellConfig& cell, const ProgramOverrides& overrides,
                           const BenchConfig* bench) {
    Program prog;
    // The end of every run (and any abort) sends the chamber to its safe set point: it must be one the cell
    // tolerates.
    if (bench && (bench->chamber.safe_setpoint_c >= cell.max_temperature_c ||
                  bench->chamber.safe_setpoint_c < cell.min_temperature_c))
        ctx.add("$", "the bench's chamber safe_setpoint_c (" + format_number(bench->chamber.safe_setpoint_c) +
                         " degC) is outside the cell's temperature range " + format_number(cell.min_temperature_c) + ".." +
                         format_number(cell.max_temperature_c) + " degC: a run's end or abort would take the cell there");
    Obj root(ctx, &j, "$");
    if (!root.ok()) return prog;

    // A bare StepProgram file: one cycler segment.
    if (const auto it = j.find("schema"); it != j.end() && it->is_string() && *it == protocol::kProgramSchema) {
        for (const auto& [k, v] : overrides)
            ctx.add("$", "override \"" + k + "\" given, but a step program file has no parameters");
        try {
            auto sp = protocol::StepProgram::from_json(j, kNestedMarker);
            prog.name = sp.name;
            prog.description = sp.description;
            std::vector<ExpandedSegment> segs;
            segs.push_back({Segment(std::in_place_type<CyclerSegment>, CyclerSegment{std::move(sp)}), "$"});
            check_limits(ctx, segs, cell, bench);
            prog.segments.push_back(std::move(segs.front().segment));
        } catch (const InputError& e) {
            ctx.add_nested("$", kNestedMarker, e.what());
        }
        return prog;
    }

    check_schema(root, kBenchProgramSchema);
    prog.name = root.string("name", true).value_or("");
    prog.description = root.string("description", false, false).value_or("");

    // Parameters: declared defaults, then overrides.
    const auto constants = cell.constants();
    if (const json* pj = root.get("parameters")) {
        if (!pj->is_object()) {
            ctx.add("$.parameters", "expected an object of name: number (or name: {\"default\": number, ...}), " + got(*pj));
        } else {
            for (const auto& [k, v] : pj->items()) {
                const std::string p = "$.parameters." + k;
                if (!valid_parameter_name(k)) {
                    ctx.add(p, "expected a name of lower-case letters, digits and _");
                } else if (constants.count(k)) {
                    ctx.add(p, "\"" + k + "\" is a cell constant and cannot be a parameter");
                } else if (v.is_object()) {
                    if (auto d = parse_parameter_declaration(ctx, v, p)) {
                        prog.parameters[k] = d->first;
                        prog.parameter_specs[k] = std::move(d->second);
                    }
                } else if (!v.is_number() || !std::isfinite(v.get<double>())) {
                    ctx.add(p, "expected a number or an object {\"default\": number, \"min\", \"max\", \"unit\"}, " + got(v));
                } else {
                    prog.parameters[k] = v.get<double>();
                    prog.parameter_specs[k] = ProgramParameter{};
                }
            }
        }
    }
    // Overrides: every problem at once (unknown name, wrong type, not a whole number, out of the declared range).
    // A refused override leaves the default in place, so the limit checks below still see the rest.
    ProgramOverrides accepted;
    for (const auto& [k, v] : overrides) {
        const std::string p = "$.parameters." + k;
        if (!prog.parameters.count(k)) {
            std::string declared;
            for (const auto& [n, x] : prog.parameters) declared += (declared.empty() ? "" : ", ") + n;
            ctx.add("$.parameters", "override \"" + k + "\" is not a parameter of this program (declared: " +
                                        (declared.empty() ? "none" : declared) + ")");
            continue;
        }
        const auto& spec = prog.parameter_specs[k];
        if (!v.is_number()) {
            ctx.add(p, "override: expected a number" + (spec.unit.empty() ? "" : " (" + spec.unit + ")") + ", " + got(v));
            continue;
        }
        const double x = v.get<double>();
        if (!std::isfinite(x)) {
            ctx.add(p, "override: expected a finite number, " + got(v));
        } else if (spec.integer && std::floor(x) != x) {
            ctx.add(p, "override: expected a whole number, got " + format_number(x));
        } else if ((spec.min && x < *spec.min) || (spec.max && x > *spec.max)) {
            const std::string unit = spec.unit.empty() ? "" : " " + spec.unit;
            ctx.add(p, "override: " + format_number(x) + unit + " is out of the declared range " +
                           (spec.min ? format_number(*spec.min) : std::string("-inf")) + ".." +
                           (spec.max ? format_number(*spec.max) : std::string("inf")) + unit);
        } else {
            prog.parameters[k] = x;
            accepted[k] = x;
        }
    }

    // Repetition of the segments over values of one parameter (a campaign over temperatures, say). An override
    // of that parameter runs the one value given instead.
    std::string repeat_name;
    std::vector<double> repeat_values;
    if (const json* rj = root.get("repeat_for")) {
        Obj r(ctx, rj, "$.repeat_for");
        if (const auto name = r.string("parameter", true)) {
            if (!prog.parameters.count(*name)) ctx.add(r.child("parameter"), "expected a declared parameter, got \"" + *name + "\"");
            else repeat_name = *name;
        }
        if (const json* vj = r.get("values", true)) {
            if (!vj->is_array() || vj->empty()) {
                ctx.add(r.child("values"), "expected a non-empty array of numbers, " + got(*vj));
            } else {
                for (std::size_t i = 0; i < vj->size(); ++i) {
                    if ((*vj)[i].is_number() && std::isfinite((*vj)[i].get<double>())) repeat_values.push_back((*vj)[i].get<double>());
                    else ctx.add(r.child("values") + "[" + std::to_string(i) + "]", "expected a number, " + got((*vj)[i]));
                }
            }
        }
        r.finish();
        if (!repeat_name.empty() && accepted.count(repeat_name)) repeat_values = {accepted.at(repeat_name).get<double>()};
    }
    if (repeat_name.empty()) repeat_values = {kInf};  // one pass, no binding

    const json* segs = root.get("segments", true);
    if (segs && (!segs->is_array() || segs->empty())) {
        ctx.add("$.segments", "expected a non-empty array of segments, " + got(*segs));
        segs = nullptr;
    }
    root.finish();

    std::vector<ExpandedSegment> expanded;
    if (segs) {
        for (const double rv : repeat_values) {
            std::map<std::string, double> names = constants;
            for (const auto& [k, v] : prog.parameters) names[k] = v;
            if (!repeat_name.empty()) names[repeat_name] = rv;
            for (std::size_t i = 0; i < segs->size(); ++i) {
                auto s = parse_segment(ctx, (*segs)[i], "$.segments[" + std::to_string(i) + "]", prog.name, names);
                if (s) expanded.push_back(std::move(*s));
            }
        }
    }
    // The segments that parsed are checked against the limits even when others did not: every problem of the
    // file at once, as for bench configs.
    check_limits(ctx, expanded, cell, bench);
    for (auto& e : expanded) prog.segments.push_back(std::move(e.segment));
    return prog;
}

}  // namespace

Program parse_program(const json& j, const std::string& source, const CellConfig& cell, const ProgramOverrides& overrides,
                      const BenchConfig* bench) {
    Ctx ctx{source, {}};
    Program p = parse_program_impl(ctx, j, cell, overrides, bench);
    ctx.throw_if_any();
    return p;
}

Program load_program(const fs::path& file, const CellConfig& cell, const ProgramOverrides& overrides,
                     const BenchConfig* bench) {
    return parse_program_text(read_text_file(file), file.string(), cell, overrides, bench);
}

Program parse_program_text(std::string_view text, const std::string& source, const CellConfig& cell,
                           const ProgramOverrides& overrides, const BenchConfig* bench) {
    return parse_program(parse_json_text(text, source), source, cell, overrides, bench);
}

// ---------------------------------------------------------------------------------------------------------
// Expected duration

ProgramEstimate estimate_duration(const Program& program, const CellConfig& cell) {
    using protocol::StepType;
    ProgramEstimate out;
    const double q_ah = cell.nominal_capacity_ah > 0 ? cell.nominal_capacity_ah : 1.0;
    double soc = ProgramEstimate::kStartSoc;
    for (const auto& seg : program.segments) {
        double t = 0.0;
        if (const auto* w = std::get_if<WaitEquilibriumSegment>(&seg)) {
            t = w->hold_s;
        } else if (const auto* c = std::get_if<CyclerSegment>(&seg)) {
            protocol::StepProgram sp = c->program;
            sp.settings.nominal_capacity_ah = q_ah;
            try {
                sp = protocol::resolve_capacity_limits(sp);
            } catch (const std::exception&) {
                // a limit that cannot be resolved without a measurement: estimated without it
            }
            std::map<std::size_t, int> passes_left;  // per cycle step: jumps back still to do
            std::size_t k = 0, guard = 0;
            while (k < sp.steps.size() && ++guard < 1000000) {
                const auto& st = sp.steps[k];
                if (st.type == StepType::end) break;
                if (st.type == StepType::cycle) {
                    auto it = passes_left.try_emplace(k, std::max(0, st.count - 1)).first;
                    if (it->second > 0 && st.start_step >= 1 && static_cast<std::size_t>(st.start_step) <= k) {
                        --it->second;
                        k = static_cast<std::size_t>(st.start_step - 1);
                    } else {
                        passes_left.erase(k);
                        ++k;
                    }
                    continue;
                }
                const int dir = protocol::step_direction(st.type);
                double dt = st.time_s.value_or(kInf);
                if (dir != 0 && st.current_a && *st.current_a > 0) {
                    const double i = *st.current_a;
                    // Constant current until the cell is full/empty (a voltage limit), then the CV tail.
                    double cc_s = 3600.0 * q_ah * (dir > 0 ? 1.0 - soc : soc) / i;
                    if (st.cutoff_capacity_ah && st.cutoff_capacity_ah->is_constant())
                        cc_s = std::min(cc_s, 3600.0 * std::max(0.0, st.cutoff_capacity_ah->constant_ah) / i);
                    double step_s = cc_s + (protocol::step_has_cv_phase(st.type) ? ProgramEstimate::kCvTailS : 0.0);
                    dt = std::min(dt, step_s);
                    const double moved = std::min(dt, cc_s) * i / 3600.0 / q_ah;
                    soc = std::clamp(soc + dir * moved, 0.0, 1.0);
                    if (protocol::step_has_cv_phase(st.type) && dt >= cc_s) soc = dir > 0 ? 1.0 : 0.0;
                }
                if (std::isfinite(dt)) t += dt;
                ++k;
            }
        }
        out.segment_s.push_back(t);
        out.total_s += t;
    }
    return out;
}

// ---------------------------------------------------------------------------------------------------------
// Files by name

namespace {

fs::path named_file(const fs::path& config_dir, const char* folder, std::string_view name) {
    const bool ok = !name.empty() && name.size() <= 100 && name.front() != '.' &&
                    std::all_of(name.begin(), name.end(), [](char c) {
                        return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-' || c == '.';
                    });
    if (!ok)
        throw InputError("\"" + std::string(name.substr(0, 100)) + "\": expected a " +
                         (std::string(folder) == "cells" ? "cell" : "program") +
                         " name of letters, digits, '_', '-' and '.' (a file under " +
                         (config_dir / folder).string() + ", without .json)");
    std::string file(name);
    if (file.size() < 5 || file.substr(file.size() - 5) != ".json") file += ".json";
    return config_dir / folder / file;
}

std::vector<std::string> list_json(const fs::path& dir, const char* schema_or_null_for_any_but) {
    std::vector<std::string> out;
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) return out;
    for (const auto& e : fs::directory_iterator(dir, ec)) {
        if (!e.is_regular_file() || e.path().extension() != ".json") continue;
        if (schema_or_null_for_any_but) {
            // Skip files of another known kind (a parameter set among the cells); keep broken ones so that
            // loading them explains what is wrong.
            try {
                const json j = read_json_file(e.path());
                if (j.is_object() && j.contains("schema") && j["schema"].is_string() &&
                    j["schema"] != schema_or_null_for_any_but)
                    continue;
            } catch (const std::exception&) {
            }
        }
        out.push_back(e.path().stem().string());
    }
    std::sort(out.begin(), out.end());
    return out;
}

}  // namespace

fs::path program_file(const fs::path& config_dir, std::string_view name) { return named_file(config_dir, "programs", name); }
fs::path cell_file(const fs::path& config_dir, std::string_view name) { return named_file(config_dir, "cells", name); }
std::vector<std::string> list_programs(const fs::path& config_dir) { return list_json(config_dir / "programs", nullptr); }
std::vector<std::string> list_cells(const fs::path& config_dir) { return list_json(config_dir / "cells", kCellSchema); }

}  // namespace cellbench::daemon
