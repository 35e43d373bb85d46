#include "cellbench/core/json_fields.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>

#include "cellbench/core/recording.hpp"

namespace cellbench::json_fields {

void fail(const std::string& source, const std::string& path, const std::string& what) {
    throw InputError(source + ": " + path + ": " + what);
}

const json& member(const json& j, const std::string& key, const std::string& source, const std::string& path) {
    if (!j.is_object()) fail(source, path, "expected an object");
    auto it = j.find(key);
    if (it == j.end()) fail(source, path + "." + key, "missing (required)");
    return *it;
}

std::uint64_t unsigned_value(const json& j, std::uint64_t max, const std::string& source, const std::string& path,
                             IntegerText text) {
    if (j.is_number_unsigned()) {
        const auto v = j.get<std::uint64_t>();
        if (v <= max) return v;
    } else if (j.is_number_integer()) {
        const auto v = j.get<std::int64_t>();
        if (v >= 0 && static_cast<std::uint64_t>(v) <= max) return static_cast<std::uint64_t>(v);
    } else if (text == IntegerText::accepted && j.is_string()) {  // "0x310" or "784"
        const std::string s = j.get<std::string>();
        const bool hex = s.size() > 2 && s[0] == '0' && (s[1] == 'x' || s[1] == 'X');
        const std::string digits = hex ? s.substr(2) : s;
        const auto digit = [&](char c) {
            return hex ? std::isxdigit(static_cast<unsigned char>(c)) != 0 : (c >= '0' && c <= '9');
        };
        if (!digits.empty() && digits.size() <= 16 && std::all_of(digits.begin(), digits.end(), digit)) {
            const std::uint64_t v = std::stoull(digits, nullptr, hex ? 16 : 10);
            if (v <= max) return v;
        }
    }
    const std::string expected = "expected an integer 0.." + std::to_string(max);
    if (text == IntegerText::accepted) fail(source, path, expected + " (a number or a string such as \"0x310\")");
    fail(source, path, expected);
}

double finite_number(const json& j, const std::string& source, const std::string& path) {
    if (!j.is_number()) fail(source, path, "expected a number, got " + std::string(j.type_name()));
    const double v = j.get<double>();
    if (!std::isfinite(v)) fail(source, path, "expected a finite number");
    return v;
}

std::string string_value(const json& j, const std::string& source, const std::string& path) {
    if (!j.is_string()) fail(source, path, "expected a string, got " + std::string(j.type_name()));
    return j.get<std::string>();
}

bool bool_value(const json& j, const std::string& source, const std::string& path) {
    if (!j.is_boolean()) fail(source, path, "expected true or false");
    return j.get<bool>();
}

}  // namespace cellbench::json_fields
