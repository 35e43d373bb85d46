#pragma once
// A recording of one cell on one clock: the columnar form of a Battery Data Format (BDF) CSV.
//
// Conventions (binding, see INTERFACES.md):
//  - SI units, names carry the unit; temperatures in degC as recorded.
//  - Current is positive when it CHARGES the cell (BDF / Neware convention).
//  - Optional channels are either empty (the recording does not measure them) or have one value per row,
//    NaN where a row has no value (e.g. cycler rows before the DAQ started).
#include <cmath>
#include <limits>
#include <stdexcept>
#include <cstddef>
#include <string>
#include <vector>

namespace cellbench {

struct Recording {
    std::string source;  // file name or description, for messages

    // Required.
    std::vector<double> time_s;     // "Test Time / s", strictly increasing after repair
    std::vector<double> voltage_v;  // "Voltage / V"
    std::vector<double> current_a;  // "Current / A", + = charge

    // Optional (empty = not measured).
    std::vector<double> unix_time_s;         // "Unix Time / s"
    std::vector<double> step_count;          // "Step Count / 1"
    std::vector<double> cycle_count;         // "Cycle Count / 1"
    std::vector<std::string> step_type;      // "Step Type"
    std::vector<double> ambient_c;           // "Ambient Temperature / degC" (chamber)
    std::vector<double> surface_c;           // "Surface Temperature / degC" (Type-T in the heat flux sensor)
    std::vector<double> t1_c;                // "Temperature T1 / degC" (Type-K, positive terminal)
    std::vector<double> t2_c;                // "Temperature T2 / degC" (Type-K, negative terminal)
    std::vector<double> heat_flux_w_per_m2;  // "Heat Flux Density / W/m^2", + = leaving the cell

    // Rows whose timestamps were repaired on reading (repeated or slightly backward stamps).
    std::size_t repaired_timestamps = 0;

    [[nodiscard]] std::size_t size() const { return time_s.size(); }
    [[nodiscard]] bool empty() const { return time_s.empty(); }
    [[nodiscard]] bool has_surface() const { return has_values(surface_c); }
    [[nodiscard]] bool has_ambient() const { return has_values(ambient_c); }
    [[nodiscard]] bool has_heat_flux() const { return has_values(heat_flux_w_per_m2); }
    [[nodiscard]] bool has_step_type() const { return !step_type.empty(); }

    // True when the channel exists and holds at least one finite value.
    static bool has_values(const std::vector<double>& channel);

    // A copy of rows [begin, end).
    [[nodiscard]] Recording slice(std::size_t begin, std::size_t end) const;

    // Resizes every present optional channel to size(), filling with NaN / "" (used by builders).
    void pad_optional_channels();

    // A recording from another bench whose only cell temperature is a thermocouple in T1 (the usual single
    // surface thermocouple of a lab without a heat flux sensor): T1 becomes the surface temperature the model
    // reads. Returns whether it did (there was no surface temperature and T1 held values).
    bool take_t1_as_surface();
};

// Bad input (file, line or JSON path, and what was expected). Maps to exit status 1.
class InputError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
inline constexpr double kZeroCelsiusK = 273.15;

}  // namespace cellbench
