#include <algorithm>
#include <cmath>
#include <cstdio>

#include <spdlog/spdlog.h>

#include "cellbench/estimator/align.hpp"
#include "cellbench/estimator/merge.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cellbench/protocol/dewesoft_export.hpp"
#include "cellbench/protocol/heat_flux.hpp"
#include "cellbench/protocol/neware_export.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

namespace {

// Nominal P45B values used only to weigh DAQ heat against cycler current when aligning clocks.
constexpr double kAlignThermalCapacityJPerK = 63.3;
constexpr double kCellAreaM2 = 5.311e-3;

// Adds the DAQ's channels to the cycler recording, on the cycler's clock.
void add_daq_channels(Recording& rec, const protocol::DewesoftExport& daq, double sensitivity, double max_offset_s) {
    // Heat flux from the raw thermopile voltage with the Type-T sensitivity correction (thesis eq. 2.2), the
    // same function the DEWE-43A driver uses. Fall back to the export's own column if there is no raw voltage.
    std::vector<double> q = daq.heat_flux_w_per_m2;
    if (!daq.thermopile_v.empty() && !daq.type_t_c.empty()) {
        q.resize(daq.thermopile_v.size());
        double sum_rel = 0, max_rel = 0;
        std::size_t n_rel = 0;
        for (std::size_t k = 0; k < q.size(); ++k) {
            q[k] = protocol::heat_flux_density_w_per_m2(daq.thermopile_v[k], daq.type_t_c[k], sensitivity);
            if (k < daq.heat_flux_w_per_m2.size() && std::abs(daq.heat_flux_w_per_m2[k]) > 5.0) {
                const double rel = std::abs(q[k] / daq.heat_flux_w_per_m2[k] - 1.0);
                sum_rel += rel;
                max_rel = std::max(max_rel, rel);
                ++n_rel;
            }
        }
        if (n_rel > 0)
            spdlog::info("heat flux recomputed from thermopile voltage (S = {:.4g} V/(W/m^2), Type-T corrected): "
                         "vs the export's own column mean |rel diff| {:.4f} %, max {:.4f} % (|q| > 5 W/m^2)",
                         sensitivity, 100 * sum_rel / n_rel, 100 * max_rel);
    } else {
        spdlog::warn("{}: no raw thermopile voltage; using the export's heat flux column as is", daq.source);
    }
    if (daq.type_t_c.empty()) throw InputError(daq.source + ": no sensor temperature column (Type-T)");

    estimator::ClockAlignment al;
    try {
        al = estimator::estimate_clock_offset(rec.time_s, rec.current_a, daq.time_s, daq.type_t_c, q,
                                              kAlignThermalCapacityJPerK, kCellAreaM2, max_offset_s);
    } catch (const InputError& e) {
        throw InputError(daq.source + ": " + e.what());  // the message names the file it is about
    }
    if (!al.note.empty()) spdlog::info("alignment: {}", al.note);
    estimator::check_clock_alignment(al, daq.source);  // weak or far-off evidence: refused with the numbers
    std::printf("clock offset applied to %s: %+.1f s (DAQ time + offset = cycler time; correlation %.3f)\n",
                daq.source.c_str(), al.offset_s, al.correlation);

    std::vector<double> daq_time(daq.time_s.size());
    for (std::size_t k = 0; k < daq_time.size(); ++k) daq_time[k] = daq.time_s[k] + al.offset_s;
    rec.surface_c = estimator::resample_linear(daq_time, daq.type_t_c, rec.time_s);
    rec.heat_flux_w_per_m2 = estimator::resample_linear(daq_time, q, rec.time_s);
    if (!daq.t1_c.empty()) rec.t1_c = estimator::resample_linear(daq_time, daq.t1_c, rec.time_s);
    if (!daq.t2_c.empty()) rec.t2_c = estimator::resample_linear(daq_time, daq.t2_c, rec.time_s);
    std::size_t covered = 0;
    for (double v : rec.surface_c) covered += std::isfinite(v);
    if (covered < rec.size())
        spdlog::warn("DAQ covers {} of {} cycler rows; the others have empty thermal cells", covered, rec.size());
}

// A cycler export's date column ("Unix Time / s") has whole seconds while its test time resolves the 0.1 s
// samples: the date of each row is then the test time plus a clock offset, truncated to the second. The offset
// is pinned between the rows where the date ticks over (floor(offset + t) = date for every row), so each row
// gets its date to the test time's resolution, in line with the test time. Pieces where the two clocks jump
// apart (a pause the test time does not count) get their own offset. Returns the rows refined.
std::size_t refine_unix_time(Recording& rec) {
    const std::size_t n = rec.unix_time_s.size();
    if (n < 2 || rec.time_s.size() != n) return 0;
    bool whole_seconds = true, finer_time = false;
    for (std::size_t i = 0; i < n; ++i) {
        if (std::isfinite(rec.unix_time_s[i]) && rec.unix_time_s[i] != std::floor(rec.unix_time_s[i])) whole_seconds = false;
        if (rec.time_s[i] != std::floor(rec.time_s[i])) finer_time = true;
    }
    if (!whole_seconds || !finer_time) return 0;
    std::size_t refined = 0;
    for (std::size_t begin = 0; begin < n;) {
        // One piece: (date - time) stays within 1 s of its first value.
        std::size_t end = begin;
        double first = NAN;
        double lo = -INFINITY, hi = INFINITY, sum = 0.0;
        std::size_t count = 0;
        for (; end < n; ++end) {
            const double d = rec.unix_time_s[end], t = rec.time_s[end];
            if (!std::isfinite(d)) continue;
            if (std::isnan(first)) first = d - t;
            if (std::abs((d - t) - first) > 1.5) break;
            lo = std::max(lo, d - t);
            hi = std::min(hi, d + 1.0 - t);
            sum += d - t;
            ++count;
        }
        if (count > 0) {
            const double offset = lo < hi ? 0.5 * (lo + hi) : sum / static_cast<double>(count) + 0.5;
            for (std::size_t i = begin; i < end; ++i)
                if (std::isfinite(rec.unix_time_s[i])) rec.unix_time_s[i] = rec.time_s[i] + offset, ++refined;
        }
        begin = std::max(end, begin + 1);
    }
    return refined;
}

// The CLI's own check of a cycler export as read (the Neware reader checks its cells too; this holds whatever
// reader produced the rows): a text cut mid-line, and time, voltage or current outside what a bench can measure.
void check_cycler_export(const std::string& text, const Recording& rec, const std::string& source) {
    if (!text.empty() && text.back() != '\n' && text.back() != '\r')
        throw InputError(source + ": the export ends mid-line (no line end after the last row): the file was cut "
                                  "short; export it again");
    const auto check = [&](const std::vector<double>& v, protocol::csv::PhysicalRange range, const char* what,
                           const char* unit) {
        for (std::size_t k = 0; k < v.size(); ++k)
            if (!range.contains(v[k]))
                throw InputError(source + ": data row " + std::to_string(k + 1) + ": impossible " + what + " " +
                                 protocol::csv::format_number(v[k]) + " " + unit + " (expected " +
                                 protocol::csv::format_number(range.lo) + ".." + protocol::csv::format_number(range.hi) +
                                 " " + unit + ")");
    };
    check(rec.time_s, protocol::csv::kTestTimeRangeS, "time", "s");
    check(rec.voltage_v, protocol::csv::kVoltageRangeV, "voltage", "V");
    check(rec.current_a, protocol::csv::kCurrentRangeA, "current", "A");
}

// An export whose cells are separated by ';' or a tab (a decimal-comma locale) is read as its program meant it.
void log_separator(const std::string& path, char separator) {
    if (separator != ',') spdlog::info("{}", protocol::csv::separator_note(path, separator));
}

}  // namespace

int run_import(const ImportOptions& o) {
    if (o.neware.empty() && o.bdf.empty())
        throw InputError("import: give a cycler recording (--neware and/or --bdf); --dewesoft alone has no current");
    OutputFiles outputs({o.output});  // the folder is checked before the work
    Recording rec;
    if (!o.neware.empty()) {
        protocol::NewareExportInfo layout;
        const std::string text = read_file(o.neware);
        rec = protocol::parse_neware_export(text, o.neware, &layout);
        spdlog::info("{}: {} (column \"{}\")", o.neware, protocol::to_string(layout.layout), layout.time_column);
        log_separator(o.neware, layout.separator);
        check_cycler_export(text, rec, o.neware);
    }
    if (rec.repaired_timestamps > 0)
        spdlog::warn("{}: repaired {} repeated or slightly backward timestamps", o.neware, rec.repaired_timestamps);
    if (const auto refined = refine_unix_time(rec); refined > 0)
        spdlog::info("{}: Unix Time of {} rows set from the test time (the export's dates have whole seconds)", o.neware,
                     refined);
    if (!o.bdf.empty()) {
        protocol::BdfReadReport report;
        Recording bdf = protocol::parse_bdf_csv(read_file(o.bdf), o.bdf, &report);
        warn_bdf_report(o.bdf, report);
        if (rec.empty()) {
            rec = std::move(bdf);
        } else {
            // One instrument, two exports: the BDF may start anywhere in the cycler's record, so search it all.
            const auto al = estimator::align_by_current(rec, bdf, INFINITY);
            std::printf("clock offset applied to %s: %+.2f s (%zu of %zu current steps matched, current RMS "
                        "mismatch %.3f A)\n",
                        o.bdf.c_str(), al.offset_s, al.matched_edges, al.edges_b, al.current_rms_a);
            rec = estimator::splice_recordings(rec, bdf, al.offset_s);
        }
    }
    if (!o.dewesoft.empty()) {
        const auto daq = protocol::parse_dewesoft_export(read_file(o.dewesoft), o.dewesoft);
        log_separator(o.dewesoft, daq.separator);
        if (daq.repaired_timestamps > 0)
            spdlog::warn("{}: repaired {} repeated or slightly backward timestamps", o.dewesoft, daq.repaired_timestamps);
        if (daq.dropped_values > 0)
            spdlog::warn("{}: {} physically impossible values read as empty cells (first at line {})", o.dewesoft,
                         daq.dropped_values, daq.first_dropped);
        // One clock offset is fitted for the whole DAQ record: across a gap (a stalled clock, two exports
        // pasted together) the rows after it would land wrong by the size of the gap. Refused, never repaired.
        if (daq.gap_s > 0)
            throw InputError(o.dewesoft + ":" + std::to_string(daq.gap_line) + ": GAP in the DAQ record: time jumps " +
                             "forward by " + protocol::csv::format_number(daq.gap_s) + " s (typical step " +
                             protocol::csv::format_number(daq.typical_interval_s) +
                             " s); one clock offset cannot align both sides of it: export the parts separately");
        add_daq_channels(rec, daq, o.sensitivity_v_per_w_per_m2, o.max_offset_s);
    }
    outputs.write(o.output, [&](std::ostream& out) { protocol::write_bdf_csv(out, rec); });
    outputs.commit();
    spdlog::info("wrote {} rows ({:.0f} s) to {}", rec.size(), rec.time_s.back() - rec.time_s.front(), o.output);
    return 0;
}

}  // namespace cellbench::cli
