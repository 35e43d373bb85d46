#include "cellbench/estimator/thermal_characterization.hpp"

#include <algorithm>
#include <cmath>

#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/estimator/model.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "cellbench/estimator/thermal_fit.hpp"
#include "golden.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {

bool has_thermal(const Recording& r) { return r.has_surface() && r.has_heat_flux(); }

nlohmann::json num(double x) { return std::isfinite(x) ? nlohmann::json(x) : nlohmann::json(nullptr); }

// Surface temperature RMS of the first-order thermal model driven by the MEASURED heat generation
// I*(V - OCV(SOC)) + I*T*dU/dT, for a given R_th (C_th and dU/dT held). Using the measured voltage keeps the
// thermal identification independent of the electrical model's errors. Exact ZOH per interval.
struct ThermalFitData {
    std::vector<double> dt_s, heat_irr_w, current_a, ehc_v_per_k, surface_c;
    std::vector<bool> segment_start;  // first row of each recording
    std::vector<double> ambient_c;    // per row
};

double measured_heat_temperature_rms(const ThermalFitData& d, double c_th, double r_th,
                                     std::vector<double>* residuals = nullptr) {
    double sum = 0, weight = 0, t = kNaN;
    if (residuals) residuals->clear();
    for (std::size_t k = 0; k < d.dt_s.size(); ++k) {
        if (d.segment_start[k] || !std::isfinite(t)) {
            t = d.surface_c[k];
            continue;
        }
        // C dT/dt = Qirr + I*EHC*(T + 273.15) - (T - Ta)/Rth  ->  dT/dt = -beta*T + c
        const double i = d.current_a[k], ehc = d.ehc_v_per_k[k];
        const double beta = (1.0 / r_th - i * ehc) / c_th;
        const double c = (d.heat_irr_w[k] + i * ehc * kZeroCelsiusK + d.ambient_c[k] / r_th) / c_th;
        const double e = std::exp(-beta * d.dt_s[k]);
        t = t * e + c / beta * (1.0 - e);
        if (std::isfinite(d.surface_c[k])) {
            const double err = t - d.surface_c[k];
            sum += err * err * d.dt_s[k];
            weight += d.dt_s[k];
            if (residuals) residuals->push_back(err);
        }
    }
    return weight > 0 ? std::sqrt(sum / weight) : kNaN;
}

// Rows merged into intervals of at least kThermalStepS (means of current and heat over each interval): the
// thermal time constant is minutes, so 1 s intervals lose nothing and make the R_th search 10x cheaper.
constexpr double kThermalStepS = 1.0;

ThermalFitData measured_heat_data(const std::vector<const Recording*>& recs, const ParameterSet& p,
                                  const std::vector<std::vector<double>>& soc_of_rec, bool ambient_from_start = false) {
    ThermalFitData d;
    for (std::size_t r = 0; r < recs.size(); ++r) {
        const auto& rec = *recs[r];
        const auto& soc = soc_of_rec[r];
        double ambient = kNaN;
        for (double v : rec.surface_c)
            if (std::isfinite(v)) { ambient = v; break; }
        bool started = false;
        double span = 0, charge = 0, heat = 0;
        for (std::size_t k = 0; k < rec.size(); ++k) {
            // Rows before the DAQ started carry no temperature: begin at the first measured one.
            if (!started) {
                if (!std::isfinite(rec.surface_c[k])) continue;
                started = true;
                d.segment_start.push_back(true);
                d.dt_s.push_back(0.0);
                d.current_a.push_back(0.0);
                d.heat_irr_w.push_back(0.0);
                d.ehc_v_per_k.push_back(0.0);
                d.surface_c.push_back(rec.surface_c[k]);
                d.ambient_c.push_back(ambient);
                continue;
            }
            const double dt = rec.time_s[k] - rec.time_s[k - 1];
            const double i = rec.current_a[k];
            span += dt;
            charge += i * dt;
            heat += i * (rec.voltage_v[k] - p.ocv_at(soc[k])) * dt;
            if (span < kThermalStepS && k + 1 < rec.size()) continue;
            d.segment_start.push_back(false);
            d.dt_s.push_back(span);
            d.current_a.push_back(charge / span);
            d.heat_irr_w.push_back(heat / span);
            d.ehc_v_per_k.push_back(p.ehc_at(soc[k]));
            d.surface_c.push_back(rec.surface_c[k]);
            d.ambient_c.push_back(!ambient_from_start && rec.has_ambient() && std::isfinite(rec.ambient_c[k]) ? rec.ambient_c[k] : ambient);
            span = charge = heat = 0;
        }
    }
    return d;
}

// The search range of R_th: a coin cell in still air to a large prismatic cell on a cold plate (an 18650 in a
// chamber has 3-15 K/W, a 60 Ah pouch about 0.4-1; a search floored at 0.5 K/W held the independent plant's
// 60 Ah pouch, seed 5, at 0.500 against its 0.407).
constexpr double kRThSearchMinKPerW = 0.01, kRThSearchMaxKPerW = 200.0;

// Whether a golden-section search on [lo, hi] ended at one of its ends: the data did not hold the value there.
bool at_search_bound(double x, double lo, double hi) { return x < 1.02 * lo || x > 0.98 * hi; }

// Golden-section search of a unimodal function of log(x) on [lo, hi].
template <typename F>
double golden_minimum(F f, double lo, double hi, int iterations) {
    return std::exp(golden_section([&](double u) { return f(std::exp(u)); }, std::log(lo), std::log(hi), iterations));
}

// Standard deviation of a scalar x fitted by minimizing the RMS f(x) of n residuals: var = 2 f^2 / (n_eff d2(f^2)/dx2),
// n_eff = n (1 - rho) / (1 + rho) for residuals with lag-1 autocorrelation rho (a temperature residual is
// strongly autocorrelated: n_eff is then a handful of independent stretches, not the rows).
template <typename F>
double curvature_sd(F rms, double x, const std::vector<double>& residuals) {
    const std::size_t n = residuals.size();
    if (n < 3 || !(x > 0)) return kNaN;
    double num = 0, den = 0;
    for (std::size_t i = 0; i < n; ++i) {
        den += residuals[i] * residuals[i];
        if (i) num += residuals[i] * residuals[i - 1];
    }
    const double rho = den > 0 ? std::clamp(num / den, 0.0, 0.9999) : 0.0;
    const double n_eff = std::max(1.0, static_cast<double>(n) * (1 - rho) / (1 + rho));
    const double h = 0.02 * x;
    const double f0 = rms(x), fp = rms(x + h), fm = rms(x - h);
    const double d2 = (fp * fp - 2 * f0 * f0 + fm * fm) / (h * h);
    if (!(d2 > 0)) return kNaN;  // flat: not identified
    return std::sqrt(2 * f0 * f0 / (n_eff * d2));
}

void add_flag(std::vector<std::string>& flags, const std::string& f) {
    if (std::find(flags.begin(), flags.end(), f) == flags.end()) flags.push_back(f);
}

// Plausibility of the thermal values (any Li-ion cell from coin to large prismatic): about 1 kJ/(kg K) at 150-250
// Wh/kg and ~3.6 V gives 15-25 J/K per Ah; a value outside 4-80 J/K per Ah, or R_th outside 0.02-100 K/W, is
// implausible (a 280 Ah prismatic cell in forced air has 0.1-0.3 K/W); an uncertainty above the value itself is
// "uncertain". (A searched value at its search range's end is flagged "at_bound" where it is searched.)
void flag_thermal(ThermalCharacterization& t, double capacity_ah) {
    const double per_ah = t.c_th_j_per_k / capacity_ah;
    if (std::isfinite(t.c_th_j_per_k) && !(per_ah >= 4.0 && per_ah <= 80.0)) add_flag(t.c_th_flags, "implausible");
    if (!std::isfinite(t.c_th_sigma_j_per_k) || t.c_th_sigma_j_per_k > t.c_th_j_per_k) add_flag(t.c_th_flags, "uncertain");
    if (std::isfinite(t.r_th_k_per_w) && !(t.r_th_k_per_w >= 0.02 && t.r_th_k_per_w <= 100.0))
        add_flag(t.r_th_flags, "implausible");
    if (!std::isfinite(t.r_th_sigma_k_per_w) || t.r_th_sigma_k_per_w > t.r_th_k_per_w) add_flag(t.r_th_flags, "uncertain");
    t.details["c_th_j_per_k_sd"] = num(t.c_th_sigma_j_per_k);
    t.details["r_th_k_per_w_sd"] = num(t.r_th_sigma_k_per_w);
    nlohmann::json flags = nlohmann::json::object();
    if (!t.c_th_flags.empty()) flags["c_th_j_per_k"] = t.c_th_flags;
    if (!t.r_th_flags.empty()) flags["r_th_k_per_w"] = t.r_th_flags;
    if (!flags.empty()) t.details["flags"] = flags;
}

}  // namespace

ThermalCharacterization fit_thermal_parameters(const std::vector<Recording>& recordings,
                                               const std::vector<RecordingSegments>& segments,
                                               const std::vector<std::vector<double>>& soc_of_row,
                                               const ParameterSet& electrical, const CharacterizationOptions& options) {
    // SOC of every row: given, or from the state the recording implies, then Coulomb counting.
    std::vector<std::vector<double>> socs(recordings.size());
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        const auto& rec = recordings[r];
        if (r < soc_of_row.size() && soc_of_row[r].size() == rec.size()) {
            socs[r] = soc_of_row[r];
            continue;
        }
        const double guess = electrical.soc_from_ocv(rec.voltage_v[0]);
        const double ohmic =
            ohmic_drop_v(electrical.rc_at(guess, -1), electrical.rc_at(guess, +1), rec.current_a[0]);
        const double soc0 = electrical.soc_from_ocv(rec.voltage_v[0] - ohmic);
        // The charge segment_recording counted (a caller's hand-made segments may lack it).
        const auto q = segments[r].charge_ah.size() == rec.size() ? segments[r].charge_ah : cumulative_charge_ah(rec);
        socs[r].resize(rec.size());
        for (std::size_t k = 0; k < rec.size(); ++k) socs[r][k] = soc0 + q[k] / electrical.capacity_ah;
    }
    ThermalCharacterization out;
    const double area = options.area_m2;

    // C_th from the energy balance of the long rests of every recording with heat flux (eq. 4.7 integrated).
    ThermalCapacityFit best_cth;
    std::string cth_source;
    {
        std::vector<ThermalRests> sets;
        for (std::size_t r = 0; r < recordings.size(); ++r) {
            if (!has_thermal(recordings[r]) || segments[r].long_rests.empty()) continue;
            ThermalRests set{&recordings[r], {}};
            for (const auto& lr : segments[r].long_rests) set.rests.push_back({lr.begin, lr.end});
            sets.push_back(std::move(set));
            cth_source += (cth_source.empty() ? "" : " + ") + recordings[r].source;
        }
        if (!sets.empty()) best_cth = fit_thermal_capacity(sets, area);
    }
    if (!std::isfinite(best_cth.c_th_j_per_k) && options.fallback_c_th_j_per_k <= 0) {
        // No heat flux sensor: C_th and R_th together from the surface temperature alone, the first-order model
        // driven by the measured heat generation (the ambient from its column, else the first reading).
        std::vector<const Recording*> recs;
        std::vector<std::vector<double>> rec_socs;
        // Recordings that heat the cell by more than 2 K carry the information (all of them if none does); the
        // ambient is each recording's first (rested) reading: a surface sensor's offset against the chamber's
        // own sensor would otherwise pass for heat.
        for (int pass = 0; pass < 2 && recs.empty(); ++pass)
            for (std::size_t r = 0; r < recordings.size(); ++r) {
                const auto& rec = recordings[r];
                if (!rec.has_surface()) continue;
                double first = kNaN, hi = -1e300;
                for (double v : rec.surface_c)
                    if (std::isfinite(v)) {
                        if (!std::isfinite(first)) first = v;
                        hi = std::max(hi, v);
                    }
                if (pass == 0 && hi - first < 2.0) continue;
                recs.push_back(&rec), rec_socs.push_back(socs[r]);
            }
        if (recs.empty()) return out;
        const auto data = measured_heat_data(recs, electrical, rec_socs, true);
        double best_r = kNaN;
        auto rms_at = [&](double c) {
            best_r = golden_minimum([&](double r) { return measured_heat_temperature_rms(data, c, r); },
                                   kRThSearchMinKPerW, kRThSearchMaxKPerW, 30);
            return measured_heat_temperature_rms(data, c, best_r);
        };
        // Weakly heated recordings cannot separate C_th from R_th: C_th is held within what a Li-ion cell of this
        // capacity can have (about 1 kJ/(kg K) at 150-250 Wh/kg and ~3.6 V: 15-25 J/K per Ah; bounds x0.4..x2).
        const double cap = electrical.capacity_ah;
        const double c_lo = 6.0 * cap, c_hi = 50.0 * cap;
        const double c_th = golden_minimum(rms_at, c_lo, c_hi, 30);
        const double rms = rms_at(c_th);
        out.c_th_j_per_k = c_th;
        out.r_th_k_per_w = best_r;
        // Uncertainties: C_th from the profile (R_th re-fitted at each C_th), R_th at the C_th found, and the
        // C_th uncertainty carried into R_th along the profile.
        {
            const double r_at = best_r;  // rms_at re-fits best_r at every C_th it is asked
            std::vector<double> res;
            measured_heat_temperature_rms(data, c_th, r_at, &res);
            out.c_th_sigma_j_per_k = curvature_sd(rms_at, c_th, res);
            const double r_stat =
                curvature_sd([&](double r) { return measured_heat_temperature_rms(data, c_th, r); }, r_at, res);
            double r_prop = 0;
            if (std::isfinite(out.c_th_sigma_j_per_k)) {
                const double dc = std::min(out.c_th_sigma_j_per_k, 0.5 * c_th);
                rms_at(c_th + dc);
                const double r_hi = best_r;
                rms_at(std::max(c_th - dc, 1e-3));
                r_prop = 0.5 * std::abs(r_hi - best_r);
            }
            out.r_th_k_per_w = best_r = r_at;
            out.r_th_sigma_k_per_w = std::sqrt(r_stat * r_stat + r_prop * r_prop);
            // At a bound of the C_th search: the temperature alone does not hold it.
            if (at_search_bound(c_th, c_lo, c_hi)) {
                add_flag(out.c_th_flags, "at_bound");
                add_flag(out.c_th_flags, "uncertain");
            }
            if (at_search_bound(out.r_th_k_per_w, kRThSearchMinKPerW, kRThSearchMaxKPerW))
                add_flag(out.r_th_flags, "at_bound");
        }
        // A heat flux sensor whose rests hold no energy balance (best_cth's note says why) is not "no sensor".
        const bool flux_measured = std::any_of(recordings.begin(), recordings.end(), [](const Recording& r) { return has_thermal(r); });
        const std::string why = flux_measured ? "heat flux measured, but no rest holds its energy balance (" + best_cth.note + ")"
                                              : "no heat flux measured";
        out.r_th_method = std::string("fitted with C_th from the surface temperature alone (") +
                          (flux_measured ? "the heat flux gave no C_th" : "no heat flux sensor") +
                          "): the first-order model driven by the measured heat I*(V - OCV) reproduces it";
        out.details["temperature_only_fit"] = {{"c_th_j_per_k", c_th}, {"r_th_k_per_w", best_r},
                                               {"temperature_rms_c", num(rms)}};
        out.notes.push_back(why + ": C_th and R_th identified together from the surface temperature (temperature RMS " +
                            printf_text("%.3f", rms) + " degC); dU/dT left out. Their uncertainties are those of a "
                            "one-node model: where the core heats faster than the surface shows (a fast discharge), "
                            "C_th reads high (the P45B's 4C discharge: about twice what its heat flux sensor measures), "
                            "and the reversible heat left out moves it by a few %");
        flag_thermal(out, cap);
        return out;
    }
    const bool c_th_from_heat_flux = std::isfinite(best_cth.c_th_j_per_k);
    if (!c_th_from_heat_flux) {
        best_cth.c_th_j_per_k = options.fallback_c_th_j_per_k;
        out.notes.push_back("thermal capacity not measured (no rests with temperature and heat flux): fallback used");
    }
    out.c_th_j_per_k = best_cth.c_th_j_per_k;
    out.c_th_sigma_j_per_k = best_cth.c_th_se_j_per_k;
    out.c_th_r_squared = best_cth.r_squared;
    out.details["c_th"] = {{"method", "rest cooling: energy balance C_th * (T(a) - T(b)) = integral of Q_out over chunks of the rests (eq. 4.7 integrated), robust zero-intercept regression"},
                           {"source", cth_source},
                           {"c_th_j_per_k", num(best_cth.c_th_j_per_k)},
                           {"se_j_per_k", num(best_cth.c_th_se_j_per_k)},
                           {"r_squared", num(best_cth.r_squared)},
                           {"points", best_cth.points},
                           {"rests_used", best_cth.rests_used},
                           {"skip_s", best_cth.skip_s},
                           {"note", best_cth.note}};

    // dU/dT from the longest CC discharge outside an HPPC (eqs. 4.4-4.6).
    const Recording* ehc_rec = nullptr;
    std::size_t ehc_index = 0;
    const Phase* ehc_phase = nullptr;
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        if (!has_thermal(recordings[r]) || !segments[r].pulse_sets.empty()) continue;
        for (const auto& ph : segments[r].cc_discharges)
            if (ph.duration_s > 300 && (!ehc_phase || ph.duration_s > ehc_phase->duration_s)) {
                ehc_phase = &ph;
                ehc_rec = &recordings[r];
                ehc_index = r;
            }
    }
    if (ehc_phase) {
        const auto& rec = *ehc_rec;
        const auto& soc = socs[ehc_index];
        std::vector<double> grid;
        for (int k = 0; k <= 20; ++k) grid.push_back(0.05 * k);
        const auto ehc = fit_entropic_coefficient(rec, {ehc_phase->begin, ehc_phase->end}, soc, electrical.soc,
                                                  electrical.ocv_v, out.c_th_j_per_k, area, grid);
        for (std::size_t k = 0; k < grid.size(); ++k)
            if (ehc.has_data[k]) {
                out.ehc_soc.push_back(grid[k]);
                out.ehc_v_per_k.push_back(ehc.ehc_v_per_k[k]);
            }
        nlohmann::json bins = nlohmann::json::array();
        for (std::size_t k = 0; k < grid.size(); ++k)
            bins.push_back({{"soc", grid[k]}, {"ehc_v_per_k", num(ehc.ehc_v_per_k[k])},
                            {"spread_v_per_k", num(ehc.spread_v_per_k[k])}, {"samples", ehc.samples[k]}});
        out.details["ehc"] = {{"source", rec.source},
                              {"mean_abs_current_a", num(ehc.mean_abs_current_a)},
                              {"joule_share", num(ehc.joule_share)},
                              {"bins", bins},
                              {"note", ehc.note}};
        if (!ehc.note.empty()) out.notes.push_back("entropic coefficient: " + ehc.note);
    } else {
        out.notes.push_back("no constant-current discharge with temperature and heat flux: entropic heat left out "
                            "(dU/dT = 0)");
    }

    // R_th (a) and (b) for every recording with thermal data.
    nlohmann::json rth = nlohmann::json::array();
    std::vector<const Recording*> thermal_recs;
    std::vector<std::vector<double>> thermal_socs;
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        const auto& rec = recordings[r];
        if (!has_thermal(rec)) continue;
        thermal_recs.push_back(&rec);
        thermal_socs.push_back(socs[r]);
        ThermalResistanceOptions ro;
        ro.c_th_se_j_per_k = std::isfinite(out.c_th_sigma_j_per_k) ? out.c_th_sigma_j_per_k : 0.0;
        if (rec.has_ambient()) ro.ambient_c = kNaN;
        const auto flux = fit_thermal_resistance(rec, {{0, rec.size()}}, area, out.c_th_j_per_k, ro);
        std::vector<RowRange> rests;
        for (const auto& lr : segments[r].long_rests) rests.push_back({lr.begin, lr.end});
        ThermalResistanceFit cool;
        if (!rests.empty()) cool = fit_thermal_resistance(rec, rests, area, out.c_th_j_per_k, ro);
        rth.push_back({{"source", rec.source},
                       {"flux_k_per_w", num(flux.r_th_flux_k_per_w)},
                       {"flux_se_k_per_w", num(flux.r_th_flux_se_k_per_w)},
                       {"flux_ambient", flux.ambient_source},
                       {"cooling_tau_s", num(cool.tau_s)},
                       {"cooling_k_per_w", num(cool.r_th_tau_k_per_w)},
                       {"cooling_se_k_per_w", num(cool.r_th_tau_se_k_per_w)},
                       {"cooling_rests_used", cool.rests_used}});
        if (std::isfinite(flux.r_th_flux_k_per_w) && std::isfinite(cool.r_th_tau_k_per_w)) {
            const double rel = (flux.r_th_flux_k_per_w - cool.r_th_tau_k_per_w) /
                               (0.5 * (flux.r_th_flux_k_per_w + cool.r_th_tau_k_per_w));
            if (std::abs(rel) > 0.15)
                out.notes.push_back(rec.source + ": R_th from heat flux (" + printf_text("%.2f", flux.r_th_flux_k_per_w) +
                                    " K/W) and from the cooling time constant (" +
                                    printf_text("%.2f", cool.r_th_tau_k_per_w) + " K/W) disagree by " +
                                    std::to_string(static_cast<int>(std::round(100 * rel))) +
                                    " %: the sensor sees one patch of the lateral surface, not the terminals");
        }
    }
    out.details["r_th_estimates"] = rth;

    // R_th (c): reproduce the measured surface temperature from the measured heat generation.
    if (!thermal_recs.empty()) {
        ParameterSet p = electrical;
        p.thermal.ehc_soc = out.ehc_soc;
        p.thermal.ehc_v_per_k = out.ehc_v_per_k;
        const auto data = measured_heat_data(thermal_recs, p, thermal_socs);
        auto cost = [&](double r) { return measured_heat_temperature_rms(data, out.c_th_j_per_k, r); };
        out.r_th_k_per_w = golden_minimum(cost, kRThSearchMinKPerW, kRThSearchMaxKPerW, 40);
        if (at_search_bound(out.r_th_k_per_w, kRThSearchMinKPerW, kRThSearchMaxKPerW)) add_flag(out.r_th_flags, "at_bound");
        {
            std::vector<double> res;
            measured_heat_temperature_rms(data, out.c_th_j_per_k, out.r_th_k_per_w, &res);
            const double r_stat = curvature_sd(cost, out.r_th_k_per_w, res);
            double r_prop = 0;  // C_th's uncertainty carried through the re-fit
            if (std::isfinite(out.c_th_sigma_j_per_k) && out.c_th_sigma_j_per_k > 0) {
                const double dc = std::min(out.c_th_sigma_j_per_k, 0.5 * out.c_th_j_per_k);
                auto refit = [&](double c) {
                    return golden_minimum([&](double r) { return measured_heat_temperature_rms(data, c, r); },
                                          kRThSearchMinKPerW, kRThSearchMaxKPerW, 40);
                };
                r_prop = 0.5 * std::abs(refit(out.c_th_j_per_k + dc) - refit(out.c_th_j_per_k - dc));
            }
            out.r_th_sigma_k_per_w = std::sqrt(r_stat * r_stat + r_prop * r_prop);
        }
        out.r_th_method = "fitted: first-order model driven by the measured heat I*(V - OCV) + I*T*dU/dT reproduces "
                          "the measured surface temperature (C_th held)";
        out.details["r_th_temperature_fit"] = {{"r_th_k_per_w", out.r_th_k_per_w},
                                               {"temperature_rms_c", num(cost(out.r_th_k_per_w))}};
    } else if (options.fallback_r_th_k_per_w > 0) {
        out.r_th_k_per_w = options.fallback_r_th_k_per_w;
        out.r_th_method = "fallback";
    }
    flag_thermal(out, electrical.capacity_ah);
    // A C_th from the heat flux that no cell of this capacity holds is most often the surface: the flux density is
    // turned into heat over options.area_m2 (fit --area-m2, by default a 21700's), and a larger cell (a 40 Ah pouch
    // on the simulated bench: C_th 136 J/K for 633) reads low by the ratio of the surfaces.
    if (c_th_from_heat_flux && std::find(out.c_th_flags.begin(), out.c_th_flags.end(), "implausible") != out.c_th_flags.end())
        out.notes.push_back(printf_text("C_th %.4g J/K is %.3g J/K per Ah of the capacity, outside the 4-80 cells hold: the heat "
                                        "flux density was turned into heat over %.4g m^2 of surface (--area-m2; the default is "
                                        "a 21700's): if the cell's surface differs, give it",
                                        out.c_th_j_per_k, out.c_th_j_per_k / electrical.capacity_ah, area));
    return out;
}

}  // namespace cellbench::estimator
