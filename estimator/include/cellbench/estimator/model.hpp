#pragma once
// The electrothermal cell model: Thevenin 2RC with Coulomb counting, and a first-order (lumped) thermal
// model with irreversible heat I*(V - OCV) and reversible heat I*T*dU/dT (thesis eq. 5.2), heat flow out
// (T - T_amb)/R_th. Exact ZOH discretization over each sample interval (see electrical.hpp for the sampling
// convention), whatever the interval length.
//
// The thermal step is exact too: with the current held, the RC voltages are exponentials in time, so the
// heat input over the interval is a constant plus exponentials and the linear thermal ODE is solved in
// closed form (no Euler step, no averaging).
//
// Extensions (params.hpp, the physics `diagnose` adds) change the step as follows:
//  - resistance_temperature: R0, R1, R2 scaled by an Arrhenius factor of the (core) temperature at the start
//    of each interval (two-way electrothermal coupling); capacitances held, so time constants scale too;
//  - resistance_current: R1, R2 scaled by asinh(x)/x, x = |I|/(2 I0), relative to the reference current;
//  - series_resistance_offset: added to R0 at the terminals (its heat is dissipated outside the cell); extra_rc: a third pair driven by the whole current;
//  - ocv_hysteresis: V += h, h relaxing towards sign(I)*M exponentially in charge throughput (exact);
//  - capacity_error: Coulomb counting with the scaled capacity; entropic_heat: dU/dT added to the table;
//  - ambient_drift: T_amb + offset + rate*t; heat_flux_sensor_gain: the sensor reading is gain * true;
//  - thermal_second_order: core and surface nodes (heat into the core, surface to ambient via R_th), solved
//    exactly for the interval's mean heat (matrix exponential of the 2x2 system).
#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"

#include <cstddef>
#include <vector>

namespace cellbench::estimator {

struct CellState {
    double soc = 1.0;            // fraction of capacity_ah
    RcVoltages<double> rc;       // RC voltages of both directions (electrical.hpp)
    double temperature_c = 25.0; // surface temperature (what the sensors see); the lumped one without core node
    double core_temperature_c = kNaN;  // core node (thermal_second_order), NaN without it
    double extra_rc_v = 0.0;     // extra_rc pair
    double hysteresis_v = 0.0;   // ocv_hysteresis state
    double elapsed_s = 0.0;      // time since the start (ambient_drift)
};

struct CellOutputs {
    double voltage_v = 0.0;
    double ocv_v = 0.0;
    double heat_irreversible_w = 0.0;  // mean over the interval
    double heat_reversible_w = 0.0;    // mean over the interval
    double heat_flow_out_w = 0.0;      // (T - T_amb)/R_th at the end of the interval
    double sensor_heat_flow_w = 0.0;   // what the heat flux sensor reports (heat_flux_sensor_gain applied)
    double ambient_c = 0.0;            // ambient in force (ambient_drift applied)
};

class CellModel {
public:
    explicit CellModel(ParameterSet params);

    [[nodiscard]] const ParameterSet& params() const { return params_; }

    // Advances the state over an interval of dt_s during which current_a flowed and the ambient was
    // ambient_c; returns the outputs at the end of the interval. dt_s == 0 only evaluates the outputs.
    CellOutputs step(CellState& state, double current_a, double ambient_c, double dt_s) const;

    // A state at rest: RC voltages zero, SOC from the rested terminal voltage (inverse OCV).
    [[nodiscard]] CellState rested_state(double terminal_voltage_v, double temperature_c) const;

    // Resistance scale factor at a cell temperature (1 without the resistance_temperature extension).
    [[nodiscard]] double resistance_factor(double temperature_c) const;
    // Polarization (R1, R2) scale factor at a current (1 without the resistance_current extension).
    [[nodiscard]] double current_factor(double current_a) const;
    [[nodiscard]] double capacity_ah() const;

private:
    ParameterSet params_;
    // asinh(x)/x at the reference current of resistance_current (1 without it): the denominator of every
    // current_factor, computed once (a drive cycle changes its current at every row).
    double reference_current_ratio_ = 1.0;
};

// The fast path of CellModel::step for long runs (simulate(), diagnose, the fits' simulations): the same exact
// ZOH step, with what repeats from one sample to the next cached instead of recomputed -- the tables' segment
// around the SOC as straight lines (one for the ten R/C columns, one for the OCV, one for the entropic table;
// re-placed when SOC leaves the segment), the parameters while SOC,
// temperature factor and current factor are unchanged (rests), and exp/expm1 of each (rate * dt): an exact
// re-evaluation when it moved far, else the last exact value times a Taylor series of the small change
// (|change| <= 1e-2, truncation < 1e-18 relative). The heat integrals reuse the same exponentials
// ((e^-a dt - e^-b dt)/(b - a) in place of a third exponential, exact formula kept where a ~ b). Results equal
// CellModel::step to ~1e-14 relative (tests/unit/model_fast_test.cpp pins it). Holds a reference to the model;
// not thread-safe (one per thread).
class CellStepper {
public:
    explicit CellStepper(const CellModel& model);
    CellOutputs step(CellState& state, double current_a, double ambient_c, double dt_s) {
        return step(state, current_a, ambient_c, dt_s, current_a);
    }
    // The state advanced over dt_s by current_a (the interval's mean current), the outputs read with the row's
    // own current output_current_a (its R0 drop): a row that opens a step shows the new current while the old one
    // flowed over the interval before it (coulomb.hpp).
    CellOutputs step(CellState& state, double current_a, double ambient_c, double dt_s, double output_current_a);

    // exp(-x) and expm1(-x) for x = rate * dt, reusing the last exact evaluation (see above).
    struct DecayCache {
        double x0 = kNaN, e0 = 1.0, m0 = 0.0;
        void eval(double x, double& e, double& m);
    };

    // K table columns over one SOC axis as straight lines on the segment last located: value = base + w slope,
    // w = (soc - x0) / dx, valid while lo <= soc < hi (a held end: slope 0). Re-located when SOC leaves it.
    template <std::size_t K>
    struct SegmentLines {
        double lo = kNaN, hi = kNaN, x0 = 0.0, inv_dx = 0.0;
        double base[K]{}, slope[K]{};
        std::size_t bracket = 0;
    };

private:
    void refresh_parameters(double soc, double f_t, double f_i);

    const CellModel& model_;
    const ParameterSet& p_;
    // The ten R/C columns (discharge r0 r1 c1 r2 c2, then charge) held at the table's ends; the entropic table
    // (held); the OCV (extrapolated beyond the ends).
    SegmentLines<10> rc_lines_;
    SegmentLines<1> ehc_lines_, ocv_lines_;
    // Parameters in force (after the factors) and the key they were computed for.
    double key_soc_ = kNaN, key_ft_ = kNaN, key_fi_ = kNaN;
    Rc2Params<double> pd_{}, pc_{};
    double ehc_ = 0.0;
    double rate_[5] = {1, 1, 1, 1, 1}, tau_[5] = {1, 1, 1, 1, 1};
    DecayCache pair_[5], beta_;
    double t_inner_key_ = kNaN, f_t_ = 1.0;
    double i_key_ = kNaN, f_i_ = 1.0;
    // Reciprocals of the constants the step divides by: 1/C_th (K/J), 1/R_th (W/K), SOC per ampere-second.
    double inv_c_th_per_j_ = 1.0, inv_r_th_w_per_k_ = 1.0, soc_per_a_s_ = 0.0;
};

}  // namespace cellbench::estimator
