#pragma once
// Step programs for the Neware tester and their step-file form. This is the ONE place that knows the
// step-file format: everything else (sequencer, daemon, simulated tester) goes through StepProgram.
//
// The step file is the real BTS Client schema (../shared/reference/neware/README.md and the BTS Client 2024
// file there): <root><config type="Step File" version="17" ...> with Head_Info, Whole_Prt, Step_Info and
// SMBUS; units 0.1 mV, mA, ms, mA*s; Step_Type codes 1 CC Chg, 2 CC DChg, 3 CV Chg, 4 Rest, 5 Cycle, 6 End,
// 7 CCCV Chg, 19 CV DChg, 20 CCCV DChg. See neware_stepfile.cpp for the mapping in full.
//
// A StepProgram maps 1:1 to JSON (config/programs/*.json, schema "cellbench.program/1"):
//   {"schema": "cellbench.program/1", "name": "hppc_1c",
//    "steps": [{"type": "rest", "time_s": 10},
//              {"type": "cccv_charge", "current_a": 4.5, "voltage_v": 4.1, "cutoff_current_a": 0.05},
//              {"type": "cc_discharge", "current_a": 4.5, "cutoff_voltage_v": 2.9,
//               "cutoff_capacity_ah": "0.1*C4 - C8 + C10"},
//              {"type": "cycle", "start_step": 8, "count": 10},
//              {"type": "end"}]}
// Steps are numbered from 1 in order (an optional "id" must equal the position). Currents are magnitudes;
// the step type gives the direction (+ = charge, the project's sign).
//
// Step semantics (what the tester does; the simulated tester follows them exactly):
//  - rest: no current for time_s.
//  - cc_charge / cc_discharge: constant current until any end condition: time_s elapsed, the terminal
//    voltage crosses cutoff_voltage_v (rising for charge, falling for discharge), or the step's capacity
//    reaches cutoff_capacity_ah.
//  - cccv_charge / cccv_discharge: constant current until the terminal voltage reaches voltage_v, then
//    constant voltage; ends when |current| falls to cutoff_current_a (CV phase only), time_s elapsed, or the
//    capacity limit is reached.
//  - cv_charge / cv_discharge: constant voltage voltage_v with the current limited to current_a (the tester
//    executes it like a CCCV step; BTS Step_Type 3 / 19).
//  - cycle: jumps back to start_step until the block start_step..cycle has run `count` times in total
//    (Neware's "Cycle count": thesis Table 2.12 runs 10 pulse sets with count 10).
//  - end: the program finishes.
//  - Step capacity: |charge| moved during the step, Ah (as the tester counts it per step). A capacity limit may
//    reference earlier steps' capacities from their latest execution, e.g. thesis eq. 2.4:
//    C12 = 0.1*C4 - C8 + C10. A step not yet executed counts 0; a limit <= 0 ends the step at once.
//
// WHAT THE REAL FORMAT CANNOT EXPRESS, and how it is handled:
//  - A capacity limit that refers to other steps (eq. 2.4): a step file carries one constant Cap. Such a
//    limit is resolved to a constant before compiling (resolve_capacity_limits): a referenced step inside the
//    same loop body as the limited step (the pulses C8, C10 of an HPPC set) is taken at its nominal capacity
//    (set current x time limit; those steps are time-limited), a step outside it (the pilot discharge C4) at
//    its measured capacity. To have that measurement, the daemon's sequencer runs such a program as two step
//    files (tester_parts): steps 1..k then End, and, once the tester has recorded step k, the whole program
//    again starting at step k+1 (Head_Info Start_Step) with the limit resolved from the rows it recorded.
//    Step ids stay those of the program. `cellbench steps` (no measurement) resolves with the cell's nominal
//    capacity and says so.
//  - Step notes: the schema has no field for them; they are not written (the program name goes to PN).
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace cellbench::protocol {

enum class StepType { rest, cc_charge, cc_discharge, cccv_charge, cccv_discharge, cycle, end, cv_charge, cv_discharge };

std::string_view to_string(StepType type);                       // "cc_charge", ...
std::optional<StepType> step_type_from_string(std::string_view);  // exact

// +1 charge, -1 discharge, 0 rest/cycle/end.
int step_direction(StepType type);
bool step_carries_current(StepType type);  // cc*, cccv*, cv*
bool step_has_cv_phase(StepType type);     // cccv*, cv*: voltage_v is the CV set value
// The step_type word a real BTS 8 reports in inquire_resp/download rows while running this step: rest, cc,
// dc, cv (a CCCV step reports cc/dc in its CC phase and cv in its CV phase; idle channels "--").
std::string_view step_type_code(StepType type);

// Capacity limit: constant_ah + sum(factor * C[step]), C[step] = capacity of that step's latest execution.
struct CapacityTerm {
    int step_id = 0;
    double factor = 1.0;
    bool operator==(const CapacityTerm&) const = default;
};
struct CapacityExpression {
    double constant_ah = 0.0;
    std::vector<CapacityTerm> terms;

    bool operator==(const CapacityExpression&) const = default;
    [[nodiscard]] bool is_constant() const { return terms.empty(); }
    // Canonical text: "0.1*C4 - C8 + C10", "3.5" for a constant.
    [[nodiscard]] std::string to_string() const;
    // Grammar: term (('+'|'-') term)*, term = [number '*'] 'C' step | 'C' step '*' number | number.
    // Throws InputError (message without location; callers prefix it).
    static CapacityExpression parse(std::string_view text);
    [[nodiscard]] double evaluate(const std::function<double(int step_id)>& step_capacity_ah) const;
};

struct Step {
    StepType type = StepType::rest;
    // Set values.
    std::optional<double> current_a;  // magnitude, cc* and cccv*
    std::optional<double> voltage_v;  // CV set value, cccv*
    // End conditions.
    std::optional<double> time_s;
    std::optional<double> cutoff_voltage_v;  // cc*
    std::optional<double> cutoff_current_a;  // cccv*, cv*
    std::optional<CapacityExpression> cutoff_capacity_ah;
    // Step-file extras (BTS per-step Record and Protect; the tester applies them, the model carries them so a
    // vendor file reads back unchanged). Unset: not written.
    std::optional<double> record_interval_s, record_delta_v, record_delta_a;
    std::optional<double> protect_upper_v, protect_lower_v;
    // Loop (cycle only).
    int start_step = 0;
    int count = 0;
    std::string note;

    bool operator==(const Step&) const = default;
};

// Whole-program settings of a step file (Head_Info MultCap, Whole_Prt): unset = not written / derived.
struct StepFileSettings {
    std::optional<double> nominal_capacity_ah;  // MultCap (mA*s), the reference of C-rates
    std::optional<double> record_interval_s;    // Whole_Prt/Record/Main/Time
    std::optional<double> protect_upper_v, protect_lower_v;  // Whole_Prt/Protect/Main/Volt
    std::optional<double> protect_upper_a, protect_lower_a;  // Whole_Prt/Protect/Main/Curr (signed, A)
    std::optional<double> protect_capacity_ah;               // Whole_Prt/Protect/Main/Cap/Upper
    std::optional<double> protect_delay_s;                   // Whole_Prt/Protect/Main/Delay_Time
    bool operator==(const StepFileSettings&) const = default;
};

struct StepProgram {
    std::string name;
    std::string description;
    std::vector<Step> steps;  // step id = index + 1
    int first_step = 1;       // where the tester starts (Head_Info Start_Step); see tester_parts()
    StepFileSettings settings;

    bool operator==(const StepProgram&) const = default;

    // Throws InputError naming the step ("steps[11] (step 12): ...") and what was expected.
    void validate() const;
    [[nodiscard]] double max_current_a() const;  // largest set current of any step

    [[nodiscard]] nlohmann::json to_json() const;
    // Throws InputError naming `source` and the JSON path ("hppc.json: steps[11].current_a: expected ...").
    // The result is validated.
    static StepProgram from_json(const nlohmann::json& j, const std::string& source = "program");
};

// The steps a tester runs, in the order it runs them (indices into program.steps): loops unrolled (a cycle step
// sends the tester back to start_step until its block has run `count` times in all; an inner loop runs in full on
// every pass of an enclosing one), cycle and end steps left out, stopping at an end step or after max_steps. The
// static twin of the simulated tester's run (drivers/sim ProgramRunner), for estimates and checks of a program.
std::vector<std::size_t> execution_order(const StepProgram& program, std::size_t max_steps = 1'000'000);

inline constexpr const char* kProgramSchema = "cellbench.program/1";

// Step file (see the top of this header). compile validates first (InputError) and resolves capacity limits
// that refer to other steps (resolve_capacity_limits with no measurement; InputError when one needs a
// measurement and settings.nominal_capacity_ah is unset). parse reads version 17 and 18, GB2312 or UTF-8
// declared; throws neware::ProtocolError for a malformed file and InputError for a well-formed but invalid
// program. Notes and descriptions are not part of the format.
struct StepFileOptions {
    std::string date;  // "YYYYMMDDhhmmss" of the config element; empty: now (UTC)
};
std::string compile_step_file(const StepProgram& program, const StepFileOptions& options = {});
StepProgram parse_step_file(std::string_view xml);

// Nominal capacity of a step (Ah): set current x time limit for a time-limited current step, the program's
// settings.nominal_capacity_ah for one that runs to a voltage or current cut-off, nullopt when unknown.
std::optional<double> nominal_step_capacity_ah(const StepProgram& program, int step_id);
// The program with every capacity limit that refers to other steps replaced by a constant (see the top of
// this header): a referenced step inside the limited step's loop body at its nominal capacity, one outside
// at measured_ah(step) when given, else nominal. Throws InputError naming the step when a value is unknown.
// A result <= 0 is kept as a tiny positive limit (the step ends at once, as on the tester).
StepProgram resolve_capacity_limits(const StepProgram& program,
                                    const std::function<std::optional<double>(int step_id)>& measured_ah = {});
// The program exactly as its step file carries it (compile writes this, parse reads it back equal): capacity
// limits resolved (no measurement), unset settings filled with the defaults compile writes (record every
// 1 s; Whole_Prt protection 0.1 V beyond the program's voltages, 1.1 x its largest current), notes and
// description dropped.
StepProgram as_tester_program(const StepProgram& program);
// How the tester runs a program: one part, or two when a capacity limit needs a measured step outside its
// loop (steps 1..k + End, then the whole program from step k+1). Parts keep the program's step ids.
std::vector<StepProgram> tester_parts(const StepProgram& program);

// The thesis' programs (reference thesis, P45B, 1C = 4.5 A, limits 2.9 V / 4.1 V).
// Table 2.10: CC discharge test at a C-rate (Table 2.11: 0.5, 1, 2, 4, 10, 13 -> 2.25 ... 58.5 A; the thesis
// ran "13C" at the 60 A limit of three parallel channels: pass discharge_current_a to get exactly that).
StepProgram thesis_cc_discharge_program(double c_rate, double one_c_a = 4.5,
                                        std::optional<double> discharge_current_a = std::nullopt);
// Table 2.12: HPPC with pilot discharge and 10 pulse sets, the -10 % SOC step limited by C12 = 0.1*C4 - C8 + C10.
StepProgram thesis_hppc_program(double one_c_a = 4.5);
// Table 5.1: Random Walk, 1C..4C discharge / charge pulses, block 2..13 run 7 times.
StepProgram thesis_random_walk_program(double one_c_a = 4.5);

}  // namespace cellbench::protocol
