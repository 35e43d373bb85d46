#include "cellbench/protocol/dewesoft_export.hpp"

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/bdf_csv.hpp"

#include <algorithm>
#include <cstdint>

namespace cellbench::protocol {
namespace {

enum class Kind { time, thermopile, heat_flux, type_k, type_t, other };

// Lower-case ASCII words of a column name ("Temperature T1 (C)" -> temperature, t1, c).
std::vector<std::string> words_of(std::string_view name) {
    std::vector<std::string> words;
    std::string word;
    for (const char c : name) {
        const bool alnum = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9');
        if (alnum) {
            word.push_back(c >= 'A' && c <= 'Z' ? static_cast<char>(c - 'A' + 'a') : c);
        } else if (!word.empty()) {
            words.push_back(std::move(word));
            word.clear();
        }
    }
    if (!word.empty()) words.push_back(std::move(word));
    return words;
}

bool has(const std::vector<std::string>& words, std::string_view w) {
    return std::find(words.begin(), words.end(), w) != words.end();
}

bool has_pair(const std::vector<std::string>& words, std::string_view a, std::string_view b) {
    for (std::size_t i = 0; i + 1 < words.size(); ++i)
        if (words[i] == a && words[i + 1] == b) return true;
    return false;
}

// Thermocouple number 1 or 2 from a word such as k1, t2, tc1; 0 if none.
int thermocouple_number(const std::vector<std::string>& words) {
    for (const auto& w : words)
        for (const std::string_view prefix : {"tc", "k", "t"})
            if (w.size() == prefix.size() + 1 && w.compare(0, prefix.size(), prefix) == 0 &&
                (w.back() == '1' || w.back() == '2'))
                return w.back() - '0';
    return 0;
}

Kind kind_of(std::string_view name, int& tc_number) {
    const std::string normalized = csv::normalize_column_name(name);
    if (normalized == "time" || normalized.rfind("time(", 0) == 0 || normalized.rfind("time[", 0) == 0)
        return Kind::time;
    const auto words = words_of(name);
    if (has(words, "voltage") && (has(words, "flux") || has(words, "thermopile") || has(words, "fhf05")))
        return Kind::thermopile;
    if (has(words, "flux") && has(words, "density")) return Kind::heat_flux;
    tc_number = thermocouple_number(words);
    if (tc_number != 0 || has(words, "thermocouple") || has(words, "typek") || has_pair(words, "type", "k"))
        return Kind::type_k;
    if (has(words, "temperature") || has(words, "typet") || has_pair(words, "type", "t")) return Kind::type_t;
    return Kind::other;
}

// Scale of a voltage column to volts from the unit in its name's last (...) or [...].
double volt_scale(std::string_view name) {
    const auto open = name.find_last_of("([");
    if (open == std::string_view::npos) return 1.0;
    const std::string unit = csv::normalize_column_name(name.substr(open + 1));
    if (unit.rfind("mv", 0) == 0) return 1e-3;
    // "uV", "µV" (U+00B5) and "μV" (U+03BC).
    if (unit.rfind("uv", 0) == 0 || unit.rfind("\xC2\xB5v", 0) == 0 || unit.rfind("\xCE\xBCv", 0) == 0) return 1e-6;
    return 1.0;
}

struct DeweColumn {
    std::size_t index = SIZE_MAX;
    std::string name;
    double scale = 1.0;
    std::vector<double>* values = nullptr;
    [[nodiscard]] bool present() const { return index != SIZE_MAX; }
};

}  // namespace

DewesoftExport parse_dewesoft_export(std::string_view text, const std::string& source) {
    csv::RecordReader reader(text, source);
    std::vector<std::string_view> fields;
    fields.reserve(16);
    if (!reader.next(fields))
        throw InputError(source +
                         ":1: empty file: expected the header row of a DewesoftX export (\"Time\", \"Thermal Flux "
                         "Sensor Voltage (V)\", \"Temperature (C)\", \"Heat Flux Density (W/m^2)\", ...)");

    DewesoftExport out;
    out.source = source;
    DeweColumn time, thermopile, heat_flux, type_t, t1, t2;
    std::vector<std::size_t> unnumbered_type_k;  // thermocouple columns without a 1/2 in the name
    const std::size_t width = fields.size();
    auto claim = [&](DeweColumn& c, std::size_t index, std::vector<double>* values, double scale = 1.0) {
        if (c.present()) return false;
        c = DeweColumn{index, std::string(fields[index]), scale, values};
        return true;
    };
    for (std::size_t i = 0; i < width; ++i) {
        int tc = 0;
        switch (kind_of(fields[i], tc)) {
            case Kind::time: claim(time, i, &out.time_s); break;
            case Kind::thermopile: claim(thermopile, i, &out.thermopile_v, volt_scale(fields[i])); break;
            case Kind::heat_flux: claim(heat_flux, i, &out.heat_flux_w_per_m2); break;
            case Kind::type_t: claim(type_t, i, &out.type_t_c); break;
            case Kind::type_k:
                if (tc == 1) claim(t1, i, &out.t1_c);
                else if (tc == 2) claim(t2, i, &out.t2_c);
                else unnumbered_type_k.push_back(i);
                break;
            case Kind::other: break;
        }
    }
    for (const std::size_t i : unnumbered_type_k)
        if (!claim(t1, i, &out.t1_c)) claim(t2, i, &out.t2_c);

    if (!time.present())
        reader.fail("no time column: expected \"Time\" (the header has " + csv::quote_cells(fields) + ")");
    const bool thermopile_usable = thermopile.present() && type_t.present();
    if (!thermopile_usable && !heat_flux.present())
        reader.fail(std::string(thermopile.present() ? "the thermopile voltage needs the sensor's Type-T column; "
                                                     : "") +
                    "expected \"Thermal Flux Sensor Voltage (V)\" with \"Temperature (C)\", or \"Heat Flux Density "
                    "(W/m^2)\" (the header has " +
                    csv::quote_cells(fields) + ")");

    std::vector<DeweColumn*> data_columns;
    for (DeweColumn* c : {&thermopile, &type_t, &heat_flux, &t1, &t2})
        if (c->present()) data_columns.push_back(c);

    const auto expected_rows = static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n')) + 1;
    out.time_s.reserve(expected_rows);
    for (DeweColumn* c : data_columns) c->values->reserve(expected_rows);

    std::vector<csv::PhysicalRange> ranges;
    for (const DeweColumn* c : data_columns)
        ranges.push_back(c == &thermopile  ? csv::kVoltageRangeV
                         : c == &heat_flux ? csv::kHeatFluxRangeWPerM2
                                           : csv::kTemperatureRangeC);
    csv::TimeStepGuard guard{time.name};
    csv::DroppedValues dropped;
    while (reader.next(fields)) {
        reader.check_width(fields, width);
        const double t = csv::read_physical(reader, fields[time.index], time.name, csv::kTestTimeRangeS, "s");
        guard.check(t, reader);
        out.time_s.push_back(t);
        for (std::size_t k = 0; k < data_columns.size(); ++k) {
            const DeweColumn* c = data_columns[k];
            const double v = csv::read_number(reader, fields[c->index], c->name, false) * c->scale;
            c->values->push_back(dropped.check(v, ranges[k], reader, c->name));
        }
    }
    if (out.time_s.empty()) throw InputError(source + ":1: header only: expected data rows after the header");
    if (reader.ends_mid_line())
        reader.fail("the export ends mid-line (no line end after the last row): the file was cut short; "
                    "export it again");

    out.repaired_timestamps = csv::repair_timestamps(out.time_s, source, time.name);
    out.dropped_values = dropped.count;
    out.first_dropped = std::move(dropped.first);
    const auto gap = csv::find_time_gap(out.time_s, guard);
    out.gap_s = gap.gap_s;
    out.gap_line = gap.line;
    out.typical_interval_s = gap.typical_interval_s;
    out.separator = reader.separator();
    return out;
}

}  // namespace cellbench::protocol
