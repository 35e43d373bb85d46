#pragma once
// Parsing JSON that comes from outside (files, request bodies, bench configs, programs, cells): one function,
// so that every parse bounds the nesting depth and turns every nlohmann error (syntax, and also the
// out_of_range "number overflow" nlohmann throws for 1e999) into InputError naming the source.
#include <cstddef>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

namespace cellbench::protocol {

// Deepest nesting of objects and arrays any cellbench JSON file or request body needs is about 6; 64 leaves
// room and keeps every later recursive walk (dump, comparisons, the config readers) far from the stack's end.
inline constexpr std::size_t kMaxJsonDepth = 64;

// The deepest [ / { nesting in `text` (outside strings), stopping the scan once `limit` is exceeded.
std::size_t json_nesting_depth(std::string_view text, std::size_t limit = kMaxJsonDepth);

// JSON text -> value. Throws InputError "SOURCE: invalid JSON: ..." on a syntax error, a number that does not
// fit a double (1e999) or nesting deeper than max_depth.
nlohmann::json parse_json_input(std::string_view text, const std::string& source,
                                std::size_t max_depth = kMaxJsonDepth);

}  // namespace cellbench::protocol
