#include "cellbench/protocol/neware_export.hpp"

#include "cellbench/protocol/bdf_csv.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <optional>
#include <system_error>

namespace cellbench::protocol {
namespace {

enum class Role { time_s, total_time, cumulative_time, step_time, current, voltage, step_type, step_id, cycle, date,
                  nda_marker, count };

constexpr double kMaxAbsVoltageV = 10.0;    // beyond: not a cell voltage (a unit or column mix-up)
constexpr double kMaxAbsCurrentA = 10000.0;

struct Alias {
    std::string_view normalized_name;  // csv::normalize_column_name form
    Role role;
    double scale;  // to SI (A, V)
};

constexpr std::array kAliases{
    Alias{"time(s)", Role::time_s, 1.0},       Alias{"testtime(s)", Role::time_s, 1.0},
    Alias{"time", Role::step_time, 1.0},       Alias{"steptime", Role::step_time, 1.0},
    Alias{"steptime(s)", Role::step_time, 1.0}, Alias{"time(h:min:s.ms)", Role::step_time, 1.0},
    Alias{"current(a)", Role::current, 1.0},
    Alias{"current", Role::current, 1.0},      Alias{"current(ma)", Role::current, 1e-3},
    Alias{"voltage(v)", Role::voltage, 1.0},   Alias{"voltage", Role::voltage, 1.0},
    Alias{"voltage(mv)", Role::voltage, 1e-3}, Alias{"steptype", Role::step_type, 1.0},
    Alias{"stepid", Role::step_id, 1.0},       Alias{"stepindex", Role::step_id, 1.0},
    Alias{"stepno", Role::step_id, 1.0},       Alias{"stepno.", Role::step_id, 1.0},
    Alias{"stepnumber", Role::step_id, 1.0},   Alias{"step", Role::step_id, 1.0},
    Alias{"cycle", Role::cycle, 1.0},          Alias{"cycleid", Role::cycle, 1.0},
    Alias{"cycleindex", Role::cycle, 1.0},     Alias{"cycleno", Role::cycle, 1.0},
    Alias{"cycleno.", Role::cycle, 1.0},       Alias{"cyclenumber", Role::cycle, 1.0},
    Alias{"date", Role::date, 1.0},            Alias{"datetime", Role::date, 1.0},
    Alias{"realtime", Role::date, 1.0},        Alias{"absolutetime", Role::date, 1.0},
    Alias{"systemtime", Role::date, 1.0},      Alias{"timestamp", Role::date, 1.0},
    Alias{"status", Role::step_type, 1.0},     Alias{"cumulativetime", Role::cumulative_time, 1.0},
    Alias{"cumulativetime(h:min:s.ms)", Role::cumulative_time, 1.0},
    // NewareNDA's CSV (Time = step time, Timestamp absolute): its capacity columns mark the layout.
    Alias{"charge_capacity(mah)", Role::nda_marker, 1.0},
};

struct NewareColumn {
    std::size_t index = SIZE_MAX;  // SIZE_MAX: absent
    std::string name;              // as in the header, for messages
    double scale = 1.0;
    [[nodiscard]] bool present() const { return index != SIZE_MAX; }
};

std::optional<Role> role_of(const std::string& normalized, double& scale) {
    for (const auto& a : kAliases)
        if (a.normalized_name == normalized) {
            scale = a.scale;
            return a.role;
        }
    if (normalized.rfind("totaltime", 0) == 0) {  // "Total Time", "Total Time(h:min:s.ms)", ...
        scale = 1.0;
        return Role::total_time;
    }
    return std::nullopt;
}

// Digits only, no sign, into an integer.
bool parse_unsigned(std::string_view s, std::uint64_t& value) {
    if (s.empty() || s.size() > 12) return false;
    const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
    return ec == std::errc{} && ptr == s.data() + s.size();
}

// Seconds field of a clock time: [0, 60] (60 for a leap second), digits and an optional fraction.
bool parse_clock_seconds(std::string_view s, double& value) {
    if (s.empty() || !(s.front() >= '0' && s.front() <= '9')) return false;
    return csv::parse_double(s, value) == csv::NumberStatus::ok && value >= 0.0 && value <= 60.0;
}

// "h:mm:ss[.fff]" (hours unbounded), "mm:ss[.fff]" or plain seconds.
bool parse_duration_s(std::string_view s, double& value) {
    const auto c1 = s.find(':');
    if (c1 == std::string_view::npos)
        return csv::parse_double(s, value) == csv::NumberStatus::ok && std::isfinite(value);
    const auto c2 = s.find(':', c1 + 1);
    std::uint64_t hours = 0, minutes = 0;
    double seconds = 0.0;
    if (c2 == std::string_view::npos) {
        if (!parse_unsigned(s.substr(0, c1), minutes) || !parse_clock_seconds(s.substr(c1 + 1), seconds)) return false;
    } else {
        if (!parse_unsigned(s.substr(0, c1), hours) || !parse_unsigned(s.substr(c1 + 1, c2 - c1 - 1), minutes) ||
            minutes >= 60 || !parse_clock_seconds(s.substr(c2 + 1), seconds))
            return false;
    }
    value = static_cast<double>(hours) * 3600.0 + static_cast<double>(minutes) * 60.0 + seconds;
    return true;
}

// Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's days_from_civil).
std::int64_t days_from_civil(std::int64_t y, unsigned m, unsigned d) {
    y -= m <= 2 ? 1 : 0;
    const std::int64_t era = (y >= 0 ? y : y - 399) / 400;
    const auto yoe = static_cast<unsigned>(y - era * 400);
    const unsigned doy = (153 * (m > 2 ? m - 3 : m + 9) + 2) / 5 + d - 1;
    const unsigned doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    return era * 146097 + static_cast<std::int64_t>(doe) - 719468;
}

unsigned days_in_month(std::uint64_t y, std::uint64_t m) {
    constexpr std::array<unsigned, 12> kDays{31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
    const bool leap = (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
    return m == 2 && leap ? 29 : kDays[static_cast<std::size_t>(m - 1)];
}

// "YYYY-MM-DD hh:mm:ss[.fff]" ('/' for '-' and 'T' for the space also accepted) as UTC Unix seconds.
bool parse_date_utc_s(std::string_view s, double& value) {
    const auto split = s.find_first_of(" T");
    if (split == std::string_view::npos) return false;
    const std::string_view date = s.substr(0, split);
    std::string_view clock = s.substr(split + 1);
    while (!clock.empty() && clock.front() == ' ') clock.remove_prefix(1);

    const char sep = date.size() > 4 ? date[4] : '\0';
    if (sep != '-' && sep != '/') return false;
    const auto d2 = date.find(sep, 5);
    if (d2 == std::string_view::npos) return false;
    std::uint64_t y = 0, mo = 0, d = 0;
    if (!parse_unsigned(date.substr(0, 4), y) || !parse_unsigned(date.substr(5, d2 - 5), mo) ||
        !parse_unsigned(date.substr(d2 + 1), d) || mo < 1 || mo > 12 || d < 1 || d > days_in_month(y, mo))
        return false;

    const auto c1 = clock.find(':');
    const auto c2 = c1 == std::string_view::npos ? c1 : clock.find(':', c1 + 1);
    if (c2 == std::string_view::npos) return false;
    std::uint64_t h = 0, mi = 0;
    double sec = 0.0;
    if (!parse_unsigned(clock.substr(0, c1), h) || !parse_unsigned(clock.substr(c1 + 1, c2 - c1 - 1), mi) || h > 23 ||
        mi > 59 || !parse_clock_seconds(clock.substr(c2 + 1), sec))
        return false;
    const auto days = days_from_civil(static_cast<std::int64_t>(y), static_cast<unsigned>(mo), static_cast<unsigned>(d));
    value = static_cast<double>(days) * 86400.0 + static_cast<double>(h * 3600 + mi * 60) + sec;
    return true;
}

}  // namespace

std::string_view to_string(NewareExportLayout layout) {
    switch (layout) {
        case NewareExportLayout::btsda_test_time: return "BTSDA record export, test time from Time(s)";
        case NewareExportLayout::btsda_total_time: return "BTSDA record export, test time from Total Time";
        case NewareExportLayout::btsda_cumulative_time: return "BTSDA record export, test time from Cumulative Time";
        case NewareExportLayout::btsda_wall_clock: return "BTSDA record export, test time from its wall clock (Realtime/Date)";
        case NewareExportLayout::newarenda: return "NewareNDA CSV (Time is step time), test time from Timestamp";
    }
    return "Neware export";
}

Recording parse_neware_export(std::string_view text, const std::string& source, NewareExportInfo* info) {
    csv::RecordReader reader(text, source);
    std::vector<std::string_view> fields;
    fields.reserve(16);
    if (!reader.next(fields))
        throw InputError(source +
                         ":1: empty file: expected the header row of a Neware record export (\"Step Type\", "
                         "\"Time(s)\", \"Total Time\" or \"Cumulative Time\", \"Current(A)\", \"Voltage(V)\", ...)");

    std::array<NewareColumn, static_cast<std::size_t>(Role::count)> cols;
    auto col = [&cols](Role r) -> NewareColumn& { return cols[static_cast<std::size_t>(r)]; };
    const std::size_t width = fields.size();
    for (std::size_t c = 0; c < width; ++c) {
        double scale = 1.0;
        const auto role = role_of(csv::normalize_column_name(fields[c]), scale);
        if (!role || col(*role).present()) continue;  // unknown, or a later alias of a mapped channel
        col(*role) = NewareColumn{c, std::string(fields[c]), scale};
    }

    // Which export this is, and where its test time comes from. Time(s) is preferred (Total Time has only
    // 1 s resolution in exports sampled faster), then Total Time, Cumulative Time, and the wall clock.
    NewareExportLayout layout;
    const NewareColumn* time_col = nullptr;
    if (col(Role::nda_marker).present() && col(Role::date).present()) {
        layout = NewareExportLayout::newarenda;
        time_col = &col(Role::date);
    } else if (col(Role::time_s).present()) {
        layout = NewareExportLayout::btsda_test_time;
        time_col = &col(Role::time_s);
    } else if (col(Role::total_time).present()) {
        layout = NewareExportLayout::btsda_total_time;
        time_col = &col(Role::total_time);
    } else if (col(Role::cumulative_time).present()) {
        layout = NewareExportLayout::btsda_cumulative_time;
        time_col = &col(Role::cumulative_time);
    } else if (col(Role::date).present()) {
        layout = NewareExportLayout::btsda_wall_clock;
        time_col = &col(Role::date);
    } else {
        reader.fail("no time column: expected \"Time(s)\", \"Total Time\", \"Cumulative Time\", \"Realtime\"/\"Date\" or "
                    "NewareNDA's \"Timestamp\" (the header has " +
                    csv::quote_cells(fields) + ")");
    }
    const bool wall_clock = layout == NewareExportLayout::newarenda || layout == NewareExportLayout::btsda_wall_clock;
    if (info) *info = NewareExportInfo{layout, time_col->name, reader.separator()};
    if (!col(Role::current).present())
        reader.fail("missing required column \"Current(A)\" (the header has " + csv::quote_cells(fields) + ")");
    if (!col(Role::voltage).present())
        reader.fail("missing required column \"Voltage(V)\" (the header has " + csv::quote_cells(fields) + ")");

    const NewareColumn& current_col = col(Role::current);
    const NewareColumn& voltage_col = col(Role::voltage);
    const NewareColumn& type_col = col(Role::step_type);
    const NewareColumn& step_id_col = col(Role::step_id);
    const NewareColumn& step_time_col = col(Role::step_time);
    const NewareColumn& cycle_col = col(Role::cycle);
    const NewareColumn& date_col = col(Role::date);
    // Steps are counted from type changes and step-time resets only when no step id column says so.
    const bool count_steps = !step_id_col.present() && (type_col.present() || step_time_col.present());

    Recording rec;
    rec.source = source;
    const auto expected_rows = static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n')) + 1;
    rec.time_s.reserve(expected_rows);
    rec.voltage_v.reserve(expected_rows);
    rec.current_a.reserve(expected_rows);

    csv::TimeStepGuard guard{time_col->name};
    double step = 0.0;
    double previous_step_time_s = kNaN;
    double first_unix_s = kNaN;
    while (reader.next(fields)) {
        reader.check_width(fields, width);

        double t = 0.0;
        const std::string_view time_cell = fields[time_col->index];
        if (wall_clock) {
            double unix_s = 0.0;
            if (!parse_date_utc_s(time_cell, unix_s))
                reader.fail_column(time_col->name, "expected a date YYYY-MM-DD hh:mm:ss[.fff], got " + csv::quote_cell(time_cell));
            if (std::isnan(first_unix_s)) first_unix_s = unix_s;
            t = unix_s - first_unix_s;
        } else if (!parse_duration_s(time_cell, t) || !std::isfinite(t)) {
            reader.fail_column(time_col->name,
                               "expected a duration hh:mm:ss, h:mm:ss.fff or seconds, got " + csv::quote_cell(time_cell));
        }
        guard.check(t, reader);
        rec.time_s.push_back(t);
        const double current = csv::read_number(reader, fields[current_col.index], current_col.name, true) *
                               current_col.scale;
        const double voltage = csv::read_number(reader, fields[voltage_col.index], voltage_col.name, true) *
                               voltage_col.scale;
        if (!std::isfinite(current) || std::abs(current) > kMaxAbsCurrentA)
            reader.fail_column(current_col.name, "physically impossible current " + csv::quote_cell(fields[current_col.index]) +
                                                     " (expected a finite value within +-10 kA)");
        if (!std::isfinite(voltage) || std::abs(voltage) > kMaxAbsVoltageV)
            reader.fail_column(voltage_col.name, "physically impossible voltage " + csv::quote_cell(fields[voltage_col.index]) +
                                                     " (expected a finite value within +-10 V)");
        rec.current_a.push_back(current);
        rec.voltage_v.push_back(voltage);

        if (type_col.present()) rec.step_type.emplace_back(fields[type_col.index]);
        if (cycle_col.present())
            rec.cycle_count.push_back(csv::read_number(reader, fields[cycle_col.index], cycle_col.name, false));
        if (date_col.present()) {
            const std::string_view cell = fields[date_col.index];
            double unix_s = kNaN;
            if (!cell.empty() && !parse_date_utc_s(cell, unix_s))
                reader.fail_column(date_col.name, "expected a date YYYY-MM-DD hh:mm:ss[.fff], got " + csv::quote_cell(cell));
            rec.unix_time_s.push_back(unix_s);
        }
        if (step_id_col.present()) {
            rec.step_count.push_back(csv::read_number(reader, fields[step_id_col.index], step_id_col.name, false));
        } else if (count_steps) {
            // Step time only helps to split two consecutive steps of the same type; text that is not a
            // duration there is not worth rejecting the file for.
            double step_time_s = kNaN;
            if (step_time_col.present() && !parse_duration_s(fields[step_time_col.index], step_time_s))
                step_time_s = kNaN;
            const std::size_t rows = rec.step_type.size();
            const bool type_changed = rows >= 2 && rec.step_type[rows - 1] != rec.step_type[rows - 2];
            const bool step_time_reset = previous_step_time_s - step_time_s >= csv::kMaxRepairableBackwardStepS;
            if (step == 0.0 || type_changed || step_time_reset) step += 1.0;
            rec.step_count.push_back(step);
            if (!std::isnan(step_time_s)) previous_step_time_s = step_time_s;
        }
    }
    if (rec.time_s.empty()) throw InputError(source + ":1: header only: expected data rows after the header");

    rec.repaired_timestamps = csv::repair_timestamps(rec.time_s, source, time_col->name);
    return rec;
}

}  // namespace cellbench::protocol
