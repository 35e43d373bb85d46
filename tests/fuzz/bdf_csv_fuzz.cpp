// libFuzzer target: the recording readers (BDF CSV, the Neware BTS record export and the DewesoftX export,
// all on the shared CSV dialect) must turn any text into a Recording or one InputError naming the source,
// never crash, hang or misbehave. A BDF recording that parses is written back and must read back the same
// (finite numbers bit-exactly, missing values as missing, step types unchanged).
// Mode: the first byte (0 BDF, 1 Neware export, 2 DewesoftX export); the rest is the file text.
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <sstream>
#include <string>
#include <string_view>
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/dewesoft_export.hpp"
#include "cellbench/protocol/neware_export.hpp"

using namespace cellbench;
using namespace cellbench::protocol;

namespace {

void check(bool condition) {
    if (!condition) __builtin_trap();
}

bool same(const std::vector<double>& a, const std::vector<double>& b) {
    if (a.size() != b.size()) return false;
    for (std::size_t i = 0; i < a.size(); ++i) {
        if (std::isnan(a[i]) && std::isnan(b[i])) continue;
        // The writer keeps 15 significant digits and writes magnitudes below 1e-12 as 0 (bdf_csv.cpp).
        const double tol = std::max(1e-12, 1e-14 * std::abs(a[i]));
        if (!(std::abs(a[i] - b[i]) <= tol)) return false;
    }
    return true;
}

// Channels present have one value per row; time is finite and strictly increasing after repair.
void check_recording(const Recording& r) {
    const std::size_t n = r.size();
    check(r.voltage_v.size() == n && r.current_a.size() == n);
    for (const auto* c : {&r.unix_time_s, &r.step_count, &r.cycle_count, &r.ambient_c, &r.surface_c, &r.t1_c, &r.t2_c,
                          &r.heat_flux_w_per_m2})
        check(c->empty() || c->size() == n);
    check(r.step_type.empty() || r.step_type.size() == n);
    for (std::size_t i = 0; i < n; ++i) {
        check(std::isfinite(r.time_s[i]));
        if (i > 0) check(r.time_s[i] > r.time_s[i - 1]);
    }
    check(r.repaired_timestamps <= n);
}

void error_names_source(const InputError& e, const std::string& source) {
    check(std::string_view(e.what()).starts_with(source));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0) return 0;
    const unsigned mode = data[0] % 3;
    const std::string_view text(reinterpret_cast<const char*>(data) + 1, size - 1);
    const std::string source = "fuzz.csv";
    try {
        if (mode == 0) {
            BdfReadReport report;
            const Recording rec = parse_bdf_csv(text, source, &report);
            check_recording(rec);
            check(report.rows == rec.size());
            std::ostringstream out;
            write_bdf_csv(out, rec);
            Recording back;
            try {
                back = parse_bdf_csv(out.str(), "written.csv");
            } catch (const InputError&) {
                check(false);  // what we write, we must read
            }
            check(back.size() == rec.size());
            check(same(back.time_s, rec.time_s) && same(back.voltage_v, rec.voltage_v) &&
                  same(back.current_a, rec.current_a));
            check(same(back.unix_time_s, rec.unix_time_s) && same(back.step_count, rec.step_count) &&
                  same(back.cycle_count, rec.cycle_count) && same(back.ambient_c, rec.ambient_c) &&
                  same(back.surface_c, rec.surface_c) && same(back.t1_c, rec.t1_c) && same(back.t2_c, rec.t2_c) &&
                  same(back.heat_flux_w_per_m2, rec.heat_flux_w_per_m2));
            check(back.step_type == rec.step_type);
        } else if (mode == 1) {
            check_recording(parse_neware_export(text, source));
        } else {
            const DewesoftExport d = parse_dewesoft_export(text, source);
            const std::size_t n = d.time_s.size();
            for (const auto* c : {&d.thermopile_v, &d.type_t_c, &d.heat_flux_w_per_m2, &d.t1_c, &d.t2_c})
                check(c->empty() || c->size() == n);
            for (std::size_t i = 1; i < n; ++i) check(d.time_s[i] > d.time_s[i - 1]);
        }
    } catch (const InputError& e) {
        error_names_source(e, source);
    }
    return 0;
}
