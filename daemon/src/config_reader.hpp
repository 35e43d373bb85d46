#pragma once
// Helpers shared by the configuration readers (internal to daemon/src): the issue collector, the checked
// member reader, file reading and the expression grammar. The readers never stop at the first problem: each
// one records an issue (file, JSON path, what was expected) and returns a default, so one load reports
// everything. Pieces: config.cpp (errors, endpoints, files by name), config_bench.cpp, config_cell.cpp,
// config_program.cpp (programs and the duration estimate), config_expression.cpp, config_reader.cpp.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/config.hpp"

namespace cellbench::daemon::config_read {

using nlohmann::json;
namespace fs = std::filesystem;

constexpr double kInf = std::numeric_limits<double>::infinity();

// Shortest text that reads back to the same double ("0.1", "4.2", "1e-05").
std::string format_number(double v);

// "got "abc"", "got -3", "got an array" — for messages.
std::string got(const json& j);

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

// The source name given to another layer's parser so its messages can be re-rooted (Ctx::add_nested).
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

// The file's text (regular files up to 16 MiB; InputError otherwise).
std::string read_text_file(const fs::path& file);
// Nesting bounded, numbers that overflow a double (1e400) rejected: InputError naming the source.
json parse_json_text(std::string_view text, const std::string& source);
json read_json_file(const fs::path& file);

// The "schema" member must be `expected` (with a hint when the file is a parameter set).
void check_schema(Obj& o, const char* expected);
// A path in a config file, relative to the file's folder.
fs::path resolve(const fs::path& base_dir, const std::string& p);
// A referenced parameter set must exist and be valid.
void check_params_file(Ctx& ctx, const std::string& json_path, const fs::path& file);
// {"host": ..., "port": ...}
std::optional<Endpoint> endpoint_of(Obj& o, bool allow_port_zero);
// An environment variable name: upper case, digits and '_', not starting with a digit.
bool valid_env_name(const std::string& s);

// ---------------------------------------------------------------------------------------------------------
// Expressions (config_expression.cpp)

// constant + sum(factor * C[step]): the value of an expression, with the tester's step capacities symbolic.
struct Linear {
    double constant = 0.0;
    std::map<int, double> terms;  // step id -> factor
    [[nodiscard]] bool is_constant() const { return terms.empty(); }
};

struct ParsedExpression {
    Linear value;
    bool used_names = false;  // the text named a program parameter or cell constant
};
// Parses an arithmetic expression over `names`; with allow_capacity_refs, C<n> (the tester's capacity of step
// n) stays symbolic. Throws InputError.
ParsedExpression parse_expression(std::string_view text, const std::map<std::string, double>& names,
                                  bool allow_capacity_refs);

// Capacity expression text in the tester's grammar, terms by step then the constant: "0.1*C4 - C8 + C10",
// "-C4 + C6 + 0.45" (CapacityExpression::parse reads them back to the same terms, in the same order).
std::string capacity_text(const Linear& v);

}  // namespace cellbench::daemon::config_read
