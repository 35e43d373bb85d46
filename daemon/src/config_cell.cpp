// Cell configurations (cellbench.cell/1): the cell's limits, constants and parameter set.
#include "config_reader.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <set>

namespace cellbench::daemon {

using namespace config_read;

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

}  // namespace cellbench::daemon
