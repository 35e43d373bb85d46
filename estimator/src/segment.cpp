#include "cellbench/estimator/segment.hpp"

#include <algorithm>
#include <cmath>

#include "cellbench/estimator/coulomb.hpp"

namespace cellbench::estimator {

const char* to_string(PhaseKind kind) {
    switch (kind) {
        case PhaseKind::Rest: return "rest";
        case PhaseKind::LongRest: return "long rest";
        case PhaseKind::DischargePulse: return "discharge pulse";
        case PhaseKind::ChargePulse: return "charge pulse";
        case PhaseKind::Discharge: return "discharge";
        case PhaseKind::Charge: return "charge";
    }
    return "?";
}

namespace {

struct Run {
    std::size_t begin, end;
    int state;
    bool step_split;  // separated from the previous run by a step boundary (same direction on both sides)
};

// Duration of rows [begin, end) under the sampling convention (row k covers (t[k-1], t[k]]).
double span_s(const std::vector<double>& t, std::size_t begin, std::size_t end) {
    if (end <= begin) return 0.0;
    const double start = begin > 0 ? t[begin - 1] : t[begin];
    const double d = t[end - 1] - start;
    return std::isfinite(d) && d > 0.0 ? d : 0.0;
}

bool step_changes(const Recording& rec, std::size_t k) {
    if (k == 0) return false;
    // The step count, when present, is the authority: a tester reports a CCCV step's CV phase under another
    // step type word ("cv") within the same step, which is not a new step.
    if (rec.step_count.size() == rec.size() && std::isfinite(rec.step_count[k - 1]) && std::isfinite(rec.step_count[k]))
        return rec.step_count[k - 1] != rec.step_count[k];
    if (rec.step_type.size() == rec.size()) {
        const auto& a = rec.step_type[k - 1];
        const auto& b = rec.step_type[k];
        if (!a.empty() && !b.empty() && a != b) return true;
    }
    return false;
}

// Row states by hysteresis on the current: +1 charge, -1 discharge, 0 rest. Non-finite currents keep the state.
std::vector<int> row_states(const std::vector<double>& current_a, const SegmentOptions& o) {
    std::vector<int> st(current_a.size(), 0);
    int s = 0;
    for (std::size_t k = 0; k < current_a.size(); ++k) {
        const double i = current_a[k];
        if (std::isfinite(i)) {
            if (s != 0 && s * i > o.off_threshold_a) {
                // still flowing in the same direction (CV tails included)
            } else if (i > o.on_threshold_a) {
                s = +1;
            } else if (i < -o.on_threshold_a) {
                s = -1;
            } else {
                s = 0;
            }
        }
        st[k] = s;
    }
    return st;
}

Phase make_phase(const Recording& rec, const std::vector<double>& charge_ah, const Run& r, const SegmentOptions& o) {
    const auto& t = rec.time_s;
    const auto& cur = rec.current_a;
    Phase p;
    p.begin = r.begin;
    p.end = r.end;
    p.direction = r.state;
    p.duration_s = span_s(t, r.begin, r.end);
    p.open_end = r.end == rec.size();
    p.voltage_begin_v = rec.voltage_v[r.begin];
    p.voltage_end_v = rec.voltage_v[r.end - 1];

    double sum = 0.0;
    std::size_t cnt = 0;
    for (std::size_t k = r.begin; k < r.end; ++k) {
        if (!std::isfinite(cur[k])) continue;
        sum += cur[k];
        ++cnt;
    }
    p.mean_current_a = cnt ? sum / static_cast<double>(cnt) : 0.0;
    // The phase's charge: from its first row to the next phase's first row (coulomb.hpp places the steps
    // between them).
    p.charge_ah = charge_ah[std::min(r.end, charge_ah.size() - 1)] - charge_ah[r.begin];

    // Peak and end current from short moving means, so that a noise spike is not a peak.
    const std::size_t n = r.end - r.begin;
    const std::size_t m = std::min<std::size_t>(5, n);
    double best = 0.0, end_mean = 0.0;
    {
        double acc = 0.0;
        std::size_t acc_n = 0;
        for (std::size_t k = r.begin; k < r.end; ++k) {
            if (std::isfinite(cur[k])) { acc += cur[k]; ++acc_n; }
            if (k >= r.begin + m) {
                const double old = cur[k - m];
                if (std::isfinite(old)) { acc -= old; --acc_n; }
            }
            if (k + 1 >= r.begin + m && acc_n) {
                const double mean = acc / static_cast<double>(acc_n);
                if (std::abs(mean) > std::abs(best)) best = mean;
                end_mean = mean;
            }
        }
    }
    if (r.state == 0) {
        p.peak_current_a = 0.0;
        p.end_current_a = end_mean;
        p.kind = classify_phase(0, p.duration_s, o);
    } else {
        p.peak_current_a = best;
        p.end_current_a = end_mean;
        p.cv_tail = std::abs(end_mean) < o.cv_tail_fraction * std::abs(best);
        p.kind = classify_phase(r.state, p.duration_s, o);
    }
    return p;
}

// The phases of rec, whose cumulative charge is charge_ah (cumulative_charge_ah(rec)).
std::vector<Phase> split_phases(const Recording& rec, const std::vector<double>& charge_ah, const SegmentOptions& o) {
    std::vector<Phase> phases;
    const std::size_t n = rec.size();
    if (n == 0 || rec.current_a.size() != n || rec.voltage_v.size() != n) return phases;

    const std::vector<int> st = row_states(rec.current_a, o);

    // Raw runs of one state; step boundaries split runs of one direction.
    std::vector<Run> runs;
    std::size_t b = 0;
    bool split_flag = false;
    for (std::size_t k = 1; k <= n; ++k) {
        const bool state_change = k == n || st[k] != st[b];
        const bool step_split = !state_change && o.use_step_boundaries && st[k] != 0 && step_changes(rec, k);
        if (state_change || step_split) {
            runs.push_back({b, k, st[b], split_flag});
            split_flag = step_split;
            b = k;
        }
    }

    auto is_glitch = [&](std::size_t begin, std::size_t end) {
        return end - begin < o.min_phase_samples && span_s(rec.time_s, begin, end) < o.min_phase_s;
    };

    // Absorb glitches into the preceding run (the following one at the start) and merge equal neighbours,
    // except across a step boundary that separates two real phases of one direction.
    std::vector<Run> out;
    std::optional<std::size_t> leading_glitch_begin;
    for (const Run& r : runs) {
        // A short run at the end of the window is not a glitch yet: it may be the start of a new phase.
        if (is_glitch(r.begin, r.end) && r.end < n) {
            if (!out.empty())
                out.back().end = r.end;
            else if (!leading_glitch_begin)
                leading_glitch_begin = r.begin;
            continue;
        }
        Run cur = r;
        if (leading_glitch_begin) {
            cur.begin = *leading_glitch_begin;
            leading_glitch_begin.reset();
        }
        if (!out.empty() && out.back().state == cur.state && !cur.step_split) {
            out.back().end = cur.end;
            continue;
        }
        if (!out.empty() && out.back().state != cur.state) cur.step_split = false;
        out.push_back(cur);
    }
    if (leading_glitch_begin) {  // the whole window is one glitch: call it what its rows mostly are
        out.push_back({*leading_glitch_begin, n, st[n - 1], false});
    }

    phases.reserve(out.size());
    for (const Run& r : out) {
        Phase p = make_phase(rec, charge_ah, r, o);
        p.index = phases.size();
        phases.push_back(p);
    }
    return phases;
}

}  // namespace

std::vector<Phase> split_phases(const Recording& rec, const SegmentOptions& o) {
    return split_phases(rec, cumulative_charge_ah(rec), o);
}

PhaseKind classify_phase(int direction, double duration_s, const SegmentOptions& o) {
    // 1 % slack: a cycler may end a 10 min rest step one sample early.
    if (direction == 0) return duration_s >= 0.99 * o.long_rest_s ? PhaseKind::LongRest : PhaseKind::Rest;
    const bool pulse = duration_s <= o.pulse_max_s;
    if (direction < 0) return pulse ? PhaseKind::DischargePulse : PhaseKind::Discharge;
    return pulse ? PhaseKind::ChargePulse : PhaseKind::Charge;
}

const char* to_string(PulseSetForm form) {
    switch (form) {
        case PulseSetForm::Thesis: return "thesis";
        case PulseSetForm::NoChargeRelaxation: return "no charge relaxation";
        case PulseSetForm::DischargeOnly: return "discharge only";
        case PulseSetForm::Other: return "other order";
    }
    return "?";
}

namespace {

// The thesis, USABC and discharge-only forms (PulseSetForm); nullopt also while one of them may still complete.
std::optional<PulseSetForm> named_form(const std::vector<Phase>& ph, std::size_t i, const SegmentOptions& o,
                                       std::size_t& count) {
    auto found = [&](PulseSetForm f, std::size_t n) {
        count = n;
        return std::optional<PulseSetForm>(f);
    };
    // Long rest (A), discharge pulse (B..C), rest (D..E): every form.
    if (i + 2 >= ph.size() || ph[i].kind != PhaseKind::LongRest || ph[i + 1].kind != PhaseKind::DischargePulse ||
        !ph[i + 2].is_rest())
        return std::nullopt;
    // What ends the USABC and discharge-only forms is a long current phase (the SOC step; while it is shorter
    // than pulse_max_s it may be a pulse, so a set waits for it), or, after a discharge pulse, a long rest: never
    // the next pulse of a drive cycle.
    auto long_current = [&](std::size_t j) {
        return j < ph.size() && (ph[j].kind == PhaseKind::Discharge || ph[j].kind == PhaseKind::Charge);
    };
    if (i + 3 < ph.size() && ph[i + 3].kind == PhaseKind::ChargePulse) {
        const bool has_after = i + 4 < ph.size();
        if (has_after && ph[i + 4].is_rest() && ph[i + 4].duration_s >= o.min_relaxation_s)
            return found(PulseSetForm::Thesis, 5);
        // The charge pulse is over once the next phase has begun: the SOC step at once, or after a short rest.
        if (long_current(i + 4)) return found(PulseSetForm::NoChargeRelaxation, 4);
        if (has_after && ph[i + 4].is_rest() && long_current(i + 5)) return found(PulseSetForm::NoChargeRelaxation, 5);
        return std::nullopt;  // the charge pulse or its rest goes on, or another pulse follows (the Other form)
    }
    // No charge pulse after a rest of min_relaxation_s: a long rest with what follows it begun, or the SOC step.
    if (i + 3 >= ph.size() || ph[i + 2].duration_s < o.min_relaxation_s) return std::nullopt;
    if (ph[i + 2].kind != PhaseKind::LongRest && !long_current(i + 3)) return std::nullopt;
    return found(PulseSetForm::DischargeOnly, 3);
}

// The Other form: after the long rest, pulses and short rests up to the next long phase, which has begun; the
// number of phases from i.
std::optional<std::size_t> other_form(const std::vector<Phase>& ph, std::size_t i) {
    if (ph[i].kind != PhaseKind::LongRest || i + 1 >= ph.size() || !ph[i + 1].is_pulse()) return std::nullopt;
    std::size_t pulses = 0;
    bool discharge = false;
    std::size_t j = i + 1;
    for (; j < ph.size() && (ph[j].is_pulse() || ph[j].kind == PhaseKind::Rest); ++j) {
        if (!ph[j].is_pulse()) continue;
        if (++pulses > kMaxOtherPulses) return std::nullopt;
        discharge = discharge || ph[j].direction < 0;
    }
    if (j >= ph.size() || !discharge) return std::nullopt;  // the next long phase has not begun (or no discharge)
    // A long rest that ends the pulses is their relaxation (and the next set's rest A, as in DischargeOnly); as
    // there, what follows it must have begun (a charge pulse after it would make it a thesis-form set).
    if (ph[j].kind != PhaseKind::LongRest) return j - i;
    if (j + 1 >= ph.size()) return std::nullopt;
    return j - i + 1;
}

}  // namespace

std::optional<PulseSetForm> pulse_set_form(const std::vector<Phase>& ph, std::size_t i, const SegmentOptions& o,
                                           std::size_t* phase_count) {
    if (i >= ph.size() || ph[i].kind != PhaseKind::LongRest) return std::nullopt;
    std::size_t count = 0;
    auto form = named_form(ph, i, o, count);
    // The Other form needs the long phase after the pulses to have begun, and by then every named form that
    // could still complete has: a set that waits for one of them never becomes an Other set early.
    if (!form) {
        if (const auto n = other_form(ph, i)) {
            form = PulseSetForm::Other;
            count = *n;
        }
    }
    if (form && phase_count) *phase_count = count;
    return form;
}

RecordingSegments segment_recording(const Recording& rec, const SegmentOptions& o) {
    RecordingSegments seg;
    seg.charge_ah = cumulative_charge_ah(rec);
    seg.phases = split_phases(rec, seg.charge_ah, o);
    const auto& ph = seg.phases;

    for (const Phase& p : ph) {
        if (p.kind == PhaseKind::LongRest) seg.long_rests.push_back(p);
        if (p.kind == PhaseKind::Discharge) seg.cc_discharges.push_back(p);
    }

    // Pulse sets of every form (pulse_set_form), each followed perhaps by the SOC step's discharge.
    std::vector<bool> is_soc_step(ph.size(), false);
    for (std::size_t i = 0; i + 2 < ph.size(); ++i) {
        std::size_t count = 0;
        const auto form = pulse_set_form(ph, i, o, &count);
        if (!form) continue;
        const Phase& rest = ph[i];
        const Phase& last = ph[i + count - 1];
        // The first pulse of each direction (the Other form may begin with a charge pulse); the thesis, USABC
        // and discharge-only forms have the discharge pulse at i + 1 and the charge pulse, if any, at i + 3.
        std::size_t d = 0, c = 0, last_pulse = 0;
        for (std::size_t j = i + 1; j < i + count; ++j) {
            if (ph[j].kind == PhaseKind::DischargePulse && d == 0) d = j;
            if (ph[j].kind == PhaseKind::ChargePulse && c == 0) c = j;
            if (ph[j].is_pulse()) last_pulse = j;
        }
        auto rest_at = [&](std::size_t j) { return j > i && j < i + count && ph[j].is_rest(); };
        const Phase& dis = ph[d];
        PulseSet ps;
        ps.form = *form;
        ps.phase_index = i;
        ps.rest_begin = rest.begin;
        ps.pulse_begin = ph[i + 1].begin;
        ps.discharge_begin = dis.begin;
        ps.discharge_end = dis.end;
        ps.end = last.end;
        ps.pulses_end = ph[last_pulse].end;
        ps.next_window_begin = last.kind == PhaseKind::LongRest ? last.begin : last.end;
        ps.ocv_v = rec.voltage_v[ps.pulse_begin - 1];
        ps.rest_duration_s = rest.duration_s;
        ps.discharge_current_a = dis.mean_current_a;
        ps.discharge_duration_s = dis.duration_s;
        ps.discharge_relaxation_s = rest_at(d + 1) ? ph[d + 1].duration_s : 0.0;
        ps.discharge_ah = dis.charge_ah;
        ps.discharge_cv = dis.cv_tail;
        ps.rest_before_discharge = d == i + 1 || rest_at(d - 1);
        ps.rest_after_discharge = rest_at(d + 1);
        if (c != 0) {
            const Phase& chg = ph[c];
            ps.charge_begin = chg.begin;
            ps.charge_end = chg.end;
            ps.charge_current_a = chg.mean_current_a;
            ps.charge_duration_s = chg.duration_s;
            ps.charge_relaxation_s = rest_at(c + 1) ? ph[c + 1].duration_s : 0.0;
            ps.charge_ah = chg.charge_ah;
            ps.charge_cv = chg.cv_tail;
            ps.rest_before_charge = c == i + 1 || rest_at(c - 1);
            ps.rest_after_charge = rest_at(c + 1);
        } else {
            ps.charge_begin = ps.charge_end = ps.end;
            ps.rest_before_charge = ps.rest_after_charge = false;
        }
        ps.relaxation_open = last.is_rest() && last.open_end;
        seg.pulse_sets.push_back(ps);

        if (const std::size_t after = i + count; after < ph.size() && ph[after].kind == PhaseKind::Discharge) {
            const Phase& d = ph[after];
            SocStep s;
            s.phase_index = d.index;
            s.pulse_set_index = seg.pulse_sets.size() - 1;
            s.begin = d.begin;
            s.end = d.end;
            s.charge_ah = d.charge_ah;
            s.mean_current_a = d.mean_current_a;
            s.followed_by_long_rest = after + 1 < ph.size() && ph[after + 1].kind == PhaseKind::LongRest;
            seg.soc_steps.push_back(s);
            is_soc_step[d.index] = true;
        }
    }

    // Pilot discharge: the first long discharge after a CCCV charge and a rest, ended (not open).
    for (std::size_t p = 2; p + 1 < ph.size(); ++p) {
        const Phase& d = ph[p];
        if (d.kind != PhaseKind::Discharge || is_soc_step[p] || d.duration_s < o.pilot_min_s) continue;
        if (!ph[p - 1].is_rest() || ph[p - 2].kind != PhaseKind::Charge || !ph[p - 2].cv_tail) continue;
        seg.pilot_discharge = d;
        break;
    }
    return seg;
}

std::optional<PulseSet> last_complete_pulse_set(const Recording& window, const SegmentOptions& options) {
    RecordingSegments seg = segment_recording(window, options);
    if (seg.pulse_sets.empty()) return std::nullopt;
    return seg.pulse_sets.back();
}

}  // namespace cellbench::estimator
