// Cycler programs: the HPPC layouts (thesis Table 2.12, USABC/FreedomCAR manual, multi-current discharge pulses),
// CC discharges (thesis Table 2.10) and a randomized drive profile; and the per-seed dataset built from them.
#include <algorithm>
#include <cmath>

#include "cellbench/plant/plant.hpp"
#include "rng.hpp"

namespace cellbench::plant {

namespace {

double taper_a(const CellSpec& c) { return c.current_1c_a() / 90.0; }  // 0.05 A at 4.5 A (Table 2.12)

Step rest(double seconds, bool fine = false) {
    Step s;
    s.type = "Rest";
    s.mode = Mode::rest;
    s.duration_s = seconds;
    s.fine_sampling = fine;
    return s;
}
// A current step of the cycler: `direction` +1 charges towards v_max (type "... Chg"), -1 discharges towards v_min
// ("... DChg"); CCCV steps taper at the limit down to taper_a, CC steps end there.
Step current_step(const CellSpec& c, Mode mode, int direction, double current_a, double seconds, bool fine) {
    Step s;
    s.type = std::string(mode == Mode::cccv ? "CCCV " : "CC ") + (direction > 0 ? "Chg" : "DChg");
    s.mode = mode;
    s.current_a = direction * current_a;
    s.voltage_limit_v = direction > 0 ? c.v_max_v : c.v_min_v;
    s.duration_s = seconds;
    if (mode == Mode::cccv) s.cutoff_current_a = taper_a(c);
    s.fine_sampling = fine;
    return s;
}
Step cccv_charge(const CellSpec& c, double current_a, double seconds = kInf, bool fine = false) {
    return current_step(c, Mode::cccv, +1, current_a, seconds, fine);
}
Step cccv_discharge(const CellSpec& c, double current_a, double seconds, bool fine) {
    return current_step(c, Mode::cccv, -1, current_a, seconds, fine);
}
Step cc_discharge(const CellSpec& c, double current_a, double seconds = kInf, bool fine = false) {
    return current_step(c, Mode::cc, -1, current_a, seconds, fine);
}
Step cc_charge(const CellSpec& c, double current_a, double seconds = kInf, bool fine = false) {
    return current_step(c, Mode::cc, +1, current_a, seconds, fine);
}
// Ah of a SOC step of `fraction` (10 % unless given) of `reference_ah`, less what the pulse set's last
// `pulse_steps` steps already moved in the step's direction (`sign` -1: a discharging step, +1: a charging one).
std::function<double(const std::vector<StepResult>&)> soc_step_ah(std::function<double(const std::vector<StepResult>&)> reference_ah,
                                                                  std::size_t pulse_steps, double fraction = 0.1,
                                                                  double sign = -1.0) {
    return [reference_ah, pulse_steps, fraction, sign](const std::vector<StepResult>& done) {
        double net = 0.0;  // signed, + charge
        for (std::size_t k = done.size() - std::min(done.size(), pulse_steps); k < done.size(); ++k) net += done[k].ah;
        return std::max(0.0, fraction * reference_ah(done) - sign * net);
    };
}

}  // namespace

// The random layout: an HPPC whose structure is drawn by seed from what labs run (RandomLayout, plant.hpp).
RandomLayout draw_random_layout(std::uint64_t seed, double sample_s) {
    Rng rng(seed, 13);
    RandomLayout l;
    static constexpr double kSteps[] = {0.05, 0.1, 0.1, 0.2};
    static constexpr double kStepRates[] = {1.0 / 3.0, 0.5, 1.0};
    static constexpr double kRestsAfterStep[] = {900.0, 1800.0, 3600.0};
    static constexpr double kDischargePulses[] = {2.0, 10.0, 18.0, 30.0};
    static constexpr double kChargePulses[] = {0.0, 2.0, 10.0};
    static constexpr double kPulseRests[] = {0.0, 20.0, 40.0};
    l.upward = rng.uniform01() < 0.25;
    l.soc_step = kSteps[rng.index(4)];
    l.step_rate_c = kStepRates[rng.index(3)];
    l.rest_after_step_s = kRestsAfterStep[rng.index(3)];
    l.pilot = rng.index(2) == 0;
    l.discharge_pulse_s = kDischargePulses[rng.index(4)];
    l.charge_pulse_s = kChargePulses[rng.index(3)];
    l.rest_between_s = kPulseRests[rng.index(3)];
    // A lab logs a pulse with at least ten samples: shorter pulses become 10 samples long.
    l.discharge_pulse_s = std::max(l.discharge_pulse_s, 10.0 * sample_s);
    if (l.charge_pulse_s > 0.0) l.charge_pulse_s = std::max(l.charge_pulse_s, 10.0 * sample_s);
    l.rest_after_pulses_s = rng.index(2) == 0 ? 0.0 : 40.0;
    l.charge_first = rng.index(4) == 0;
    l.discharge_rate_c = std::round(rng.uniform(0.5, 3.0) * 4.0) / 4.0;
    l.charge_rate_c = std::round(rng.uniform(0.25, 1.0) * l.discharge_rate_c * 4.0) / 4.0;
    if (l.charge_rate_c <= 0.0) l.charge_rate_c = 0.25;
    l.currents_per_level = rng.index(3) == 0 ? 2 : 1;
    return l;
}


GittLayout draw_gitt_layout(std::uint64_t seed) {
    Rng rng(seed, 14);
    GittLayout l;
    static constexpr double kRates[] = {0.1, 0.2, 1.0 / 3.0};
    l.rate_c = kRates[rng.index(3)];
    l.soc_step = rng.index(2) == 0 ? 0.05 : 0.1;
    l.rest_s = rng.index(2) == 0 ? 1800.0 : 3600.0;
    l.upward = rng.index(2) == 0;
    return l;
}

Program hppc_program(const CellSpec& c, Layout layout, const PlantOptions& options) {
    const double i1c = c.current_1c_a();
    Program p;
    switch (layout) {
        case Layout::thesis: {  // Table 2.12
            p.push_back(rest(10.0));                  // 1
            p.push_back(cccv_charge(c, i1c));         // 2 full charge
            p.push_back(rest(600.0));                 // 3
            p.push_back(cc_discharge(c, i1c));        // 4 pilot discharge: capacity C4
            p.push_back(rest(3600.0));                // 5
            p.push_back(cccv_charge(c, i1c));         // 6
            p.push_back(rest(3600.0));                // 7
            auto c4 = [](const std::vector<StepResult>& done) { return std::abs(done.at(3).ah); };
            for (int set = 0; set < 11; ++set) {      // 14: steps 8-13, 11 times
                p.push_back(cccv_discharge(c, i1c, options.thesis_discharge_pulse_s, true));  // 8
                p.push_back(rest(40.0, true));                                                 // 9
                p.push_back(cccv_charge(c, i1c, 10.0, true));                                  // 10
                p.push_back(rest(40.0, true));                                                 // 11
                Step step = cc_discharge(c, i1c);                                              // 12: C4*0.1 - C8 + C10
                step.ah_limit = soc_step_ah(c4, 4);
                p.push_back(step);
                p.push_back(rest(3600.0));                                                     // 13
            }
            Step final_discharge = cc_discharge(c, i1c);  // 15
            final_discharge.tail = true;
            p.push_back(final_discharge);
            p.push_back(rest(1800.0));  // 16
            break;
        }
        case Layout::usabc: {  // USABC/FreedomCAR manual HPPC, no pilot discharge (capacity: rated)
            Rng rng(c.seed, 11);
            const double step_rate = rng.index(2) == 0 ? 1.0 / 3.0 : 1.0;
            const double rated = c.nominal_capacity_ah;
            p.push_back(rest(10.0));
            p.push_back(cccv_charge(c, i1c));
            p.push_back(rest(3600.0));
            for (int level = 0; level < 10; ++level) {
                // Pulses held for their full time, the current clamped (CV) at a voltage limit.
                Step pulse = cccv_discharge(c, i1c, 30.0, true);
                pulse.cutoff_current_a = 0.0;
                p.push_back(pulse);                                   // discharge pulse
                p.push_back(rest(40.0, true));
                Step regen = cccv_charge(c, 0.75 * i1c, 10.0, true);  // regen pulse at 0.75x, no rest after it
                regen.cutoff_current_a = 0.0;
                p.push_back(regen);
                Step step = cc_discharge(c, step_rate * i1c, kInf, true);
                step.ah_limit = soc_step_ah([rated](const std::vector<StepResult>&) { return rated; }, 3);
                step.end_loop_on_cutoff = true;
                p.push_back(step);
                p.push_back(rest(3600.0));
            }
            Step final_discharge = cc_discharge(c, i1c / 3.0);
            final_discharge.tail = true;
            p.push_back(final_discharge);
            p.push_back(rest(1800.0));
            break;
        }
        case Layout::random: {
            const RandomLayout l = draw_random_layout(c.seed, c.measurement.sample_s);
            const double rated = c.nominal_capacity_ah;
            p.push_back(rest(10.0));
            p.push_back(cccv_charge(c, i1c));
            p.push_back(rest(1800.0));
            if (l.pilot || l.upward) {  // a capacity test first (an upward test starts from empty after it anyway)
                p.push_back(cc_discharge(c, l.step_rate_c * i1c));
                p.push_back(rest(1800.0));
                if (!l.upward) {
                    p.push_back(cccv_charge(c, i1c));
                    p.push_back(rest(1800.0));
                }
            }
            const int levels = static_cast<int>(std::round(1.0 / l.soc_step));  // 100 % .. one step (or up to 100 %)
            if (l.upward) {  // from empty: the first level one step up
                Step first_step = cc_charge(c, l.step_rate_c * i1c, kInf, true);
                first_step.ah_limit = soc_step_ah([rated](const std::vector<StepResult>&) { return rated; }, 0, l.soc_step, 1.0);
                p.push_back(first_step);
                p.push_back(rest(l.rest_after_step_s));
            }
            for (int level = 0; level < levels; ++level) {
                std::size_t set_steps = 0;
                for (int k = 0; k < l.currents_per_level; ++k) {
                    const double scale = k == 0 ? 1.0 : 0.5;
                    Step dis = cccv_discharge(c, scale * l.discharge_rate_c * i1c, l.discharge_pulse_s, true);
                    dis.cutoff_current_a = 0.0;
                    Step chg;
                    const bool has_charge = l.charge_pulse_s > 0.0;
                    if (has_charge) {
                        chg = cccv_charge(c, scale * l.charge_rate_c * i1c, l.charge_pulse_s, true);
                        chg.cutoff_current_a = 0.0;
                    }
                    const Step& first = l.charge_first && has_charge ? chg : dis;
                    const Step& second = l.charge_first && has_charge ? dis : chg;
                    p.push_back(first), ++set_steps;
                    if (has_charge) {
                        if (l.rest_between_s > 0.0) p.push_back(rest(l.rest_between_s, true)), ++set_steps;
                        p.push_back(second), ++set_steps;
                    }
                    const bool last = k + 1 == l.currents_per_level;
                    const double after = last ? l.rest_after_pulses_s : std::max(40.0, l.rest_after_pulses_s);
                    if (after > 0.0) p.push_back(rest(after, true)), ++set_steps;
                }
                const auto reference = [rated](const std::vector<StepResult>&) { return rated; };
                Step step = l.upward ? cc_charge(c, l.step_rate_c * i1c, kInf, true)
                                     : cc_discharge(c, l.step_rate_c * i1c, kInf, true);
                step.ah_limit = soc_step_ah(reference, set_steps, l.soc_step, l.upward ? 1.0 : -1.0);
                step.end_loop_on_cutoff = true;
                p.push_back(step);
                p.push_back(rest(l.rest_after_step_s));
            }
            Step final_step = l.upward ? cccv_charge(c, i1c) : cc_discharge(c, i1c / 3.0);
            final_step.tail = true;
            p.push_back(final_step);
            p.push_back(rest(1800.0));
            break;
        }
        case Layout::gitt: {
            const GittLayout l = draw_gitt_layout(c.seed);
            const double rated = c.nominal_capacity_ah;
            const auto reference = [rated](const std::vector<StepResult>&) { return rated; };
            p.push_back(rest(10.0));
            p.push_back(cccv_charge(c, i1c));
            p.push_back(rest(3600.0));
            const int levels = static_cast<int>(std::round(1.0 / l.soc_step)) + 1;  // the last one ends at the cut-off
            for (int level = 0; level < levels; ++level) {
                Step step = cc_discharge(c, l.rate_c * i1c, kInf, true);
                step.ah_limit = soc_step_ah(reference, 0, l.soc_step);
                step.end_loop_on_cutoff = true;
                p.push_back(step);
                p.push_back(rest(l.rest_s));
            }
            Step empty = rest(l.rest_s);
            empty.tail = true;
            p.push_back(empty);
            if (l.upward)
                for (int level = 0; level < levels; ++level) {
                    Step step = cc_charge(c, l.rate_c * i1c, kInf, true);
                    step.ah_limit = soc_step_ah(reference, 0, l.soc_step, 1.0);
                    p.push_back(step);  // the last one ends at the upper limit
                    p.push_back(rest(l.rest_s));
                }
            break;
        }
        case Layout::multi: {  // discharge-only pulses at five currents per level (Panasonic 18650PF style)
            const double rated = c.nominal_capacity_ah;
            static constexpr double kRates[] = {0.5, 1.0, 2.0, 3.0, 4.0};
            p.push_back(rest(10.0));
            p.push_back(cccv_charge(c, i1c));
            p.push_back(rest(3600.0));
            for (int level = 0; level < 10; ++level) {
                for (std::size_t k = 0; k < 5; ++k) {
                    p.push_back(cc_discharge(c, kRates[k] * i1c, 10.0, true));
                    p.push_back(rest(k + 1 < 5 ? 600.0 : 60.0));
                }
                Step step = cc_discharge(c, i1c / 3.0);
                step.ah_limit = soc_step_ah([rated](const std::vector<StepResult>&) { return rated; }, 10);
                step.end_loop_on_cutoff = true;
                p.push_back(step);
                p.push_back(rest(1800.0));
            }
            Step final_discharge = cc_discharge(c, i1c / 3.0);
            final_discharge.tail = true;
            p.push_back(final_discharge);
            p.push_back(rest(1800.0));
            break;
        }
    }
    return p;
}

Program cc_discharge_program(const CellSpec& c, double c_rate) {  // Table 2.10
    const double i1c = c.current_1c_a();
    const bool low = c_rate < 0.5;
    Program p;
    p.push_back(rest(10.0));
    p.push_back(cccv_charge(c, i1c));
    p.push_back(rest(low ? 3600.0 : 600.0));
    p.push_back(cc_discharge(c, c_rate * i1c, kInf, !low));
    p.push_back(rest(low ? 3600.0 : 1800.0));  // the cool-down after a hot discharge
    return p;
}

Program drive_program(const CellSpec& c, std::uint64_t seed) {
    Rng rng(seed, 21);
    const double i1c = c.current_1c_a();
    const double soc_start = 0.95, soc_end = 0.15, duration_s = 3600.0;
    Program p;
    p.push_back(rest(300.0, true));
    double t = 0.0, planned = soc_start, level = 0.0;
    while (t < duration_s) {
        const double hold = std::round(rng.uniform(5.0, 60.0));
        if (rng.uniform01() < 0.15) {
            level = 0.0;
            p.push_back(rest(hold, true));
        } else {
            const double target = soc_start - (soc_start - soc_end) * t / duration_s;
            const double mean = std::clamp(-0.85 - 8.0 * (planned - target), -3.0, 1.0);
            level = std::clamp(0.5 * level + 0.5 * mean + 1.3 * rng.normal(), -4.0, 2.0);
            level = std::round(level * 20.0) / 20.0;  // the profile's set values: 0.05C steps
            if (level == 0.0) level = -0.05;
            Step s = level > 0.0 ? cccv_charge(c, level * i1c, hold, true) : cccv_discharge(c, -level * i1c, hold, true);
            s.cutoff_current_a = 0.0;  // the profile holds the step time; the limits only taper the current
            p.push_back(s);
            planned += level * hold / 3600.0;
        }
        t += hold;
    }
    p.push_back(rest(600.0, true));
    return p;
}

// ---------------------------------------------------------------------------------------------------------------
namespace {
InitialState bench_start(const CellSpec& c, std::uint64_t stream) {
    Rng rng(c.seed, stream);
    return {rng.uniform(0.3, 0.6), false};
}
}  // namespace

Recording generate_hppc(const CellSpec& c, const PlantOptions& o) {
    return simulate(c, hppc_program(c, o.layout, o), bench_start(c, 31), false, splitmix64(c.seed) ^ 1, o.noise, "hppc");
}
Recording generate_cc_low(const CellSpec& c, const PlantOptions& o) {
    return simulate(c, cc_discharge_program(c, 0.05), bench_start(c, 32), false, splitmix64(c.seed) ^ 2, o.noise, "cc_low");
}
Recording generate_cc_high(const CellSpec& c, const PlantOptions& o) {
    Rng rng(c.seed, 33);
    // 3C or 4C by seed, raised (up to 6C) until the discharge heats the cell by more than 10 K by estimate, lowered
    // (down to 2C) where it would heat it by more than ~30 K.
    double rate = rng.index(2) == 0 ? 3.0 : 4.0;
    auto rise_k = [&](double r) {
        const double soc = 0.5, i = r * c.current_1c_a();
        const double p = i * i * (c.r0_ohm(soc, Direction::discharge) + c.r1_ohm(soc, Direction::discharge) +
                                  c.r2_ohm(soc, Direction::discharge));
        const double seconds = 0.9 * 3600.0 / r;
        return p * c.r_th_k_per_w * (1.0 - std::exp(-seconds / (c.r_th_k_per_w * c.c_th_j_per_k)));
    };
    while (rate < 6.0 && rise_k(rate) < 13.0) rate += 1.0;
    while (rate > 2.0 && rise_k(rate) > 30.0) rate -= 0.5;  // nor beyond what a cell survives
    return simulate(c, cc_discharge_program(c, rate), bench_start(c, 34), false, splitmix64(c.seed) ^ 3, o.noise, "cc_high");
}
Recording generate_drive(const CellSpec& c, const PlantOptions& o) {
    Rng rng(c.seed, 35);
    const InitialState start{rng.uniform(0.9, 0.98), true};
    return simulate(c, drive_program(c, c.seed), start, true, splitmix64(c.seed) ^ 4, o.noise, "drive");
}

Recording generate_second_drive(const CellSpec& c, const PlantOptions& o) {
    Rng rng(c.seed, 36);
    const InitialState start{rng.uniform(0.9, 0.98), true};
    return simulate(c, drive_program(c, splitmix64(c.seed) ^ 0x5eedULL), start, true, splitmix64(c.seed) ^ 5, o.noise,
                    "drive2");
}

Dataset generate(const PlantOptions& o) {
    Dataset d;
    d.cell = make_cell(o);
    d.truth = make_truth(d.cell, o.layout);
    d.hppc = generate_hppc(d.cell, o);
    d.cc_low = generate_cc_low(d.cell, o);
    d.cc_high = generate_cc_high(d.cell, o);
    d.drive = generate_drive(d.cell, o);
    return d;
}

}  // namespace cellbench::plant
