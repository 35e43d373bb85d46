#pragma once
// Segmentation of a recording into constant-mode phases (rest / discharge / charge) and detection of what a
// characterization test is made of: HPPC pulse sets (thesis section 2.2.2, Table 2.12, Figure 3.6), the SOC
// steps between them, the pilot discharge, plain CC discharges and long rests.
//
// Phases come from the current, not from the cycler's step log:
//  - each row is rest / discharge / charge by a hysteresis on |I| (enter a current above on_threshold_a, leave
//    it below off_threshold_a), so a CCCV charge whose current tapers towards its 0.05 A cut-off stays one
//    charge phase, and current noise around zero stays a rest;
//  - runs shorter than min_phase_samples rows AND shorter than min_phase_s are glitches and are absorbed by
//    the preceding phase (noise spikes, a vendor's one-row step artefacts); a short run at the very end of
//    the window is kept as its own (open) phase, since it may be the start of a new step;
//  - when the recording carries `Step Count` or `Step Type`, a step boundary inside a run of one current
//    direction splits it (e.g. a discharge step followed at once by another discharge step); the step log is
//    never needed and never overrides the current (a rest is a rest whatever its step says).
//  - CV tails are not split off: without a step log, a same-direction level change inside a phase is kept
//    in that phase (documented limitation).
//
// Index ranges are half-open [begin, end) into the recording's rows. By the sampling convention of
// electrical.hpp the current of row k flowed during (t[k-1], t[k]], so a phase [begin, end) lasted
// t[end-1] - t[begin-1] (t[end-1] - t[begin] for a phase starting at row 0).
//
// Online use: segment_recording works on any window of rows. A pulse set is reported only when it is
// complete: a thesis-form set when its charge relaxation has lasted at least min_relaxation_s AND is either
// followed by a new current or reaches the end of the window (then PulseSet::relaxation_open is true and `end`
// is the window's end); the other forms (PulseSetForm) when the long phase after their last one has begun (a
// current phase once it has lasted pulse_max_s, before which it may be a pulse), since until then a rest after a
// discharge pulse may still be followed by a charge pulse, and pulses by more pulses (a drive cycle). A daemon that passes the
// window when the relaxation step has ended gets the same pulse set (same rows) as an offline run over the
// whole recording. The long rest before the discharge pulse must be inside the window for at least long_rest_s
// (start the window at the start of that rest step: PulseSet::next_window_begin).
//
// Not recognized (the global fit still uses their every row): pulses after a rest shorter than long_rest_s, more
// than kMaxOtherPulses pulses before the next long phase, pulses of one direction only charging.
#include <cstddef>
#include <optional>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

struct SegmentOptions {
    double on_threshold_a = 0.05;    // |I| above this starts a current phase
    double off_threshold_a = 0.02;   // |I| below this ends it (hysteresis; CV tails end at 0.05 A)
    std::size_t min_phase_samples = 3;  // shorter runs (in rows) ...
    double min_phase_s = 1.5;           // ... that are also shorter than this are glitches
    double long_rest_s = 600.0;      // a rest this long (1 % slack) is a long rest (OCV); thesis: 1 h before pulses
    double pulse_max_s = 60.0;       // a current phase this short is a pulse; longer ones are CC phases
    double min_relaxation_s = 30.0;  // a pulse set is complete once its charge relaxation lasted this long
    double pilot_min_s = 600.0;      // shortest discharge that counts as a pilot (full) discharge
    double cv_tail_fraction = 0.8;   // a current phase ending below this fraction of its peak |I| has a CV tail
    bool use_step_boundaries = true; // split same-direction runs at Step Count / Step Type changes
};

enum class PhaseKind {
    Rest,            // rest shorter than long_rest_s
    LongRest,        // rest of at least long_rest_s (OCV is read at its end)
    DischargePulse,  // discharge of at most pulse_max_s
    ChargePulse,     // charge of at most pulse_max_s
    Discharge,       // longer discharge (CC or CCCV)
    Charge,          // longer charge (CC or CCCV)
};

const char* to_string(PhaseKind kind);

struct Phase {
    PhaseKind kind = PhaseKind::Rest;
    std::size_t index = 0;  // position in RecordingSegments::phases
    std::size_t begin = 0, end = 0;  // rows [begin, end)
    int direction = 0;               // +1 charge, -1 discharge, 0 rest
    double duration_s = 0.0;         // see the header comment
    double mean_current_a = 0.0;     // + = charge
    double peak_current_a = 0.0;     // largest |I| with its sign (0 for a rest)
    double end_current_a = 0.0;      // mean current of the last few rows
    double charge_ah = 0.0;          // integral of I dt over the phase (+ = charged into the cell)
    double voltage_begin_v = 0.0, voltage_end_v = 0.0;  // first and last row
    bool cv_tail = false;            // current phase whose |I| tapered (CV: voltage limit reached)
    bool open_end = false;           // the phase runs to the end of the window (it may go on)

    [[nodiscard]] bool is_rest() const { return direction == 0; }
    [[nodiscard]] bool is_pulse() const { return kind == PhaseKind::DischargePulse || kind == PhaseKind::ChargePulse; }
    [[nodiscard]] std::size_t size() const { return end - begin; }
};

// The layouts a pulse set is recognized in. Every form starts with a long rest (A, the OCV) and a discharge
// pulse (B..C) followed by a rest (D..E).
enum class PulseSetForm {
    // Thesis Table 2.12 / Figure 3.6: ... -> charge pulse (F..G) -> rest (H..I) of at least min_relaxation_s.
    Thesis,
    // The USABC/FreedomCAR manual's: ... -> charge (regen) pulse (F..G) -> at once the SOC step (a current phase
    // longer than pulse_max_s), or a rest shorter than min_relaxation_s and then the SOC step. The set ends with
    // that rest (or with G); the step at G is read only where a rest follows it.
    NoChargeRelaxation,
    // Discharge pulses alone (the Panasonic 18650PF's five currents per level, labs' discharge-only HPPCs):
    // the rest after the discharge pulse lasts at least min_relaxation_s and is either a long rest (then it is
    // also the next pulse set's rest A) with what follows it begun, or followed by the SOC step. No charge rows:
    // charge_begin = charge_end = end.
    DischargeOnly,
    // Any other order after the long rest: up to kMaxOtherPulses pulses of either direction (at least one a
    // discharge pulse), with or without rests between them, that end where the next long phase (a CC step or a
    // long rest, which is then the set's last phase) begins: a charge pulse first, pulses with no rest between,
    // several currents per level. The discharge_* and charge_* fields describe the first pulse of each direction;
    // an R0 step is read only where a rest is on its other side. More pulses before the next long phase (a drive
    // cycle) make no pulse set.
    Other,
};
inline constexpr std::size_t kMaxOtherPulses = 4;
const char* to_string(PulseSetForm form);

// One HPPC pulse set (Figure 3.6): long rest (A) -> discharge pulse (B..C) -> rest (D..E) -> charge pulse
// (F..G) -> rest (H..I), or one of the other forms of PulseSetForm.
struct PulseSet {
    PulseSetForm form = PulseSetForm::Thesis;
    std::size_t phase_index = 0;   // index of the long rest in RecordingSegments::phases
    std::size_t rest_begin = 0;    // first row of the long rest
    std::size_t pulse_begin = 0;   // first row of the first pulse; row pulse_begin-1 is A (the OCV)
    std::size_t discharge_begin = 0;  // first discharge row (B); = pulse_begin but in the Other form
    std::size_t discharge_end = 0; // one past the last discharge row (C); = first row of the relaxation (D)
    std::size_t charge_begin = 0;  // first charge row (F); row charge_begin-1 is E
    std::size_t charge_end = 0;    // one past the last charge row (G); = first row of the charge relaxation (H)
    std::size_t end = 0;           // one past the last row of the charge relaxation
    double ocv_v = 0.0;            // voltage at the end of the long rest (A), thesis eq. 3.1
    double rest_duration_s = 0.0;  // duration of the long rest
    double discharge_current_a = 0.0;  // mean current of the discharge pulse (negative: BDF, + = charge)
    double charge_current_a = 0.0;     // mean current of the charge pulse (positive)
    double discharge_duration_s = 0.0, discharge_relaxation_s = 0.0;
    double charge_duration_s = 0.0, charge_relaxation_s = 0.0;
    double discharge_ah = 0.0;  // charge moved by the discharge pulse (negative)
    double charge_ah = 0.0;     // charge moved by the charge pulse (positive)
    bool discharge_cv = false;  // the discharge pulse hit the lower voltage limit and its current tapered
    bool charge_cv = false;     // the charge pulse hit the upper voltage limit and its current tapered
    bool relaxation_open = false;  // the charge relaxation runs to the end of the window
    // Whether a rest lies on the other side of each R0 step (eq. 3.2: AB, CD, EF, GH); a step into another
    // current moves two directions' R0 at once and is not read.
    bool rest_before_discharge = true, rest_after_discharge = true;
    bool rest_before_charge = true, rest_after_charge = true;
    // One past the last row of the last pulse (G, or C without a charge pulse, or the last of the Other form's
    // pulses): where the relaxation the fits use begins.
    std::size_t pulses_end = 0;

    [[nodiscard]] bool has_charge_pulse() const { return charge_end > charge_begin; }
    // Where a later window has to start to see the next pulse set's long rest: that rest is this set's last
    // phase when it is long (DischargeOnly), else the next set starts after `end`.
    std::size_t next_window_begin = 0;
};

// A CC discharge that moves the SOC between two pulse sets (Table 2.12 step 12).
struct SocStep {
    std::size_t phase_index = 0;      // the discharge phase
    std::size_t pulse_set_index = 0;  // the pulse set it follows
    std::size_t begin = 0, end = 0;
    double charge_ah = 0.0;           // negative
    double mean_current_a = 0.0;
    bool followed_by_long_rest = false;
};

struct RecordingSegments {
    std::vector<Phase> phases;           // contiguous, cover every row
    std::vector<PulseSet> pulse_sets;    // complete pulse sets, in time order
    std::vector<Phase> long_rests;       // copies of the LongRest phases
    std::vector<Phase> cc_discharges;    // copies of the Discharge phases (SOC steps and pilot included)
    std::optional<Phase> pilot_discharge;  // first full discharge after a CCCV charge and a rest
    std::vector<SocStep> soc_steps;
    std::vector<double> charge_ah;       // charge moved up to every row, Ah (cumulative_charge_ah: charging positive)
};

// What a phase of `direction` (+1 charge, -1 discharge, 0 rest) lasting duration_s is (one rule for every caller:
// a rest of long_rest_s with 1 % slack is long, a current phase of at most pulse_max_s is a pulse).
PhaseKind classify_phase(int direction, double duration_s, const SegmentOptions& options = {});

// Whether the phases from i on make a complete pulse set, and of which form (PulseSetForm; the thesis form is
// tried first); how many phases it spans in *phase_count. A set is complete when what follows it is known: the
// thesis form when its last rest lasted min_relaxation_s, the others when the next phase has begun.
// segment_recording's test, and `cellbench check`'s on a program's steps.
std::optional<PulseSetForm> pulse_set_form(const std::vector<Phase>& phases, std::size_t i,
                                           const SegmentOptions& options = {}, std::size_t* phase_count = nullptr);
inline bool begins_pulse_set(const std::vector<Phase>& phases, std::size_t i, const SegmentOptions& options = {}) {
    return pulse_set_form(phases, i, options).has_value();
}

// Splits a recording (or a window of one) into phases and finds what they make up. Never throws on odd
// input: an empty recording gives empty results.
RecordingSegments segment_recording(const Recording& rec, const SegmentOptions& options = {});

// The phases alone (first stage of segment_recording).
std::vector<Phase> split_phases(const Recording& rec, const SegmentOptions& options = {});

// Online helper: the last complete pulse set of a window (see the header comment), if any.
std::optional<PulseSet> last_complete_pulse_set(const Recording& window, const SegmentOptions& options = {});

}  // namespace cellbench::estimator
