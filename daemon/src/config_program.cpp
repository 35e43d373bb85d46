// Programs (cellbench.bench-program/1): parameters and overrides, expressions expanded, segments checked
// against the cell's and the bench's limits; and the expected duration of a program.
#include "config_reader.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <set>

#include "cellbench/protocol/json_input.hpp"

namespace cellbench::daemon {

using namespace config_read;

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
                const auto parsed = parse_expression(text, names, true);
                const Linear& v = parsed.value;
                if (v.is_constant()) value = v.constant;
                else if (parsed.used_names) value = capacity_text(v);
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
            for (const std::size_t k : protocol::execution_order(sp)) {
                const auto& st = sp.steps[k];
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
            }
        }
        out.segment_s.push_back(t);
        out.total_s += t;
    }
    return out;
}

}  // namespace cellbench::daemon
