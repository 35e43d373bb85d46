#include "cellbench/protocol/bdf_csv.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <span>
#include <ostream>
#include <stdexcept>
#include <system_error>
#include <utility>

namespace cellbench::protocol {
namespace csv {

namespace {
constexpr std::string_view kUtf8Bom = "\xEF\xBB\xBF";

// The separator of the header line (the text's first line that is not blank): ',' if it holds a comma outside
// quotes, else ';' or a tab if it holds one (the more frequent of the two), else ','.
char header_separator(std::string_view text) {
    std::size_t commas = 0, semicolons = 0, tabs = 0;
    bool quoted = false, seen = false;
    for (const char c : text) {
        if (c == '"') quoted = !quoted;
        if (quoted) continue;
        if (c == '\n' || c == '\r') {
            if (seen) break;
            continue;
        }
        if (c != ' ' && c != '\t') seen = true;
        commas += c == ',';
        semicolons += c == ';';
        tabs += c == '\t';
    }
    if (commas > 0 || (semicolons == 0 && tabs == 0)) return ',';
    return semicolons >= tabs ? ';' : '\t';
}

// Whether `cell` is a number or a duration written with one decimal comma: digits, at most one comma, and
// otherwise only sign, exponent and time characters ("-3,5", "1,2e-3", "00:00:01,500").
bool has_decimal_comma(std::string_view cell) {
    std::size_t commas = 0, digits = 0;
    for (const char c : cell) {
        if (c == ',') {
            ++commas;
        } else if (c >= '0' && c <= '9') {
            ++digits;
        } else if (c != '+' && c != '-' && c != 'e' && c != 'E' && c != ':') {
            return false;
        }
    }
    return commas == 1 && digits > 0;
}
}  // namespace

RecordReader::RecordReader(std::string_view text, std::string source) : text_(text), source_(std::move(source)) {
    if (text_.substr(0, kUtf8Bom.size()) == kUtf8Bom) text_.remove_prefix(kUtf8Bom.size());
    separator_ = header_separator(text_);
}

std::string separator_note(std::string_view source, char separator) {
    if (separator == ',') return {};
    return std::string(source) + ": " + (separator == ';' ? "semicolon" : "tab") +
           "-separated (a decimal-comma locale's export): read so, numbers with a decimal comma as well";
}

std::string_view RecordReader::trim(std::string_view s) const {
    while (!s.empty() && is_blank(s.front())) s.remove_prefix(1);
    while (!s.empty() && is_blank(s.back())) s.remove_suffix(1);
    return s;
}

std::string_view RecordReader::decimal_point(std::string_view cell) {
    if (separator_ == ',' || !has_decimal_comma(cell)) return cell;
    std::string& owned = unescaped_.emplace_back(cell);
    std::replace(owned.begin(), owned.end(), ',', '.');
    return owned;
}

bool RecordReader::next(std::vector<std::string_view>& fields) {
    const std::size_t n = text_.size();
    const char* const data = text_.data();
    for (;;) {
        fields.clear();
        unescaped_.clear();
        if (pos_ >= n) return false;
        line_ = next_line_;
        const std::size_t record_begin = pos_;
        for (;;) {  // one cell per pass
            while (pos_ < n && is_blank(data[pos_])) ++pos_;
            if (pos_ < n && data[pos_] == '"') {
                ++pos_;
                const std::size_t begin = pos_;
                bool has_escapes = false;
                for (;;) {
                    if (pos_ >= n) fail("a quoted cell is never closed (missing '\"')");
                    const char c = data[pos_];
                    if (c == '"') {
                        if (pos_ + 1 < n && data[pos_ + 1] == '"') {
                            has_escapes = true;
                            pos_ += 2;
                            continue;
                        }
                        break;
                    }
                    // Line breaks inside quotes still count as lines, so later line numbers stay right.
                    if (c == '\n' || (c == '\r' && !(pos_ + 1 < n && data[pos_ + 1] == '\n'))) ++next_line_;
                    ++pos_;
                }
                std::string_view cell = text_.substr(begin, pos_ - begin);
                ++pos_;  // closing quote
                if (has_escapes) {
                    std::string& owned = unescaped_.emplace_back();
                    owned.reserve(cell.size());
                    for (std::size_t i = 0; i < cell.size(); ++i) {
                        owned.push_back(cell[i]);
                        if (cell[i] == '"') ++i;  // "" -> "
                    }
                    cell = owned;
                }
                while (pos_ < n && is_blank(data[pos_])) ++pos_;
                if (pos_ < n && data[pos_] != separator_ && data[pos_] != '\n' && data[pos_] != '\r')
                    fail("unexpected text after a closing quote (expected " +
                         (separator_ == '\t' ? std::string("a tab") : "'" + std::string(1, separator_) + "'") +
                         " or the end of the line)");
                fields.push_back(decimal_point(cell));
            } else {
                const std::size_t begin = pos_;
                while (pos_ < n && data[pos_] != separator_ && data[pos_] != '\n' && data[pos_] != '\r') ++pos_;
                fields.push_back(decimal_point(trim(text_.substr(begin, pos_ - begin))));
            }
            if (pos_ < n && data[pos_] == separator_) {
                ++pos_;
                continue;
            }
            // End of the record: consume its line end.
            if (pos_ < n) {  // here data[pos_] is '\r' or '\n'
                if (data[pos_] == '\r' && pos_ + 1 < n && data[pos_ + 1] == '\n') ++pos_;
                ++pos_;
                ++next_line_;
            }
            break;
        }
        if (pos_ - record_begin > kMaxRecordBytes)
            fail("a line of " + std::to_string(pos_ - record_begin) + " bytes (the limit is " +
                 std::to_string(kMaxRecordBytes) + "): not a CSV recording, or binary data");
        if (fields.size() == 1 && fields.front().empty()) continue;  // blank line
        return true;
    }
}

bool RecordReader::ends_mid_line() const {
    return !text_.empty() && text_.back() != '\n' && text_.back() != '\r';
}

void RecordReader::fail(std::string_view what) const {
    throw InputError(source_ + ":" + std::to_string(line_) + ": " + std::string(what));
}

void RecordReader::fail_column(std::string_view column, std::string_view what) const {
    fail("column \"" + std::string(column) + "\": " + std::string(what));
}

void RecordReader::check_width(const std::vector<std::string_view>& fields, std::size_t header_width) const {
    if (fields.size() == header_width) return;
    const bool extras_empty =
        fields.size() > header_width &&
        std::all_of(fields.begin() + static_cast<std::ptrdiff_t>(header_width), fields.end(),
                    [](std::string_view f) { return f.empty(); });
    if (extras_empty) return;
    fail("expected " + std::to_string(header_width) + " cells as in the header, got " + std::to_string(fields.size()));
}

namespace {
// Clinger's fast path for the common cell, [-]digits[.digits] with at most 15 significant digits and no
// exponent: the mantissa (< 10^15 < 2^53) and the power of ten (<= 10^15) are exact doubles, so one IEEE
// division gives the correctly rounded value -- what from_chars gives, bit for bit. Anything else: false.
bool parse_simple_decimal(std::string_view cell, double& value) noexcept {
    static constexpr double kPow10[16] = {1e0, 1e1, 1e2,  1e3,  1e4,  1e5,  1e6,  1e7,
                                          1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15};
    const char* p = cell.data();
    const char* const end = p + cell.size();
    const bool negative = p != end && *p == '-';
    if (negative) ++p;
    std::uint64_t mantissa = 0;
    int digits = 0, decimals = 0;
    bool dot = false;
    for (; p != end; ++p) {
        const char c = *p;
        if (c >= '0' && c <= '9') {
            if (++digits > 15) return false;
            mantissa = mantissa * 10 + static_cast<std::uint64_t>(c - '0');
            decimals += dot ? 1 : 0;
        } else if (c == '.' && !dot) {
            dot = true;
        } else {
            return false;
        }
    }
    if (digits == 0) return false;
    double x = static_cast<double>(mantissa);
    if (decimals > 0) x /= kPow10[decimals];
    value = negative ? -x : x;
    return true;
}
}  // namespace

NumberStatus parse_double(std::string_view cell, double& value) noexcept {
    if (cell.empty()) return NumberStatus::empty;
    // from_chars rejects a leading '+', which spreadsheets sometimes write.
    if (cell.front() == '+' && cell.size() > 1 && cell[1] != '-' && cell[1] != '+') cell.remove_prefix(1);
    if (parse_simple_decimal(cell, value)) return NumberStatus::ok;
    const char* const end = cell.data() + cell.size();
    const auto [ptr, ec] = std::from_chars(cell.data(), end, value);
    if (ec == std::errc::result_out_of_range) return NumberStatus::out_of_range;
    if (ec != std::errc{} || ptr != end) return NumberStatus::invalid;
    return NumberStatus::ok;
}

double read_number(const RecordReader& reader, std::string_view cell, std::string_view column, bool required) {
    double v = kNaN;
    switch (parse_double(cell, v)) {
        case NumberStatus::ok:
            if (std::isinf(v)) reader.fail_column(column, "expected a finite number, got " + quote_cell(cell));
            if (std::isnan(v)) {
                if (required) reader.fail_column(column, "expected a number, got " + quote_cell(cell));
                return kNaN;  // canonical NaN whatever sign or payload was written
            }
            return v;
        case NumberStatus::empty:
            if (required) reader.fail_column(column, "expected a number, got an empty cell");
            return kNaN;
        case NumberStatus::out_of_range:
            reader.fail_column(column, "number out of range: " + quote_cell(cell));
        case NumberStatus::invalid:
            break;
    }
    reader.fail_column(column, "expected a number, got " + quote_cell(cell));
}

std::string normalize_column_name(std::string_view name) {
    std::string out;
    out.reserve(name.size());
    for (const char c : name) {
        if (c == ' ' || c == '\t' || c == '\r' || c == '\n') continue;
        out.push_back(c >= 'A' && c <= 'Z' ? static_cast<char>(c - 'A' + 'a') : c);
    }
    return out;
}

std::string format_number(double value) {
    std::array<char, 64> buf{};
    const auto [ptr, ec] = std::to_chars(buf.data(), buf.data() + buf.size(), value);
    return ec == std::errc{} ? std::string(buf.data(), ptr) : std::string("?");
}

std::string quote_cell(std::string_view cell) {
    constexpr std::size_t kMaxShown = 40;  // fuzzed or binary junk must not flood the message
    const bool shorten = cell.size() > kMaxShown;
    std::string out;
    out.reserve(kMaxShown + 5);
    out += '"';
    out.append(cell.substr(0, kMaxShown));
    if (shorten) out += "...";
    out += '"';
    return out;
}

std::string quote_cells(const std::vector<std::string_view>& cells) {
    std::string out;
    for (const auto& c : cells) {
        if (!out.empty()) out += ", ";
        out += quote_cell(c);
    }
    return out;
}

double read_physical(const RecordReader& reader, std::string_view cell, std::string_view column, PhysicalRange range,
                     std::string_view unit, UnitConversion to_si) {
    const double v = to_si.to_si(read_number(reader, cell, column, true));
    if (!range.contains(v))
        reader.fail_column(column, "impossible value " + quote_cell(cell) +
                                       (to_si.identity() ? "" : " (" + format_number(v) + " " + std::string(unit) + ")") +
                                       " (expected " + format_number(range.lo) + ".." + format_number(range.hi) + " " +
                                       std::string(unit) + ")");
    return v;
}

double DroppedValues::check(double v, PhysicalRange range, const RecordReader& reader, std::string_view column) {
    if (std::isnan(v) || range.contains(v)) return v;
    if (count++ == 0)
        first = std::to_string(reader.line()) + ": column \"" + std::string(column) + "\": " + format_number(v);
    return kNaN;
}

void TimeStepGuard::check(double time_s, const RecordReader& reader) {
    const std::size_t row = rows_++;
    if (time_s - latest_s_ > largest_step_s_ && std::isfinite(latest_s_)) {
        largest_step_s_ = time_s - latest_s_;
        largest_step_line_ = reader.line();
    }
    if (latest_s_ - time_s >= kMaxRepairableBackwardStepS) {
        const BackwardStep step{row, reader.line(), latest_s_, time_s};
        if (!defer_) throw InputError(error(step, reader.source()));
        backward_.push_back(step);
        latest_s_ = time_s;  // the rows after it are guarded against this stamp
        return;
    }
    latest_s_ = std::max(latest_s_, time_s);
}

std::string TimeStepGuard::error(const BackwardStep& step, const std::string& source) const {
    // The step itself rounded to 6 digits: 5 - 3.9 reads 1.1, not 1.0999999999999996.
    std::array<char, 64> buf{};
    const double back = step.from_s - step.to_s;
    const auto [ptr, ec] = std::to_chars(buf.data(), buf.data() + buf.size(), back, std::chars_format::general, 6);
    const std::string text = ec == std::errc{} ? std::string(buf.data(), ptr) : format_number(back);
    return source + ":" + std::to_string(step.line) + ": column \"" + column_ + "\": time steps back by " + text +
           " s (from " + format_number(step.from_s) + " s to " + format_number(step.to_s) +
           " s); only steps back of less than 1 s are repaired";
}

namespace {
// Median of the positive intervals between consecutive raw stamps; NaN when there is none.
double typical_interval_s(const std::vector<double>& t) {
    std::vector<double> steps;
    steps.reserve(t.size());
    for (std::size_t i = 1; i < t.size(); ++i)
        if (t[i] > t[i - 1]) steps.push_back(t[i] - t[i - 1]);
    if (steps.empty()) return kNaN;
    const auto mid = steps.begin() + static_cast<std::ptrdiff_t>(steps.size() / 2);
    std::nth_element(steps.begin(), mid, steps.end());
    return *mid;
}
}  // namespace

TimeGap find_time_gap(const std::vector<double>& time_s, const TimeStepGuard& guard) {
    TimeGap g;
    const double largest = guard.largest_step_s();
    if (!(largest > kMinGapS)) return g;  // the common case: no need for the median
    g.typical_interval_s = typical_interval_s(time_s);
    if (largest > kGapFactor * g.typical_interval_s) {
        g.gap_s = largest;
        g.line = guard.largest_step_line();
    }
    return g;
}

std::size_t repair_timestamps(std::vector<double>& t, const std::string& source, std::string_view column) {
    const std::size_t n = t.size();
    std::size_t i = 1;
    while (i < n && t[i] > t[i - 1]) ++i;  // the common case: nothing to repair
    if (i >= n) return 0;

    // A run reaching the end has no later stamp to spread towards; it continues at the typical interval,
    // which must be taken from the raw stamps before they are overwritten.
    double typical_s = kNaN;
    const double last_raw = t[n - 1];
    if (std::any_of(t.begin(), t.end() - 1, [last_raw](double v) { return !(v < last_raw); })) {
        typical_s = typical_interval_s(t);
        if (!(typical_s > 0.0))
            throw InputError(source + ": column \"" + std::string(column) + "\": time never advances (all " +
                             std::to_string(n) + " rows at " + format_number(t[0]) + " s)");
    }

    // Invariant: t[0, i) holds repaired, strictly increasing stamps; t[i, n) the raw ones.
    std::size_t repaired = 0;
    while (i < n) {
        if (t[i] > t[i - 1]) {
            ++i;
            continue;
        }
        const double anchor = t[i - 1];
        std::size_t end = i;
        while (end < n && !(t[end] > anchor)) ++end;
        const std::size_t run = end - i;
        const double step = end < n ? (t[end] - anchor) / static_cast<double>(run + 1) : typical_s;
        for (std::size_t k = 0; k < run; ++k) {
            double v = anchor + step * static_cast<double>(k + 1);
            // Rounding must never undo strict order (stamps huge relative to the interval).
            const double floor = std::nextafter(t[i + k - 1], std::numeric_limits<double>::infinity());
            if (!(v >= floor)) v = floor;
            if (!std::isfinite(v))
                throw InputError(source + ": column \"" + std::string(column) + "\": time out of range while repairing");
            t[i + k] = v;
        }
        repaired += run;
        i = end;
    }
    return repaired;
}

}  // namespace csv

namespace {

enum class Channel { time, voltage, current, unix_time, step_count, cycle_count, step_type, ambient, surface, t1, t2, heat_flux };

// A unit a column may be given in (matched ignoring case and whitespace) and its conversion to SI.
struct UnitName {
    std::string_view name;
    csv::UnitConversion to_si;
};
constexpr UnitName kSeconds[] = {{"s", {}}, {"ms", {1e-3, 0.0}}, {"min", {60.0, 0.0}}, {"h", {3600.0, 0.0}}};
constexpr UnitName kUnixSeconds[] = {{"s", {}}, {"ms", {1e-3, 0.0}}};
constexpr UnitName kVolts[] = {{"V", {}}, {"mV", {1e-3, 0.0}}};
constexpr UnitName kAmperes[] = {{"A", {}}, {"mA", {1e-3, 0.0}}};
constexpr UnitName kCelsius[] = {{"degC", {}}, {"\u00b0C", {}}, {"\u2103", {}}, {"celsius", {}}, {"K", {1.0, -273.15}}};
constexpr UnitName kWattsPerSquareMetre[] = {{"W/m^2", {}}, {"W/m2", {}}};
constexpr UnitName kCount[] = {{"1", {}}};

struct Label {
    std::string_view label;    // the BDF preferred label, written verbatim
    std::string_view mr_name;  // the BDF machine-readable name (empty: our extension has none)
    Channel channel;
    bool required;
    std::vector<double> Recording::*values;  // nullptr for the text channel (Step Type)
    std::span<const UnitName> units;         // the first is the label's own (SI)
};

// Header order when writing: as in the bench's own files (time, electrical, step info, temperatures, flux).
const std::array<Label, 12> kLabels{{
    {kBdfTestTime, "test_time_second", Channel::time, true, &Recording::time_s, kSeconds},
    {kBdfVoltage, "voltage_volt", Channel::voltage, true, &Recording::voltage_v, kVolts},
    {kBdfCurrent, "current_ampere", Channel::current, true, &Recording::current_a, kAmperes},
    {kBdfUnixTime, "unix_time_second", Channel::unix_time, false, &Recording::unix_time_s, kUnixSeconds},
    {kBdfStepCount, "step_count", Channel::step_count, false, &Recording::step_count, kCount},
    {kBdfCycleCount, "cycle_count", Channel::cycle_count, false, &Recording::cycle_count, kCount},
    {kBdfStepType, "step_type", Channel::step_type, false, nullptr, {}},
    {kBdfAmbientTemperature, "ambient_temperature_celsius", Channel::ambient, false, &Recording::ambient_c, kCelsius},
    {kBdfSurfaceTemperature, "surface_temperature_celsius", Channel::surface, false, &Recording::surface_c, kCelsius},
    {kBdfTemperatureT1, "temperature_t1_celsius", Channel::t1, false, &Recording::t1_c, kCelsius},
    {kBdfTemperatureT2, "temperature_t2_celsius", Channel::t2, false, &Recording::t2_c, kCelsius},
    {kBdfHeatFluxDensity, "", Channel::heat_flux, false, &Recording::heat_flux_w_per_m2, kWattsPerSquareMetre},
}};

struct UsedColumn {
    std::size_t index;  // position in the header
    const Label* label;
    csv::UnitConversion to_si;
};

// What a header cell names: a label, with the conversion of its unit; nullptr where it names nothing we read.
// Throws (through `reader`) where it names a quantity we read in a unit we do not know.
std::pair<const Label*, csv::UnitConversion> resolve_column(std::string_view cell, const csv::RecordReader& reader) {
    const std::string name = csv::normalize_column_name(cell);
    for (const Label& l : kLabels) {
        if (name == csv::normalize_column_name(l.label) || (!l.mr_name.empty() && name == l.mr_name))
            return {&l, {}};
    }
    // "Base / unit" with another unit of a quantity we read: the base before the first '/'.
    const auto slash = name.find('/');
    if (slash == std::string::npos) return {nullptr, {}};
    const std::string_view base = std::string_view(name).substr(0, slash);
    const std::string_view unit = std::string_view(name).substr(slash + 1);
    for (const Label& l : kLabels) {
        const std::string own = csv::normalize_column_name(l.label);
        if (own.substr(0, own.find('/')) != base || l.units.empty()) continue;
        for (const UnitName& u : l.units)
            if (csv::normalize_column_name(u.name) == unit) return {&l, u.to_si};
        std::string known;
        for (const UnitName& u : l.units) known += (known.empty() ? "" : ", ") + std::string(u.name);
        reader.fail("column " + csv::quote_cell(cell) + ": a unit of " + std::string(l.label.substr(0, l.label.find(" /"))) +
                    " this reader does not convert (it reads " + known + ")");
    }
    return {nullptr, {}};
}

// A test time that steps back by 1 s or more (a cycler that restarts its test clock, the "Time_Bug" of a
// published Neware export) while the Unix time beside it runs on: each run of rows after such a step keeps its own
// intervals and is shifted so that its first row follows the row before by the Unix time's interval. Returns how
// many steps were placed so; throws the guard's error where the Unix time cannot place one (missing, or stepping
// back too).
std::size_t place_rows_after_time_jumps_by_unix_time(Recording& rec, const csv::TimeStepGuard& guard,
                                                     const std::string& source) {
    const auto& steps = guard.backward_steps();
    for (const auto& step : steps) {
        const std::size_t k = step.row;
        const bool placeable = k > 0 && k < rec.size() && rec.unix_time_s.size() == rec.size() &&
                               std::isfinite(rec.unix_time_s[k]) && std::isfinite(rec.unix_time_s[k - 1]) &&
                               rec.unix_time_s[k] >= rec.unix_time_s[k - 1];
        if (!placeable)
            throw InputError(guard.error(step, source) + " (the Unix time beside it does not run on there, so it cannot "
                                                         "place the rows after it either)");
        const double shift = rec.time_s[k - 1] + (rec.unix_time_s[k] - rec.unix_time_s[k - 1]) - rec.time_s[k];
        for (std::size_t j = k; j < rec.size(); ++j) {
            rec.time_s[j] += shift;
            // A Unix time that leaps by centuries would place the rows where no test time can be (and where this
            // reader, given the file it writes, would refuse them).
            if (!csv::kTestTimeRangeS.contains(rec.time_s[j]))
                throw InputError(guard.error(step, source) + " (placed by the Unix time beside it, its rows would " +
                                 "reach a test time of " + csv::format_number(rec.time_s[j]) + " s: no test runs so long)");
        }
    }
    return steps.size();
}

bool is_step_index_name(std::string_view cell) {
    const std::string name = csv::normalize_column_name(cell);
    return name == csv::normalize_column_name("Step Index / 1") || name == "step_index" || name == "step_id";
}

// Step Count from a step index: 1 at the first row, one more at each row whose index differs from the row
// before (an empty cell continues the step). A step that repeats at once under the same index (a one-step loop)
// reads as one step.
std::vector<double> step_count_from_index(const std::vector<double>& index) {
    std::vector<double> count(index.size(), kNaN);
    double n = 1, last = kNaN;
    for (std::size_t k = 0; k < index.size(); ++k) {
        if (std::isfinite(index[k])) {
            if (std::isfinite(last) && index[k] != last) ++n;
            last = index[k];
        }
        count[k] = n;
    }
    return count;
}

// The pace beyond which a test time runs ahead of the Unix time beside it (over the whole recording).
constexpr double kAheadOfWallClock = 1.5;

// Test time against Unix time between the first and the last row with a Unix time: {test s, wall s}, or NaNs
// when there is no Unix time column or less than 60 s of it (too short to tell a pace).
std::pair<double, double> test_and_wall_spans_s(const Recording& rec) {
    if (rec.unix_time_s.size() != rec.time_s.size() || rec.time_s.size() < 2) return {kNaN, kNaN};
    std::size_t first = 0, last = rec.time_s.size() - 1;
    while (first < last && !std::isfinite(rec.unix_time_s[first])) ++first;
    while (last > first && !std::isfinite(rec.unix_time_s[last])) --last;
    const double wall_s = rec.unix_time_s[last] - rec.unix_time_s[first];
    if (!(wall_s >= 60.0)) return {kNaN, kNaN};
    return {rec.time_s[last] - rec.time_s[first], wall_s};
}

// A time column that advances faster than the wall clock beside it is in another unit than its label says
// (a published HPPC keeps milliseconds under "test_time_second"): its pulses would read 1000 times too long.
// Exactly 1000 times as fast (within 1 %) is read as milliseconds, and says so (returns 1000); any other rate
// ahead of the wall clock is an error. A test time may pause while the wall clock runs on (returns 1).
double check_time_against_unix_time(const Recording& rec, const std::string& source) {
    const auto [test_s, wall_s] = test_and_wall_spans_s(rec);
    if (!(test_s > kAheadOfWallClock * wall_s)) return 1.0;
    const double ratio = test_s / wall_s;
    if (std::abs(ratio / 1000.0 - 1.0) <= 0.01) return 1000.0;
    throw InputError(source + ": " + std::string(kBdfTestTime) + " advances " + csv::format_number(std::round(ratio)) +
                     " times as fast as " + std::string(kBdfUnixTime) + " (" + csv::format_number(test_s) + " s against " +
                     csv::format_number(wall_s) + " s between the first and the last row): is it in another unit than "
                     "seconds? Say so in its label (e.g. \"Test Time / ms\")");
}

}  // namespace

Recording parse_bdf_csv(std::string_view text, const std::string& source, BdfReadReport* report) {
    csv::RecordReader reader(text, source);
    std::vector<std::string_view> fields;
    fields.reserve(16);
    if (!reader.next(fields))
        throw InputError(source + ":1: empty file: expected a header row of BDF labels (\"" + std::string(kBdfTestTime) +
                         "\", \"" + std::string(kBdfVoltage) + "\", \"" + std::string(kBdfCurrent) + "\", ...)");

    Recording rec;
    rec.source = source;
    std::vector<std::string> ignored;
    std::vector<UsedColumn> used;
    std::array<std::size_t, kLabels.size()> column_of{};
    column_of.fill(SIZE_MAX);
    const std::size_t width = fields.size();
    // A step index (the schedule's step number: "Step Index / 1", machine names step_index and step_id) marks the
    // step boundaries where a file has no Step Count: a change of index is a new step.
    std::size_t step_index_column = SIZE_MAX;
    for (std::size_t c = 0; c < width; ++c) {
        if (is_step_index_name(fields[c])) {
            if (step_index_column == SIZE_MAX) step_index_column = c;
            continue;
        }
        const auto [label, to_si] = resolve_column(fields[c], reader);
        if (label == nullptr) {
            if (!(fields[c].empty() && c + 1 == width)) ignored.emplace_back(fields[c]);  // not a trailing comma
            continue;
        }
        const auto k = static_cast<std::size_t>(label - kLabels.data());
        if (column_of[k] != SIZE_MAX)
            reader.fail("column \"" + std::string(label->label) + "\" appears twice (columns " +
                        std::to_string(column_of[k] + 1) + " and " + std::to_string(c + 1) + ")");
        column_of[k] = c;
        used.push_back({c, label, to_si});
    }
    for (std::size_t k = 0; k < kLabels.size(); ++k)
        if (kLabels[k].required && column_of[k] == SIZE_MAX)
            reader.fail("missing required column \"" + std::string(kLabels[k].label) + "\" (the header has " +
                        csv::quote_cells(fields) + ")");

    // One line per row in the usual file: reserve once instead of growing 436k-row vectors repeatedly.
    const auto expected_rows = static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n')) + 1;
    for (const auto& u : used) {
        if (u.label->values != nullptr)
            (rec.*(u.label->values)).reserve(expected_rows);
        else
            rec.step_type.reserve(expected_rows);
    }

    auto reads = [&used](Channel channel) {
        return std::any_of(used.begin(), used.end(), [channel](const UsedColumn& u) { return u.label->channel == channel; });
    };
    const bool has_step_count = reads(Channel::step_count);
    const bool steps_from_index = step_index_column != SIZE_MAX && !has_step_count;
    const std::string step_index_name(steps_from_index ? fields[step_index_column] : std::string_view());  // as the file names it
    if (step_index_column != SIZE_MAX && has_step_count) ignored.emplace_back(fields[step_index_column]);
    std::vector<double> step_index;
    if (steps_from_index) step_index.reserve(expected_rows);

    csv::TimeStepGuard guard{std::string(kBdfTestTime)};
    if (reads(Channel::unix_time)) guard.defer_backward_steps();
    csv::DroppedValues dropped;
    while (reader.next(fields)) {
        reader.check_width(fields, width);
        if (steps_from_index) step_index.push_back(csv::read_number(reader, fields[step_index_column], step_index_name, false));
        for (const auto& u : used) {
            const std::string_view cell = fields[u.index];
            if (u.label->values == nullptr) {
                rec.step_type.emplace_back(cell);
                continue;
            }
            const std::string_view column = u.label->label;
            double v = kNaN;
            switch (u.label->channel) {
                case Channel::time:
                    v = csv::read_physical(reader, cell, column, csv::kTestTimeRangeS, "s", u.to_si);
                    guard.check(v, reader);
                    break;
                case Channel::voltage:
                    v = csv::read_physical(reader, cell, column, csv::kVoltageRangeV, "V", u.to_si);
                    break;
                case Channel::current:
                    v = csv::read_physical(reader, cell, column, csv::kCurrentRangeA, "A", u.to_si);
                    break;
                default: {
                    v = u.to_si.to_si(csv::read_number(reader, cell, column, false));
                    const auto range = u.label->channel == Channel::heat_flux   ? csv::kHeatFluxRangeWPerM2
                                       : u.label->channel == Channel::unix_time ? csv::kUnixTimeRangeS
                                       : (u.label->channel == Channel::step_count ||
                                          u.label->channel == Channel::cycle_count)
                                           ? csv::kCountRange
                                           : csv::kTemperatureRangeC;
                    v = dropped.check(v, range, reader, column);
                }
            }
            (rec.*(u.label->values)).push_back(v);
        }
    }
    if (rec.time_s.empty()) throw InputError(source + ":1: header only: expected data rows after the header");
    if (steps_from_index) rec.step_count = step_count_from_index(step_index);
    const std::size_t time_jumps = place_rows_after_time_jumps_by_unix_time(rec, guard, source);

    const double time_divisor = check_time_against_unix_time(rec, source);
    if (time_divisor != 1.0) {
        for (double& t : rec.time_s) t /= time_divisor;
        guard.rescale(time_divisor);
    }
    rec.repaired_timestamps = csv::repair_timestamps(rec.time_s, source, kBdfTestTime);
    // Repeated stamps at the end continue at the recording's typical interval. Where that interval is no pace of
    // the logger (a file of a few rows around a gap), the repaired test time could run ahead of the Unix time
    // beside it: a recording this reader, given the file it writes from it, would refuse (found by the fuzzer).
    if (rec.repaired_timestamps > 0) {
        const auto [test_s, wall_s] = test_and_wall_spans_s(rec);
        if (test_s > kAheadOfWallClock * wall_s)
            throw InputError(source + ": column \"" + std::string(kBdfTestTime) + "\": " +
                             std::to_string(rec.repaired_timestamps) +
                             " repeated or backward stamps cannot be repaired in step with the Unix time beside them "
                             "(spread at the recording's typical interval, the test time would advance " +
                             csv::format_number(std::round(test_s / wall_s)) + " times as fast): check the time columns");
    }
    if (report != nullptr) {
        report->separator = reader.separator();
        report->rows = rec.size();
        report->repaired_timestamps = rec.repaired_timestamps;
        report->ignored_columns = std::move(ignored);
        report->dropped_values = dropped.count;
        report->first_dropped = std::move(dropped.first);
        const auto gap = csv::find_time_gap(rec.time_s, guard);
        report->gap_s = gap.gap_s;
        report->gap_line = gap.line;
        report->typical_interval_s = gap.typical_interval_s;
        report->ends_mid_line = reader.ends_mid_line();
        report->time_read_as_ms = time_divisor == 1000.0;
        report->steps_counted_from_index = steps_from_index;
        report->time_jumps_placed_by_unix_time = time_jumps;
        if (time_jumps > 0) {
            const auto& first = guard.backward_steps().front();
            report->first_time_jump = "line " + std::to_string(first.line) + ": from " + csv::format_number(first.from_s) +
                                      " s to " + csv::format_number(first.to_s) + " s";
        }
    }
    return rec;
}

std::vector<BdfReadMessage> describe(const BdfReadReport& report, const std::string& source) {
    std::vector<BdfReadMessage> out;
    if (report.separator != ',') out.push_back({false, csv::separator_note(source, report.separator)});
    if (report.time_read_as_ms)
        out.push_back({true, source + ": the test time runs 1000 times as fast as the Unix time beside it: read as "
                                      "milliseconds (label it \"Test Time / ms\" to say so)"});
    if (report.time_jumps_placed_by_unix_time > 0)
        out.push_back({true, source + ": the test time steps back " +
                                 (report.time_jumps_placed_by_unix_time == 1
                                      ? "once (at " + report.first_time_jump + "): the rows after the step are"
                                      : std::to_string(report.time_jumps_placed_by_unix_time) + " times (first at " +
                                            report.first_time_jump + "): the rows after each step are") +
                                 " placed by the Unix time beside them"});
    if (report.steps_counted_from_index)
        out.push_back({false, source + ": no Step Count column: the steps are counted from the step index (a new "
                                       "step wherever it changes)"});
    if (report.repaired_timestamps > 0)
        out.push_back({true, source + ": repaired " + std::to_string(report.repaired_timestamps) +
                                 " repeated or slightly backward timestamps"});
    if (report.dropped_values > 0)
        out.push_back({true, source + ": " + std::to_string(report.dropped_values) +
                                 " physically impossible values in optional columns read as empty cells (first at line " +
                                 report.first_dropped + ")"});
    if (report.gap_s > 0) {
        std::array<char, 160> buf{};
        std::snprintf(buf.data(), buf.size(), "time jumps forward by %.6g s (typical step %.3g s)", report.gap_s,
                      report.typical_interval_s);
        out.push_back({true, source + ":" + std::to_string(report.gap_line) + ": GAP in the recording: " + buf.data() +
                                 "; the rows after it are used as recorded"});
    }
    if (report.ends_mid_line)
        out.push_back({true, source + ": the file ends mid-line (no line end after the last row): was it cut short?"});
    return out;
}

// Writer: decimal places kept per column, chosen from the unit of its label (finer than any instrument of the
// bench resolves: 0.1 ms, 1 uV, 1 uA, 0.1 mK, 1 mW/m^2), so a value computed by arithmetic (0.1 + 0.2) is written
// as what was measured (0.3), not with its float noise (0.30000000000000004). -1: written as is.
namespace {

int writer_decimals(std::string_view label) {
    const auto slash = label.rfind(" / ");
    if (slash == std::string_view::npos) return -1;
    const std::string_view unit = label.substr(slash + 3);
    if (unit == "s") return 4;
    if (unit == "V" || unit == "A" || unit == "V/K") return 6;
    if (unit == "degC" || unit == "K") return 4;
    if (unit == "W/m^2" || unit == "W") return 3;
    if (unit == "Ah" || unit == "Wh") return 7;
    if (unit == "1") return 6;
    return -1;
}

// Appends v with 15 significant digits, the shortest form that keeps them ("-0" is written "0"). Every digit an
// instrument or an export carries survives (a 0.1 ms Unix time needs 14), while the binary noise of arithmetic in
// the 16th-17th digit (0.1 + 0.2 = 0.30000000000000004) goes; so does a magnitude below 1e-12 (no bench quantity
// is resolved that finely in SI units).
void append_number(std::string& buf, double v, int /*decimals*/) {
    if (std::abs(v) < 1e-12) v = 0.0;  // -0, and arithmetic residue far below any instrument's resolution
    std::array<char, 64> num{};
    const auto [ptr, ec] = std::to_chars(num.data(), num.data() + num.size(), v, std::chars_format::general, 15);
    if (ec == std::errc{}) buf.append(num.data(), static_cast<std::size_t>(ptr - num.data()));
}

}  // namespace

void write_bdf_csv(std::ostream& out, const Recording& rec, const std::vector<ExtraColumn>& extra) {
    const std::size_t n = rec.size();
    std::vector<const Label*> present;
    for (const auto& l : kLabels) {
        const std::size_t len = l.values != nullptr ? (rec.*(l.values)).size() : rec.step_type.size();
        if (!l.required && len == 0) continue;
        if (len != n)
            throw std::invalid_argument("write_bdf_csv: channel \"" + std::string(l.label) + "\" has " +
                                        std::to_string(len) + " values for " + std::to_string(n) + " rows");
        present.push_back(&l);
    }
    for (const auto& e : extra)
        if (e.values == nullptr || e.values->size() != n)
            throw std::invalid_argument("write_bdf_csv: extra column \"" + e.label + "\" has " +
                                        std::to_string(e.values ? e.values->size() : 0) + " values for " +
                                        std::to_string(n) + " rows");

    std::string buf;
    buf.reserve(1 << 16);
    auto append_text = [&buf](std::string_view s) {
        const bool needs_quotes =
            !s.empty() && (s.find_first_of(",\"\r\n") != std::string_view::npos || s.front() == ' ' ||
                           s.front() == '\t' || s.back() == ' ' || s.back() == '\t');
        if (!needs_quotes) {
            buf.append(s);
            return;
        }
        buf.push_back('"');
        for (const char c : s) {
            if (c == '"') buf.push_back('"');
            buf.push_back(c);
        }
        buf.push_back('"');
    };

    for (std::size_t k = 0; k < present.size(); ++k) {
        if (k > 0) buf.push_back(',');
        append_text(present[k]->label);
    }
    for (const auto& e : extra) {
        buf.push_back(',');
        append_text(e.label);
    }
    buf.push_back('\n');

    std::vector<int> decimals, extra_decimals;
    for (const Label* l : present) decimals.push_back(writer_decimals(l->label));
    for (const auto& e : extra) extra_decimals.push_back(writer_decimals(e.label));
    for (std::size_t row = 0; row < n; ++row) {
        for (std::size_t k = 0; k < present.size(); ++k) {
            if (k > 0) buf.push_back(',');
            const Label& l = *present[k];
            if (l.values == nullptr) {
                append_text(rec.step_type[row]);
                continue;
            }
            const double v = (rec.*(l.values))[row];
            if (std::isnan(v)) continue;  // empty cell
            append_number(buf, v, decimals[k]);
        }
        for (std::size_t k = 0; k < extra.size(); ++k) {
            buf.push_back(',');
            const double v = (*extra[k].values)[row];
            if (std::isnan(v)) continue;
            append_number(buf, v, extra_decimals[k]);
        }
        buf.push_back('\n');
        if (buf.size() > (1 << 16) - 1024) {
            out.write(buf.data(), static_cast<std::streamsize>(buf.size()));
            buf.clear();
        }
    }
    out.write(buf.data(), static_cast<std::streamsize>(buf.size()));
}

}  // namespace cellbench::protocol
