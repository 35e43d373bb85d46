#pragma once
// Neware BTS record export (CSV as saved by BTSDA), e.g.
//   DataPoint,Step Type,Time,Total Time,Current(A),Voltage(V),Capacity(Ah),Energy(Wh),Date,Power(W),Time(s)
//
// Column names are matched ignoring case and whitespace; columns not listed here are ignored.
//  - time (required): "Time(s)" if present, else "Total Time", else "Cumulative Time", each as seconds or
//    h:mm:ss[.fff] (hours may exceed 24; "mm:ss" is accepted too); without any of them the wall clock
//    ("Realtime"/"Date", or NewareNDA's "Timestamp") relative to the first row. NewareNDA's CSV (columns
//    Index, Cycle, Step, Status, Time, Voltage, Current(mA), Charge_Capacity(mAh), ..., Timestamp) is told
//    apart by its capacity columns: its "Time" is the step time. Repeated stamps and steps back of less than 1 s are
//    repaired as for BDF (Recording::repaired_timestamps); a step back of 1 s or more is an error.
//  - "Current(A)" / "Current(mA)" (required, sign kept: + = charge, as in BDF),
//    "Voltage(V)" / "Voltage(mV)" (required).
//  - "Step Type" -> step_type.
//  - step_count: from a step id column ("Step ID", "Step Index", "Step No", "Step") if present; otherwise
//    1-based, incremented whenever "Step Type" changes or the step time ("Time" / "Step Time") falls back by
//    1 s or more while the type stays (two consecutive steps of the same type). Empty if neither exists.
//  - cycle_count: from "Cycle" / "Cycle ID" / "Cycle Index" if present.
//  - unix_time_s: from "Date" ("YYYY-MM-DD hh:mm:ss[.fff]", '/' also accepted, 'T' also accepted between
//    date and time), read as UTC: the export carries no zone, so a bench clock on local time gives stamps
//    offset by the zone. Values as exported (1 s resolution; not made monotonic).
// When several columns map to the same channel, the first one wins.
#include "cellbench/core/recording.hpp"

#include <string>
#include <string_view>

namespace cellbench::protocol {

// The layouts told apart (by their columns), and where the test time came from.
enum class NewareExportLayout {
    btsda_test_time,        // "Time(s)": seconds, or hh:mm:ss / h:mm:ss.fff in some BTSDA versions
    btsda_total_time,       // "Total Time" (h:mm:ss[.fff])
    btsda_cumulative_time,  // "Cumulative Time" (h:mm:ss[.fff])
    btsda_wall_clock,       // no test-time column: "Realtime"/"Date" minus the first row's
    newarenda,              // NewareNDA's CSV: "Time" is the STEP time; test time = "Timestamp" minus the first row's
};
std::string_view to_string(NewareExportLayout layout);  // for the log line of `import`
struct NewareExportInfo {
    NewareExportLayout layout = NewareExportLayout::btsda_test_time;
    std::string time_column;  // as in the header
    char separator = ',';     // ';' or a tab: a spreadsheet's export (csv::RecordReader)
};

// Every row's voltage and current must be finite and physically possible (|V| <= 10 V, |I| <= 10 kA):
// anything else is an InputError naming the line and column.
Recording parse_neware_export(std::string_view text, const std::string& source, NewareExportInfo* info = nullptr);

}  // namespace cellbench::protocol
