// Step programs and the step file in the real BTS Client schema (../shared/reference/neware/: a file written
// by BTS Client 2024.06.24, schema version 17, and the schema facts in the README there). The format is
// described above compile_step_file below; what it cannot express is described in the header.
#include "cellbench/protocol/neware_stepfile.hpp"

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/core/json_fields.hpp"
#include "neware_xml.hpp"

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <limits>
#include <map>
#include <set>

#include <boost/property_tree/ptree.hpp>
#include <nlohmann/json.hpp>

namespace cellbench::protocol {
namespace {

using nlohmann::json;
namespace pt = boost::property_tree;

// Shortest text that reads back to the same double.
std::string number_text(double v) {
    char buf[64];
    const auto [ptr, ec] = std::to_chars(buf, buf + sizeof buf, v);
    if (ec != std::errc()) return std::to_string(v);
    std::string s(buf, ptr);
    if (s == "-0") s = "0";
    return s;
}

std::optional<double> parse_number(std::string_view text) {
    while (!text.empty() && std::isspace(static_cast<unsigned char>(text.front()))) text.remove_prefix(1);
    while (!text.empty() && std::isspace(static_cast<unsigned char>(text.back()))) text.remove_suffix(1);
    if (!text.empty() && text.front() == '+') text.remove_prefix(1);
    double v = 0.0;
    const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (text.empty() || ec != std::errc() || ptr != text.data() + text.size() || !std::isfinite(v))
        return std::nullopt;
    return v;
}

std::optional<int> parse_int(std::string_view text) {
    while (!text.empty() && std::isspace(static_cast<unsigned char>(text.front()))) text.remove_prefix(1);
    while (!text.empty() && std::isspace(static_cast<unsigned char>(text.back()))) text.remove_suffix(1);
    if (!text.empty() && text.front() == '+') text.remove_prefix(1);
    int v = 0;
    const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (text.empty() || ec != std::errc() || ptr != text.data() + text.size()) return std::nullopt;
    return v;
}

// The first problem of a program: the JSON path ("steps[3].current_a"), what was expected, and the step.
struct Problem {
    std::string path;
    std::string what;
    std::size_t index = 0;
    bool in_step = true;
    // For people: "steps[3] (step 4).current_a: expected ..."
    [[nodiscard]] std::string text() const {
        if (!in_step) return path + ": " + what;
        const std::string head = "steps[" + std::to_string(index) + "]";
        return head + " (step " + std::to_string(index + 1) + ")" + path.substr(head.size()) + ": " + what;
    }
    // For configuration messages: "steps[3].current_a: expected ... (step 4)"
    [[nodiscard]] std::string json_text() const {
        return path + ": " + what + (in_step ? " (step " + std::to_string(index + 1) + ")" : "");
    }
};

std::optional<Problem> find_problem(const StepProgram& p) {
    if (p.steps.empty()) return Problem{"steps", "expected at least one step (and an end step last)", 0, false};
    if (p.first_step < 1 || p.first_step > static_cast<int>(p.steps.size()))
        return Problem{"first_step", "expected a step of the program (1.." + std::to_string(p.steps.size()) + ")", 0,
                       false};
    auto positive = [](const std::optional<double>& v) { return v && std::isfinite(*v) && *v > 0.0; };
    for (std::size_t i = 0; i < p.steps.size(); ++i) {
        const Step& s = p.steps[i];
        const int id = static_cast<int>(i) + 1;
        const std::string at = "steps[" + std::to_string(i) + "]";
        auto bad = [&](const std::string& field, const std::string& what) -> std::optional<Problem> {
            return Problem{at + (field.empty() ? "" : "." + field), what, i, true};
        };
        const std::string kind = std::string(to_string(s.type));
        auto unused = [&](bool present, const char* field) -> std::optional<Problem> {
            if (present) return bad(field, "not used by a " + kind + " step");
            return std::nullopt;
        };
        if (s.type == StepType::end && i + 1 != p.steps.size())
            return bad("type", "an end step must be the last step");
        if (i + 1 == p.steps.size() && s.type != StepType::end)
            return bad("type", "the last step must be an end step");
        if (s.type != StepType::cycle) {
            if (auto e = unused(s.start_step != 0, "start_step")) return e;
            if (auto e = unused(s.count != 0, "count")) return e;
        }
        for (const auto& [value, field] : {std::pair{&s.current_a, "current_a"}, std::pair{&s.voltage_v, "voltage_v"},
                                           std::pair{&s.time_s, "time_s"},
                                           std::pair{&s.cutoff_voltage_v, "cutoff_voltage_v"},
                                           std::pair{&s.cutoff_current_a, "cutoff_current_a"}}) {
            if (value->has_value() && !positive(*value)) return bad(field, "expected a positive number");
        }
        switch (s.type) {
            case StepType::rest:
                if (!s.time_s) return bad("time_s", "a rest step needs its duration");
                if (auto e = unused(s.current_a.has_value(), "current_a")) return e;
                if (auto e = unused(s.voltage_v.has_value(), "voltage_v")) return e;
                if (auto e = unused(s.cutoff_voltage_v.has_value(), "cutoff_voltage_v")) return e;
                if (auto e = unused(s.cutoff_current_a.has_value(), "cutoff_current_a")) return e;
                if (auto e = unused(s.cutoff_capacity_ah.has_value(), "cutoff_capacity_ah")) return e;
                break;
            case StepType::cc_charge:
            case StepType::cc_discharge:
                if (!s.current_a) return bad("current_a", "a constant-current step needs its current");
                if (auto e = unused(s.voltage_v.has_value(), "voltage_v")) return e;
                if (auto e = unused(s.cutoff_current_a.has_value(), "cutoff_current_a")) return e;
                if (!s.time_s && !s.cutoff_voltage_v && !s.cutoff_capacity_ah)
                    return bad("", "a constant-current step needs an end condition (time_s, cutoff_voltage_v or "
                                   "cutoff_capacity_ah)");
                break;
            case StepType::cccv_charge:
            case StepType::cccv_discharge:
            case StepType::cv_charge:
            case StepType::cv_discharge:
                if (!s.current_a) return bad("current_a", "a CCCV step needs its current");
                if (!s.voltage_v) return bad("voltage_v", "a CCCV step needs its constant-voltage set value");
                if (auto e = unused(s.cutoff_voltage_v.has_value(), "cutoff_voltage_v")) return e;
                if (!s.cutoff_current_a && !s.time_s && !s.cutoff_capacity_ah)
                    return bad("", "a CCCV step needs an end condition (cutoff_current_a, time_s or "
                                   "cutoff_capacity_ah)");
                if (s.cutoff_current_a && *s.cutoff_current_a >= *s.current_a)
                    return bad("cutoff_current_a", "expected less than current_a");
                break;
            case StepType::cycle:
            case StepType::end:
                if (auto e = unused(s.current_a.has_value(), "current_a")) return e;
                if (auto e = unused(s.voltage_v.has_value(), "voltage_v")) return e;
                if (auto e = unused(s.time_s.has_value(), "time_s")) return e;
                if (auto e = unused(s.cutoff_voltage_v.has_value(), "cutoff_voltage_v")) return e;
                if (auto e = unused(s.cutoff_current_a.has_value(), "cutoff_current_a")) return e;
                if (auto e = unused(s.cutoff_capacity_ah.has_value(), "cutoff_capacity_ah")) return e;
                if (s.type == StepType::end) {
                    if (auto e = unused(s.start_step != 0, "start_step")) return e;
                    if (auto e = unused(s.count != 0, "count")) return e;
                }
                break;
        }
        if (s.type == StepType::cycle) {
            if (s.start_step < 1 || s.start_step >= id)
                return bad("start_step", "expected an earlier step (1.." + std::to_string(id - 1) + ")");
            if (s.count < 1) return bad("count", "expected a positive integer");
            // Nested loops must nest: an inner cycle's block lies inside this block.
            for (int k = s.start_step; k < id; ++k) {
                const Step& inner = p.steps[static_cast<std::size_t>(k - 1)];
                if (inner.type == StepType::cycle && inner.start_step < s.start_step)
                    return bad("start_step", "loop overlaps the loop of step " + std::to_string(k));
            }
        }
        if (s.cutoff_capacity_ah) {
            const auto& c = *s.cutoff_capacity_ah;
            if (!std::isfinite(c.constant_ah)) return bad("cutoff_capacity_ah", "expected finite numbers");
            if (c.is_constant() && c.constant_ah <= 0.0)
                return bad("cutoff_capacity_ah", "expected a positive capacity");
            for (const auto& t : c.terms) {
                if (!std::isfinite(t.factor)) return bad("cutoff_capacity_ah", "expected finite numbers");
                if (t.step_id < 1 || t.step_id >= id)
                    return bad("cutoff_capacity_ah", "C" + std::to_string(t.step_id) +
                                                         ": only earlier steps' capacities can be referenced");
                if (!step_carries_current(p.steps[static_cast<std::size_t>(t.step_id - 1)].type))
                    return bad("cutoff_capacity_ah",
                               "C" + std::to_string(t.step_id) + ": that step carries no current");
            }
        }
    }
    return std::nullopt;
}

// ---------------------------------------------------------------------------------------------------------
// JSON helpers (errors name the JSON path, worded by json_fields::fail like the other JSON files).

std::optional<double> json_number(const json& obj, const char* key, const std::string& source,
                                  const std::string& path) {
    const auto it = obj.find(key);
    if (it == obj.end() || it->is_null()) return std::nullopt;
    if (!it->is_number()) json_fields::fail(source, path + "." + key, "expected a number");
    const double v = it->get<double>();
    if (!std::isfinite(v)) json_fields::fail(source, path + "." + key, "expected a finite number");
    return v;
}

int json_int(const json& obj, const char* key, const std::string& source, const std::string& path) {
    const auto it = obj.find(key);
    if (it == obj.end() || it->is_null()) return 0;
    if (!it->is_number_integer()) json_fields::fail(source, path + "." + key, "expected an integer");
    const auto v = it->get<long long>();
    if (v < 0 || v > 1'000'000'000) json_fields::fail(source, path + "." + key, "expected a non-negative integer");
    return static_cast<int>(v);
}

}  // namespace

// -------------------------------------------------------------------------------------------------------------
// Step types

std::string_view to_string(StepType type) {
    switch (type) {
        case StepType::rest: return "rest";
        case StepType::cc_charge: return "cc_charge";
        case StepType::cc_discharge: return "cc_discharge";
        case StepType::cccv_charge: return "cccv_charge";
        case StepType::cccv_discharge: return "cccv_discharge";
        case StepType::cycle: return "cycle";
        case StepType::end: return "end";
        case StepType::cv_charge: return "cv_charge";
        case StepType::cv_discharge: return "cv_discharge";
    }
    return "rest";
}

std::optional<StepType> step_type_from_string(std::string_view text) {
    for (const auto t : {StepType::rest, StepType::cc_charge, StepType::cc_discharge, StepType::cccv_charge,
                         StepType::cccv_discharge, StepType::cycle, StepType::end, StepType::cv_charge,
                         StepType::cv_discharge})
        if (to_string(t) == text) return t;
    return std::nullopt;
}

int step_direction(StepType type) {
    switch (type) {
        case StepType::cc_charge:
        case StepType::cccv_charge:
        case StepType::cv_charge: return +1;
        case StepType::cc_discharge:
        case StepType::cccv_discharge:
        case StepType::cv_discharge: return -1;
        default: return 0;
    }
}

bool step_carries_current(StepType type) { return step_direction(type) != 0; }

std::vector<std::size_t> execution_order(const StepProgram& program, std::size_t max_steps) {
    std::vector<std::size_t> order;
    std::map<std::size_t, int> passes_left;  // per cycle step: jumps back still to do
    std::size_t k = 0, guard = 0;
    while (k < program.steps.size() && order.size() < max_steps && ++guard < 10 * max_steps) {
        const Step& st = program.steps[k];
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
        order.push_back(k++);
    }
    return order;
}

bool step_has_cv_phase(StepType type) {
    return type == StepType::cccv_charge || type == StepType::cccv_discharge || type == StepType::cv_charge ||
           type == StepType::cv_discharge;
}

std::string_view step_type_code(StepType type) {
    switch (type) {
        case StepType::rest: return "rest";
        case StepType::cc_charge: return "cc";
        case StepType::cc_discharge: return "dc";
        case StepType::cccv_charge: return "cc";     // "cv" in its CV phase (the runner reports that)
        case StepType::cccv_discharge: return "dc";
        case StepType::cv_charge:
        case StepType::cv_discharge: return "cv";
        default: return "--";
    }
}

// -------------------------------------------------------------------------------------------------------------
// Capacity expressions

std::string CapacityExpression::to_string() const {
    std::string out;
    auto append_signed = [&](double magnitude_signed, const std::string& body_if_one, bool is_term) {
        const bool negative = magnitude_signed < 0.0;
        const double mag = std::fabs(magnitude_signed);
        if (out.empty()) {
            if (negative) out += "-";
        } else {
            out += negative ? " - " : " + ";
        }
        if (is_term) {
            if (mag != 1.0) out += number_text(mag) + "*";
            out += body_if_one;
        } else {
            out += number_text(mag);
        }
    };
    for (const auto& t : terms) {
        std::string ref(1, 'C');  // (not "C" + to_string: GCC 12 raises a false -Wrestrict on that)
        ref += std::to_string(t.step_id);
        append_signed(t.factor, ref, true);
    }
    if (constant_ah != 0.0 || terms.empty()) append_signed(constant_ah, "", false);
    return out;
}

CapacityExpression CapacityExpression::parse(std::string_view text) {
    CapacityExpression e;
    std::size_t i = 0;
    const std::string original(text);
    auto fail = [&](const std::string& what) -> void {
        throw InputError("capacity expression '" + original + "': " + what +
                         " (expected e.g. '0.1*C4 - C8 + C10' or a number of Ah)");
    };
    auto skip_ws = [&] {
        while (i < text.size() && std::isspace(static_cast<unsigned char>(text[i]))) ++i;
    };
    auto read_number = [&]() -> std::optional<double> {
        const std::size_t start = i;
        while (i < text.size() && (std::isdigit(static_cast<unsigned char>(text[i])) || text[i] == '.' ||
                                   text[i] == 'e' || text[i] == 'E' ||
                                   ((text[i] == '-' || text[i] == '+') && i > start &&
                                    (text[i - 1] == 'e' || text[i - 1] == 'E'))))
            ++i;
        if (i == start) return std::nullopt;
        const auto v = parse_number(text.substr(start, i - start));
        if (!v) fail("bad number '" + std::string(text.substr(start, i - start)) + "'");
        return v;
    };
    auto read_ref = [&]() -> std::optional<int> {
        if (i >= text.size() || (text[i] != 'C' && text[i] != 'c')) return std::nullopt;
        ++i;
        const std::size_t start = i;
        while (i < text.size() && std::isdigit(static_cast<unsigned char>(text[i]))) ++i;
        const auto v = parse_int(text.substr(start, i - start));
        if (!v || *v < 1) fail("expected a step number after 'C'");
        return v;
    };
    skip_ws();
    if (i >= text.size()) fail("empty");
    bool first = true;
    while (true) {
        skip_ws();
        double sign = 1.0;
        if (i < text.size() && (text[i] == '+' || text[i] == '-')) {
            sign = text[i] == '-' ? -1.0 : 1.0;
            ++i;
            skip_ws();
        } else if (!first) {
            fail("expected '+' or '-' at position " + std::to_string(i + 1));
        }
        first = false;
        if (auto ref = read_ref()) {
            double factor = 1.0;
            skip_ws();
            if (i < text.size() && text[i] == '*') {
                ++i;
                skip_ws();
                const auto n = read_number();
                if (!n) fail("expected a number after '*'");
                factor = *n;
            }
            e.terms.push_back({*ref, sign * factor});
        } else if (auto n = read_number()) {
            skip_ws();
            if (i < text.size() && text[i] == '*') {
                ++i;
                skip_ws();
                const auto r = read_ref();
                if (!r) fail("expected C<step> after '*'");
                e.terms.push_back({*r, sign * *n});
            } else {
                e.constant_ah += sign * *n;
            }
        } else {
            fail("expected a number or C<step> at position " + std::to_string(i + 1));
        }
        skip_ws();
        if (i >= text.size()) break;
    }
    return e;
}

double CapacityExpression::evaluate(const std::function<double(int)>& step_capacity_ah) const {
    double v = constant_ah;
    for (const auto& t : terms) v += t.factor * step_capacity_ah(t.step_id);
    return v;
}

// -------------------------------------------------------------------------------------------------------------
// StepProgram

void StepProgram::validate() const {
    if (auto problem = find_problem(*this))
        throw InputError("program '" + name + "': " + problem->text());
}

double StepProgram::max_current_a() const {
    double m = 0.0;
    for (const auto& s : steps)
        if (s.current_a) m = std::max(m, *s.current_a);
    return m;
}

nlohmann::json StepProgram::to_json() const {
    json j = json::object();
    j["schema"] = kProgramSchema;
    j["name"] = name;
    if (!description.empty()) j["description"] = description;
    json steps_json = json::array();
    for (std::size_t i = 0; i < steps.size(); ++i) {
        const Step& s = steps[i];
        json o = json::object();
        o["id"] = i + 1;
        o["type"] = std::string(protocol::to_string(s.type));
        if (s.current_a) o["current_a"] = *s.current_a;
        if (s.voltage_v) o["voltage_v"] = *s.voltage_v;
        if (s.time_s) o["time_s"] = *s.time_s;
        if (s.cutoff_voltage_v) o["cutoff_voltage_v"] = *s.cutoff_voltage_v;
        if (s.cutoff_current_a) o["cutoff_current_a"] = *s.cutoff_current_a;
        if (s.cutoff_capacity_ah) {
            if (s.cutoff_capacity_ah->is_constant())
                o["cutoff_capacity_ah"] = s.cutoff_capacity_ah->constant_ah;
            else
                o["cutoff_capacity_ah"] = s.cutoff_capacity_ah->to_string();
        }
        if (s.type == StepType::cycle) {
            o["start_step"] = s.start_step;
            o["count"] = s.count;
        }
        if (!s.note.empty()) o["note"] = s.note;
        steps_json.push_back(std::move(o));
    }
    j["steps"] = std::move(steps_json);
    return j;
}

StepProgram StepProgram::from_json(const nlohmann::json& j, const std::string& source) {
    if (!j.is_object()) json_fields::fail(source, "(root)", "expected an object");
    static const std::set<std::string> kTopKeys{"schema", "name", "description", "steps"};
    for (const auto& [key, value] : j.items())
        if (!kTopKeys.count(key)) json_fields::fail(source, key, "unknown key (expected schema, name, description, steps)");
    StepProgram p;
    if (const auto it = j.find("schema"); it != j.end()) {
        if (!it->is_string() || it->get<std::string>() != kProgramSchema)
            json_fields::fail(source, "schema", std::string("expected \"") + kProgramSchema + "\"");
    }
    if (const auto it = j.find("name"); it != j.end()) {
        if (!it->is_string()) json_fields::fail(source, "name", "expected a string");
        p.name = it->get<std::string>();
    }
    if (const auto it = j.find("description"); it != j.end()) {
        if (!it->is_string()) json_fields::fail(source, "description", "expected a string");
        p.description = it->get<std::string>();
    }
    const auto steps_it = j.find("steps");
    if (steps_it == j.end()) json_fields::fail(source, "steps", "missing (expected an array of steps)");
    if (!steps_it->is_array()) json_fields::fail(source, "steps", "expected an array of steps");
    static const std::set<std::string> kStepKeys{"id",           "type",     "current_a",        "voltage_v",
                                                 "time_s",       "cutoff_voltage_v", "cutoff_current_a",
                                                 "cutoff_capacity_ah", "start_step", "count", "note"};
    std::size_t index = 0;
    for (const auto& sj : *steps_it) {
        const std::string path = "steps[" + std::to_string(index) + "]";
        if (!sj.is_object()) json_fields::fail(source, path, "expected an object");
        for (const auto& [key, value] : sj.items())
            if (!kStepKeys.count(key)) json_fields::fail(source, path + "." + key, "unknown key");
        Step s;
        const auto type_it = sj.find("type");
        if (type_it == sj.end() || !type_it->is_string())
            json_fields::fail(source, path + ".type",
                      "expected one of rest, cc_charge, cc_discharge, cccv_charge, cccv_discharge, cv_charge, "
                      "cv_discharge, cycle, end");
        const auto type = step_type_from_string(type_it->get<std::string>());
        if (!type)
            json_fields::fail(source, path + ".type",
                      "unknown step type \"" + type_it->get<std::string>() +
                          "\" (expected rest, cc_charge, cc_discharge, cccv_charge, cccv_discharge, cv_charge, "
                          "cv_discharge, cycle, end)");
        s.type = *type;
        if (const auto it = sj.find("id"); it != sj.end()) {
            if (!it->is_number_integer() || it->get<long long>() != static_cast<long long>(index + 1))
                json_fields::fail(source, path + ".id", "expected " + std::to_string(index + 1) + " (steps are numbered in order)");
        }
        s.current_a = json_number(sj, "current_a", source, path);
        s.voltage_v = json_number(sj, "voltage_v", source, path);
        s.time_s = json_number(sj, "time_s", source, path);
        s.cutoff_voltage_v = json_number(sj, "cutoff_voltage_v", source, path);
        s.cutoff_current_a = json_number(sj, "cutoff_current_a", source, path);
        if (const auto it = sj.find("cutoff_capacity_ah"); it != sj.end() && !it->is_null()) {
            if (it->is_number()) {
                s.cutoff_capacity_ah = CapacityExpression{it->get<double>(), {}};
            } else if (it->is_string()) {
                try {
                    s.cutoff_capacity_ah = CapacityExpression::parse(it->get<std::string>());
                } catch (const InputError& e) {
                    json_fields::fail(source, path + ".cutoff_capacity_ah", e.what());
                }
            } else {
                json_fields::fail(source, path + ".cutoff_capacity_ah", "expected a number (Ah) or an expression string");
            }
        }
        s.start_step = json_int(sj, "start_step", source, path);
        s.count = json_int(sj, "count", source, path);
        if (const auto it = sj.find("note"); it != sj.end()) {
            if (!it->is_string()) json_fields::fail(source, path + ".note", "expected a string");
            s.note = it->get<std::string>();
        }
        p.steps.push_back(std::move(s));
        ++index;
    }
    if (auto problem = find_problem(p)) throw InputError(source + ": " + problem->json_text());
    return p;
}

// -------------------------------------------------------------------------------------------------------------
// Capacity limits the format cannot express, defaults, parts

namespace {

// Steps in the body of the innermost loop that contains step `id` (its cycle step excluded), or {} when `id`
// is in no loop. Loops nest (validated), so the innermost is the one with the latest start.
std::pair<int, int> innermost_loop(const StepProgram& p, int id) {
    std::pair<int, int> best{0, 0};
    for (std::size_t k = 0; k < p.steps.size(); ++k) {
        const Step& c = p.steps[k];
        const int cid = static_cast<int>(k) + 1;
        if (c.type == StepType::cycle && c.start_step <= id && id < cid && c.start_step > best.first)
            best = {c.start_step, cid - 1};
    }
    return best;
}

bool referenced_outside_loop(const StepProgram& p, int limited_step, int referenced) {
    const auto [first, last] = innermost_loop(p, limited_step);
    return !(first != 0 && referenced >= first && referenced <= last);
}

double whole_mas(double ah) { return std::round(ah * 3.6e6) / 3.6e6; }  // the file's resolution: 1 mA*s

}  // namespace

std::optional<double> nominal_step_capacity_ah(const StepProgram& program, int step_id) {
    if (step_id < 1 || step_id > static_cast<int>(program.steps.size())) return std::nullopt;
    const Step& s = program.steps[static_cast<std::size_t>(step_id - 1)];
    if (!step_carries_current(s.type) || !s.current_a) return std::nullopt;
    if (s.time_s) return *s.current_a * *s.time_s / 3600.0;
    return program.settings.nominal_capacity_ah;
}

StepProgram resolve_capacity_limits(const StepProgram& program,
                                    const std::function<std::optional<double>(int)>& measured_ah) {
    StepProgram out = program;
    for (std::size_t i = 0; i < out.steps.size(); ++i) {
        Step& s = out.steps[i];
        if (!s.cutoff_capacity_ah || s.cutoff_capacity_ah->is_constant()) continue;
        const int id = static_cast<int>(i) + 1;
        double ah = s.cutoff_capacity_ah->constant_ah;
        for (const auto& t : s.cutoff_capacity_ah->terms) {
            std::optional<double> c;
            if (measured_ah && referenced_outside_loop(program, id, t.step_id)) c = measured_ah(t.step_id);
            if (!c) c = nominal_step_capacity_ah(program, t.step_id);
            if (!c)
                throw InputError("step " + std::to_string(id) + ": capacity limit " + s.cutoff_capacity_ah->to_string() +
                                 " needs C" + std::to_string(t.step_id) +
                                 ", which only a measurement or the cell's nominal capacity gives");
            ah += t.factor * *c;
        }
        s.cutoff_capacity_ah = CapacityExpression{std::max(whole_mas(ah), 1.0 / 3.6e6), {}};
    }
    return out;
}

StepProgram as_tester_program(const StepProgram& program) {
    program.validate();
    StepProgram p = resolve_capacity_limits(program);
    p.description.clear();
    for (auto& s : p.steps) s.note.clear();
    auto& st = p.settings;
    if (!st.record_interval_s) st.record_interval_s = 1.0;
    double v_hi = 0.0, v_lo = std::numeric_limits<double>::infinity(), i_max = 0.0;
    for (const auto& s : p.steps) {
        for (const auto& v : {s.voltage_v, s.cutoff_voltage_v}) {
            if (!v) continue;
            v_hi = std::max(v_hi, *v);
            v_lo = std::min(v_lo, *v);
        }
        if (s.current_a) i_max = std::max(i_max, *s.current_a);
    }
    auto tenth_mv = [](double v) { return std::round(v * 1e4) / 1e4; };
    auto milliamp = [](double a) { return std::round(a * 1e3) / 1e3; };
    if (!st.protect_upper_v && v_hi > 0.0) st.protect_upper_v = tenth_mv(v_hi + 0.1);
    if (!st.protect_lower_v && std::isfinite(v_lo)) st.protect_lower_v = tenth_mv(std::max(0.0, v_lo - 0.1));
    if (!st.protect_upper_a && i_max > 0.0) st.protect_upper_a = milliamp(1.1 * i_max);
    if (!st.protect_lower_a && i_max > 0.0) st.protect_lower_a = -milliamp(1.1 * i_max);
    return p;
}

std::vector<StepProgram> tester_parts(const StepProgram& program) {
    program.validate();
    int k = 0;  // the last step that must have been measured before the rest can be written
    for (std::size_t i = 0; i < program.steps.size(); ++i) {
        const Step& s = program.steps[i];
        if (!s.cutoff_capacity_ah) continue;
        for (const auto& t : s.cutoff_capacity_ah->terms)
            if (referenced_outside_loop(program, static_cast<int>(i) + 1, t.step_id)) k = std::max(k, t.step_id);
    }
    if (k < program.first_step) return {program};
    // A loop around step k would have to run across the two files: not split, nominal values instead.
    for (std::size_t c = 0; c < program.steps.size(); ++c)
        if (program.steps[c].type == StepType::cycle && program.steps[c].start_step <= k &&
            static_cast<int>(c) + 1 > k)
            return {program};
    StepProgram first = program;
    first.steps.resize(static_cast<std::size_t>(k));
    Step end;
    end.type = StepType::end;
    first.steps.push_back(end);
    StepProgram second = program;
    second.first_step = k + 1;
    first.validate();
    second.validate();
    return {first, second};
}

// -------------------------------------------------------------------------------------------------------------
// Step file: the BTS Client schema.
//
//   <?xml version="1.0" encoding="GB2312"?>                      (UTF-8 when the name is not ASCII)
//   <root>
//     <config type="Step File" version="17" client_version="cellbench" date="YYYYMMDDhhmmss" Guid="...">
//       <Head_Info> Operate 65, Scale 1, Start_Step (first_step), PN (name), RateType 105, MultCap (mA*s)
//       <Whole_Prt> <Protect><Main> Volt Upper/Lower (0.1 mV), Curr Upper/Lower (mA), Delay_Time (ms),
//                   Cap Upper (mA*s) </Main></Protect> <Record><Main><Time (ms)/></Main></Record>
//       <Step_Info Num="N"> <StepK Step_ID="K" Step_Type="T"> [Record] <Limit><Main> Curr (mA), Volt (0.1 mV,
//                   the CV set value), Time (ms), Stop_Volt (0.1 mV), Stop_Curr (mA), Cap (mA*s) </Main>
//                   | <Other> Start_Step, Cycle_Count </Other></Limit> [Protect] </StepK>
//       <SMBUS><SMBUS_Info Num="0" AdjacentInterval="0" /></SMBUS>
//   </config></root>
// Rate / Stop_Rate (C-rates against MultCap) are read when Curr / Stop_Curr are absent.

namespace {

constexpr double kTenthMv = 1e4;    // per V
constexpr double kMa = 1e3;         // per A
constexpr double kMs = 1e3;         // per s
constexpr double kMaS = 3.6e6;      // mA*s per Ah

int step_type_code_number(StepType t) {
    switch (t) {
        case StepType::cc_charge: return 1;
        case StepType::cc_discharge: return 2;
        case StepType::cv_charge: return 3;
        case StepType::rest: return 4;
        case StepType::cycle: return 5;
        case StepType::end: return 6;
        case StepType::cccv_charge: return 7;
        case StepType::cv_discharge: return 19;
        case StepType::cccv_discharge: return 20;
    }
    return 4;
}

std::optional<StepType> step_type_of_number(int code) {
    switch (code) {
        case 1: return StepType::cc_charge;
        case 2: return StepType::cc_discharge;
        case 3: return StepType::cv_charge;
        case 4: return StepType::rest;
        case 5: return StepType::cycle;
        case 6: return StepType::end;
        case 7: return StepType::cccv_charge;
        case 19: return StepType::cv_discharge;
        case 20: return StepType::cccv_discharge;
        default: return std::nullopt;
    }
}

std::string unit_text(double v) { return neware::format_number(v, 3); }

std::string fnv_guid(std::string_view text) {
    std::uint64_t h1 = 1469598103934665603ull, h2 = 1099511628211ull * 31;
    for (const char c : text) {
        h1 = (h1 ^ static_cast<unsigned char>(c)) * 1099511628211ull;
        h2 = (h2 ^ static_cast<unsigned char>(c)) * 1099511628211ull + 0x9e3779b97f4a7c15ull;
    }
    char buf[48];
    std::snprintf(buf, sizeof buf, "%08x-%04x-4%03x-a%03x-%012llx", static_cast<unsigned>(h1 >> 32),
                  static_cast<unsigned>((h1 >> 16) & 0xffff), static_cast<unsigned>(h1 & 0xfff),
                  static_cast<unsigned>((h2 >> 52) & 0xfff), static_cast<unsigned long long>(h2 & 0xffffffffffffull));
    return buf;
}

std::string utc_stamp() {
    const std::time_t t = std::time(nullptr);
    std::tm tm{};
    gmtime_r(&t, &tm);
    char buf[32];
    std::strftime(buf, sizeof buf, "%Y%m%d%H%M%S", &tm);
    return buf;
}

}  // namespace

std::string compile_step_file(const StepProgram& program, const StepFileOptions& options) {
    const StepProgram p = as_tester_program(program);
    const std::string nl = "\r\n";
    auto value = [&](std::string& out, int indent, const char* tag, double v) {
        out += std::string(static_cast<std::size_t>(indent), ' ') + "<" + tag + " Value=\"" + unit_text(v) + "\" />" + nl;
    };
    auto escaped = [](std::string_view text) {
        std::string out;
        neware::xml::append_escaped(out, text, neware::xml::Escape::whitespace);
        return out;
    };
    const auto& st = p.settings;
    std::string body;
    body += "    <Head_Info>" + nl;
    body += "      <Operate Value=\"65\" />" + nl;
    body += "      <Scale Value=\"1\" />" + nl;
    body += "      <Start_Step Value=\"" + std::to_string(p.first_step) + "\" Hide_Ctrl_Step=\"0\" />" + nl;
    body += "      <PN Value=\"" + escaped(p.name) + "\" />" + nl;
    body += "      <RateType Value=\"105\" />" + nl;
    if (st.nominal_capacity_ah) value(body, 6, "MultCap", *st.nominal_capacity_ah * kMaS);
    body += "    </Head_Info>" + nl;
    body += "    <Whole_Prt>" + nl + "      <Protect>" + nl + "        <Main>" + nl;
    if (st.protect_upper_v || st.protect_lower_v) {
        body += "          <Volt>" + nl;
        if (st.protect_upper_v) value(body, 12, "Upper", *st.protect_upper_v * kTenthMv);
        if (st.protect_lower_v) value(body, 12, "Lower", *st.protect_lower_v * kTenthMv);
        body += "          </Volt>" + nl;
    }
    if (st.protect_upper_a || st.protect_lower_a) {
        body += "          <Curr>" + nl;
        if (st.protect_upper_a) value(body, 12, "Upper", *st.protect_upper_a * kMa);
        if (st.protect_lower_a) value(body, 12, "Lower", *st.protect_lower_a * kMa);
        body += "          </Curr>" + nl;
    }
    if (st.protect_delay_s) value(body, 10, "Delay_Time", *st.protect_delay_s * kMs);
    if (st.protect_capacity_ah) {
        body += "          <Cap>" + nl;
        value(body, 12, "Upper", *st.protect_capacity_ah * kMaS);
        body += "          </Cap>" + nl;
    }
    body += "        </Main>" + nl + "      </Protect>" + nl;
    body += "      <Record>" + nl + "        <Main>" + nl;
    value(body, 10, "Time", *st.record_interval_s * kMs);
    body += "        </Main>" + nl + "      </Record>" + nl + "    </Whole_Prt>" + nl;
    body += "    <Step_Info Num=\"" + std::to_string(p.steps.size()) + "\">" + nl;
    for (std::size_t i = 0; i < p.steps.size(); ++i) {
        const Step& s = p.steps[i];
        const std::string tag = "Step" + std::to_string(i + 1);
        body += "      <" + tag + " Step_ID=\"" + std::to_string(i + 1) + "\" Step_Type=\"" +
                std::to_string(step_type_code_number(s.type)) + "\">" + nl;
        if (s.record_interval_s || s.record_delta_v || s.record_delta_a) {
            body += "        <Record>" + nl + "          <Main>" + nl;
            if (s.record_interval_s) value(body, 12, "Time", *s.record_interval_s * kMs);
            if (s.record_delta_v) value(body, 12, "Volt", *s.record_delta_v * kTenthMv);
            if (s.record_delta_a) value(body, 12, "Curr", *s.record_delta_a * kMa);
            body += "          </Main>" + nl + "        </Record>" + nl;
        }
        if (s.type == StepType::cycle) {
            body += "        <Limit>" + nl + "          <Other>" + nl;
            body += "            <Start_Step Value=\"" + std::to_string(s.start_step) + "\" />" + nl;
            body += "            <Cycle_Count Value=\"" + std::to_string(s.count) + "\" />" + nl;
            body += "          </Other>" + nl + "        </Limit>" + nl;
        } else if (s.type != StepType::end) {
            body += "        <Limit>" + nl + "          <Main>" + nl;
            if (s.current_a) value(body, 12, "Curr", *s.current_a * kMa);
            if (s.voltage_v) value(body, 12, "Volt", *s.voltage_v * kTenthMv);
            if (s.time_s) value(body, 12, "Time", *s.time_s * kMs);
            if (s.cutoff_voltage_v) value(body, 12, "Stop_Volt", *s.cutoff_voltage_v * kTenthMv);
            if (s.cutoff_current_a) value(body, 12, "Stop_Curr", *s.cutoff_current_a * kMa);
            if (s.cutoff_capacity_ah) value(body, 12, "Cap", s.cutoff_capacity_ah->constant_ah * kMaS);
            body += "          </Main>" + nl + "        </Limit>" + nl;
        }
        if (s.protect_upper_v || s.protect_lower_v) {
            body += "        <Protect>" + nl + "          <Main>" + nl + "            <Volt>" + nl;
            if (s.protect_upper_v) value(body, 14, "Upper", *s.protect_upper_v * kTenthMv);
            if (s.protect_lower_v) value(body, 14, "Lower", *s.protect_lower_v * kTenthMv);
            body += "            </Volt>" + nl + "          </Main>" + nl + "        </Protect>" + nl;
        }
        body += "      </" + tag + ">" + nl;
    }
    body += "    </Step_Info>" + nl;
    body += "    <SMBUS>" + nl + "      <SMBUS_Info Num=\"0\" AdjacentInterval=\"0\" />" + nl + "    </SMBUS>" + nl;
    const bool ascii = std::all_of(p.name.begin(), p.name.end(), [](char c) { return static_cast<unsigned char>(c) < 0x80; });
    std::string out = std::string("<?xml version=\"1.0\" encoding=\"") + (ascii ? "GB2312" : "UTF-8") + "\"?>" + nl;
    out += "<root>" + nl;
    out += "  <config type=\"Step File\" version=\"17\" client_version=\"cellbench\" date=\"" +
           (options.date.empty() ? utc_stamp() : escaped(options.date)) + "\" Guid=\"" + fnv_guid(body) + "\">" + nl;
    out += body;
    out += "  </config>" + nl + "</root>";
    return out;
}

StepProgram parse_step_file(std::string_view xml) {
    using neware::ProtocolError;
    // GB2312 and UTF-8 agree on ASCII, which is all the schema's markup and numbers use; a non-ASCII program
    // name is kept as the file's bytes.
    const pt::ptree tree = neware::xml::read_document(xml, "step file: ");
    const pt::ptree* root = nullptr;
    for (const auto& [key, child] : tree) {
        if (key == "<xmlcomment>") continue;
        if (key != "root" || root != nullptr)
            throw ProtocolError("step file: expected one <root> element (BTS Client step file), found <" +
                                key.substr(0, 40) + ">");
        root = &child;
    }
    if (root == nullptr) throw ProtocolError("step file: expected a <root> element (BTS Client step file)");
    const auto cfg_it = root->find("config");
    if (cfg_it == root->not_found()) throw ProtocolError("step file: <root> without <config>");
    const pt::ptree& cfg = cfg_it->second;
    auto attr = [](const pt::ptree& node, const char* name) -> std::optional<std::string> {
        const auto a = node.find("<xmlattr>");
        if (a == node.not_found()) return std::nullopt;
        const auto it = a->second.find(name);
        if (it == a->second.not_found()) return std::nullopt;
        return it->second.data();
    };
    const auto type = attr(cfg, "type");
    if (!type || *type != "Step File")
        throw ProtocolError("step file: expected <config type=\"Step File\">, got type=\"" + type.value_or("").substr(0, 40) + "\"");
    const auto version = attr(cfg, "version");
    const auto vnum = version ? parse_int(*version) : std::nullopt;
    if (!vnum || (*vnum != 17 && *vnum != 18))
        throw ProtocolError("step file: schema version \"" + version.value_or("").substr(0, 20) +
                            "\" is not one this reader knows (17, 18)");

    // <A><B><C Value=".."/> under a node: the number, or nullopt.
    auto number_at = [&](const pt::ptree& node, const std::string& path, const std::string& where) -> std::optional<double> {
        const auto child = node.get_child_optional(pt::ptree::path_type(path, '/'));
        if (!child) return std::nullopt;
        const auto text = attr(*child, "Value");
        if (!text) throw ProtocolError(where + ": <" + path + "> without Value");
        const auto v = parse_number(*text);
        if (!v) throw ProtocolError(where + ": <" + path + "> Value=\"" + text->substr(0, 30) + "\": expected a number");
        return v;
    };
    auto scaled = [](std::optional<double> v, double per_unit) -> std::optional<double> {
        if (!v) return std::nullopt;
        return *v / per_unit;
    };

    StepProgram p;
    const std::string head = "step file: <Head_Info>";
    if (const auto h = cfg.get_child_optional("Head_Info")) {
        if (const auto pn = h->get_child_optional("PN")) p.name = attr(*pn, "Value").value_or("");
        if (const auto ss = number_at(*h, "Start_Step", head)) p.first_step = static_cast<int>(*ss);
        p.settings.nominal_capacity_ah = scaled(number_at(*h, "MultCap", head), kMaS);
    }
    if (const auto w = cfg.get_child_optional("Whole_Prt")) {
        const std::string where = "step file: <Whole_Prt>";
        auto& st = p.settings;
        st.protect_upper_v = scaled(number_at(*w, "Protect/Main/Volt/Upper", where), kTenthMv);
        st.protect_lower_v = scaled(number_at(*w, "Protect/Main/Volt/Lower", where), kTenthMv);
        st.protect_upper_a = scaled(number_at(*w, "Protect/Main/Curr/Upper", where), kMa);
        st.protect_lower_a = scaled(number_at(*w, "Protect/Main/Curr/Lower", where), kMa);
        st.protect_delay_s = scaled(number_at(*w, "Protect/Main/Delay_Time", where), kMs);
        st.protect_capacity_ah = scaled(number_at(*w, "Protect/Main/Cap/Upper", where), kMaS);
        st.record_interval_s = scaled(number_at(*w, "Record/Main/Time", where), kMs);
    }
    const auto info = cfg.get_child_optional("Step_Info");
    if (!info) throw ProtocolError("step file: <Step_Info> missing");
    std::vector<std::pair<int, const pt::ptree*>> nodes;
    for (const auto& [key, node] : *info) {
        if (key == "<xmlattr>" || key == "<xmlcomment>") continue;
        const auto id_text = attr(node, "Step_ID");
        const auto id = id_text ? parse_int(*id_text) : std::nullopt;
        if (key.rfind("Step", 0) != 0 || !id)
            throw ProtocolError("step file: <Step_Info>: unexpected element <" + key.substr(0, 40) + "> (expected StepK with Step_ID)");
        nodes.emplace_back(id.value_or(0), &node);  // checked above (value_or: GCC 12 warns on *id)
    }
    std::sort(nodes.begin(), nodes.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
    if (const auto num = attr(*info, "Num"); num && parse_int(*num) != static_cast<int>(nodes.size()))
        throw ProtocolError("step file: <Step_Info Num=\"" + num->substr(0, 20) + "\"> but " +
                            std::to_string(nodes.size()) + " steps");
    for (std::size_t i = 0; i < nodes.size(); ++i) {
        const auto& [id, node] = nodes[i];
        const std::string where = "step file: step " + std::to_string(id);
        if (id != static_cast<int>(i) + 1)
            throw ProtocolError(where + ": expected Step_ID " + std::to_string(i + 1) + " (steps are numbered in order)");
        const auto code_text = attr(*node, "Step_Type");
        const auto code = code_text ? parse_int(*code_text) : std::nullopt;
        if (!code) throw ProtocolError(where + ": Step_Type missing or not a number");
        const auto type = step_type_of_number(*code);
        if (!type)
            throw ProtocolError(where + ": Step_Type " + std::to_string(*code) +
                                " is not supported (known: 1 CC Chg, 2 CC DChg, 3 CV Chg, 4 Rest, 5 Cycle, 6 End, "
                                "7 CCCV Chg, 19 CV DChg, 20 CCCV DChg)");
        Step s;
        s.type = *type;
        const pt::ptree& n = *node;
        if (s.type == StepType::cycle) {
            const auto start = number_at(n, "Limit/Other/Start_Step", where);
            const auto count = number_at(n, "Limit/Other/Cycle_Count", where);
            if (!start || !count) throw ProtocolError(where + ": a cycle step needs Limit/Other/Start_Step and Cycle_Count");
            s.start_step = static_cast<int>(*start);
            s.count = static_cast<int>(*count);
        } else if (s.type != StepType::end) {
            s.current_a = scaled(number_at(n, "Limit/Main/Curr", where), kMa);
            if (!s.current_a && p.settings.nominal_capacity_ah)
                if (const auto rate = number_at(n, "Limit/Main/Rate", where))
                    s.current_a = *rate * *p.settings.nominal_capacity_ah;
            s.voltage_v = scaled(number_at(n, "Limit/Main/Volt", where), kTenthMv);
            s.time_s = scaled(number_at(n, "Limit/Main/Time", where), kMs);
            s.cutoff_voltage_v = scaled(number_at(n, "Limit/Main/Stop_Volt", where), kTenthMv);
            s.cutoff_current_a = scaled(number_at(n, "Limit/Main/Stop_Curr", where), kMa);
            if (!s.cutoff_current_a && p.settings.nominal_capacity_ah)
                if (const auto rate = number_at(n, "Limit/Main/Stop_Rate", where))
                    s.cutoff_current_a = *rate * *p.settings.nominal_capacity_ah;
            if (const auto cap = scaled(number_at(n, "Limit/Main/Cap", where), kMaS))
                s.cutoff_capacity_ah = CapacityExpression{*cap, {}};
            if (s.type == StepType::rest) s.current_a.reset();  // some clients write a 0 current on rests
            if (!step_has_cv_phase(s.type)) s.voltage_v.reset();
        }
        s.record_interval_s = scaled(number_at(n, "Record/Main/Time", where), kMs);
        s.record_delta_v = scaled(number_at(n, "Record/Main/Volt", where), kTenthMv);
        s.record_delta_a = scaled(number_at(n, "Record/Main/Curr", where), kMa);
        s.protect_upper_v = scaled(number_at(n, "Protect/Main/Volt/Upper", where), kTenthMv);
        s.protect_lower_v = scaled(number_at(n, "Protect/Main/Volt/Lower", where), kTenthMv);
        p.steps.push_back(std::move(s));
    }
    p.validate();
    return p;
}

// -------------------------------------------------------------------------------------------------------------
// The thesis' programs

namespace {

Step rest(double time_s, std::string note = {}) {
    Step s;
    s.type = StepType::rest;
    s.time_s = time_s;
    s.note = std::move(note);
    return s;
}
Step cccv(StepType type, double current_a, double voltage_v, double cutoff_current_a,
          std::optional<double> time_s, std::string note) {
    Step s;
    s.type = type;
    s.current_a = current_a;
    s.voltage_v = voltage_v;
    s.cutoff_current_a = cutoff_current_a;
    s.time_s = time_s;
    s.note = std::move(note);
    return s;
}
Step cc(StepType type, double current_a, double cutoff_voltage_v, std::optional<double> time_s, std::string note) {
    Step s;
    s.type = type;
    s.current_a = current_a;
    s.cutoff_voltage_v = cutoff_voltage_v;
    s.time_s = time_s;
    s.note = std::move(note);
    return s;
}
Step cycle(int start_step, int count) {
    Step s;
    s.type = StepType::cycle;
    s.start_step = start_step;
    s.count = count;
    return s;
}
Step end() {
    Step s;
    s.type = StepType::end;
    return s;
}

constexpr double kUpperV = 4.1, kLowerV = 2.9, kCvCutoffA = 0.05;

}  // namespace

StepProgram thesis_cc_discharge_program(double c_rate, double one_c_a, std::optional<double> discharge_current_a) {
    StepProgram p;
    const double i_dis = discharge_current_a.value_or(c_rate * one_c_a);
    p.name = "cc_discharge_" + number_text(c_rate) + "c";
    p.description = "Thesis Table 2.10: full CCCV charge at 1C, constant-current discharge at " + number_text(c_rate) +
                    "C (" + number_text(i_dis) + " A) to 2.9 V";
    p.steps = {rest(10),
               cccv(StepType::cccv_charge, one_c_a, kUpperV, kCvCutoffA, std::nullopt, "Full Chg"),
               rest(600),
               cc(StepType::cc_discharge, i_dis, kLowerV, std::nullopt, "Full DChg"),
               rest(600),
               end()};
    p.validate();
    return p;
}

StepProgram thesis_hppc_program(double one_c_a) {
    StepProgram p;
    p.name = "hppc_1c";
    p.description = "Thesis Table 2.12: HPPC at 1C, pilot discharge, 10 pulse sets at -10 % SOC each";
    Step soc_step = cc(StepType::cc_discharge, one_c_a, kLowerV, std::nullopt, "10% SOC DChg");
    // Thesis eq. 2.4: discharge 10 % of the pilot capacity, corrected for what the pulses moved.
    soc_step.cutoff_capacity_ah = CapacityExpression{0.0, {{4, 0.1}, {8, -1.0}, {10, 1.0}}};
    p.steps = {rest(10),                                                                          // 1
               cccv(StepType::cccv_charge, one_c_a, kUpperV, kCvCutoffA, std::nullopt, "Full Chg"),  // 2
               rest(600),                                                                         // 3
               cc(StepType::cc_discharge, one_c_a, kLowerV, std::nullopt, "Full DChg"),           // 4
               rest(3600),                                                                        // 5
               cccv(StepType::cccv_charge, one_c_a, kUpperV, kCvCutoffA, std::nullopt, "Full Chg"),  // 6
               rest(3600),                                                                        // 7
               cccv(StepType::cccv_discharge, one_c_a, kLowerV, kCvCutoffA, 30.0, "DChg Pulse"),  // 8
               rest(40),                                                                          // 9
               cccv(StepType::cccv_charge, one_c_a, kUpperV, kCvCutoffA, 10.0, "Chg Pulse"),      // 10
               rest(40),                                                                          // 11
               soc_step,                                                                          // 12
               rest(3600),                                                                        // 13
               cycle(8, 10),                                                                      // 14
               cc(StepType::cc_discharge, one_c_a, kLowerV, std::nullopt, "Final DChg"),          // 15
               rest(1800),                                                                        // 16
               end()};                                                                            // 17
    p.validate();
    return p;
}

StepProgram thesis_random_walk_program(double one_c_a) {
    StepProgram p;
    p.name = "random_walk";
    p.description = "Thesis Table 5.1: Random Walk, 1C..4C discharge and up to 3C charge pulses";
    auto dis = [&](double c, std::string note) {
        return cc(StepType::cc_discharge, c * one_c_a, kLowerV, 60.0, std::move(note));
    };
    auto chg = [&](double c, std::string note) {
        return cc(StepType::cc_charge, c * one_c_a, kUpperV, 20.0, std::move(note));
    };
    p.steps = {rest(60),                                // 1
               dis(1, "1C Discharge"), chg(1, "1C Charge"), rest(10),  // 2-4
               dis(2, "2C Discharge"), chg(2, "2C Charge"), rest(10),  // 5-7
               dis(3, "3C Discharge"), chg(3, "3C Charge"), rest(10),  // 8-10
               dis(4, "4C Discharge"), chg(3, "3C Charge"), rest(10),  // 11-13
               cycle(2, 7),                                                                 // 14
               cc(StepType::cc_discharge, one_c_a, kLowerV, std::nullopt, "Final 1C Discharge"),  // 15
               end()};                                                                      // 16
    p.validate();
    return p;
}

}  // namespace cellbench::protocol
