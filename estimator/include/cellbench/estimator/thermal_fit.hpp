#pragma once
// Thermal parameters of the first-order (lumped) thermal model from measured surface temperature and heat
// flux (thesis chapter 4), and charge throughput / capacity. Pure computation: no I/O.
//
// Heat balance (thesis eq. 4.2):   C_th * dT/dt = Q_gen - Q_out,   Q_out = q'' * A   (q'' + = leaving the cell)
// Heat generation (eq. 4.1, BDF sign, I + = charge):   Q_gen = I*(V - OCV) + I*T[K]*dU/dT
//
// Conventions
//  - Row ranges are half-open [begin, end) into the recording's rows, chosen by the caller (segmentation).
//  - Temperatures in degC as recorded; T[K] = T + 273.15 where an absolute temperature is needed (eq. 4.6).
//  - The surface temperature used everywhere is Recording::surface_c (Type-T inside the heat flux sensor, the
//    thesis' T); the heat flux is Recording::heat_flux_w_per_m2, scaled by the TOTAL cell surface area
//    (thesis: Q_out = q'' * A_tot, A_tot = pi*d*L + 2*pi*(d/2)^2 = 5.311e-3 m^2 for a 21700 cell).
//  - Rows whose temperature or heat flux is NaN (DAQ gaps) are skipped, never interpolated.
//
// Defaults and why
//  - kDefaultRestSkipS = 300 s: the start of a rest is not lumped: the core is hotter than the surface and
//    heat is still spreading. The radial diffusion time of a 21700 cell is r^2/alpha = (10.5 mm)^2 /
//    (k/(rho*c) = 1 W/(m K) / (2890 kg/m^3 * 904 J/(kg K))) ~ 290 s; the first cylinder mode decays with
//    r^2/(2.405^2*alpha) ~ 50 s, so after ~300 s (6 mode time constants) only the lumped (slow) mode is left.
//    On the P45B HPPC rests the ratio Q_out / (-dT/dt) is ~100 J/K at 200 s and settles at ~61 J/K from
//    300 s on.
//  - kDefaultDerivativeWindowS = 60 s: the cooling time constant after a rest is ~330 s, so a 60 s local
//    line biases dT/dt by (w/2/tau)^2/6 < 0.2 %, while averaging ~600 samples at 0.1 s beats the 0.1 mK
//    quantization and the chamber's temperature ripple. In the C_th fit the chunk ends' temperatures come from
//    centred lines over half of it (30 s): for an exponential cooling the value is biased by (w/tau)^2/24 of
//    the excess, 0.3 % at the shortest time constant the validation plant has (120 s).
#include <cstddef>
#include <string>
#include <vector>

#include "cellbench/core/recording.hpp"

namespace cellbench::estimator {

// Half-open row range [begin, end).
struct RowRange {
    std::size_t begin = 0, end = 0;
    [[nodiscard]] std::size_t size() const { return end > begin ? end - begin : 0; }
};

inline constexpr double kDefaultRestSkipS = 300.0;
inline constexpr double kDefaultDerivativeWindowS = 60.0;

// ---------------------------------------------------------------------------------------------------------------
// Noise-robust derivative.
//
// Local linear regression (first-order Savitzky-Golay on the real, possibly non-uniform time stamps): the slope
// of the least-squares line through the samples with |t - t_k| <= window_s/2, restricted to rows [begin, end).
// Near the range ends the window is truncated (one-sided), which keeps it exact for straight lines. Samples with
// a non-finite y are left out. Returns end - begin values (element i belongs to row begin + i); NaN where the
// window holds fewer than 3 finite samples or no time spread. O(n) (prefix sums).
std::vector<double> smooth_derivative(const std::vector<double>& time_s, const std::vector<double>& y,
                                      std::size_t begin, std::size_t end, double window_s);

// ---------------------------------------------------------------------------------------------------------------
// Thermal capacity from rests (thesis section 4.2.1, eq. 4.7-4.8, Script 4.2).
//
// In a rest Q_gen = 0, so Q_out = C_th * (-dT/dt). Script 4.2 regresses Q_out on a differentiated temperature; the
// derivative's noise then sits in the regressor and biases the slope towards zero (errors in variables: on a
// rest that cools by a few tenths of a kelvin the 60 s slopes are mostly noise, and C_th came out 20-97 % low on
// the validation plant). Here eq. 4.7 is integrated instead: each rest, from skip_s on, is cut into chunks of
// max(skip_s, 2 window_s) and per chunk C_th * (T(a) - T(b)) = integral_a^b Q_out dt, T(a) and T(b) from local
// lines over window_s / 2 centred on the chunk ends (whose variance is subtracted from the regressor's sum of
// squares). The chunks of every rest given are regressed through the origin with Tukey-biweight weights (IRLS,
// tuning 4.685 robust sigma, started from the weighted median of the chunk ratios): chunks where the lumped
// premise is violated (a rest's end smeared by DAQ filtering or clock skew, chamber disturbances) get weight 0.
struct ThermalCapacityFit {
    double c_th_j_per_k = kNaN;
    // Standard error of C_th. Points 0.1 s apart are not independent: the error is the cluster-robust
    // (per rest) sandwich estimate when there are >= 3 informative rests, otherwise the OLS error with the
    // sample count reduced to the effective number of independent samples (lag-1 autocorrelation of the
    // residuals); the larger of the two when both exist.
    double c_th_se_j_per_k = kNaN;
    // 1 - SSE/SST with SST centred on the mean (as MATLAB fitlm reports it, also without intercept), over the
    // points kept by the robust weights.
    double r_squared = kNaN;
    std::size_t points = 0;          // rows of the chunks that entered the regression
    std::size_t points_rejected = 0; // of those, rows of the chunks the robust weights dropped (weight 0)
    std::size_t rests_used = 0;      // rests that contributed at least one row
    std::vector<double> per_rest_c_th_j_per_k;  // OLS slope of each rest alone (NaN if it had no rows)
    double skip_s = kDefaultRestSkipS, window_s = kDefaultDerivativeWindowS;
    std::string note;
};

// Throws InputError if the recording lacks surface temperature or heat flux, or area_m2 <= 0.
ThermalCapacityFit fit_thermal_capacity(const Recording& rec, const std::vector<RowRange>& rests, double area_m2,
                                        double skip_s = kDefaultRestSkipS,
                                        double window_s = kDefaultDerivativeWindowS);

// The rests of several recordings in one regression (one cluster per rest): a hot discharge's cool-down and an
// HPPC's many weakly heated rests weigh by what they hold.
struct ThermalRests {
    const Recording* recording = nullptr;
    std::vector<RowRange> rests;
};
ThermalCapacityFit fit_thermal_capacity(const std::vector<ThermalRests>& sets, double area_m2,
                                        double skip_s = kDefaultRestSkipS,
                                        double window_s = kDefaultDerivativeWindowS);

// ---------------------------------------------------------------------------------------------------------------
// Thermal resistance surface -> ambient, two independent ways (thesis eq. 4.9, Script 4.3; eq. 1.37).
//  (a) convection law: Q_out = (T - T_amb) / R_th over every usable row of every range (rests and current
//      phases alike: it holds at the surface at any time). T_amb per row from the ambient column if the
//      recording has one, else options.ambient_c if given, else estimated per range as an intercept (common
//      slope 1/R_th, one T_amb per range: fixed-effects regression).
//  (b) cooling time constant of rests: T(t) = T_inf + dT * exp(-(t - t0)/tau) fitted (Ceres, Cauchy loss) from
//      skip_s into each rest (|I| <= rest_current_a throughout; other ranges are not used for (b)); rests
//      with |dT| < min_delta_t_k carry no information and are left out. tau is the weighted median over
//      rests (weights 1/se^2); R_th = tau / C_th.
// Both with standard errors; `disagree` when |a - b| / mean(a, b) > disagree_fraction, with the likely
// reasons in `note`.
struct ThermalResistanceOptions {
    double skip_s = kDefaultRestSkipS;  // (b) only: start of each rest left out (core-surface equilibration)
    double ambient_c = kNaN;            // (a): used when the recording has no ambient column (NaN: estimate)
    double min_delta_t_k = 0.1;         // (b): smallest initial excess temperature of a usable rest
    double rest_current_a = 0.05;       // (b): a range is a rest when |I| stays below this
    double disagree_fraction = 0.15;
    double c_th_se_j_per_k = 0.0;       // uncertainty of the given C_th, propagated into (b)
};

struct RestCoolingFit {
    RowRange range;
    double tau_s = kNaN, tau_se_s = kNaN;
    double t_inf_c = kNaN;    // asymptote (the ambient the rest cools towards)
    double delta_t_k = kNaN;  // excess temperature at t0 = start + skip_s
    double rms_c = kNaN;      // residual RMS
    bool used = false;        // entered the aggregate
    std::string reason;       // why not, if not used
};

struct ThermalResistanceFit {
    // (a) Q_out against T - T_amb
    double r_th_flux_k_per_w = kNaN, r_th_flux_se_k_per_w = kNaN;
    double flux_r_squared = kNaN;
    std::size_t flux_points = 0;
    std::string ambient_source;         // "ambient column", "given", "intercept per range"
    std::vector<double> ambient_per_range_c;  // T_amb used/estimated for each range (NaN if not applicable)
    // (b) cooling time constant
    double tau_s = kNaN, tau_se_s = kNaN;
    double r_th_tau_k_per_w = kNaN, r_th_tau_se_k_per_w = kNaN;
    std::size_t rests_used = 0;
    std::vector<RestCoolingFit> rests;
    // comparison
    double relative_difference = kNaN;  // (a - b) / mean(a, b)
    bool disagree = false;
    std::string note;
};

// Throws InputError if the recording lacks surface temperature or heat flux, area_m2 <= 0 or c_th <= 0.
ThermalResistanceFit fit_thermal_resistance(const Recording& rec, const std::vector<RowRange>& ranges,
                                            double area_m2, double c_th_j_per_k,
                                            const ThermalResistanceOptions& options = {});

// ---------------------------------------------------------------------------------------------------------------
// Entropic heat coefficient from a constant-current discharge (thesis section 4.1.2, eq. 4.4-4.6, Script 4.1):
//   Q_rev = C_th*dT/dt + Q_out - I*(V - OCV(SOC)),    dU/dT = Q_rev / (I * T[K])
// dT/dt by smooth_derivative (window_s); OCV by linear interpolation in the table (linear extrapolation outside
// it; bins outside the table's SOC span are flagged `extrapolated_ocv`). Per-row values beyond
// +-max_abs_v_per_k are discarded (outliers, not physics: Li-ion EHCs are within +-0.5 mV/K). Each grid point
// gets the median of the rows whose SOC is nearer to it than to its neighbours, and a robust spread
// (1.4826 * MAD). A bin with fewer than min_samples rows has no data (NaN, has_data false).
//
// The reversible heat is a small difference of large terms when |I| is high: at 4C the Joule heat is ~4x
// the reversible one, so a 10 mV OCV error moves dU/dT by ~0.03 mV/K and the surface lags the core at the
// start; `joule_share` (median Q_irr / (|Q_irr| + |Q_rev|)) measures that and `note` says so.
struct EntropicOptions {
    double window_s = 30.0;            // derivative window (at 4C the cell heats ~0.02 K/s, tau ~ 330 s)
    double skip_s = 30.0;              // start of the discharge left out (surface lags the core)
    double max_abs_v_per_k = 1.0e-3;   // a bin's value is held within +-this (named in the note)
    double min_current_a = 0.05;       // rows with |I| below this carry no information (division by I)
    std::size_t min_samples = 20;      // fewer rows in a bin: no data
};

struct EntropicFit {
    std::vector<double> soc;                 // the grid
    std::vector<double> ehc_v_per_k;         // dU/dT, NaN where no data
    std::vector<double> spread_v_per_k;      // 1.4826 * MAD of the rows in the bin
    std::vector<std::size_t> samples;        // rows in the bin (after rejection)
    std::vector<bool> has_data;
    std::vector<bool> extrapolated_ocv;      // bin centre outside the OCV table's SOC span
    std::size_t rows_used = 0, rows_rejected = 0;
    double mean_abs_current_a = kNaN;
    double joule_share = kNaN;               // median of Q_irr / (|Q_irr| + |Q_rev|) over used rows
    std::string note;
};

// soc_of_row: SOC (0..1) of every row of the recording (Coulomb counting by the caller).
// Throws InputError on inconsistent sizes, missing channels, or non-ascending OCV table / grid.
EntropicFit fit_entropic_coefficient(const Recording& rec, RowRange cc_discharge, const std::vector<double>& soc_of_row,
                                     const std::vector<double>& ocv_soc, const std::vector<double>& ocv_v,
                                     double c_th_j_per_k, double area_m2, const std::vector<double>& soc_grid,
                                     const EntropicOptions& options = {});

// ---------------------------------------------------------------------------------------------------------------
// Charge throughput and capacity.
enum class CurrentIntegration {
    Hold,       // the model's convention (electrical.hpp): I[k] flowed during (t[k-1], t[k]]; row `begin`'s
                // interval counts when begin > 0
    Trapezoid,  // (I[k-1] + I[k])/2 over (t[k-1], t[k]] for k in (begin, end)
};

// Integral of I dt over rows [begin, end), in Ah, + = charged into the cell. 0 for an empty range.
double charge_throughput_ah(const Recording& rec, RowRange range,
                            CurrentIntegration method = CurrentIntegration::Hold);

// Capacity from a pilot discharge (full charge -> cut-off): the |Ah| discharged over the range (rows with a
// charging current are netted out, as in Coulomb counting). Throws InputError if the range moves no charge out.
double pilot_discharge_capacity_ah(const Recording& rec, RowRange pilot,
                                   CurrentIntegration method = CurrentIntegration::Hold);

}  // namespace cellbench::estimator
