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
// Two-way coupling: when the parameter set carries the `resistance_temperature` extension, R0, R1 and R2 are
// scaled by an Arrhenius factor of the cell temperature at the start of each interval.
#include "cellbench/estimator/params.hpp"

namespace cellbench::estimator {

struct CellState {
    double soc = 1.0;            // fraction of capacity_ah
    RcVoltages<double> rc;       // RC voltages of both directions (electrical.hpp)
    double temperature_c = 25.0; // lumped cell temperature (what the surface sensor sees in this model)
};

struct CellOutputs {
    double voltage_v = 0.0;
    double ocv_v = 0.0;
    double heat_irreversible_w = 0.0;  // mean over the interval
    double heat_reversible_w = 0.0;    // mean over the interval
    double heat_flow_out_w = 0.0;      // (T - T_amb)/R_th at the end of the interval
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

private:
    ParameterSet params_;
};

}  // namespace cellbench::estimator
