#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/voltage_spikes.hpp"

#include <algorithm>
#include <cmath>
#include <atomic>
#include <map>
#include <thread>

#include "cellbench/estimator/coulomb.hpp"
#include "cellbench/estimator/logger_timing.hpp"
#include "cellbench/estimator/merge.hpp"
#include "cellbench/estimator/thermal_characterization.hpp"

#include "median.hpp"
#include "printf_text.hpp"

namespace cellbench::estimator {

namespace {

// How much of the long rest after a SOC step the extended joint fit covers (see PulseFitOptions).
constexpr double kExtendedRestS = 300.0;

bool usable(const Rc2Params<double>& p) {
    for (double v : {p.r0_ohm, p.r1_ohm, p.tau1_s, p.r2_ohm, p.tau2_s})
        if (!std::isfinite(v) || v <= 0) return false;
    return true;
}

nlohmann::json rc_json(const Rc2Params<double>& p) {
    const auto v = to_rc_values(p);
    auto num = [](double x) -> nlohmann::json { return std::isfinite(x) ? nlohmann::json(x) : nlohmann::json(nullptr); };
    return {{"r0_ohm", num(v.r0_ohm)}, {"r1_ohm", num(v.r1_ohm)}, {"c1_f", num(v.c1_f)},
            {"r2_ohm", num(v.r2_ohm)}, {"c2_f", num(v.c2_f)},     {"tau1_s", num(p.tau1_s)},
            {"tau2_s", num(p.tau2_s)}};
}

nlohmann::json num_or_null(double x) { return std::isfinite(x) ? nlohmann::json(x) : nlohmann::json(nullptr); }

}  // namespace

ParameterSet assemble_parameter_set(const std::vector<PulseSetFit>& fits, const std::vector<OcvPoint>& ocv_points,
                                    double capacity_ah, const ThermalCharacterization& thermal,
                                    const CharacterizationOptions& options) {
    if (ocv_points.size() < 2) throw InputError("characterization: fewer than two OCV points (long rests) found");
    ParameterSet p;
    p.cell = options.cell;
    p.capacity_ah = capacity_ah;
    for (const auto& pt : ocv_points) {
        p.soc.push_back(pt.soc);
        p.ocv_v.push_back(pt.ocv_v);
    }
    double temp_sum = 0;
    std::size_t temp_n = 0;
    for (const auto& f : fits)
        if (std::isfinite(f.temperature_c)) temp_sum += f.temperature_c, ++temp_n;
    p.reference_temperature_c = temp_n ? temp_sum / static_cast<double>(temp_n) : 25.0;

    for (int dir : {-1, +1}) {
        RcTable& table = dir > 0 ? p.charge : p.discharge;
        for (double s : p.soc) {
            const PulseSetFit* best = nullptr;
            for (const auto& f : fits) {
                const bool limited = dir > 0 ? f.pulse_set.charge_cv : f.pulse_set.discharge_cv;
                if (limited || !usable(dir > 0 ? f.chosen_charge() : f.chosen_discharge())) continue;
                if (!best || std::abs(f.soc - s) < std::abs(best->soc - s)) best = &f;
            }
            if (!best)
                throw InputError(std::string("characterization: no usable HPPC pulse set for the ") +
                                 (dir > 0 ? "charge" : "discharge") + " direction");
            const auto v = to_rc_values(dir > 0 ? best->chosen_charge() : best->chosen_discharge());
            table.r0_ohm.push_back(v.r0_ohm);
            table.r1_ohm.push_back(v.r1_ohm);
            table.c1_f.push_back(v.c1_f);
            table.r2_ohm.push_back(v.r2_ohm);
            table.c2_f.push_back(v.c2_f);
        }
    }
    p.thermal.c_th_j_per_k = thermal.c_th_j_per_k;
    p.thermal.r_th_k_per_w = thermal.r_th_k_per_w;
    p.thermal.area_m2 = options.area_m2;
    p.thermal.ehc_soc = thermal.ehc_soc;
    p.thermal.ehc_v_per_k = thermal.ehc_v_per_k;
    p.validate("fitted parameter set");
    return p;
}

namespace {

// Row of a recording where SOC is 1: the end of the last CCCV charge before the first pulse (a current phase of
// at most pulse_max_s) or, without pulses, before the first discharge; else the first row (a characterization
// recording starts fully charged, as Table 2.12's pulse part and the USABC manual's test do).
std::size_t anchor_row(const RecordingSegments& seg) {
    std::size_t first_activity = SIZE_MAX;
    for (const auto& ph : seg.phases)
        if (ph.is_pulse()) {
            first_activity = ph.begin;
            break;
        }
    if (first_activity == SIZE_MAX)
        for (const auto& ph : seg.phases)
            if (ph.direction < 0) {
                first_activity = ph.begin;
                break;
            }
    std::size_t anchor = 0;
    for (const auto& ph : seg.phases)
        if (ph.direction > 0 && ph.cv_tail && ph.end <= first_activity && ph.kind == PhaseKind::Charge) anchor = ph.end - 1;
    return anchor;
}

// Current phases that run from one long rest straight into the next: the titration steps of a GITT or an
// incremental-OCV test (and the SOC steps of an HPPC). A charge held at its voltage limit (CCCV) is a full charge.
std::size_t titration_steps(const RecordingSegments& seg) {
    std::size_t steps = 0;
    for (std::size_t i = 1; i + 1 < seg.phases.size(); ++i)
        steps += !seg.phases[i].is_rest() && !seg.phases[i].cv_tail && seg.phases[i - 1].kind == PhaseKind::LongRest &&
                 seg.phases[i + 1].kind == PhaseKind::LongRest;
    return steps;
}
constexpr std::size_t kMinTitrationSteps = 5;

// A recording of a characterization test (SOC anchored at its full charge): pulse sets, pulses between several
// long rests, or a GITT / incremental-OCV test (at least kMinTitrationSteps current steps between long rests:
// each step's edges and relaxations identify R0 and the pairs as a pulse's do, at the step's one current).
bool has_pulses(const RecordingSegments& seg) {
    if (!seg.pulse_sets.empty()) return true;
    std::size_t pulses = 0;
    for (const auto& ph : seg.phases)
        pulses += ph.is_pulse();
    return pulses >= 2 && seg.long_rests.size() >= 3;
}
bool is_characterization(const RecordingSegments& seg) {
    return has_pulses(seg) || titration_steps(seg) >= kMinTitrationSteps;
}

// Overlapping recordings of one test (the cycler's export of the whole test and a finer recording of part of
// it): the finer one is spliced into the coarser one, as `cellbench import --neware X --bdf Y` does, so the
// finest data serve once, the coarser only where they alone hold data, and any arrangement of the same files
// gives the same recordings. Recognized by their current steps (at least 3, 80 % matched on one offset).
std::vector<Recording> merge_overlapping(const std::vector<Recording>& in, std::vector<std::string>& notes) {
    std::vector<Recording> recs = in;
    // Deterministic whatever the order the files came in: longest first.
    std::stable_sort(recs.begin(), recs.end(), [](const Recording& a, const Recording& b) {
        const double da = a.time_s.back() - a.time_s.front(), db = b.time_s.back() - b.time_s.front();
        return da != db ? da > db : a.size() > b.size();
    });
    merge_pairwise(recs, [&](const Recording& coarse, const Recording& fine) -> std::optional<Recording> {
        const double d_coarse = coarse.time_s.back() - coarse.time_s.front();
        const double d_fine = fine.time_s.back() - fine.time_s.front();
        if (d_fine > d_coarse || !(median_interval_s(fine) < median_interval_s(coarse))) return std::nullopt;
        CurrentAlignment al;
        try {
            al = align_by_current(coarse, fine, d_coarse);
        } catch (const InputError&) {
            return std::nullopt;
        }
        if (al.edges_b < 3 || al.matched_edges * 5 < al.edges_b * 4) return std::nullopt;
        notes.push_back(fine.source + " and " + coarse.source + " record the same test (" +
                        std::to_string(al.matched_edges) + " of " + std::to_string(al.edges_b) +
                        " current steps at offset " + printf_text("%.2f", al.offset_s) +
                        " s): spliced, the finer rows serve once");
        return splice_recordings(coarse, fine, al.offset_s);  // named "coarse + fine"
    });
    // The remaining order: characterization-like recordings first does not matter; keep a stable content order.
    return recs;
}

// Starting values when no pulse set of the thesis' layout was found: OCV from the rests, R0 from the voltage
// steps at current steps, polarization of typical proportions.
ParameterSet generic_start(const std::vector<Recording>& recs, const std::vector<OcvPoint>& ocv, double cap,
                           const CharacterizationOptions& options) {
    std::vector<double> r0s;
    for (const auto& rec : recs)
        for (std::size_t k = 1; k < rec.size(); ++k) {
            const double di = rec.current_a[k] - rec.current_a[k - 1];
            if (std::abs(di) > 0.5 && std::abs(rec.current_a[k - 1]) < 0.05) {
                const double r = (rec.voltage_v[k] - rec.voltage_v[k - 1]) / di;
                if (std::isfinite(r) && r > 0) r0s.push_back(r);
            }
        }
    double r0 = 0.05 / std::max(cap, 0.1);
    if (!r0s.empty()) r0 = upper_median(std::move(r0s));
    ParameterSet p;
    p.cell = options.cell;
    p.capacity_ah = cap;
    for (const auto& pt : ocv) p.soc.push_back(pt.soc), p.ocv_v.push_back(pt.ocv_v);
    for (auto* t : {&p.discharge, &p.charge})
        for (std::size_t k = 0; k < p.soc.size(); ++k) {
            t->r0_ohm.push_back(r0);
            t->r1_ohm.push_back(0.3 * r0);
            t->c1_f.push_back(3.0 / (0.3 * r0));
            t->r2_ohm.push_back(0.4 * r0);
            t->c2_f.push_back(60.0 / (0.4 * r0));
        }
    p.thermal.c_th_j_per_k = 1.0;
    p.thermal.r_th_k_per_w = 1.0;
    p.thermal.area_m2 = options.area_m2;
    return p;
}

// Whether a discharge ends on the knee of an emptying cell: over its last tenth of charge its voltage falls at
// least 3 times as fast per Ah as the rested voltage does from one long rest of the recording to the next
// (their median). A test stopped part-way (its last SOC step at mid SOC) ends on the OCV's own slope: it does
// not measure the capacity. The P45B's HPPC to its 2.9 V cut-off ends at 5.0x (1.13 against 0.22 V/Ah): a knee
// cut short by a cut-off above the steepest part, which a 5x rule refused.
bool ends_on_knee(const Recording& rec, const std::vector<double>& q, const Phase& d, const std::vector<Phase>& rests) {
    if (d.end < d.begin + 2) return false;
    const double q0 = q[d.begin], total = q0 - q[d.end - 1];
    if (!(total > 0)) return false;
    std::vector<double> slopes;  // V per Ah between consecutive rests that more than 1 % of the discharge apart
    for (std::size_t k = 1; k < rests.size(); ++k) {
        const std::size_t i = rests[k - 1].end - 1, j = rests[k].end - 1;
        const double dq = q[i] - q[j], dv = rec.voltage_v[i] - rec.voltage_v[j];
        if (std::abs(dq) > 0.01 * total && std::isfinite(dv)) slopes.push_back(std::abs(dv / dq));
    }
    if (slopes.empty()) return true;  // nothing to compare with: as before, the lowest voltage is the cut-off
    const double ocv_slope = upper_median(std::move(slopes));
    // The last row at or before 90 % of the discharge's charge (a coarse log may have only its two ends).
    std::size_t k90 = d.begin;
    for (std::size_t k = d.begin; k + 1 < d.end; ++k)
        if (q0 - q[k] <= 0.9 * total && std::isfinite(rec.voltage_v[k])) k90 = k;
    const double end_slope = (rec.voltage_v[k90] - rec.voltage_v[d.end - 1]) / (q[k90] - q[d.end - 1]);
    return std::isfinite(end_slope) && end_slope > 3.0 * ocv_slope;
}

// The test's SOC levels, as the global fit's table breakpoints: in each characterization recording, in time
// order, the long rests that end more than kLevelStep of SOC away from the previous one (an SOC step between two
// levels; the rests between the pulses of one level move it less), the first rest included. Levels of several
// recordings of one test (a cycler export beside the logger's file) closer than kLevelStep are one level. Gaps
// wider than kMaxGap (a layout with few levels) are divided evenly: a straight line over 20 % of SOC does not follow
// the tables towards the ends (the plant's random layout, levels 20 % apart, kMaxGap 0.2 -> 0.125: seed 19 R1+R2
// 14.6 -> 2.9 % and tau2 48.6 -> 18.0 % off; seed 6 R0 11.3 -> 8.4 %; seed 38, an LFP cell, its discharge tau2 an
// integrator at 20 % SOC before, 79 % off after, still a poor fit, flagged; seed 7 R0 1.5 -> 2.2 %). Any layout: 5 %
// steps at the ends and 10 % in the middle (the Panasonic 18650PF's HPPC) give a breakpoint at every level, where
// a uniform grid would put half of them between levels, where only the SOC-step discharges reach (the resistances
// then alternate).
std::vector<double> level_knots(const std::vector<Recording>& recordings, const std::vector<bool>& characterization,
                                const std::vector<RecordingSegments>& segs,
                                const std::vector<std::vector<double>>& soc_of_row) {
    constexpr double kLevelStep = 0.02, kMaxGap = 0.125, kLattice = 0.005;
    std::vector<double> levels;
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        if (!characterization[r] || soc_of_row[r].empty()) continue;
        double prev = kNaN;
        for (const auto& lr : segs[r].long_rests) {
            const double s = std::clamp(soc_of_row[r][lr.end - 1], 0.0, 1.0);
            if (!(std::abs(s - prev) <= kLevelStep)) levels.push_back(s);
            prev = s;
        }
    }
    std::sort(levels.begin(), levels.end());
    std::vector<double> merged;
    for (std::size_t k = 0; k < levels.size();) {
        std::size_t e = k;
        double sum = 0;
        while (e < levels.size() && levels[e] - levels[k] <= kLevelStep) sum += levels[e++];
        // On a 0.5 % lattice: the same test handed in another arrangement (its levels a hair apart by Coulomb
        // counting) gets the same breakpoints.
        const double level = std::round(sum / static_cast<double>(e - k) / kLattice) * kLattice;
        if (merged.empty() || level > merged.back()) merged.push_back(level);
        k = e;
    }
    std::vector<double> knots;
    for (std::size_t k = 0; k < merged.size(); ++k) {
        if (k > 0) {
            const double gap = merged[k] - merged[k - 1];
            const int parts = static_cast<int>(std::ceil(gap / kMaxGap - 1e-9));
            for (int p = 1; p < parts; ++p) knots.push_back(merged[k - 1] + gap * p / parts);
        }
        knots.push_back(merged[k]);
    }
    return knots;
}

// The charge a slow capacity test leaves in the cell at its cut-off: the discharge stops where the voltage under
// load meets the cut-off, while its OCV still lies above it by the overpotential, which the rest after it shows
// (the voltage relaxes from the cut-off towards the OCV). The cell's capacity down to the cut-off counts that
// charge as well: the relaxation divided by the voltage's slope per Ah over the discharge's last 0.5 %
// (at C/10 or slower the loaded voltage runs parallel to the OCV there; faster, the overpotential grows towards
// the end and the slope says nothing about the OCV's). 0 where the test does not show it: a faster discharge, no
// rest of 10 min after it, an end above the cut-off, fewer than 3 rows in the last 0.5 %, or a figure beyond 2 %
// of the charge. Independent plant (C/20 test, a 1 h rest after it): 2.5-9.4 mAh, up to 0.37 % of the capacity.
double charge_below_cutoff_ah(const Recording& rec, const RecordingSegments& seg, const Phase& d, double v_floor) {
    const double delivered_ah = -d.charge_ah;
    if (!(delivered_ah > 0) || d.index + 1 >= seg.phases.size()) return 0.0;
    if (std::abs(d.mean_current_a) > 0.1 * delivered_ah) return 0.0;  // faster than C/10 (per hour)
    const Phase& rest = seg.phases[d.index + 1];
    if (!rest.is_rest() || rest.duration_s < 600.0 || !(d.voltage_end_v <= v_floor + 0.02)) return 0.0;
    double relaxed_v = kNaN;
    for (std::size_t k = rest.end; k-- > rest.begin;)
        if (std::isfinite(rec.voltage_v[k])) {
            relaxed_v = rec.voltage_v[k];
            break;
        }
    const auto& q = seg.charge_ah;
    const double q_end = q[d.end - 1];
    double sq = 0, sv = 0, sqq = 0, sqv = 0;
    int n = 0;
    for (std::size_t k = d.end; k-- > d.begin && q[k] - q_end <= 0.005 * delivered_ah;) {
        if (!std::isfinite(rec.voltage_v[k])) continue;
        const double x = q[k] - q_end, v = rec.voltage_v[k];
        sq += x, sv += v, sqq += x * x, sqv += x * v, ++n;
    }
    if (n < 3 || !std::isfinite(relaxed_v)) return 0.0;
    const double slope_v_per_ah = (n * sqv - sq * sv) / (n * sqq - sq * sq);
    const double below_ah = (relaxed_v - rec.voltage_v[d.end - 1]) / slope_v_per_ah;
    return std::isfinite(below_ah) && below_ah > 0 && below_ah < 0.02 * delivered_ah ? below_ah : 0.0;
}

// The capacity's uncertainty from the characterization's own recordings: the global fit gives each slow discharge
// that does not start from the test's full charge (an OCV test, a pilot discharge of another day) its own charge
// scale. Where that scale departs from 1, the recording's charge and the SOC axis the HPPC's rests laid out
// disagree by that fraction, and no capacity figure can be better than their disagreement. RMS over the windows
// that span at least half the SOC range (a short one says more about the OCV's local slope than about the
// capacity); NaN without one. Independent plant, controls of seeds 1-5: 0.12-0.49 %.
double capacity_disagreement_ah(const GlobalFitResult& g, double capacity_ah) {
    double ss = 0;
    int n = 0;
    for (const auto& w : g.windows) {
        if (!w.capacity_scale_fitted || !(w.soc_max - w.soc_min >= 0.5)) continue;
        ss += (w.capacity_scale - 1.0) * (w.capacity_scale - 1.0), ++n;
    }
    return n ? capacity_ah * std::sqrt(ss / n) : kNaN;
}

// The temperature a recording was made at: its ambient column's median, else its first surface reading (a test
// starts rested at the chamber's temperature). NaN without either.
double ambient_of(const Recording& rec) {
    if (rec.has_ambient()) return finite_upper_median(rec.ambient_c);
    for (const double v : rec.surface_c)
        if (std::isfinite(v)) return v;
    return kNaN;
}

// One characterization is one ambient temperature: the model's tables hold the resistances there (with their
// Arrhenius dependence on the cell's own heating), its OCV and capacity too. Characterization tests (pulses) more
// than kOtherAmbientK apart are an error; another recording that far from them (a C/20 OCV test at 25 degC beside
// a 0 degC HPPC: its capacity 20 % larger, its resistances a quarter) is left out with a warning. Before, it moved
// the 0 degC fit's OCV and slow pair until US06 was predicted at 227 mV instead of 36.
void leave_out_other_ambients(std::vector<Recording>& recordings, std::vector<RecordingSegments>& segs,
                              std::vector<bool>& characterization, std::vector<std::string>& warnings) {
    constexpr double kOtherAmbientK = 10.0;
    std::vector<double> ambient(recordings.size());
    double lo = kNaN, hi = kNaN;
    std::size_t lo_r = 0, hi_r = 0;
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        ambient[r] = ambient_of(recordings[r]);
        if (!characterization[r] || !std::isfinite(ambient[r])) continue;
        if (!(ambient[r] >= lo)) lo = ambient[r], lo_r = r;
        if (!(ambient[r] <= hi)) hi = ambient[r], hi_r = r;
    }
    if (!std::isfinite(lo)) return;
    if (hi - lo > kOtherAmbientK)
        throw InputError(printf_text("characterization: %s was made at %.1f degC and %s at %.1f degC: one fit is one "
                                     "ambient temperature; fit each on its own (to carry one set to the other "
                                     "temperature, `cellbench diagnose --improved` of a recording made there "
                                     "identifies the resistances' temperature dependence: docs/command-line.md)",
                                     recordings[lo_r].source.c_str(), lo, recordings[hi_r].source.c_str(), hi));
    const double ref = 0.5 * (lo + hi);
    for (std::size_t r = recordings.size(); r-- > 0;) {
        if (characterization[r] || !std::isfinite(ambient[r]) || std::abs(ambient[r] - ref) <= kOtherAmbientK) continue;
        warnings.push_back(printf_text("%s left out: made at %.1f degC, %.1f K from the characterization's %.1f degC "
                                       "(its OCV, capacity and resistances belong to another temperature)",
                                       recordings[r].source.c_str(), ambient[r], std::abs(ambient[r] - ref), ref));
        recordings.erase(recordings.begin() + static_cast<std::ptrdiff_t>(r));
        segs.erase(segs.begin() + static_cast<std::ptrdiff_t>(r));
        characterization.erase(characterization.begin() + static_cast<std::ptrdiff_t>(r));
    }
}

// A characterization test without a charge to full before its first pulse is taken to start fully charged
// (anchor_row): its first row is SOC 1. Where another recording of the cell starts rested more than 50 mV higher,
// it does not (a test's later part handed in alone; parts that continue one another are joined before this), and
// every SOC, the OCV table and the capacity counted from it would be wrong: an error, not a silent table. Where no
// recording confirms it, the assumption is stated.
void check_full_start(const std::vector<Recording>& recordings, const std::vector<RecordingSegments>& segs,
                      const std::vector<bool>& characterization, std::vector<std::string>& warnings) {
    constexpr double kHigherV = 0.05;
    // The voltage a recording rests at before it first draws current (NaN: it does not start with a rest).
    auto rested_start_v = [&](std::size_t r) {
        const auto& ph = segs[r].phases;
        if (ph.empty() || !ph.front().is_rest() || ph.front().end == 0) return kNaN;
        return recordings[r].voltage_v[ph.front().end - 1];
    };
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        if (!characterization[r] || anchor_row(segs[r]) != 0) continue;
        const double v = rested_start_v(r);
        double highest = kNaN;
        std::size_t by = r;
        bool confirmed = false;
        for (std::size_t q = 0; q < recordings.size(); ++q) {
            const double vq = rested_start_v(q);
            if (q == r || !std::isfinite(vq)) continue;
            if (!(vq <= highest)) highest = vq, by = q;
            confirmed = confirmed || std::abs(vq - v) <= kHigherV;
        }
        if (std::isfinite(v) && highest > v + kHigherV)
            throw InputError("characterization: " + recordings[r].source + " does not start fully charged: it rests at " +
                             printf_text("%.4f V", v) + " before it first draws current, " + recordings[by].source +
                             " at " + printf_text("%.4f V", highest) +
                             ", and it holds no charge to full before its first pulse, so its SOC is not known. Hand "
                             "in the part of the test that starts at full charge too (parts that continue one another "
                             "are joined), or leave out " + recordings[by].source +
                             " if its cell was charged to another voltage");
        if (!confirmed)
            warnings.push_back(recordings[r].source + ": SOC 100 % taken at its first row (" +
                               printf_text("%.4f V", recordings[r].voltage_v.front()) +
                               "): it holds no charge to full before its first pulse, and no other recording starts "
                               "rested near that voltage to confirm it");
    }
}

}  // namespace

Characterization characterize(const std::vector<Recording>& given, const CharacterizationOptions& options) {
    // Progress: segmenting up to 5 %, pulse sets to 30 %, the global fit to 85 %, the thermal fits the rest.
    ProgressReporter progress(options.progress);
    progress(0.0, "segmenting");
    Characterization out;
    for (const auto& rec : given) {
        if (rec.size() < 2) throw InputError(rec.source + ": recording has fewer than two rows");
        if (auto reversed = reversed_current_text(rec); !reversed.empty()) throw InputError(reversed);
        // Missing values: a current gap breaks the Coulomb counting (an error); a voltage gap only removes
        // residuals (the fits run around it, and say so).
        std::size_t missing_v = 0, first_v = 0;
        for (std::size_t k = 0; k < rec.size(); ++k) {
            if (!std::isfinite(rec.current_a[k]) || !std::isfinite(rec.time_s[k]))
                throw InputError(rec.source + ": row " + std::to_string(k + 1) +
                                 " has no current or time (NaN): the charge cannot be counted across it");
            if (!std::isfinite(rec.voltage_v[k]) && missing_v++ == 0) first_v = k;
        }
        if (missing_v)
            out.warnings.push_back(rec.source + ": " + std::to_string(missing_v) +
                                   " rows without a voltage (NaN, missing), the first at t = " +
                                   printf_text("%.1f", rec.time_s[first_v]) + " s: left out of the fits");
    }
    std::vector<Recording> recordings = join_continued_recordings(merge_overlapping(given, out.warnings), out.warnings);
    for (auto& rec : recordings)
        for (auto& note : correct_logging_artifacts(rec)) out.warnings.push_back(std::move(note));
    std::vector<RecordingSegments> segs;
    for (const auto& rec : recordings) {
        if (rec.size() < 2) throw InputError(rec.source + ": recording has fewer than two rows");
        segs.push_back(segment_recording(rec));
    }
    std::vector<bool> characterization(recordings.size());
    for (std::size_t r = 0; r < recordings.size(); ++r) characterization[r] = is_characterization(segs[r]);
    leave_out_other_ambients(recordings, segs, characterization, out.warnings);
    check_full_start(recordings, segs, characterization, out.warnings);
    if (std::none_of(characterization.begin(), characterization.end(), [](bool b) { return b; })) {
        // What each recording holds instead, so that a test whose rests are too short to read the OCV says so.
        std::string found;
        for (std::size_t r = 0; r < recordings.size(); ++r) {
            const auto& ph = segs[r].phases;
            std::size_t pulses = 0, currents = 0;
            std::vector<double> between;  // rests with a current phase on both sides
            for (std::size_t i = 0; i < ph.size(); ++i) {
                pulses += ph[i].is_pulse();
                currents += !ph[i].is_rest();
                if (ph[i].is_rest() && i > 0 && i + 1 < ph.size()) between.push_back(ph[i].duration_s);
            }
            found += printf_text("; %s: %zu current phases (%zu of them pulses of at most %.0f s), %zu rests of %.0f s "
                                 "or more",
                                 recordings[r].source.c_str(), currents, pulses, SegmentOptions{}.pulse_max_s,
                                 segs[r].long_rests.size(), SegmentOptions{}.long_rest_s);
            if (!between.empty())
                found += printf_text(", the rests between its current phases %.0f s (median)", upper_median(std::move(between)));
        }
        throw InputError("characterization: no recording holds pulses between rests (an HPPC test) or " +
                         std::to_string(kMinTitrationSteps) + " or more current steps between rests of " +
                         printf_text("%.0f", SegmentOptions{}.long_rest_s) +
                         " s or more (a GITT; the OCV is read at the end of those rests): nothing to identify the "
                         "resistances from" + found);
    }
    {
        bool pulses = false;
        std::size_t steps = 0;
        for (std::size_t r = 0; r < recordings.size(); ++r)
            if (characterization[r]) pulses = pulses || has_pulses(segs[r]), steps += titration_steps(segs[r]);
        if (!pulses)
            out.warnings.push_back(
                "no pulses: R0 and the RC pairs come from the " + std::to_string(steps) +
                " current steps between long rests alone (a GITT or incremental-OCV test), at their one current "
                "each; the first pair only where rows follow a step within its time constant");
    }
    // Without any cell temperature the thermal part cannot be identified: say so before the long fit, not after.
    if (std::none_of(recordings.begin(), recordings.end(), [](const Recording& r) { return r.has_surface(); }) &&
        !(options.fallback_c_th_j_per_k > 0 && options.fallback_r_th_k_per_w > 0))
        throw InputError("characterization: no recording has a cell (surface) temperature, so C_th and R_th cannot be "
                         "identified: record one, or give both (cellbench fit --c-th-j-per-k and --r-th-k-per-w; an "
                         "18650 in still air has about 15-20 J/K per Ah and 5-15 K/W)");

    // Capacity: a pilot discharge if any recording has one (of several, the lowest rate: the closest to the charge
    // the cell holds between its voltage limits, whatever order the files came in); else a characterization
    // test's own throughput from its full charge to the cut-off; else a full CC discharge handed in beside it;
    // else the given value.
    double v_floor = 1e9;  // the lowest voltage any recording reaches: the cut-off
    for (const auto& rec : recordings)
        for (double v : rec.voltage_v)
            if (std::isfinite(v)) v_floor = std::min(v_floor, v);
    std::optional<std::pair<std::size_t, Phase>> capacity_test;  // the discharge that measured it, if one did
    {
        double pilot_rate = 1e300;
        for (std::size_t r = 0; r < recordings.size(); ++r)
            if (const auto& pd = segs[r].pilot_discharge;
                pd && pd->voltage_end_v <= v_floor + 0.1 && std::abs(pd->mean_current_a) < pilot_rate) {
                pilot_rate = std::abs(pd->mean_current_a);
                out.capacity = {-pd->charge_ah, "pilot discharge", recordings[r].source};
                capacity_test = {r, *pd};
            }
    }
    if (!std::isfinite(out.capacity.capacity_ah)) {
        for (std::size_t r = 0; r < recordings.size(); ++r) {
            if (!characterization[r] || segs[r].cc_discharges.empty()) continue;
            const auto& last = segs[r].cc_discharges.back();
            if (last.voltage_end_v > v_floor + 0.1) continue;
            const auto& q = segs[r].charge_ah;
            // The cut-off is where the cell runs empty: the discharge ends on the knee (ends_on_knee). A test
            // stopped part-way (its last SOC step at mid SOC) does not measure the capacity.
            if (!ends_on_knee(recordings[r], q, last, segs[r].long_rests)) continue;
            const std::size_t anchor = anchor_row(segs[r]);
            out.capacity = {q[anchor] - q[std::min(last.end, q.size() - 1)], "throughput from full charge to the cut-off",
                            recordings[r].source};
            out.warnings.push_back("no pilot discharge found: capacity taken from " + recordings[r].source +
                                   "'s own throughput from full charge to the cut-off");
            break;
        }
    }
    if (!std::isfinite(out.capacity.capacity_ah)) {
        // A full CC discharge on its own: starts rested near the top, ends at the cut-off. Lowest rate wins. The
        // lowest voltage of the recordings is the cut-off only where the cell runs empty there (ends_on_knee): an
        // HPPC stopped at 40 % SOC beside a 1C discharge stopped at 45 % had the discharge's 2.1 Ah taken for the
        // capacity of a 3.8 Ah cell.
        double best_rate = 1e300;
        for (std::size_t r = 0; r < recordings.size(); ++r) {
            if (characterization[r]) continue;
            for (const auto& ph : segs[r].cc_discharges) {
                if (ph.voltage_end_v > v_floor + 0.1 || ph.duration_s < 1800) continue;
                if (!ends_on_knee(recordings[r], segs[r].charge_ah, ph, segs[r].long_rests)) continue;
                const bool rested_start = ph.begin == 0 || segs[r].phases[ph.index - 1].is_rest();
                if (!rested_start || std::abs(ph.mean_current_a) >= best_rate) continue;
                best_rate = std::abs(ph.mean_current_a);
                out.capacity = {-ph.charge_ah, "full CC discharge at " + printf_text("%.3g", best_rate) + " A",
                                recordings[r].source};
                capacity_test = {r, ph};
            }
        }
    }
    if (capacity_test) {
        const auto& [r, d] = *capacity_test;
        out.capacity.below_cutoff_ah = charge_below_cutoff_ah(recordings[r], segs[r], d, v_floor);
        out.capacity.capacity_ah += out.capacity.below_cutoff_ah;
    }
    if (!std::isfinite(out.capacity.capacity_ah)) {
        if (options.fallback_capacity_ah <= 0)
            throw InputError("characterization: no recording measures the capacity (no pilot discharge, no test "
                             "from full charge to the cut-off, no full CC discharge): give it with --capacity-ah "
                             "or in the cell config");
        out.capacity = {options.fallback_capacity_ah, "given", options.fallback_capacity_source};
        out.warnings.push_back("capacity not measured: using " + options.fallback_capacity_source);
    }
    if (options.fallback_capacity_ah > 0 && out.capacity.method != "given")
        out.warnings.push_back(printf_text("%s %.4g Ah not used: %s measures %.4f Ah (%s, %+.1f %%)",
                                           options.fallback_capacity_source.c_str(), options.fallback_capacity_ah,
                                           out.capacity.source.c_str(), out.capacity.capacity_ah,
                                           out.capacity.method.c_str(),
                                           100.0 * (out.capacity.capacity_ah / options.fallback_capacity_ah - 1.0)));
    const double cap = out.capacity.capacity_ah;
    if (!(cap > 0) || !std::isfinite(cap)) throw InputError("characterization: the measured capacity is not positive");

    // OCV points and SOC by Coulomb counting from the full charge, for the characterization tests.
    std::vector<std::vector<double>> soc_of_row(recordings.size());
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        if (!characterization[r]) continue;
        const auto& rec = recordings[r];
        const auto& q = segs[r].charge_ah;
        const std::size_t anchor = anchor_row(segs[r]);
        auto& soc = soc_of_row[r];
        soc.resize(rec.size());
        for (std::size_t k = 0; k < rec.size(); ++k) soc[k] = 1.0 + (q[k] - q[anchor]) / cap;
        for (const auto& lr : segs[r].long_rests) {
            const std::size_t k = lr.end - 1;
            out.ocv_points.push_back({std::clamp(soc[k], 0.0, 1.0), rec.voltage_v[k], lr.duration_s, rec.source});
        }
    }
    // One point per SOC: where two rests end within 0.5 % SOC keep the longer rest.
    std::sort(out.ocv_points.begin(), out.ocv_points.end(), [](auto& a, auto& b) { return a.soc < b.soc; });
    std::vector<OcvPoint> ocv;
    for (const auto& pt : out.ocv_points) {
        if (!ocv.empty() && pt.soc - ocv.back().soc < 0.005) {
            if (pt.rest_s > ocv.back().rest_s) ocv.back() = pt;
            continue;
        }
        ocv.push_back(pt);
    }
    out.ocv_points = ocv;
    if (ocv.size() < 2) throw InputError("characterization: fewer than two long rests (OCV points) found");
    std::vector<double> ocv_soc, ocv_v;
    for (const auto& pt : ocv) ocv_soc.push_back(pt.soc), ocv_v.push_back(pt.ocv_v);

    // The thesis' per-pulse-set fits, where the recordings have its pulse sets (the reported comparison, and
    // the global fit's starting point).
    struct Job {
        std::size_t r;
        const PulseSet* ps;
        PulseFitOptions po;
        double soc;
    };
    std::vector<Job> jobs;
    for (std::size_t r = 0; r < recordings.size(); ++r) {
        if (!characterization[r]) continue;
        for (const auto& ps : segs[r].pulse_sets) {
            const double s = soc_of_row[r][ps.pulse_begin > 0 ? ps.pulse_begin - 1 : 0];
            PulseFitOptions po;
            const double h = 0.01;
            po.docv_dah_v_per_ah =
                (interp_extrap(ocv_soc, ocv_v, s + h) - interp_extrap(ocv_soc, ocv_v, s - h)) / (2 * h) / cap;
            // Extend the joint fit over the SOC step and the long rest after it, when the recording has them.
            const std::size_t idx = static_cast<std::size_t>(&ps - segs[r].pulse_sets.data());
            for (const auto& step : segs[r].soc_steps) {
                if (step.pulse_set_index != idx || !step.followed_by_long_rest) continue;
                for (const auto& lr : segs[r].long_rests)
                    if (lr.begin >= step.end && lr.begin <= step.end + 1) {
                        std::size_t e = lr.begin;
                        while (e < lr.end && recordings[r].time_s[e] - recordings[r].time_s[lr.begin] < kExtendedRestS)
                            ++e;
                        po.extended_end = e;
                        po.extended_end_ocv_v = recordings[r].voltage_v[lr.end - 1];
                    }
            }
            jobs.push_back({r, &ps, po, s});
        }
    }
    std::vector<PulseSetFit> fits(jobs.size());
    std::atomic<std::size_t> next{0}, done{0};
    progress(0.05, "pulse sets 0/" + std::to_string(jobs.size()));
    auto worker = [&] {
        for (std::size_t j; (j = next.fetch_add(1)) < jobs.size();) {
            fits[j] = fit_pulse_set(recordings[jobs[j].r], *jobs[j].ps, jobs[j].po);
            fits[j].soc = jobs[j].soc;
            const std::size_t k = ++done;
            progress(0.05 + 0.25 * static_cast<double>(k) / static_cast<double>(jobs.size()),
                     "pulse sets " + std::to_string(k) + "/" + std::to_string(jobs.size()));
        }
    };
    {
        const std::size_t n_threads =
            std::clamp<std::size_t>(std::thread::hardware_concurrency(), 1, std::max<std::size_t>(jobs.size(), 1));
        std::vector<std::thread> pool;
        for (std::size_t t = 1; t < n_threads; ++t) pool.emplace_back(worker);
        worker();
        for (auto& t : pool) t.join();
    }
    for (auto& f : fits) out.pulse_fits.push_back(std::move(f));
    if (jobs.empty()) {
        std::size_t pulses = 0;
        for (std::size_t r = 0; r < recordings.size(); ++r)
            if (characterization[r])
                for (const auto& ph : segs[r].phases)
                    pulses += ph.is_pulse();
        if (pulses > 0)
            out.warnings.push_back(
                "no pulse set (a long rest of " + std::to_string(static_cast<int>(SegmentOptions{}.long_rest_s)) +
                " s, then up to four pulses, one of them discharging, up to the next long phase) among the " +
                std::to_string(pulses) +
                " pulses: no per-pulse-set tables to compare with, and cellbenchd would fit no pulse set of such a "
                "program online; the global fit uses every pulse");
    }

    ThermalCharacterization placeholder;
    placeholder.c_th_j_per_k = 1.0;
    placeholder.r_th_k_per_w = 1.0;
    ParameterSet electrical;
    const bool any_charge_pulse = std::any_of(out.pulse_fits.begin(), out.pulse_fits.end(),
                                              [](const PulseSetFit& f) { return f.pulse_set.has_charge_pulse(); });
    if (!out.pulse_fits.empty() && !any_charge_pulse) {
        out.warnings.push_back("per-pulse-set tables not assembled: no pulse set has a charge pulse (their discharge "
                               "values are in the summary's pulse_sets)");
    } else if (!out.pulse_fits.empty()) {
        try {
            out.per_pulse_set_params = assemble_parameter_set(out.pulse_fits, out.ocv_points, cap, placeholder, options);
        } catch (const InputError& e) {
            out.warnings.push_back(std::string("per-pulse-set tables not assembled: ") + e.what());
        }
    }
    if (options.global_fit || !out.per_pulse_set_params) {
        // The global fit starts from the thesis-form sets' tables (and its own uniform starts). Tables from the
        // other forms' shorter windows are a worse start: on the independent plant's USABC layout they took the
        // fit to a lower objective with the pairs' roles lost (seed 15, LFP: tau2 9.5 -> 61 %, R0 3.1 -> 7.4 %).
        std::vector<PulseSetFit> thesis_form;
        for (const auto& f : out.pulse_fits)
            if (f.pulse_set.form == PulseSetForm::Thesis) thesis_form.push_back(f);
        std::optional<ParameterSet> thesis_tables;
        if (thesis_form.size() == out.pulse_fits.size()) {
            thesis_tables = out.per_pulse_set_params;
        } else if (!thesis_form.empty()) {
            try {
                thesis_tables = assemble_parameter_set(thesis_form, out.ocv_points, cap, placeholder, options);
            } catch (const InputError&) {
            }
        }
        const ParameterSet start =
            thesis_tables ? *thesis_tables : generic_start(recordings, out.ocv_points, cap, options);
        std::vector<const Recording*> ptrs;
        std::vector<std::vector<std::pair<std::size_t, std::size_t>>> rests;
        for (std::size_t r = 0; r < recordings.size(); ++r) {
            ptrs.push_back(&recordings[r]);
            rests.emplace_back();
            for (const auto& lr : segs[r].long_rests) rests.back().emplace_back(lr.begin, lr.end);
        }
        GlobalFitOptions go = options.global;
        if (!std::isfinite(go.knot_spacing) && go.knot_soc.empty()) go.knot_soc = level_knots(recordings, characterization, segs, soc_of_row);
        if (!std::isfinite(go.knot_spacing) && go.knot_soc.size() < 3) {
            go.knot_soc.clear();
            // Knots from the spacing of the test's rest points (its SOC levels), between 5 % and 12.5 %.
            std::vector<double> gaps;
            for (std::size_t k = 1; k < ocv_soc.size(); ++k)
                if (ocv_soc[k] - ocv_soc[k - 1] > 0.02) gaps.push_back(ocv_soc[k] - ocv_soc[k - 1]);
            double g = 0.1;
            if (!gaps.empty()) g = upper_median(std::move(gaps));
            // The levels' own spacing. Half of it would follow what bends between two levels (the validation
            // plant's OCV knee towards empty: 30 mV off at 10 % SOC on 10 % knots, 6 mV on 5 %), but on the P45B
            // 5 % knots predict the 4C discharge at 74 mV instead of 18 (OCV and resistance trade off along the
            // SOC-step discharges between levels). The nearest spacing that divides [0, 1] into whole steps.
            double best = 0.1;
            for (double c : {0.05, 1.0 / 15, 0.1, 0.125})
                if (std::abs(std::log(c / g)) < std::abs(std::log(best / g))) best = c;
            go.knot_spacing = best;
        }
        go.progress = [&](double f, std::string_view stage) { progress(0.30 + 0.55 * f, stage); };
        out.global = fit_global(ptrs, soc_of_row, rests, cap, start, go);
        out.capacity.capacity_ah_sd = capacity_disagreement_ah(*out.global, cap);
        electrical = out.global->params;
        electrical.capacity_ah_sd = out.capacity.capacity_ah_sd;
        // The OCV's uncertainty per table row, where the fit stated one for every row (the table is its OCV grid).
        if (out.global->ocv.size() == electrical.soc.size() &&
            std::all_of(out.global->ocv.begin(), out.global->ocv.end(), [](const FittedValue& v) {
                return std::isfinite(v.sd) && v.sd >= 0;
            }))
            for (const auto& v : out.global->ocv) electrical.ocv_v_sd.push_back(v.sd);
        electrical.cell = options.cell;
        electrical.thermal.c_th_j_per_k = 1.0;
        electrical.thermal.r_th_k_per_w = 1.0;
        electrical.thermal.area_m2 = options.area_m2;
        for (const auto& n : out.global->notes) out.warnings.push_back("global fit: " + n);
        if (const auto flagged = out.global->flagged_count())
            out.warnings.push_back("global fit: " + std::to_string(flagged) +
                                   " table values flagged (implausible, uncertain or unidentified): see the summary");
    } else {
        electrical = *out.per_pulse_set_params;
    }

    progress(0.85, "thermal parameters");
    // The heat I*(V - OCV(SOC)) needs each row's SOC: where the global fit ran, as it ends with it (a capacity
    // discharge whose first row is logged under load has no rested voltage to start its count from).
    out.thermal = fit_thermal_parameters(recordings, segs, out.global ? out.global->soc_of_row : soc_of_row, electrical,
                                         options);
    if (!std::isfinite(out.thermal.c_th_j_per_k) || !std::isfinite(out.thermal.r_th_k_per_w))
        throw InputError("characterization: no recording measures the thermal parameters (surface temperature, "
                         "with heat flux or ambient)");
    for (const auto& n : out.thermal.notes) out.warnings.push_back(n);
    out.params = electrical;
    out.params.thermal.c_th_j_per_k = out.thermal.c_th_j_per_k;
    out.params.thermal.r_th_k_per_w = out.thermal.r_th_k_per_w;
    out.params.thermal.area_m2 = options.area_m2;
    out.params.thermal.ehc_soc = out.thermal.ehc_soc;
    out.params.thermal.ehc_v_per_k = out.thermal.ehc_v_per_k;
    out.params.validate("fitted parameter set");
    if (out.per_pulse_set_params) {
        out.per_pulse_set_params->thermal = out.params.thermal;
        out.per_pulse_set_params->validate("per-pulse-set parameter set");
    }
    progress(1.0, "done");
    return out;
}

nlohmann::json Characterization::summary_json() const {
    nlohmann::json j;
    j["schema"] = "cellbench.fit-summary/1";
    j["capacity"] = {{"capacity_ah", capacity.capacity_ah}, {"capacity_ah_sd", num_or_null(capacity.capacity_ah_sd)},
                     {"method", capacity.method}, {"source", capacity.source},
                     {"below_cutoff_ah", capacity.below_cutoff_ah}};
    j["ocv_points"] = nlohmann::json::array();
    for (const auto& pt : ocv_points)
        j["ocv_points"].push_back({{"soc", pt.soc}, {"ocv_v", pt.ocv_v}, {"rest_s", pt.rest_s}, {"source", pt.source}});
    j["pulse_sets"] = nlohmann::json::array();
    for (const auto& f : pulse_fits) {
        nlohmann::json e;
        e["soc"] = f.soc;
        e["form"] = to_string(f.pulse_set.form);
        e["ocv_v"] = f.ocv_v;
        e["temperature_c"] = num_or_null(f.temperature_c);
        e["r0_steps_ohm"] = {{"ab", num_or_null(f.r0.ab_ohm)}, {"cd", num_or_null(f.r0.cd_ohm)},
                             {"ef", num_or_null(f.r0.ef_ohm)}, {"gh", num_or_null(f.r0.gh_ohm)},
                             {"discharge_sampling_corrected", num_or_null(f.r0.discharge_corrected_ohm)},
                             {"charge_sampling_corrected", num_or_null(f.r0.charge_corrected_ohm)}};
        e["thesis"] = {{"discharge", rc_json(f.thesis_discharge)},
                       {"charge", rc_json(f.thesis_charge)},
                       {"rms_v", num_or_null(f.thesis_rms_v)}};
        e["joint"] = {{"discharge", rc_json(f.joint_discharge)},
                      {"charge", rc_json(f.joint_charge)},
                      {"discharge_sigma",
                       {{"r0_ohm", num_or_null(f.joint_discharge_sigma.r0_ohm)},
                        {"r1_ohm", num_or_null(f.joint_discharge_sigma.r1_ohm)},
                        {"tau1_s", num_or_null(f.joint_discharge_sigma.tau1_s)},
                        {"r2_ohm", num_or_null(f.joint_discharge_sigma.r2_ohm)},
                        {"tau2_s", num_or_null(f.joint_discharge_sigma.tau2_s)}}},
                      {"charge_sigma",
                       {{"r0_ohm", num_or_null(f.joint_charge_sigma.r0_ohm)},
                        {"r1_ohm", num_or_null(f.joint_charge_sigma.r1_ohm)},
                        {"tau1_s", num_or_null(f.joint_charge_sigma.tau1_s)},
                        {"r2_ohm", num_or_null(f.joint_charge_sigma.r2_ohm)},
                        {"tau2_s", num_or_null(f.joint_charge_sigma.tau2_s)}}},
                      {"ocv_offset_v", num_or_null(f.joint_ocv_offset_v)},
                      {"rms_v", num_or_null(f.joint_rms_v)}};
        e["chosen"] = to_string(f.chosen);
        e["charge_pulse_hit_voltage_limit"] = f.pulse_set.charge_cv;
        e["warnings"] = f.warnings;
        j["pulse_sets"].push_back(e);
    }
    j["thermal"] = thermal.details;
    j["thermal"]["c_th_j_per_k"] = thermal.c_th_j_per_k;
    j["thermal"]["r_th_k_per_w"] = thermal.r_th_k_per_w;
    j["thermal"]["r_th_method"] = thermal.r_th_method;
    j["global"] = global ? global->to_json() : nlohmann::json(nullptr);
    j["warnings"] = warnings;
    return j;
}

}  // namespace cellbench::estimator
