// The expression grammar of programs: numbers, + - * / and parentheses, the program's parameters and the
// cell's constants by name, and (in a cutoff capacity) C<n>, the tester's capacity of step n.
#include "config_reader.hpp"

#include <charconv>
#include <cctype>

namespace cellbench::daemon {

using namespace config_read;

namespace {

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

}  // namespace

namespace config_read {

ParsedExpression parse_expression(std::string_view text, const std::map<std::string, double>& names,
                                  bool allow_capacity_refs) {
    ExpressionParser parser(text, names, allow_capacity_refs);
    Linear v = parser.parse();
    return {std::move(v), parser.used_names()};
}

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

}  // namespace config_read

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

}  // namespace cellbench::daemon
