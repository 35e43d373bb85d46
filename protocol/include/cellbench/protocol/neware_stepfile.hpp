#pragma once
// Step programs for the Neware tester and their step-file form. This is the ONE place that knows the
// step-file format: everything else (sequencer, daemon, simulated tester) goes through StepProgram.
//
// !! Neware's step-file schema is NOT public. The file written here is cellbench's own documented XML
// !! (format "cellbench.neware-steps/1", see neware_stepfile.cpp for the full description and the shape of
// !! vendor files seen in the field). The simulated tester executes it; a real BTS will reject it, which is
// !! the safe failure until the format is matched to a real file from Neware's step editor.
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
//  - cycle: jumps back to start_step until the block start_step..cycle has run `count` times in total
//    (Neware's "Cycle count": thesis Table 2.12 runs 10 pulse sets with count 10).
//  - end: the program finishes.
//  - Step capacity: |charge| moved during the step, Ah (as the tester counts it per step). A capacity limit may
//    reference earlier steps' capacities from their latest execution, e.g. thesis eq. 2.4:
//    C12 = 0.1*C4 - C8 + C10. A step not yet executed counts 0; a limit <= 0 ends the step at once.
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace cellbench::protocol {

enum class StepType { rest, cc_charge, cc_discharge, cccv_charge, cccv_discharge, cycle, end };

std::string_view to_string(StepType type);                       // "cc_charge", ...
std::optional<StepType> step_type_from_string(std::string_view);  // exact

// +1 charge, -1 discharge, 0 rest/cycle/end.
int step_direction(StepType type);
bool step_carries_current(StepType type);  // cc*, cccv*
// The step_type word the tester reports in inquire_resp while running this step. Seen in the field: rest,
// cc, dc, cv; the CCCV words ("cccv", "cccv_dc") are unverified guesses (the simulated tester reports "cv"
// during the CV phase of a CCCV step).
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
    std::optional<double> cutoff_current_a;  // cccv*
    std::optional<CapacityExpression> cutoff_capacity_ah;
    // Loop (cycle only).
    int start_step = 0;
    int count = 0;
    std::string note;

    bool operator==(const Step&) const = default;
};

struct StepProgram {
    std::string name;
    std::string description;
    std::vector<Step> steps;  // step id = index + 1

    bool operator==(const StepProgram&) const = default;

    // Throws InputError naming the step ("steps[11] (step 12): ...") and what was expected.
    void validate() const;
    [[nodiscard]] double max_current_a() const;  // largest set current of any step

    [[nodiscard]] nlohmann::json to_json() const;
    // Throws InputError naming `source` and the JSON path ("hppc.json: steps[11].current_a: expected ...").
    // The result is validated.
    static StepProgram from_json(const nlohmann::json& j, const std::string& source = "program");
};

inline constexpr const char* kProgramSchema = "cellbench.program/1";
inline constexpr const char* kStepFileFormat = "cellbench.neware-steps/1";

// Step file (see the top of this header). compile validates first (InputError); parse throws
// neware::ProtocolError for a malformed file and InputError for a well-formed but invalid program.
std::string compile_step_file(const StepProgram& program);
StepProgram parse_step_file(std::string_view xml);

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
