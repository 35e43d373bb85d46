#include "cellbench/sim/plant.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <random>

#include "cellbench/protocol/heat_flux.hpp"
#include "cellbench/sim/pace_gate.hpp"

namespace cellbench::sim {

namespace {

// Longest interval integrated in one exact step. The model freezes its parameters (SOC, temperature) over a
// step and the chamber air feeds the cell as a held ambient, so long steps would lose those couplings.
constexpr double kMaxTickS = 0.1;

// Chamber air without ripple over dt: first order towards target with time constant tau, its rate limited
// to [-down, +up] degC/s. Solved exactly: a linear ramp while the first-order rate would exceed the limit,
// then the exponential (the limit is only active while |target - air| > rate * tau).
double chamber_air_step(double air_c, double target_c, double tau_s, double up_c_per_s, double down_c_per_s,
                        double dt_s) {
    const double error_c = target_c - air_c;
    if (error_c == 0.0 || dt_s <= 0.0) return air_c;
    const double limit_c_per_s = error_c > 0 ? up_c_per_s : down_c_per_s;
    if (limit_c_per_s > 0 && std::isfinite(limit_c_per_s)) {
        const double threshold_c = limit_c_per_s * tau_s;  // error below which first order is slower than the limit
        const double excess_c = std::abs(error_c) - threshold_c;
        if (excess_c > 0) {
            const double ramp_time_s = excess_c / limit_c_per_s;
            const double sign = error_c > 0 ? 1.0 : -1.0;
            if (dt_s <= ramp_time_s) return air_c + sign * limit_c_per_s * dt_s;
            air_c += sign * excess_c;
            dt_s -= ramp_time_s;
        }
    }
    return target_c - (target_c - air_c) * std::exp(-dt_s / tau_s);
}

// Gaussian noise with a sequence fixed by the seed on every platform (std::normal_distribution is not).
class Noise {
public:
    explicit Noise(std::uint32_t seed) : engine_(seed) {}
    double gaussian(double sigma) {
        if (sigma <= 0) return 0.0;
        if (has_spare_) {
            has_spare_ = false;
            return sigma * spare_;
        }
        // Box-Muller on two uniforms in (0, 1].
        const double u1 = uniform(), u2 = uniform();
        const double radius = std::sqrt(-2.0 * std::log(u1));
        const double angle = 2.0 * std::numbers::pi * u2;
        spare_ = radius * std::sin(angle);
        has_spare_ = true;
        return sigma * radius * std::cos(angle);
    }

private:
    double uniform() { return (static_cast<double>(engine_() >> 11) + 1.0) * 0x1.0p-53; }
    std::mt19937_64 engine_;
    double spare_ = 0.0;
    bool has_spare_ = false;
};

}  // namespace

struct BenchPlant::Impl {
    explicit Impl(PlantOptions o)
        : options(std::move(o)), model(options.cell), noise(options.seed) {
        state.soc = options.initial_soc;
        state.temperature_c = options.initial_temperature_c;
        air_base_c = options.initial_temperature_c;
        setpoint_c = options.chamber_setpoint_c;
        cell_voltage_v = cell_voltage_at(current_a);
    }

    mutable std::mutex mutex;
    PlantOptions options;
    estimator::CellModel model;
    estimator::CellState state;
    mutable Noise noise;  // read() draws noise; guarded by mutex

    double now_s = 0.0;
    double current_a = 0.0;
    double hold_until_s = std::numeric_limits<double>::infinity();  // current_a is the cycler's up to here
    double cell_voltage_v = 0.0;  // model terminal voltage (no harness) at now_s and current_a
    double charge_ah = 0.0, energy_wh = 0.0;
    double air_base_c = 0.0;      // chamber air without the control ripple
    double setpoint_c = 0.0;
    bool running = true;
    bool heater_failed = false;

    double ripple_c(double t_s) const {
        if (!running || options.chamber_ripple_c <= 0 || options.chamber_ripple_period_s <= 0) return 0.0;
        return options.chamber_ripple_c * std::sin(2.0 * std::numbers::pi * t_s / options.chamber_ripple_period_s);
    }
    double air_c(double t_s) const { return air_base_c + ripple_c(t_s); }

    double cell_voltage_at(double i_a) const {
        estimator::CellState copy = state;
        return model.step(copy, i_a, air_c(now_s), 0.0).voltage_v;
    }

    void step_chamber(double dt_s) {
        if (running) {
            const double target_c =
                heater_failed ? std::min(setpoint_c, options.lab_temperature_c) : setpoint_c;
            air_base_c = chamber_air_step(air_base_c, target_c, options.chamber_time_constant_s,
                                          options.chamber_ramp_up_c_per_min / 60.0,
                                          options.chamber_ramp_down_c_per_min / 60.0, dt_s);
        } else {
            // No control: free drift, no ramp limit (the insulation is slower than any limit).
            air_base_c = chamber_air_step(air_base_c, options.lab_temperature_c,
                                          options.chamber_stopped_time_constant_s, 0.0, 0.0, dt_s);
        }
    }

    void advance_to(double t_s) {
        t_s = std::min(t_s, hold_until_s);  // what the cell gets after that is the cycler's next decision
        while (now_s < t_s) {
            const double remaining_s = t_s - now_s;
            const double dt_s = std::min(kMaxTickS, remaining_s);
            const double air_start_c = air_c(now_s);
            step_chamber(dt_s);
            now_s = dt_s == remaining_s ? t_s : now_s + dt_s;
            // The cell sees the mean air of the tick as its held ambient.
            const double ambient_c = 0.5 * (air_start_c + air_c(now_s));
            const double v_start_v = cell_voltage_v + options.harness_resistance_ohm * current_a;
            cell_voltage_v = model.step(state, current_a, ambient_c, dt_s).voltage_v;
            const double v_end_v = cell_voltage_v + options.harness_resistance_ohm * current_a;
            charge_ah += current_a * dt_s / 3600.0;
            energy_wh += current_a * 0.5 * (v_start_v + v_end_v) * dt_s / 3600.0;
        }
    }
};

BenchPlant::BenchPlant(PlantOptions options) : impl_(std::make_shared<Impl>(std::move(options))) {}

void BenchPlant::advance_to(double bench_time_s) {
    std::lock_guard lock(impl_->mutex);
    impl_->advance_to(bench_time_s);
}

void BenchPlant::set_current(double current_a, double hold_until_s) {
    std::lock_guard lock(impl_->mutex);
    impl_->current_a = current_a;
    impl_->hold_until_s = std::isnan(hold_until_s) ? std::numeric_limits<double>::infinity() : hold_until_s;
    impl_->cell_voltage_v = impl_->cell_voltage_at(current_a);  // the ohmic step is immediate
}

void BenchPlant::set_chamber_setpoint(double setpoint_c) {
    std::lock_guard lock(impl_->mutex);
    impl_->setpoint_c = setpoint_c;
}

void BenchPlant::set_chamber_running(bool running) {
    std::lock_guard lock(impl_->mutex);
    // Keep the process value continuous: the ripple disappears into (or appears from) the base air.
    const double air_c = impl_->air_c(impl_->now_s);
    impl_->running = running;
    impl_->air_base_c = air_c - impl_->ripple_c(impl_->now_s);
}

void BenchPlant::set_chamber_heater_failed(bool failed) {
    std::lock_guard lock(impl_->mutex);
    impl_->heater_failed = failed;
}

double BenchPlant::voltage_at(double current_a) const {
    std::lock_guard lock(impl_->mutex);
    return impl_->cell_voltage_at(current_a) + impl_->options.harness_resistance_ohm * current_a;
}

PlantReading BenchPlant::read() const {
    std::lock_guard lock(impl_->mutex);
    const Impl& p = *impl_;
    const PlantOptions& o = p.options;
    Noise& noise = p.noise;
    const auto& thermal = p.model.params().thermal;

    PlantReading r;
    r.bench_time_s = p.now_s;
    r.current_a = p.current_a + noise.gaussian(o.current_noise_a);
    r.terminal_voltage_v = p.cell_voltage_v + o.harness_resistance_ohm * p.current_a + noise.gaussian(o.voltage_noise_v);
    r.soc = p.state.soc;
    r.charge_ah = p.charge_ah;
    r.energy_wh = p.energy_wh;
    r.cell_temperature_c = p.state.temperature_c;
    r.surface_type_t_c = p.state.temperature_c + noise.gaussian(o.temperature_noise_c);
    r.terminal_pos_c = p.state.temperature_c + noise.gaussian(o.temperature_noise_c);
    r.terminal_neg_c = p.state.temperature_c + noise.gaussian(o.temperature_noise_c);
    r.chamber_air_c = p.air_c(p.now_s);
    r.chamber_setpoint_c = p.setpoint_c;
    r.chamber_running = p.running;
    // Heat leaving the surface: the model's (T - T_air)/R_th spread over the whole cell surface.
    r.heat_flux_w_per_m2 = (p.state.temperature_c - r.chamber_air_c) / thermal.r_th_k_per_w / thermal.area_m2;
    // The thermopile's output at its true temperature (the inverse of protocol::heat_flux_density_w_per_m2),
    // scaled by the hidden gain error of the sensor.
    r.thermopile_v = r.heat_flux_w_per_m2 * o.heat_flux_sensitivity_v_per_w_per_m2 *
                         (1.0 + protocol::kFhf05SensitivityTempCoeffPerK *
                                 (p.state.temperature_c - protocol::kFhf05CalibrationTemperatureC)) * o.heat_flux_sensor_gain +
                     noise.gaussian(o.thermopile_noise_v);
    return r;
}

double BenchPlant::now_s() const {
    std::lock_guard lock(impl_->mutex);
    return impl_->now_s;
}

// ---- BenchClock -------------------------------------------------------------------------------------------

namespace {
constexpr std::size_t kTrail = 2048;  // pace()/hold() calls kept for at() (about 20 s at the daemon's 10 ms)
constexpr std::size_t kHistory = 11;  // about 10 s of (wall, bench) pairs at 1 s spacing
}  // namespace

BenchClock::BenchClock(double time_scale, double bench_start_s)
    : time_scale_(time_scale > 0 && std::isfinite(time_scale) ? time_scale : 1.0),
      bench_start_s_(bench_start_s),
      wall_start_(WallClock::now()),
      anchor_wall_(wall_start_),
      anchor_bench_(bench_start_s),
      last_read_(bench_start_s),
      rate_(time_scale_) {}

BenchClock::BenchClock(double time_scale, double bench_start_s, Paced paced) : BenchClock(time_scale, bench_start_s) {
    paced_ = true;
    max_step_wall_s_ = paced.max_step_wall_s > 0 && std::isfinite(paced.max_step_wall_s) ? paced.max_step_wall_s : 0.1;
    history_.emplace_back(anchor_wall_, anchor_bench_);
}

double BenchClock::max_step_s() const {
    return paced_ ? max_step_wall_s_ * time_scale_ : std::numeric_limits<double>::infinity();
}

double BenchClock::read_locked(WallClock::time_point wall) const {
    if (wall >= anchor_wall_) {
        // at the last step's rate (0 when held): no reader runs ahead of the pacer by more than one step
        return anchor_bench_ + std::min(wall_seconds(wall - anchor_wall_), max_step_wall_s_) * rate_;
    }
    // An instant before the last pace(): between the two pace()/hold() calls around it (every call of the last
    // ~20 s is kept): linear at the scale when that step was whole, squeezed when it was bounded, flat when held.
    const auto after = std::upper_bound(trail_.begin(), trail_.end(), wall,
                                        [](WallClock::time_point w, const auto& p) { return w < p.first; });
    if (after == trail_.begin()) {
        const auto& [w0, b0] = trail_.empty() ? std::pair{anchor_wall_, anchor_bench_} : trail_.front();
        return b0 - wall_seconds(w0 - wall) * time_scale_;  // older than the trail: extrapolated
    }
    const auto& [w1, b1] = *std::prev(after);
    if (after == trail_.end()) return b1;
    const auto& [w2, b2] = *after;
    const double span = wall_seconds(w2 - w1);
    return span > 0 ? b1 + (b2 - b1) * std::min(1.0, wall_seconds(wall - w1) / span) : b1;
}

double BenchClock::at(WallClock::time_point wall) const {
    if (!paced_) return bench_start_s_ + time_scale_ * wall_seconds(wall - wall_start_);
    std::lock_guard lock(mutex_);
    const double v = read_locked(wall);
    if (wall >= anchor_wall_) {  // "now": never earlier than what a reader saw before
        last_read_ = std::max(last_read_, v);
        return last_read_;
    }
    return v;
}

BenchClock::WallClock::time_point BenchClock::wall_at(double bench_time_s) const {
    if (!paced_)
        return wall_start_ + std::chrono::duration_cast<WallClock::duration>(
                                 std::chrono::duration<double>((bench_time_s - bench_start_s_) / time_scale_));
    std::lock_guard lock(mutex_);
    return anchor_wall_ + std::chrono::duration_cast<WallClock::duration>(
                              std::chrono::duration<double>((bench_time_s - anchor_bench_) / time_scale_));
}

double BenchClock::pace(WallClock::time_point wall) {
    if (!paced_) return at(wall);
    std::lock_guard lock(mutex_);
    return advance_locked(wall, time_scale_);
}

double BenchClock::pace(WallClock::time_point wall, double scale) {
    if (!paced_) return at(wall);
    std::lock_guard lock(mutex_);
    return advance_locked(wall, std::isfinite(scale) ? std::clamp(scale, 0.0, time_scale_) : time_scale_);
}

double BenchClock::hold(WallClock::time_point wall) {
    if (!paced_) return at(wall);
    std::lock_guard lock(mutex_);
    return advance_locked(wall, 0.0);
}

double BenchClock::advance_locked(WallClock::time_point wall, double rate) {
    if (wall <= anchor_wall_) {
        rate_ = std::min(rate_, rate);
        return anchor_bench_;
    }
    const double dt = wall_seconds(wall - anchor_wall_);
    const double step = std::min(dt, max_step_wall_s_);
    const double next = std::max(anchor_bench_ + step * rate, last_read_);
    lost_wall_s_ += dt - (next - anchor_bench_) / time_scale_;
    if (trail_.empty()) trail_.emplace_back(anchor_wall_, anchor_bench_);
    trail_.emplace_back(wall, next);
    while (trail_.size() > kTrail) trail_.pop_front();
    anchor_wall_ = wall;
    anchor_bench_ = next;
    last_read_ = anchor_bench_;
    rate_ = rate;
    if (wall_seconds(wall - history_.back().first) >= 1.0) {
        history_.emplace_back(wall, anchor_bench_);
        while (history_.size() > kHistory) history_.pop_front();
    }
    return anchor_bench_;
}

double BenchClock::achieved_scale() const {
    if (!paced_) return time_scale_;
    std::lock_guard lock(mutex_);
    const double span = wall_seconds(anchor_wall_ - history_.front().first);
    if (span < 1.0) return time_scale_;
    return (anchor_bench_ - history_.front().second) / span;
}

double BenchClock::lost_wall_s() const {
    if (!paced_) return 0.0;
    std::lock_guard lock(mutex_);
    return lost_wall_s_;
}

}  // namespace cellbench::sim
