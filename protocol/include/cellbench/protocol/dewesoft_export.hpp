#pragma once
// DewesoftX CSV export of the heat flux bench channels, e.g.
//   Time,Thermal Flux Sensor Voltage (V),Temperature (C),Heat Flux Density (W/m^2),Heat Flux Test Area (W),...
//
// Columns are mapped by name (case and spacing ignored); the first column of each kind wins, the rest are
// ignored:
//  - time (required): "Time" / "Time (s)", seconds on the DAQ's own clock. Repeated stamps and steps back of
//    less than 1 s are repaired as for BDF; a step back of 1 s or more is an error.
//  - thermopile_v: a voltage of the flux sensor ("... Flux ... Voltage", "Thermopile ... Voltage"), scaled
//    from (mV) or (uV) when the name says so.
//  - heat_flux_w_per_m2: "Heat Flux Density ..." (DewesoftX's own conversion).
//  - t1_c / t2_c: Type-K thermocouples, recognised by a K1/K2, T1/T2 or TC1/TC2 word, "Type K" or
//    "Thermocouple" in the name (numbered by that digit, else in order of appearance).
//  - type_t_c: any other "Temperature" column (the Type-T inside the heat flux sensor), or one named "Type T".
// Required: time, and either the thermopile voltage with the Type-T temperature or the heat flux density.
// A channel the export lacks is an empty vector; present channels have one value per row, NaN for an empty
// cell. A time outside +-1e10 s is an error naming the line; so is a text that ends mid-line (an export cut
// short: DewesoftX ends every row with a line end), since a cut export silently shortens the record the clock
// alignment works on.
#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

namespace cellbench::protocol {

struct DewesoftExport {
    std::string source;
    std::vector<double> time_s, thermopile_v, type_t_c, heat_flux_w_per_m2;
    std::vector<double> t1_c, t2_c; /* empty if absent */
    std::size_t repaired_timestamps = 0;  // rows whose time stamp was repaired on reading
    // Values outside what the quantity can physically be (csv::PhysicalRange: temperatures -100..300 degC,
    // heat flux +-1e6 W/m^2, thermopile +-10 V), read as empty cells: how many, and the first one.
    std::size_t dropped_values = 0;
    std::string first_dropped;
    // The largest forward step of the time column when it is a gap (csv::find_time_gap), else 0.
    double gap_s = 0.0;
    std::size_t gap_line = 0;
    double typical_interval_s = 0.0;
    char separator = ',';  // ';' or a tab: an export in a decimal-comma locale (csv::RecordReader)
};

DewesoftExport parse_dewesoft_export(std::string_view text, const std::string& source);

}  // namespace cellbench::protocol
