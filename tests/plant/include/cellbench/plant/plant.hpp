#pragma once
// The independent validation plant (issues 11 and 13): synthetic bench recordings with known truth, from code
// that shares nothing with estimator/, drivers/sim/ or tests/unit/hppc_synthetic.hpp.
//
// Physics (continuous time, integrated by Boost.Odeint's controlled dense-output Dormand-Prince 5(4) with tight
// tolerances, piecewise between current breakpoints, so a current step is exact):
//   V = OCV_ref(soc) + dU/dT(soc)·(T - T_ref) + h + I·(R0 + R_series) + v1 + v2 (+ v3 + v4)      (I > 0 charges)
//   dv_k/dt = -v_k/tau_k + R_k·g_k(I)/tau_k,  g_1(I) = I (or I_c·tanh(I/I_c) with current dependence), g_2 = I
//   C_th·dT/dt = I·(V_int - OCV) + I·(T + 273.15)·dU/dT - (T - T_amb)/R_th
// Parameters are closed-form smooth functions of SOC (no tables), randomized by seed; the tables in Truth are
// these functions sampled at SOC 0.05..0.95.
//
// Measurement: Gaussian noise, then ADC quantization (decimal rounding the truth does not know).
// Experiments: a simulated cycler (CC, CCCV with current taper at the voltage limit, voltage cut-offs,
// Ah limits, time limits) running the HPPC layouts, CC discharges and a randomized drive profile.
#include <array>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

namespace cellbench::plant {

inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
inline constexpr double kInf = std::numeric_limits<double>::infinity();

enum class Chemistry { nmc, nca, lfp, lmo };
enum class Layout { thesis, usabc, multi, random, gitt };
enum class Direction { discharge, charge };

// Hidden effects (INTERFACES.md effect ids). Physics effects apply to every recording of the cell, bench/ageing
// effects (series_resistance_offset, heat_flux_sensor_gain, capacity_error, ambient_drift) to the drive only.
enum class Effect {
    none,
    resistance_temperature,
    resistance_current,
    thermal_second_order,
    ocv_hysteresis,
    extra_rc,
    series_resistance_offset,
    heat_flux_sensor_gain,
    capacity_error,
    ambient_drift,
};
std::string_view effect_id(Effect effect);
std::optional<Effect> parse_effect(std::string_view id);  // nullopt for an unknown id
bool is_bench_effect(Effect effect);
const std::vector<Effect>& all_effects();                 // every id except none
std::string_view chemistry_name(Chemistry chemistry);
std::string_view layout_name(Layout layout);
std::optional<Layout> parse_layout(std::string_view name);

// ---------------------------------------------------------------------------------------------------------------
// The cell: every coefficient of the closed-form parameter functions.
struct TemperatureDependence {
    enum class Form { none, exponential, linear };
    Form form = Form::none;
    double coefficient_per_k = 0.0;  // exponential: R = R_ref·exp(-k·(T - T_ref)); linear: R_ref·(1 - k·(T - T_ref))
};

struct CurrentDependence {  // RC1 driven by I_c·tanh(I/I_c) instead of I (saturating overpotential)
    bool enabled = false;
    double saturation_current_a = 0.0;
};

struct ThreeNodeThermal {  // core (heat source) - can (to ambient via R_th, heat flux sensor) - sensor node
    bool enabled = false;
    double core_fraction = 0.7;          // C_core = f·C_th, C_can = (1 - f)·C_th
    double r_core_can_k_per_w = 1.0;
    double sensor_time_constant_s = 20.0;  // thermocouple node lag behind the can
};

struct Hysteresis {  // two throughput-driven states h_f, h_s: dh/dt = |I|/(Q·eps)·(sign(I)·M·w(soc) - h)
    bool enabled = false;
    double m_fast_v = 0.0, m_slow_v = 0.0;
    double eps_fast = 0.01, eps_slow = 0.08;  // throughput (fraction of capacity) per e-fold
    double low_soc_gain = 0.0;                // w(soc) = 1 + g·exp(-soc/0.15)
};

struct ExtraRc {  // a short RC chain (Warburg-like slow diffusion): two more elements driven by I
    bool enabled = false;
    double r3_ohm = 0.0, tau3_s = 0.0, r4_ohm = 0.0, tau4_s = 0.0;
};

struct BenchEffects {  // drive recording only
    double series_resistance_ohm = 0.0;
    double heat_flux_gain = 1.0;
    double heat_flux_offset_w_per_m2 = 0.0;
    double capacity_scale = 1.0;
    double ambient_drift_k_per_h = 0.0;
    double ambient_ripple_k = 0.0;
    double ambient_ripple_period_s = 3600.0;
};

struct Measurement {
    double sample_s = 0.1;          // around pulses and in drive profiles
    double coarse_sample_s = 1.0;   // long rests and CC steps (max(1 s, sample_s))
    double voltage_noise_v = 2e-4, current_noise_a = 2e-3, temperature_noise_c = 0.02, heat_flux_noise_w_per_m2 = 0.3;
    int voltage_decimals = 4, current_decimals = 3, temperature_decimals = 2, heat_flux_decimals = 2;
};

struct CellSpec {
    std::uint64_t seed = 1;
    Chemistry chemistry = Chemistry::nmc;
    double capacity_ah = 3.0;          // charge between OCV = v_min (SOC 0) and OCV = v_max (SOC 1)
    double nominal_capacity_ah = 3.0;  // what the cycler programs are written with (rated, rounded)
    double v_min_v = 2.5, v_max_v = 4.2;
    double reference_temperature_c = 25.0;  // = chamber set point
    double area_m2 = 0.005311;
    std::string format;  // "18650" or "21700"

    std::array<double, 8> ocv_coef{};     // chemistry-specific shape coefficients
    double ocv_lin_a = 0.0, ocv_lin_b = 0.0;  // linear correction that pins OCV(0) = v_min, OCV(1) = v_max
    std::array<double, 4> entropic_coef{};

    double r0_ref_ohm = 0.02, r0_low_amp = 0.5, r0_low_width = 0.1, r0_bowl = 0.2;
    double r1_ref_ohm = 0.01, r1_low_amp = 1.0, r1_low_width = 0.12, r1_slope = 0.0;
    double r2_ref_ohm = 0.01, r2_low_amp = 1.0, r2_low_width = 0.15, r2_slope = 0.0;
    double tau1_base_s = 3.0, tau1_phase = 0.0, tau2_base_s = 60.0, tau2_phase = 0.0;
    std::array<double, 2> charge_r_offset{};    // charge R = discharge R·(1 + a + b·(soc - 0.5))
    std::array<double, 2> charge_tau_offset{};  // charge tau = discharge tau·(1 + a + b·(soc - 0.5))

    double c_th_j_per_k = 70.0, r_th_k_per_w = 8.0;

    TemperatureDependence temperature_dependence;
    CurrentDependence current_dependence;
    ThreeNodeThermal thermal3;
    Hysteresis hysteresis;
    ExtraRc extra_rc;
    BenchEffects bench;  // applied only to the drive recording
    std::vector<Effect> effects;

    Measurement measurement;

    // Closed-form parameter functions (soc is a fraction; t_c in degC).
    double ocv_ref_v(double soc) const;
    double entropic_v_per_k(double soc) const;
    double ocv_v(double soc, double t_c) const { return ocv_ref_v(soc) + entropic_v_per_k(soc) * (t_c - reference_temperature_c); }
    double r0_ohm(double soc, Direction d) const;  // at T_ref, without temperature dependence
    double r1_ohm(double soc, Direction d) const;
    double r2_ohm(double soc, Direction d) const;
    double tau1_s(double soc, Direction d) const;
    double tau2_s(double soc, Direction d) const;
    double resistance_factor(double t_c) const;  // temperature dependence (1 when off)
    double current_1c_a() const { return nominal_capacity_ah; }
};

struct PlantOptions {
    std::uint64_t seed = 1;
    Layout layout = Layout::thesis;
    std::vector<Effect> effects;          // none, one or two
    std::optional<double> sample_s;       // default: chosen by seed from {0.1, 0.2, 0.5, 1.0}
    bool noise = true;                    // noise and quantization (false: exact truth values are written)
    // Base-cell options with known truth (both off for the characterization truth):
    bool temperature_dependence = false;  // exponential in T (or linear, by seed), not Arrhenius
    bool current_dependence = false;      // tanh-saturating RC1 overpotential, not asinh
    double thesis_discharge_pulse_s = 30.0;  // Table 2.12, step 8
    // A cell of another size: the seed's cell scaled to this capacity by f = capacity / drawn capacity (resistances
    // and current noise by 1/f and f, C_th by f, the surface area by f^(2/3) and R_th by its inverse; "pouch" above
    // 10 Ah). The seed's draws are unchanged, so the same seed gives the same chemistry, shapes and programs.
    std::optional<double> capacity_ah;
};

// Builds the cell for a seed: base parameters depend on the seed only; each effect's magnitude on the seed and
// the effect, so adding an effect never changes the base cell.
CellSpec make_cell(const PlantOptions& options);

// ---------------------------------------------------------------------------------------------------------------
// Cycler programs.
enum class Mode { rest, cc, cccv };
struct StepResult;
struct Step {
    std::string type;                 // "Rest", "CC DChg", "CCCV Chg", ... (written to Step Type)
    Mode mode = Mode::rest;
    double current_a = 0.0;           // signed set value (+ charges)
    double voltage_limit_v = kNaN;    // cc: cut-off that ends the step; cccv: the CV voltage
    double duration_s = kInf;
    double cutoff_current_a = 0.0;    // cccv: the step ends when |I| falls to this (0: only by duration)
    std::function<double(const std::vector<StepResult>&)> ah_limit;  // |Ah| that ends the step (from what the cycler measured)
    bool fine_sampling = false;       // sample at Measurement::sample_s (else coarse)
    bool end_loop_on_cutoff = false;  // a voltage cut-off here jumps to the first `tail` step
    bool tail = false;
};
struct StepResult {
    int count = 0;
    std::string type;
    double start_s = 0.0, end_s = 0.0;
    double ah = 0.0;                  // signed charge (+ charge), integrated exactly
    std::string end_reason;           // "time", "voltage", "current", "ah", "end"
    bool reached_cv = false;
};
using Program = std::vector<Step>;

Program hppc_program(const CellSpec& cell, Layout layout, const PlantOptions& options = {});

// Layout::random: an HPPC whose structure the seed draws from what labs run, so that a fit tested on it cannot rely
// on one layout's timing. Always from full charge at 1C CCCV; then, by seed: a capacity test at the step rate
// (pilot), SOC levels `soc_step` apart (5-20 % of the rated capacity) stepped down by discharging or up by charging
// from empty (`upward`, after a discharge to the cut-off), at each level one or two pulse pairs (the second at half
// the current, 40 s rest between), discharge pulses of 2-30 s at 0.5-3C, charge pulses of 0 (none), 2 or 10 s at
// 0.25-1x the discharge current, either first, 0-40 s rest between them and 0 or 40 s after, the SOC step at C/3-1C
// right after, then 15 min - 1 h rest. A pulse lasts at least ten sample intervals; pulses are held for their full
// time (clamped at the voltage limits).
// Layout::gitt: a GITT / incremental-OCV test, no pulses: from full charge at 1C CCCV and 1 h rest, titration
// steps of `soc_step` (5 or 10 % of the rated capacity) at `rate_c` (C/10, C/5 or C/3), each followed by a rest of
// `rest_s` (30 min or 1 h), down to the cut-off; on half the seeds (`upward`) the same steps charging back up to
// the upper limit after a rest at empty. Steps are logged at the sampling interval, rests every second.
struct GittLayout {
    double soc_step = 0.05, rate_c = 0.2, rest_s = 3600.0;
    bool upward = false;
};
GittLayout draw_gitt_layout(std::uint64_t seed);

struct RandomLayout {
    bool upward = false, pilot = false, charge_first = false;
    double soc_step = 0.1, step_rate_c = 1.0, rest_after_step_s = 3600.0;
    double discharge_pulse_s = 30.0, charge_pulse_s = 10.0, rest_between_s = 40.0, rest_after_pulses_s = 40.0;
    double discharge_rate_c = 1.0, charge_rate_c = 0.75;
    int currents_per_level = 1;
};
RandomLayout draw_random_layout(std::uint64_t seed, double sample_s);
Program cc_discharge_program(const CellSpec& cell, double c_rate);  // Table 2.10: charge, rest, CC discharge, rest
Program drive_program(const CellSpec& cell, std::uint64_t seed);    // ~1 h randomized profile from near full

// ---------------------------------------------------------------------------------------------------------------
// Recordings: a plain struct (tests adapt it to cellbench::Recording). Measured columns are what the CSV holds;
// true_* are the noise-free values at the same instants (never written).
struct Recording {
    std::string name;
    double unix_start_s = 0.0;
    std::vector<double> time_s, voltage_v, current_a, ambient_c, surface_c, heat_flux_w_per_m2;
    std::vector<int> step_count;
    std::vector<std::string> step_type;
    std::vector<double> true_voltage_v, true_current_a, true_soc, true_ocv_v, true_core_c, true_surface_c,
        true_ambient_c, true_heat_flux_w_per_m2, true_heat_generated_j, true_heat_out_j;
    std::vector<StepResult> steps;
    double initial_soc = 1.0;
    std::size_t size() const { return time_s.size(); }
};

struct InitialState {
    double soc = 0.5;
    bool charged_last = true;  // hysteresis state at the charge (or discharge) branch
};

// Runs a program on the cell. `bench_effects` applies CellSpec::bench (the drive recording's bench/ageing).
Recording simulate(const CellSpec& cell, const Program& program, const InitialState& initial, bool bench_effects,
                   std::uint64_t noise_seed, bool noise = true, std::string name = {});

// ---------------------------------------------------------------------------------------------------------------
// Truth.
struct DirectionTable {
    std::vector<double> r0_ohm, r1_ohm, r2_ohm, tau1_s, tau2_s;
};
struct Truth {
    std::uint64_t seed = 0;
    std::string chemistry, format, layout;
    double capacity_ah = 0.0, nominal_capacity_ah = 0.0, drive_capacity_ah = 0.0;
    double v_min_v = 0.0, v_max_v = 0.0, reference_temperature_c = 0.0, area_m2 = 0.0;
    std::vector<double> soc, ocv_v, entropic_v_per_k;
    DirectionTable discharge, charge;
    double c_th_j_per_k = 0.0, r_th_k_per_w = 0.0;
    std::vector<std::string> effects;
    nlohmann::json options;  // effect / option parameters and the measurement settings
};
Truth make_truth(const CellSpec& cell, Layout layout);
nlohmann::json to_json(const Truth& truth);

// ---------------------------------------------------------------------------------------------------------------
// Everything for one seed.
struct Dataset {
    CellSpec cell;
    Truth truth;
    Recording hppc, cc_low, cc_high, drive;
};
Recording generate_hppc(const CellSpec& cell, const PlantOptions& options);
Recording generate_cc_low(const CellSpec& cell, const PlantOptions& options);   // C/20
Recording generate_cc_high(const CellSpec& cell, const PlantOptions& options);  // 3-4C by seed
Recording generate_drive(const CellSpec& cell, const PlantOptions& options);
// A second drive of the same cell on the same bench set-up (its effects included): another randomized profile,
// start and noise; an independent recording to confirm a diagnosis of the first on (diagnose --confirm).
Recording generate_second_drive(const CellSpec& cell, const PlantOptions& options);
Dataset generate(const PlantOptions& options);

// A cycler's record conditions: a row when a step begins and ends, and between those when the voltage has moved by
// dv_v or the current by di_a since the last row written, or dt_s has passed. Cyclers log this way by default
// ("5 mV, 50 mA, 60 s"): a CV taper and a rest are then a row a minute, a pulse's relaxation a row per 5 mV.
struct RecordConditions {
    double dv_v = 0.005, di_a = 0.05, dt_s = 60.0;
};
// The rows of `dense` such a logger writes (every per-row column, the true values too); the steps are kept.
Recording log_on_change(const Recording& dense, const RecordConditions& conditions);

// BDF CSV (INTERFACES.md "Recordings"), shortest round-trip numbers. Throws std::runtime_error on I/O failure.
void write_bdf_csv(const Recording& recording, const std::filesystem::path& path);
void write_truth_json(const Truth& truth, const std::filesystem::path& path);

}  // namespace cellbench::plant
