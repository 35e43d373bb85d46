// The run store's export: one run as a Recording on the cycler's time base (the BDF export and the fit
// replay read it), with the DAQ and chamber channels interpolated onto it where the instruments were not silent.
#include "run_store_impl.hpp"

#include <cmath>

namespace cellbench::daemon {

using namespace store;

namespace {

// Linear interpolation of (t, y) at ascending query times; NaN outside [t.front(), t.back()] and where the
// two bracketing samples are more than max_gap_s apart (the instrument was silent: do not invent data).
std::vector<double> interpolate_with_gaps(const std::vector<double>& t, const std::vector<double>& y,
                                          const std::vector<double>& q, double max_gap_s) {
    std::vector<double> out(q.size(), kNaN);
    if (t.empty()) return out;
    std::size_t j = 0;
    for (std::size_t k = 0; k < q.size(); ++k) {
        const double x = q[k];
        if (!(x >= t.front()) || !(x <= t.back())) continue;
        while (j + 1 < t.size() && t[j + 1] <= x) ++j;
        if (t[j] == x) {
            out[k] = y[j];
            continue;
        }
        if (j + 1 >= t.size()) continue;
        const double dt = t[j + 1] - t[j];
        if (!(dt > 0.0) || dt > max_gap_s) continue;
        const double w = (x - t[j]) / dt;
        out[k] = y[j] + w * (y[j + 1] - y[j]);
    }
    return out;
}

}  // namespace

Recording RunStore::export_recording(RunId run, std::optional<double> from_s, std::optional<double> to_s,
                                     double max_gap_s) const {
    auto lease = impl_->acquire();
    StmtCache& db = lease.stmts();
    return guarded_read(impl_->path, [&] {
        ReadTxn txn(db);
        Recording rec;
        rec.source = impl_->path.filename().string() + " run " + std::to_string(run);
        // (Infinite bounds would bind as NULL; use finite sentinels.)
        const double lo = from_s && std::isfinite(*from_s) ? *from_s : -1e300;
        const double hi = to_s && std::isfinite(*to_s) ? *to_s : 1e300;

        Stmt c(db,
               "SELECT t_s, unix_s, voltage_v, current_a, step_id, cycle, step_type FROM cycler_samples "
               "WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s");
        c.integer(1, run).real(2, lo).real(3, hi);
        bool any_type = false;
        while (c.step()) {
            rec.time_s.push_back(c.col_real(0));
            rec.unix_time_s.push_back(c.col_real(1));
            rec.voltage_v.push_back(c.col_real(2));
            rec.current_a.push_back(c.col_real(3));
            rec.step_count.push_back(c.is_null(4) ? kNaN : static_cast<double>(c.col_int(4)));
            rec.cycle_count.push_back(c.is_null(5) ? kNaN : static_cast<double>(c.col_int(5)));
            rec.step_type.push_back(c.col_text(6));
            any_type = any_type || !rec.step_type.back().empty();
        }
        if (!any_type) rec.step_type.clear();
        if (rec.empty()) {
            rec.unix_time_s.clear();
            rec.step_count.clear();
            rec.cycle_count.clear();
            return rec;
        }

        // DAQ / chamber rows around the cycler's span (a margin so the edge rows can interpolate).
        const double a = rec.time_s.front() - max_gap_s;
        const double b = rec.time_s.back() + max_gap_s;
        auto read_source = [&](const char* sql, std::size_t channels, std::vector<double>& t,
                               std::vector<std::vector<double>>& ys) {
            Stmt s(db, sql);
            s.integer(1, run).real(2, a).real(3, b);
            ys.assign(channels, {});
            while (s.step()) {
                t.push_back(s.col_real(0));
                for (std::size_t k = 0; k < channels; ++k) ys[k].push_back(s.col_real(static_cast<int>(k + 1)));
            }
        };
        std::vector<double> td;
        std::vector<std::vector<double>> yd;
        read_source("SELECT t_s, surface_c, t1_c, t2_c, heat_flux_w_per_m2 FROM daq_samples "
                    "WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s",
                    4, td, yd);
        if (!td.empty()) {
            rec.surface_c = interpolate_with_gaps(td, yd[0], rec.time_s, max_gap_s);
            rec.t1_c = interpolate_with_gaps(td, yd[1], rec.time_s, max_gap_s);
            rec.t2_c = interpolate_with_gaps(td, yd[2], rec.time_s, max_gap_s);
            rec.heat_flux_w_per_m2 = interpolate_with_gaps(td, yd[3], rec.time_s, max_gap_s);
            // A channel the layout does not carry (all NULL) is "not measured", not a column of NaN.
            for (auto* ch : {&rec.surface_c, &rec.t1_c, &rec.t2_c, &rec.heat_flux_w_per_m2})
                if (!Recording::has_values(*ch)) ch->clear();
        }
        std::vector<double> tc;
        std::vector<std::vector<double>> yc;
        read_source("SELECT t_s, ambient_c FROM chamber_samples WHERE run_id = ?1 AND t_s >= ?2 AND t_s <= ?3 ORDER BY t_s",
                    1, tc, yc);
        if (!tc.empty()) {
            rec.ambient_c = interpolate_with_gaps(tc, yc[0], rec.time_s, max_gap_s);
            if (!Recording::has_values(rec.ambient_c)) rec.ambient_c.clear();
        }
        return rec;
    });
}

}  // namespace cellbench::daemon
