#include "cellbench/sequencer/safety_rules.hpp"

#include <cmath>
#include <cstdio>

namespace cellbench::sequencer {

namespace {

std::string fmt(const char* f, double x) {
    char b[96];
    std::snprintf(b, sizeof b, f, x);
    return b;
}

class VoltageWindow final : public SafetyRule {
public:
    VoltageWindow(double min_v, double max_v) : min_v_(min_v), max_v_(max_v) {}
    const char* name() const override { return "voltage_window"; }
    AbortReason on_cycler(const CyclerSample& s, bool, const SafetyContext&) override {
        if (s.voltage_v >= min_v_ && s.voltage_v <= max_v_) return {};
        return "voltage " + fmt("%.3f V", s.voltage_v) + " outside the safety window " + fmt("%.2f", min_v_) +
               fmt("-%.2f V", max_v_);
    }

private:
    double min_v_, max_v_;
};

class CurrentLimit final : public SafetyRule {
public:
    explicit CurrentLimit(double max_a) : max_a_(max_a) {}
    const char* name() const override { return "current_limit"; }
    AbortReason on_cycler(const CyclerSample& s, bool, const SafetyContext&) override {
        if (!(std::abs(s.current_a) > max_a_)) return {};
        return "current " + fmt("%.2f A", s.current_a) + " over the limit " + fmt("%.1f A", max_a_);
    }

private:
    double max_a_;
};

// The tester's own protection tripped: it says so in its live status (its recorded rows do not).
class CyclerProtect final : public SafetyRule {
public:
    const char* name() const override { return "cycler_protect"; }
    AbortReason on_cycler(const CyclerSample& s, bool record, const SafetyContext&) override {
        if (record || s.status != "protect") return {};
        return std::string("the cycler went to protect");
    }
};

class CellTemperature final : public SafetyRule {
public:
    explicit CellTemperature(double max_c) : max_c_(max_c) {}
    const char* name() const override { return "cell_temperature"; }
    AbortReason on_daq(const DaqSample& s, const SafetyContext&) override {
        for (double temp : {s.surface_c, s.t1_c, s.t2_c})
            if (std::isfinite(temp) && temp > max_c_)
                return "cell temperature " + fmt("%.2f degC", temp) + " over the maximum " + fmt("%.1f degC", max_c_);
        return {};
    }

private:
    double max_c_;
};

class ChamberAlarm final : public SafetyRule {
public:
    const char* name() const override { return "chamber_alarm"; }
    AbortReason on_chamber(const ChamberSample& s, const SafetyContext&) override {
        if (s.alarm_bits == 0) return {};
        return "chamber alarm (bits " + std::to_string(s.alarm_bits) + ")";
    }
};

// Chamber air off the program's set point, once it has reached it (within 0.5 K) after the last change.
class ChamberDeviation final : public SafetyRule {
public:
    explicit ChamberDeviation(double max_k) : max_k_(max_k) {}
    const char* name() const override { return "chamber_deviation"; }
    void reset() override {
        settled_ = false;
        target_c_ = kNaN;
    }
    AbortReason on_chamber(const ChamberSample& s, const SafetyContext& ctx) override {
        if (!std::isfinite(ctx.chamber_target_c)) return {};
        if (ctx.chamber_target_c != target_c_) {  // a new set point: the air has to get there first
            target_c_ = ctx.chamber_target_c;
            settled_ = false;
        }
        const double dev = std::abs(s.air_c - target_c_);
        if (!settled_ && dev < 0.5) settled_ = true;
        if (!settled_ || !(dev > max_k_)) return {};
        return "chamber air " + fmt("%.2f degC", s.air_c) + " off its set point " + fmt("%.1f degC", target_c_) +
               " by more than " + fmt("%.1f K", max_k_);
    }

private:
    double max_k_;
    bool settled_ = false;
    double target_c_ = kNaN;
};

// No reading from one instrument for longer than its grace (bench seconds), counted from the run's start
// until its first reading.
class InstrumentSilence final : public SafetyRule {
public:
    enum class Which { cycler, daq, chamber };
    InstrumentSilence(Which w, double grace_s) : which_(w), grace_s_(grace_s) {}
    const char* name() const override {
        return which_ == Which::cycler ? "cycler_silence" : which_ == Which::daq ? "daq_silence" : "chamber_silence";
    }
    AbortReason on_tick(double t, const SafetyContext& ctx) override {
        const double last = which_ == Which::cycler ? ctx.last_cycler_s
                            : which_ == Which::daq  ? ctx.last_daq_s
                                                    : ctx.last_chamber_s;
        const bool silent = last < 0 ? t - ctx.run_start_s > grace_s_ : t - last > grace_s_;
        if (!silent) return {};
        const std::string g = fmt("%.0f s", grace_s_);
        switch (which_) {
            case Which::cycler: return "no cell voltage: cycler silent for more than " + g;
            case Which::daq: return "no cell temperature for more than " + g;
            case Which::chamber: return "chamber silent for more than " + g;
        }
        return {};
    }

private:
    Which which_;
    double grace_s_;
};

}  // namespace

SafetyRules default_safety_rules(const SafetyLimits& lim) {
    auto grace = [&](double g) { return g > 0 ? g : lim.instrument_loss_grace_s; };
    using W = InstrumentSilence::Which;
    return {std::make_shared<VoltageWindow>(lim.min_voltage_v, lim.max_voltage_v),
            std::make_shared<CurrentLimit>(lim.max_current_a),
            std::make_shared<CyclerProtect>(),
            std::make_shared<CellTemperature>(lim.max_temperature_c),
            std::make_shared<ChamberAlarm>(),
            std::make_shared<ChamberDeviation>(lim.chamber_deviation_c),
            std::make_shared<InstrumentSilence>(W::cycler, grace(lim.cycler_loss_grace_s)),
            std::make_shared<InstrumentSilence>(W::daq, grace(lim.daq_loss_grace_s)),
            std::make_shared<InstrumentSilence>(W::chamber, grace(lim.chamber_loss_grace_s))};
}

}  // namespace cellbench::sequencer
