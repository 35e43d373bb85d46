#pragma once
// Field readers for the project's JSON files (the chamber register map, the DEWE CAN layout, step programs, the
// cell parameter set): one copy of the checks, so that every file reports a bad field the same way, as
// InputError "SOURCE: JSON.PATH: what was expected" (the tests and the users read these messages).
#include <cstdint>
#include <string>

#include <nlohmann/json.hpp>

namespace cellbench::json_fields {

using nlohmann::json;

// Throws InputError "SOURCE: PATH: WHAT".
[[noreturn]] void fail(const std::string& source, const std::string& path, const std::string& what);

// j[key]; fails at PATH when j is not an object, at PATH.KEY when the key is missing.
const json& member(const json& j, const std::string& key, const std::string& source, const std::string& path);

// Whether an integer may also be written as a JSON string, decimal ("784") or hexadecimal ("0x310"): CAN
// identifiers are hex in every data sheet, register addresses are not.
enum class IntegerText { rejected, accepted };

// An integer 0..max (a JSON number; with IntegerText::accepted also a decimal or "0x" string).
std::uint64_t unsigned_value(const json& j, std::uint64_t max, const std::string& source, const std::string& path,
                             IntegerText text = IntegerText::rejected);

double finite_number(const json& j, const std::string& source, const std::string& path);
std::string string_value(const json& j, const std::string& source, const std::string& path);
bool bool_value(const json& j, const std::string& source, const std::string& path);

}  // namespace cellbench::json_fields
