// The plant's own BDF CSV writer (INTERFACES.md "Recordings") and the truth JSON.
#include <charconv>
#include <fstream>
#include <stdexcept>
#include <string>

#include "cellbench/plant/plant.hpp"

namespace cellbench::plant {

namespace {
void append_number(std::string& out, double v) {
    char buf[32];
    const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);  // shortest round trip
    if (ec != std::errc{}) throw std::runtime_error("plant: number formatting failed");
    out.append(buf, end);
}
}  // namespace

void write_bdf_csv(const Recording& r, const std::filesystem::path& path) {
    std::string out;
    out.reserve(r.size() * 96 + 256);
    out += "Test Time / s,Unix Time / s,Voltage / V,Current / A,Step Count / 1,Step Type,"
           "Ambient Temperature / degC,Surface Temperature / degC,Heat Flux Density / W/m^2\n";
    for (std::size_t k = 0; k < r.size(); ++k) {
        append_number(out, r.time_s[k]);
        out += ',';
        append_number(out, std::round((r.unix_start_s + r.time_s[k]) * 1000.0) / 1000.0);
        out += ',';
        append_number(out, r.voltage_v[k]);
        out += ',';
        append_number(out, r.current_a[k]);
        out += ',';
        out += std::to_string(r.step_count[k]);
        out += ',';
        out += r.step_type[k];
        out += ',';
        append_number(out, r.ambient_c[k]);
        out += ',';
        append_number(out, r.surface_c[k]);
        out += ',';
        append_number(out, r.heat_flux_w_per_m2[k]);
        out += '\n';
    }
    std::ofstream f(path, std::ios::binary | std::ios::trunc);
    if (!f) throw std::runtime_error("plant: cannot write " + path.string());
    f.write(out.data(), static_cast<std::streamsize>(out.size()));
    if (!f) throw std::runtime_error("plant: write failed: " + path.string());
}

void write_truth_json(const Truth& truth, const std::filesystem::path& path) {
    std::ofstream f(path, std::ios::trunc);
    if (!f) throw std::runtime_error("plant: cannot write " + path.string());
    f << to_json(truth).dump(2) << '\n';
    if (!f) throw std::runtime_error("plant: write failed: " + path.string());
}

}  // namespace cellbench::plant
