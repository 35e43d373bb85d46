#pragma once
// `cellbench fit --db BENCH.sqlite --run ID`: a stored run replayed through the run engine's own online
// fitter (sequencer::Sequencer: the pulse-set detector, the per-pulse-set fit, the final characterization),
// so that it gives the parameters the daemon gave, or the ones it would have given when the daemon died first.
//
// How: the run's expanded program (its record's config) is started on a Sequencer whose instruments do
// nothing; the stored samples are fed in the order the daemon stored them, on the run's clock (t_s), with
// DAQ and chamber samples merged in by time. What the stored rows do not carry is taken from the run's events:
// a cycler segment ends where its "step program finished" event is, a wait for equilibrium where its
// "equilibrium" event is. Safety limits are not re-applied (the run already ran). Pulse fits are numbered and
// placed (start time, SOC from the Coulomb count since the last full charge) by the rule the daemon uses.
//
// Exact: every fitted value of a pulse set (R0, R1, C1, R2, C2 both ways, OCV, method, RMS) - the fit sees the
// same rows. Close, not exact: SOC (the daemon counts charge on another thread than the one that sees the step
// start: up to one download batch of rows apart) and temperature (the daemon attaches the DAQ reading current
// when a row arrives; the replay the one current at the row's time).
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/run_store.hpp"
#include "cellbench/estimator/params.hpp"

namespace cellbench::daemon {

struct ReplayedRun {
    RunInfo run;                              // as stored (config included)
    std::vector<PulseFitRecord> fits;         // as the daemon would record them (GET /runs/{id}/fits)
    std::optional<estimator::ParameterSet> params;  // the final characterization of the replayed recording
    nlohmann::json summary;                   // its summary (fit --json), null without params
    std::string params_error;                 // why there is no parameter set
    std::vector<std::string> warnings;        // fit warnings the sequencer raised during the replay
    std::size_t cycler_rows = 0, daq_rows = 0, chamber_rows = 0;
};

// Throws InputError: unknown run, a run record without its program, a run without cycler samples.
ReplayedRun replay_run_fits(const RunStore& store, RunId run);

}  // namespace cellbench::daemon
