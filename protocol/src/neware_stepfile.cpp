// Step programs and the step-file format.
//
// NEWARE'S STEP-FILE SCHEMA IS NOT PUBLIC. The format below is cellbench's own; it lives only in this file so
// that it can be replaced by the real one once a file from Neware's step editor can be compared.
//
// Format "cellbench.neware-steps/1" (UTF-8 XML, SI units, attribute names carry the unit):
//   <?xml version="1.0" encoding="UTF-8"?>
//   <cellbench_steps format="cellbench.neware-steps/1" name="hppc_1c" description="...">
//     <step id="1" type="rest" time_s="10"/>
//     <step id="2" type="cccv_charge" current_a="4.5" voltage_v="4.1" cutoff_current_a="0.05" note="Full Chg"/>
//     <step id="12" type="cc_discharge" current_a="4.5" cutoff_voltage_v="2.9"
//           cutoff_capacity_ah="0.1*C4 - C8 + C10"/>
//     <step id="14" type="cycle" start_step="8" count="10"/>
//     <step id="17" type="end"/>
//   </cellbench_steps>
// One <step> per step, in order, id = position (1-based). Attributes are exactly the StepProgram/JSON fields;
// absent = not set. Numbers are written in shortest round-trip form, so compile -> parse is exact.
//
// For the later match, the shape of vendor files seen in public third-party tools (BTS Client 8.0,
// unverified, do not rely on it):
//   <root><config type="Step File" version="17|18" ...><Head_Info>...</Head_Info><Whole_Prt>...</Whole_Prt>
//     <Step_Info Num="N"><Step1 Step_ID="1" Step_Type="4"><Limit><Main><Time Value="600000"/></Main></Limit>
//     </Step1>...</Step_Info></config></root>
//   Step_Type seen: 1 CC Chg, 2 CC DChg, 4 Rest, 5 Cycle (Limit/Other/Start_Step, Cycle_Count), 6 End,
//   7 CCCV Chg (CCCV DChg unknown). Limit/Main fields seen: Curr (mA), Volt (0.1 mV), Stop_Volt (0.1 mV),
//   Stop_Curr (mA), Time (ms), Cap (mA*s). How custom capacity functions (eq. 2.4) are stored is unknown.
#include "cellbench/protocol/neware_stepfile.hpp"

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "json_fields.hpp"
#include "neware_xml.hpp"

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
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
    }
    return "rest";
}

std::optional<StepType> step_type_from_string(std::string_view text) {
    for (const auto t : {StepType::rest, StepType::cc_charge, StepType::cc_discharge, StepType::cccv_charge,
                         StepType::cccv_discharge, StepType::cycle, StepType::end})
        if (to_string(t) == text) return t;
    return std::nullopt;
}

int step_direction(StepType type) {
    switch (type) {
        case StepType::cc_charge:
        case StepType::cccv_charge: return +1;
        case StepType::cc_discharge:
        case StepType::cccv_discharge: return -1;
        default: return 0;
    }
}

bool step_carries_current(StepType type) { return step_direction(type) != 0; }

std::string_view step_type_code(StepType type) {
    switch (type) {
        case StepType::rest: return "rest";
        case StepType::cc_charge: return "cc";
        case StepType::cc_discharge: return "dc";
        case StepType::cccv_charge: return "cccv";
        case StepType::cccv_discharge: return "cccv_dc";
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
                      "expected one of rest, cc_charge, cc_discharge, cccv_charge, cccv_discharge, cycle, end");
        const auto type = step_type_from_string(type_it->get<std::string>());
        if (!type)
            json_fields::fail(source, path + ".type",
                      "unknown step type \"" + type_it->get<std::string>() +
                          "\" (expected rest, cc_charge, cc_discharge, cccv_charge, cccv_discharge, cycle, end)");
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
// Step file

std::string compile_step_file(const StepProgram& program) {
    program.validate();
    auto escaped = [](std::string_view text) {
        std::string out;
        neware::xml::append_escaped(out, text, neware::xml::Escape::whitespace);
        return out;
    };
    std::string out = "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n";
    out += "<cellbench_steps format=\"" + std::string(kStepFileFormat) + "\" name=\"" + escaped(program.name) + "\"";
    if (!program.description.empty()) out += " description=\"" + escaped(program.description) + "\"";
    out += ">\n";
    for (std::size_t i = 0; i < program.steps.size(); ++i) {
        const Step& s = program.steps[i];
        out += "  <step id=\"" + std::to_string(i + 1) + "\" type=\"" + std::string(to_string(s.type)) + "\"";
        auto num = [&](const char* name, const std::optional<double>& v) {
            if (v) out += std::string(" ") + name + "=\"" + number_text(*v) + "\"";
        };
        num("current_a", s.current_a);
        num("voltage_v", s.voltage_v);
        num("time_s", s.time_s);
        num("cutoff_voltage_v", s.cutoff_voltage_v);
        num("cutoff_current_a", s.cutoff_current_a);
        if (s.cutoff_capacity_ah) out += " cutoff_capacity_ah=\"" + s.cutoff_capacity_ah->to_string() + "\"";
        if (s.type == StepType::cycle)
            out += " start_step=\"" + std::to_string(s.start_step) + "\" count=\"" + std::to_string(s.count) + "\"";
        if (!s.note.empty()) out += " note=\"" + escaped(s.note) + "\"";
        out += "/>\n";
    }
    out += "</cellbench_steps>\n";
    return out;
}

StepProgram parse_step_file(std::string_view xml) {
    using neware::ProtocolError;
    const pt::ptree tree = neware::xml::read_document(xml, "step file: ");
    const pt::ptree* root = nullptr;
    for (const auto& [key, child] : tree) {
        if (key == "<xmlcomment>") continue;
        if (key != "cellbench_steps" || root != nullptr)
            throw ProtocolError("step file: expected one <cellbench_steps> root element (format " +
                                std::string(kStepFileFormat) + ")");
        root = &child;
    }
    if (root == nullptr)
        throw ProtocolError("step file: expected a <cellbench_steps> root element (format " +
                            std::string(kStepFileFormat) + ")");
    auto attrs_of = [](const pt::ptree& node) -> const pt::ptree* {
        const auto it = node.find("<xmlattr>");
        return it == node.not_found() ? nullptr : &it->second;
    };
    auto attr = [&](const pt::ptree& node, const char* name) -> std::optional<std::string> {
        const pt::ptree* a = attrs_of(node);
        if (a == nullptr) return std::nullopt;
        const auto it = a->find(name);
        if (it == a->not_found()) return std::nullopt;
        return it->second.data();
    };
    const auto format = attr(*root, "format");
    if (!format || *format != kStepFileFormat)
        throw ProtocolError(std::string("step file: expected format=\"") + kStepFileFormat + "\"");

    StepProgram p;
    p.name = attr(*root, "name").value_or("");
    p.description = attr(*root, "description").value_or("");
    static const std::set<std::string> kKnown{"id",           "type",     "current_a",        "voltage_v",
                                              "time_s",       "cutoff_voltage_v", "cutoff_current_a",
                                              "cutoff_capacity_ah", "start_step", "count", "note"};
    for (const auto& child : *root) {
        const std::string& key = child.first;
        const pt::ptree& node = child.second;  // (not a structured binding: lambdas below capture it)
        if (key == "<xmlattr>" || key == "<xmlcomment>") continue;
        if (key != "step") throw ProtocolError("step file: unexpected element <" + key.substr(0, 40) + ">");
        const std::size_t index = p.steps.size();
        const std::string where = "step file: <step> #" + std::to_string(index + 1);
        if (const pt::ptree* a = attrs_of(node))
            for (const auto& [name, value] : *a)
                if (!kKnown.count(name)) throw ProtocolError(where + ": unknown attribute '" + name.substr(0, 40) + "'");
        Step s;
        const auto id = attr(node, "id");
        if (id) {
            const auto v = parse_int(*id);
            if (!v || *v != static_cast<int>(index + 1))
                throw ProtocolError(where + ": expected id=\"" + std::to_string(index + 1) + "\"");
        }
        const auto type_text = attr(node, "type");
        if (!type_text) throw ProtocolError(where + ": attribute 'type' missing");
        const auto type = step_type_from_string(*type_text);
        if (!type) throw ProtocolError(where + ": unknown type '" + type_text->substr(0, 40) + "'");
        s.type = *type;
        auto num = [&](const char* name) -> std::optional<double> {
            const auto text = attr(node, name);
            if (!text) return std::nullopt;
            const auto v = parse_number(*text);
            if (!v) throw ProtocolError(where + ": attribute '" + name + "': expected a number");
            return v;
        };
        auto integer = [&](const char* name) -> int {
            const auto text = attr(node, name);
            if (!text) return 0;
            const auto v = parse_int(*text);
            if (!v || *v < 0) throw ProtocolError(where + ": attribute '" + name + "': expected a non-negative integer");
            return *v;
        };
        s.current_a = num("current_a");
        s.voltage_v = num("voltage_v");
        s.time_s = num("time_s");
        s.cutoff_voltage_v = num("cutoff_voltage_v");
        s.cutoff_current_a = num("cutoff_current_a");
        if (const auto cap = attr(node, "cutoff_capacity_ah")) {
            try {
                s.cutoff_capacity_ah = CapacityExpression::parse(*cap);
            } catch (const InputError& e) {
                throw ProtocolError(where + ": cutoff_capacity_ah: " + e.what());
            }
        }
        s.start_step = integer("start_step");
        s.count = integer("count");
        s.note = attr(node, "note").value_or("");
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
