#include "cellbench/protocol/json_input.hpp"

#include <algorithm>

#include "cellbench/core/recording.hpp"

namespace cellbench::protocol {

std::size_t json_nesting_depth(std::string_view text, std::size_t limit) {
    std::size_t depth = 0, deepest = 0;
    bool in_string = false, escaped = false;
    for (const char c : text) {
        if (in_string) {
            if (escaped) escaped = false;
            else if (c == '\\') escaped = true;
            else if (c == '"') in_string = false;
            continue;
        }
        if (c == '"') {
            in_string = true;
        } else if (c == '[' || c == '{') {
            deepest = std::max(deepest, ++depth);
            if (deepest > limit) return deepest;
        } else if ((c == ']' || c == '}') && depth > 0) {
            --depth;
        }
    }
    return deepest;
}

nlohmann::json parse_json_input(std::string_view text, const std::string& source, std::size_t max_depth) {
    if (json_nesting_depth(text, max_depth) > max_depth)
        throw InputError(source + ": invalid JSON: nested deeper than " + std::to_string(max_depth) +
                         " levels of objects and arrays");
    try {
        return nlohmann::json::parse(text.begin(), text.end());
    } catch (const nlohmann::json::exception& e) {
        // nlohmann's message carries "parse error at line L, column C: ..." (or "number overflow parsing
        // '1e999'"); drop its "[json.exception...]" tag.
        std::string what = e.what();
        if (const auto p = what.find("] "); what.rfind("[json.exception", 0) == 0 && p != std::string::npos)
            what = what.substr(p + 2);
        throw InputError(source + ": invalid JSON: " + what);
    }
}

}  // namespace cellbench::protocol
