#pragma once
// cellbenchd configuration: the bench (instruments, simulation, safety limits, database, API), the cell under
// test, and the test programs. Every field is documented in config/README.md.
//
// Loading collects EVERY problem of a file (file, JSON path such as `$.instruments.cycler.port`, what was
// expected) and throws one ConfigError listing them all, so a bad configuration is fixed in one go and never
// starts a run. Sub-objects owned by other layers (the DEWE CAN layout, the chamber's Modbus register map, the
// simulation's hidden physics) are kept as JSON, validated by their layer where it offers a parser, so the
// daemon does not depend on their internals.
//
// Programs (config/programs/*.json, schema "cellbench.bench-program/1") are a named sequence of segments:
//   - "cycler": a protocol::StepProgram (the tester runs the whole step list by itself),
//   - "chamber_setpoint": a new chamber set point,
//   - "wait_equilibrium": wait until cell and chamber are within tolerance_c of the set point for hold_s.
// Numbers inside segments may be expressions over the program's parameters and the cell's constants, e.g.
//   "parameters": {"c_rate": 1.0},  ...  "current_a": "c_rate * one_c_a"
// (grammar and names: evaluate_expression below). A bare StepProgram file (schema "cellbench.program/1",
// with "steps") is accepted as a program of one cycler segment.
#include <cstdint>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "cellbench/protocol/parallel_group.hpp"

namespace cellbench::daemon {

inline constexpr const char* kBenchSchema = "cellbench.bench/1";
inline constexpr const char* kCellSchema = "cellbench.cell/1";
inline constexpr const char* kBenchProgramSchema = "cellbench.bench-program/1";

// ---------------------------------------------------------------------------------------------------------
// Errors

// One problem in one file: "bench.sim.json: $.instruments.cycler.port: expected an integer 1..65535, got "x"".
struct ConfigIssue {
    std::string file;     // as given to the loader
    std::string path;     // JSON path, "$" = the whole document; empty for file-level problems
    std::string message;  // what was expected (and what was found)

    [[nodiscard]] std::string to_string() const;
    bool operator==(const ConfigIssue&) const = default;
};

// All problems found while loading; what() lists them one per line.
class ConfigError : public InputError {
public:
    explicit ConfigError(std::vector<ConfigIssue> issues);
    [[nodiscard]] const std::vector<ConfigIssue>& issues() const { return issues_; }

private:
    std::vector<ConfigIssue> issues_;
};

// ---------------------------------------------------------------------------------------------------------
// Bench

// "host:port" (IPv4 literal or name; port 1..65535, or 0 = any free port for instruments the daemon hosts).
struct Endpoint {
    std::string host = "127.0.0.1";
    int port = 0;
    [[nodiscard]] std::string to_string() const;  // "host:port"
    bool operator==(const Endpoint&) const = default;
};
// Parses "HOST:PORT"; nullopt when malformed.
std::optional<Endpoint> parse_endpoint(std::string_view text);

// Neware BTS-4008: N channels wired in parallel and run as one channel (the thesis: 3 x 20 A = 60 A).
struct CyclerConfig {
    enum class Mode { simulated, tcp };
    Mode mode = Mode::simulated;             // simulated: the daemon hosts the simulated tester at `endpoint`
    Endpoint endpoint{"127.0.0.1", 502};     // the BTS PC (API port, 502 by default)
    std::vector<protocol::neware::ChannelAddress> channels;  // the parallel group's members, first = leader
    int poll_period_ms = 100;                // inquire period (live values)
    int response_timeout_ms = 2000;          // a reply later than this counts as a lost reply
    double channel_max_current_a = 20.0;     // per member; the group can source members * this
    // Group consistency (members must agree; see protocol/parallel_group.hpp): "group" in the JSON.
    protocol::ParallelGroupOptions group;

    [[nodiscard]] double group_max_current_a() const {
        return channel_max_current_a * static_cast<double>(channels.size());
    }
};

// DEWE-43A streaming the heat flux sensor (thermopile + Type-T) and two Type-K thermocouples over CAN.
struct DaqConfig {
    enum class Mode { simulated, can };
    enum class Transport { can_dgram, socketcan };
    Mode mode = Mode::simulated;              // simulated: the daemon hosts the simulated DAQ on the transport
    Transport transport = Transport::can_dgram;
    std::string socket_path;                  // can-dgram: Unix datagram socket (INTERFACES.md)
    std::string interface;                    // socketcan: network interface ("can0", "vcan0")
    nlohmann::json layout;                    // cellbench.dewe-can/1 (validated by protocol::DeweCanLayout)
    double sensitivity_v_per_w_per_m2 = 17.39e-6;  // heat flux sensor S at 20 degC (certificate)
    double sensor_area_m2 = 36e-3 * 36e-3;    // heat flux sensor area (36 x 36 mm)
    double cell_area_m2 = 5.311e-3;           // total cell surface, heat flux density -> heat flow
    double stale_after_s = 2.0;               // no sample for this long = instrument lost
};

// MSL climatic chamber over Modbus TCP.
struct ChamberConfig {
    enum class Mode { simulated, modbus_tcp };
    Mode mode = Mode::simulated;
    Endpoint endpoint{"127.0.0.1", 502};
    int unit_id = 1;                          // Modbus unit (slave) id, 0..247
    // cellbench.chamber-modbus/1, validated by protocol::ChamberRegisterMap; absent in the file = the
    // simulated chamber's map (ChamberRegisterMap::bench_default()), stored here in full.
    nlohmann::json register_map;
    int poll_period_ms = 1000;
    double safe_setpoint_c = 25.0;            // set when a run ends or aborts
    double setpoint_min_c = -50.0, setpoint_max_c = 180.0;  // from the register map (what it can carry)
};

// The daemon hosts the simulated instruments (every instrument whose mode is "simulated").
struct SimulationConfig {
    double time_scale = 1.0;                  // bench seconds per wall second
    std::uint32_t seed = 1;
    std::filesystem::path params_path;        // parameter set of the simulated cell (resolved, absolute)
    double initial_soc = 1.0;
    double initial_temperature_c = 25.0;
    nlohmann::json hidden = nlohmann::json::object();  // hidden physics, interpreted by drivers/sim
};

struct SafetyLimits {
    double max_temperature_c = 60.0;          // any cell thermocouple above this aborts the run
    double min_voltage_v = 2.8, max_voltage_v = 4.2;  // terminal voltage window (hard limits, not cut-offs)
    double max_current_a = 60.0;              // |group current|
    double chamber_deviation_c = 5.0;         // |air - set point| beyond this (after settling) is an alarm
    double instrument_loss_grace_s = 5.0;     // an instrument silent this long aborts the run
};

// What the daemon does when an instrument misbehaves ("fault_policy" in the bench file; config/README.md).
// Recoverable faults (a lost connection, a lost or malformed answer, a silent stream) are retried with backoff
// while the run goes on, for at most the instrument's grace_s (bench seconds without a valid reading); past it
// the run aborts: current off, chamber to its safe set point. Immediately fatal, whatever the policy: a
// parallel-group member in protect (or the group disagreeing), a cycler that does not acknowledge start/stop,
// a chamber alarm bit, and the safety limits. Every fault and every recovery is a run event.
enum class FaultAction { reconnect, abort };  // a fault that may clear: retry within the grace, or end the run now
enum class SetpointAction { event, abort };

struct CyclerFaultPolicy {
    double grace_s = 5.0;                     // no cell voltage this long aborts (default: safety.instrument_loss_grace_s)
    int reconnect_initial_ms = 100;           // first reconnect delay (wall), doubled per failure ...
    int reconnect_max_ms = 5000;              // ... up to this
};
struct ChamberFaultPolicy {
    double grace_s = 5.0;                     // no chamber reading this long aborts (default: instrument_loss_grace_s)
    int response_timeout_ms = 500;            // Modbus answer timeout (wall)
    int retries = 2;                          // further attempts of a timed-out / transient request, fresh connection
    FaultAction exception_response = FaultAction::reconnect;  // a Modbus exception answer
    double setpoint_tolerance_c = 1.0;        // the set point counts as reached within this
    double setpoint_timeout_s = 1800.0;       // not reached within this (bench s) after a set point write: a fault
    SetpointAction setpoint_not_reached = SetpointAction::event;
};
struct DaqFaultPolicy {
    double grace_s = 5.0;                     // no cell temperature this long aborts (default: instrument_loss_grace_s)
    double loss_event_interval_s = 60.0;      // lost/garbage frames: at most one event per this many bench s
};
struct FaultPolicy {
    CyclerFaultPolicy cycler;
    ChamberFaultPolicy chamber;
    DaqFaultPolicy daq;
};

struct DatabaseConfig {
    std::filesystem::path path = "cellbench.sqlite";  // relative: to the daemon's working directory
    int flush_period_ms = 200;                // samples are committed at least this often
    std::size_t queue_capacity_samples = 500000;  // writer queue bound (overflow drops new samples)
};

struct BenchConfig {
    std::string name;
    std::filesystem::path source;             // the file loaded
    std::filesystem::path config_dir;         // its folder: cells/ and programs/ are looked up here
    CyclerConfig cycler;
    DaqConfig daq;
    ChamberConfig chamber;
    std::optional<SimulationConfig> simulation;  // present when any instrument is simulated
    SafetyLimits safety;
    FaultPolicy faults;                       // "fault_policy"
    DatabaseConfig database;
    Endpoint listen{"127.0.0.1", 8750};
    std::string token_env = "CELLBENCH_TOKEN";  // environment variable holding the API token
    nlohmann::json document;                  // the file as loaded (for the run record)

    [[nodiscard]] bool any_simulated() const {
        return cycler.mode == CyclerConfig::Mode::simulated || daq.mode == DaqConfig::Mode::simulated ||
               chamber.mode == ChamberConfig::Mode::simulated;
    }
};

// ---------------------------------------------------------------------------------------------------------
// Cell

struct CellConfig {
    std::string id;                           // file name without .json ("p45b")
    std::string name;                         // "Molicel INR-21700-P45B"
    double nominal_capacity_ah = 0.0;
    double min_voltage_v = 0.0, max_voltage_v = 0.0;  // test window (program cut-offs stay inside)
    double max_charge_current_a = 0.0;
    double max_discharge_current_a = 0.0;
    double min_temperature_c = 0.0, max_temperature_c = 0.0;  // chamber set points stay inside
    double surface_area_m2 = 0.0;             // total surface; 0 = not given
    std::optional<std::filesystem::path> params_path;  // a cellbench.params/1 starting point (resolved)
    nlohmann::json document;                  // the file as loaded

    [[nodiscard]] double one_c_a() const { return nominal_capacity_ah; }  // 1C in A (1 h)
    // The surface that turns the heat flux density into heat for this cell's runs: its own, else the bench DAQ's
    // cell_area_m2 (the run's end-of-run fit, and `cellbench fit --db --run` replaying it).
    [[nodiscard]] double surface_or(double bench_cell_area_m2) const {
        return surface_area_m2 > 0 ? surface_area_m2 : bench_cell_area_m2;
    }
    [[nodiscard]] nlohmann::json to_json() const;
    // Names and values usable in program expressions (see evaluate_expression).
    [[nodiscard]] std::map<std::string, double> constants() const;
};

// ---------------------------------------------------------------------------------------------------------
// Programs

struct CyclerSegment {
    protocol::StepProgram program;
    bool operator==(const CyclerSegment&) const = default;
};
struct ChamberSetpointSegment {
    double setpoint_c = 25.0;
    bool operator==(const ChamberSetpointSegment&) const = default;
};
// Thermal equilibrium: the chamber air AND the cell (every cell thermocouple) within tolerance_c of the
// current chamber set point, continuously for hold_s. Not reached within timeout_s: the run aborts (or, with
// abort_on_timeout = false, an alarm event is recorded and the program continues).
struct WaitEquilibriumSegment {
    double tolerance_c = 0.5;
    double hold_s = 1800.0;
    double timeout_s = 4.0 * 3600.0;
    bool abort_on_timeout = true;
    bool operator==(const WaitEquilibriumSegment&) const = default;
};
using Segment = std::variant<CyclerSegment, ChamberSetpointSegment, WaitEquilibriumSegment>;
std::string_view segment_type(const Segment& segment);  // "cycler", "chamber_setpoint", "wait_equilibrium"

// A program's declared parameter beyond its default value. A declaration is either a number (the default,
// any finite override allowed) or an object:
//   "c_rate": {"default": 1.0, "min": 0.05, "max": 5, "unit": "C", "description": "pulse current / 1C"}
// with optional "integer": true (an override must be a whole number). Overrides outside [min, max] are refused
// by the loader, as are overrides the program does not declare; the expanded program is then checked against
// the cell's and the bench's limits as always.
struct ProgramParameter {
    std::optional<double> min, max;  // inclusive
    bool integer = false;
    std::string unit;
    std::string description;

    [[nodiscard]] bool plain() const { return !min && !max && !integer && unit.empty() && description.empty(); }
    bool operator==(const ProgramParameter&) const = default;
};

struct Program {
    std::string name;
    std::string description;
    std::map<std::string, double> parameters;  // values used (defaults with overrides applied)
    std::map<std::string, ProgramParameter> parameter_specs;  // declarations (every declared name has one)
    std::vector<Segment> segments;             // expanded: no expressions, repetitions unrolled

    bool operator==(const Program&) const = default;
    [[nodiscard]] double max_current_a() const;
    // Expanded form (schema cellbench.bench-program/1, numbers only); parse_program reads it back unchanged.
    [[nodiscard]] nlohmann::json to_json() const;
};

// Overrides of declared parameters, by name, as a client sent them (POST /runs "parameters", `--param K=V`).
// Values are JSON so that the loader, the one validator, reports a wrong type ("c_rate": "fast") with the rest.
using ProgramOverrides = std::map<std::string, nlohmann::json>;

// How long a program is expected to run on a cell, in bench seconds (progress by expected time, `check`).
// An estimate: time limits as written; a constant-current phase that runs to a voltage limit moves the SOC to
// 0 or 1 at its current with the nominal capacity; a capacity limit is taken at its value (step capacities at
// their nominal values, as `cellbench steps` writes them); the CV phase of a CCCV step adds kCvTailS; a loop
// runs its body `count` times in all; a wait for equilibrium its hold_s. The SOC starts at kStartSoc.
struct ProgramEstimate {
    static constexpr double kStartSoc = 0.5;
    static constexpr double kCvTailS = 900.0;
    double total_s = 0.0;
    std::vector<double> segment_s;  // per segment of the program
};
ProgramEstimate estimate_duration(const Program& program, const CellConfig& cell);

// `K=V` as given on a command line: V is a JSON number when it reads as one ("2", "0.5", "1e-3"), true/false
// as booleans, else a string (which the loader then refuses as the wrong type, naming it). Throws InputError
// for text without '=' or with an empty name.
std::pair<std::string, nlohmann::json> parse_override_argument(std::string_view text);

// ---------------------------------------------------------------------------------------------------------
// Loaders. All throw ConfigError listing every problem (InputError for an unreadable file or invalid JSON,
// naming the line and column).

BenchConfig load_bench_config(const std::filesystem::path& file);
// base_dir resolves relative file references (simulation.params).
BenchConfig parse_bench_config(const nlohmann::json& j, const std::string& source,
                               const std::filesystem::path& base_dir);

CellConfig load_cell_config(const std::filesystem::path& file);
CellConfig parse_cell_config(const nlohmann::json& j, const std::string& source,
                             const std::filesystem::path& base_dir, std::string id = {});

// Expands a program for a cell: parameters (declared defaults, then overrides; an override the program does
// not declare is an error), expressions, repetitions. Every step and set point is checked against the cell's
// limits and, when given, the bench's (safety limits, cycler group current, chamber set point range).
Program load_program(const std::filesystem::path& file, const CellConfig& cell,
                     const ProgramOverrides& overrides = {}, const BenchConfig* bench = nullptr);
Program parse_program(const nlohmann::json& j, const std::string& source, const CellConfig& cell,
                      const ProgramOverrides& overrides = {}, const BenchConfig* bench = nullptr);

// The same loaders from JSON text as read from a file (no file I/O for the document itself; files it refers
// to, such as a parameter set, are still read). `source` names the text in messages as the file name does;
// invalid JSON throws InputError naming source, line and column. load_* read the file and call these.
BenchConfig parse_bench_config_text(std::string_view text, const std::string& source,
                                    const std::filesystem::path& base_dir);
CellConfig parse_cell_config_text(std::string_view text, const std::string& source,
                                  const std::filesystem::path& base_dir, std::string id = {});
Program parse_program_text(std::string_view text, const std::string& source, const CellConfig& cell,
                           const ProgramOverrides& overrides = {}, const BenchConfig* bench = nullptr);

// Files by name, as POST /runs names them ({"program": "hppc", "cell": "p45b"}): config_dir/programs/NAME.json
// and config_dir/cells/NAME.json. Names are [A-Za-z0-9_.-]+ without a leading dot (never a path): anything
// else throws InputError. The file need not exist (the loader says so).
std::filesystem::path program_file(const std::filesystem::path& config_dir, std::string_view name);
std::filesystem::path cell_file(const std::filesystem::path& config_dir, std::string_view name);
// Names (file stems) of the loadable files in config_dir/programs and config_dir/cells, sorted. Cell files
// whose schema is not cellbench.cell/1 (parameter sets such as p45b-thesis.json) are skipped.
std::vector<std::string> list_programs(const std::filesystem::path& config_dir);
std::vector<std::string> list_cells(const std::filesystem::path& config_dir);

// ---------------------------------------------------------------------------------------------------------
// Expressions in program files.
//
// Grammar: sum = term (('+'|'-') term)*; term = factor (('*'|'/') factor)*; factor = ['-'|'+'] (number |
// name | '(' sum ')'). Names: the program's parameters and the cell's constants (nominal_capacity_ah,
// one_c_a, min_voltage_v, max_voltage_v, max_charge_current_a, max_discharge_current_a, min_temperature_c,
// max_temperature_c). In `cutoff_capacity_ah` the tester's step capacities C1, C2, ... may also appear
// (linearly: "0.1*C4 - C8 + C10", "soc_step * nominal_capacity_ah - C4 + C6"); they stay symbolic and are
// evaluated by the tester when the step runs.
//
// Throws InputError (message without location) for syntax errors, unknown names, division by zero and
// non-finite results.
double evaluate_expression(std::string_view text, const std::map<std::string, double>& names);

}  // namespace cellbench::daemon
