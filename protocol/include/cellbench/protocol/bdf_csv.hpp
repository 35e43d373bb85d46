#pragma once
// Battery Data Format (BDF 1.x) CSV recordings, and the CSV dialect shared by every recording parser in
// protocol/ (BDF, Neware BTS export, DewesoftX export).
//
// Pure: text in, Recording out; no file I/O, no clocks. Bad input throws cellbench::InputError whose message
// reads "SOURCE:LINE: what was expected", lines 1-based with the header as line 1.
#include "cellbench/core/recording.hpp"

#include <cstddef>
#include <deque>
#include <iosfwd>
#include <limits>
#include <string>
#include <string_view>
#include <vector>

namespace cellbench::protocol {

// BDF labels (INTERFACES.md). Reading matches them ignoring case and whitespace; writing uses them verbatim.
inline constexpr std::string_view kBdfTestTime = "Test Time / s";
inline constexpr std::string_view kBdfVoltage = "Voltage / V";
inline constexpr std::string_view kBdfCurrent = "Current / A";
inline constexpr std::string_view kBdfUnixTime = "Unix Time / s";
inline constexpr std::string_view kBdfStepCount = "Step Count / 1";
inline constexpr std::string_view kBdfCycleCount = "Cycle Count / 1";
inline constexpr std::string_view kBdfStepType = "Step Type";
inline constexpr std::string_view kBdfAmbientTemperature = "Ambient Temperature / degC";
inline constexpr std::string_view kBdfSurfaceTemperature = "Surface Temperature / degC";
inline constexpr std::string_view kBdfTemperatureT1 = "Temperature T1 / degC";
inline constexpr std::string_view kBdfTemperatureT2 = "Temperature T2 / degC";
inline constexpr std::string_view kBdfHeatFluxDensity = "Heat Flux Density / W/m^2";

struct BdfReadReport {
    std::size_t rows = 0;
    std::size_t repaired_timestamps = 0;
    std::vector<std::string> ignored_columns;  // header names of columns that are not BDF labels we use
    // Values of optional columns outside what the quantity can physically be (see csv::physical_range),
    // read as empty cells: how many, and the first one ("LINE: column "NAME": VALUE").
    std::size_t dropped_values = 0;
    std::string first_dropped;
    // The largest forward step of the time column when it is a gap (csv::TimeGap), else gap_s = 0.
    double gap_s = 0.0;
    std::size_t gap_line = 0;
    double typical_interval_s = 0.0;
    bool ends_mid_line = false;  // the text does not end with a line end (a file cut short?)
    // The time column advanced 1000 times as fast as the Unix time beside it (within 1 %) and was read as ms.
    bool time_read_as_ms = false;
    // No Step Count column: the steps were counted from a step index column ("Step Index / 1", step_index,
    // step_id), a new step wherever the index changes.
    bool steps_counted_from_index = false;
    // The test time stepped back by 1 s or more this many times while the Unix time ran on: the rows after each
    // such step were shifted to follow the row before by the Unix time's interval. first_time_jump: "line L: from
    // X s to Y s".
    std::size_t time_jumps_placed_by_unix_time = 0;
    std::string first_time_jump;
    // The cells are separated by ';' or a tab, not ',' (csv::RecordReader: numbers with a decimal comma read too).
    char separator = ',';
};

// Parses a BDF CSV. Columns in any order; unknown columns are ignored (listed in the report). A column is known by
// its BDF preferred label ("Current / A"), by the label with another unit of the same quantity ("Current / mA",
// "Test Time / ms", "Voltage / mV", "Surface Temperature / K": converted to SI on reading; a unit it does not
// know is an error naming the units it does), or by its BDF machine-readable name ("current_ampere", the
// normative form of the Battery Data Alliance's reference files). A time column that advances faster than the
// Unix time column beside it is read as ms where it runs exactly 1000 times as fast (within 1 %: a test time in ms
// under a seconds name; BdfReadReport::time_read_as_ms) and is an error at any other rate. Tolerates a
// UTF-8 BOM, CRLF or LF line ends, blank lines, whitespace around cells and RFC 4180 quoted cells.
// Empty cells are NaN in optional numeric columns and errors in required ones. Timestamps that repeat or
// step back by less than 1 s are repaired (see csv::repair_timestamps); a step back of 1 s or more is an error.
// Physically impossible values (csv::physical_range) are an error naming the line in the required columns
// (time, voltage, current) and read as empty cells, counted in the report, in the optional ones. A forward
// gap in the time column is reported (gap_s), never repaired.
Recording parse_bdf_csv(std::string_view text, const std::string& source, BdfReadReport* report = nullptr);

// What a reader of the file should be told about how it was read, one line each, prefixed with `source` (and the
// line where it has one): `warning` when rows were changed or the file may be incomplete, else a note. The CLI and
// the daemon log these same words.
struct BdfReadMessage {
    bool warning = false;
    std::string text;
};
std::vector<BdfReadMessage> describe(const BdfReadReport& report, const std::string& source);

// Writes a header of the BDF labels for the channels present (required ones always), then one row per
// sample, LF line ends. Numbers are rounded to a resolution finer than any instrument's, chosen from the
// column's unit (s: 0.1 ms, V and A: 1 u, degC: 0.1 mK, W/m^2: 1 m; other units as they are) and written in
// their shortest round-trip form, so 0.1 + 0.2 is written "0.3" and reads back as 0.3; NaN is an empty cell. Throws std::invalid_argument if a present channel's length differs
// from the number of rows.
// extra: further numeric columns written after the BDF ones (e.g. simulated traces beside the measured ones),
// each with one value per row.
struct ExtraColumn {
    std::string label;
    const std::vector<double>* values = nullptr;
};
void write_bdf_csv(std::ostream& out, const Recording& rec, const std::vector<ExtraColumn>& extra = {});

// ---------------------------------------------------------------------------------------------------------
// The CSV dialect of the recording parsers, shared by bdf_csv, neware_export and dewesoft_export.
namespace csv {

// Reads CSV records one at a time from a text held by the caller: comma separated; LF, CRLF or lone CR
// line ends; a leading UTF-8 BOM is skipped; spaces and tabs around cells are trimmed; cells may be quoted
// ("" is a literal quote, quoted cells may span lines); lines holding nothing but whitespace are skipped.
// A header line with no comma outside quotes but a semicolon or a tab (what a spreadsheet or a DAQ program
// writes in a locale whose decimal mark is the comma) makes that character the separator, and then a
// numeric cell with one decimal comma ("3,7125", "-1,5e-3", a duration "00:00:01,500") reads as with a
// point: the file is read as its program meant it, not refused for its locale.
class RecordReader {
public:
    RecordReader(std::string_view text, std::string source);

    // The cell separator found in the header line: ',' (also for a one-column file), ';' or '\t'.
    [[nodiscard]] char separator() const { return separator_; }

    // Reads the next record into `fields`. Returns false at the end of the text. The views point into the
    // text (or into the reader for cells with "" escapes) and stay valid until the next call.
    bool next(std::vector<std::string_view>& fields);

    // 1-based line on which the record last returned by next() starts (the header is line 1).
    [[nodiscard]] std::size_t line() const { return line_; }
    [[nodiscard]] const std::string& source() const { return source_; }
    // Whether the text ends without a line end after its last record (a file cut mid-line).
    [[nodiscard]] bool ends_mid_line() const;

    // Throws InputError "SOURCE:LINE: what" for the current record.
    [[noreturn]] void fail(std::string_view what) const;
    // Throws InputError "SOURCE:LINE: column "NAME": what" for the current record.
    [[noreturn]] void fail_column(std::string_view column, std::string_view what) const;
    // Checks a data record against the header width: fewer cells is an error, extra cells must be empty
    // (a trailing separator).
    void check_width(const std::vector<std::string_view>& fields, std::size_t header_width) const;

private:
    std::string_view text_;
    std::size_t pos_ = 0;
    std::size_t line_ = 0;       // line of the current record
    std::size_t next_line_ = 1;  // line at pos_
    std::string source_;
    std::deque<std::string> unescaped_;  // owned copies of cells that contained "" or a decimal comma
    char separator_ = ',';

    bool is_blank(char c) const { return c == ' ' || (c == '\t' && separator_ != '\t'); }
    std::string_view trim(std::string_view s) const;
    // With a separator other than ',': a numeric cell with one decimal comma, as a copy with a point.
    std::string_view decimal_point(std::string_view cell);
};

// The note a reader's user gets for a file read with another separator than ',' ("SOURCE: semicolon-separated
// ..."), empty for ','.
std::string separator_note(std::string_view source, char separator);

enum class NumberStatus { ok, empty, invalid, out_of_range };

// Parses a whole cell as a decimal floating-point number (std::from_chars, plus an optional leading '+').
// "nan" and "inf" parse as such; the caller decides whether they are allowed.
NumberStatus parse_double(std::string_view cell, double& value) noexcept;

// Reads a numeric cell of `column`. Empty cells and NaN give NaN unless `required`; infinities, text and
// (when required) empty cells or NaN throw InputError naming the line and column.
double read_number(const RecordReader& reader, std::string_view cell, std::string_view column, bool required);

// Column name for tolerant matching: ASCII lower case, all whitespace removed ("Test Time / s" -> "testtime/s").
std::string normalize_column_name(std::string_view name);

// Shortest round-trip decimal form of a number, for messages and writing.
std::string format_number(double value);

// Cell text for a message: quoted, shortened if long.
std::string quote_cell(std::string_view cell);
// A header for a message: its cells quoted and comma separated.
std::string quote_cells(const std::vector<std::string_view>& cells);

// Guards the time column while rows are read: throws when a stamp lies 1 s or more before the latest stamp
// seen so far (smaller steps back are left for repair_timestamps).
class TimeStepGuard {
public:
    // A step back of 1 s or more, kept instead of thrown in deferred mode.
    struct BackwardStep {
        std::size_t row = 0;   // 0-based data row of the stamp that steps back
        std::size_t line = 0;  // its line in the file
        double from_s = 0.0, to_s = 0.0;
    };

    explicit TimeStepGuard(std::string column) : column_(std::move(column)) {}
    void check(double time_s, const RecordReader& reader);
    // Deferred mode (a reader with another clock to place the rows by): a step back of 1 s or more is recorded
    // and the stamps after it are guarded from there on; the reader decides afterwards (error() words it).
    void defer_backward_steps() { defer_ = true; }
    [[nodiscard]] const std::vector<BackwardStep>& backward_steps() const { return backward_; }
    [[nodiscard]] std::string error(const BackwardStep& step, const std::string& source) const;
    // The largest forward step seen and the line of the row after it.
    [[nodiscard]] double largest_step_s() const { return largest_step_s_; }
    [[nodiscard]] std::size_t largest_step_line() const { return largest_step_line_; }
    // The stamps seen were in units `divisor` times finer than seconds (a test time read as ms after the fact).
    void rescale(double divisor) {
        latest_s_ /= divisor;
        largest_step_s_ /= divisor;
    }

private:
    std::string column_;
    bool defer_ = false;
    std::size_t rows_ = 0;
    std::vector<BackwardStep> backward_;
    double latest_s_ = -std::numeric_limits<double>::infinity();
    double largest_step_s_ = 0.0;
    std::size_t largest_step_line_ = 0;
};

// Longest record (line, or lines of one quoted record) the readers accept: recordings have lines of about
// 100 bytes; binary junk or a file without line ends fails here instead of being held as one huge line.
inline constexpr std::size_t kMaxRecordBytes = 64 * 1024;

// What a measured quantity can physically be on this bench; outside is corrupt data, not a measurement.
struct PhysicalRange {
    double lo, hi;
    [[nodiscard]] bool contains(double v) const { return v >= lo && v <= hi; }
};
inline constexpr PhysicalRange kVoltageRangeV{-10.0, 10.0};
inline constexpr PhysicalRange kCurrentRangeA{-1e4, 1e4};
inline constexpr PhysicalRange kTemperatureRangeC{-100.0, 300.0};
inline constexpr PhysicalRange kHeatFluxRangeWPerM2{-1e6, 1e6};
inline constexpr PhysicalRange kTestTimeRangeS{-1e9, 1e10};      // ~300 years of test time
inline constexpr PhysicalRange kUnixTimeRangeS{0.0, 1e11};
inline constexpr PhysicalRange kCountRange{-1e9, 1e9};           // step and cycle counts

// A column's unit to the SI unit of its quantity: si = value * scale + offset ("Current / mA": 1e-3, 0).
struct UnitConversion {
    double scale = 1.0;
    double offset = 0.0;
    [[nodiscard]] double to_si(double v) const { return v * scale + offset; }
    [[nodiscard]] bool identity() const { return scale == 1.0 && offset == 0.0; }
};

// Reads a required numeric cell (read_number), converts it to SI (`to_si`) and checks it against `range`:
// outside is an error naming the line, the column and the value.
double read_physical(const RecordReader& reader, std::string_view cell, std::string_view column, PhysicalRange range,
                     std::string_view unit, UnitConversion to_si = {});

// Counts values of optional columns outside their physical range (they read as NaN).
struct DroppedValues {
    std::size_t count = 0;
    std::string first;  // "LINE: column "NAME": VALUE"
    // The value, or NaN (counted) when outside `range`.
    double check(double v, PhysicalRange range, const RecordReader& reader, std::string_view column);
};

// The largest forward step of a (repaired, increasing) time column, and whether it is a gap: longer than
// kGapFactor typical (median) intervals and than kMinGapS. Real recordings have such gaps (a logger that slows
// down in a long rest), so it is reported, not an error; but never repaired away.
struct TimeGap {
    double gap_s = 0.0;          // 0 when there is no gap
    std::size_t line = 0;        // line of the row after the gap
    double typical_interval_s = 0.0;
};
inline constexpr double kGapFactor = 1000.0;
inline constexpr double kMinGapS = 60.0;
class TimeStepGuard;
TimeGap find_time_gap(const std::vector<double>& time_s, const TimeStepGuard& guard);

// Backward steps of at least this much are errors rather than repairable artefacts.
inline constexpr double kMaxRepairableBackwardStepS = 1.0;

// Makes finite stamps strictly increasing without drift, changing only the rows that are not after the
// previous (repaired) stamp, and returns how many rows it changed:
//  - a run of such rows (repeated stamps, or a small step back and the rows that are still not past the
//    stamp before it) is spread evenly over the interval from the stamp before the run to the next stamp
//    that is later than it, so every stamp after the run keeps its recorded value;
//  - a run at the end of the recording, with no later stamp, continues at the recording's typical
//    (median positive) interval.
// Throws InputError naming `source` and `column` when there are two or more stamps and none is later than
// the first (time never advances).
std::size_t repair_timestamps(std::vector<double>& time_s, const std::string& source, std::string_view column);

}  // namespace csv
}  // namespace cellbench::protocol
