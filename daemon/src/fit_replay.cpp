// A stored run replayed through the sequencer's online fitter: see fit_replay.hpp.
#include "cellbench/daemon/fit_replay.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>

#include "cellbench/core/recording.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/sequencer/sequencer.hpp"
#include "sequencer_program.hpp"

namespace cellbench::daemon {

namespace {

constexpr double kNoLimit = std::numeric_limits<double>::infinity();
// A wait for equilibrium in the replay: reached only by the synthetic readings placed at the stored
// "equilibrium" event (exactly at the target), never by a stored sample.
constexpr double kReplayTolerance = 1e-12;

class NullCycler : public sequencer::Cycler {
public:
    void start(const protocol::StepProgram&, const std::string&) override {}
    void stop() override {}
    void pause() override {}
    void resume() override {}
};
class NullChamber : public sequencer::Chamber {
public:
    void set_setpoint(double) override {}
    void set_running(bool) override {}
};

// Collects what the sequencer reports and turns pulse fits into the records the daemon stores: SOC and the
// pulse set's time as the sequencer (SOC's one owner) gives them, as bench_daemon.cpp's RunContext does.
class ReplaySink : public sequencer::RunSink {
public:
    explicit ReplaySink(RunId id) : id_(id) {}

    void on_state(sequencer::RunState, const std::string&) override {}
    void on_step(double, int, int, int, const std::string&) override {}
    void on_event(double, const std::string& severity, const std::string& kind, const std::string& message) override {
        if (severity != "warning" || kind != "fit") return;
        std::lock_guard lock(m_);
        warnings_.push_back(message);
    }
    void on_pulse_fit(const estimator::PulseSetFit& fit, double t_s) override {
        std::lock_guard lock(m_);
        const int n = static_cast<int>(fits_.size()) + 1;
        fits_.push_back(pulse_fit_record(id_, n, t_s, kNaN, fit));
    }
    void on_parameter_set(const estimator::ParameterSet& params, const nlohmann::json& summary) override {
        std::lock_guard lock(m_);
        params_ = params;
        summary_ = summary;
    }

    void take(ReplayedRun& out) {
        std::lock_guard lock(m_);
        out.fits = std::move(fits_);
        out.params = std::move(params_);
        out.summary = std::move(summary_);
        out.warnings = std::move(warnings_);
    }

private:
    RunId id_;
    std::mutex m_;
    std::vector<PulseFitRecord> fits_;
    std::optional<estimator::ParameterSet> params_;
    nlohmann::json summary_;
    std::vector<std::string> warnings_;
};

// The run's program as the daemon gave it to its sequencer, with every equilibrium wait made to pass as soon as
// the recorded temperatures allow (a replay has no chamber to wait for).
sequencer::Program replay_program(const Program& p) {
    sequencer::Program out = to_sequencer_program(p);
    for (auto& s : out.segments)
        if (s.kind == sequencer::Segment::Kind::WaitEquilibrium) {
            s.tolerance_c = kReplayTolerance;
            s.hold_s = 0.0;
            s.timeout_s = kNoLimit;
        }
    return out;
}

bool starts_with(const std::string& s, std::string_view prefix) { return s.rfind(prefix, 0) == 0; }

}  // namespace

ReplayedRun replay_run_fits(const RunStore& store, RunId run) {
    ReplayedRun out;
    const auto info = store.get_run(run);
    if (!info) throw InputError(store.path().string() + ": no run " + std::to_string(run));
    out.run = *info;
    const std::string source = store.path().filename().string() + " run " + std::to_string(run);
    const auto& config = info->config;
    if (!config.is_object() || !config.contains("program") || !config.contains("cell"))
        throw InputError(source + ": the run record has no program or cell (a database from an older cellbench?)");

    // The cell as the run recorded it; its parameter-set reference is not needed (and is relative to a config
    // folder this tool may not have).
    nlohmann::json cell_doc = config["cell"];
    if (cell_doc.is_object()) cell_doc.erase("params");
    const CellConfig cell = parse_cell_config(cell_doc, source + " cell", ".", info->cell);
    const Program program = parse_program(config["program"], source + " program", cell);

    // The capacity the daemon counted SOC with: in the "run started" event, else the cell's nominal one.
    double capacity_ah = cell.nominal_capacity_ah;
    std::vector<double> equilibrium_t, finished_t;
    std::int64_t after = 0;
    for (;;) {
        const auto events = store.events(run, after, 10000);
        for (const auto& e : events) {
            after = e.id;
            if (e.kind == "operator" && starts_with(e.message, "run started") && e.detail.is_object() &&
                e.detail.contains("capacity_ah") && e.detail["capacity_ah"].is_number() &&
                e.detail["capacity_ah"].get<double>() > 0)
                capacity_ah = e.detail["capacity_ah"].get<double>();
            if (!e.t_s) continue;
            if (e.kind == "equilibrium" && starts_with(e.message, "cell and chamber at")) equilibrium_t.push_back(*e.t_s);
            if (e.kind == "cycler" && starts_with(e.message, "step program finished")) finished_t.push_back(*e.t_s);
        }
        if (events.size() < 10000) break;
    }

    const auto cycler = store.cycler_rows(run);
    if (cycler.empty()) throw InputError(source + ": the run has no cycler samples to replay");
    const auto daq = store.daq_rows(run);
    const auto chamber = store.chamber_rows(run);
    out.cycler_rows = cycler.size();
    out.daq_rows = daq.size();
    out.chamber_rows = chamber.size();

    sequencer::SequencerOptions so;
    so.limits.max_temperature_c = kNoLimit;
    so.limits.min_voltage_v = -kNoLimit;
    so.limits.max_voltage_v = kNoLimit;
    so.limits.max_current_a = kNoLimit;
    so.limits.chamber_deviation_c = kNoLimit;
    so.limits.instrument_loss_grace_s = kNoLimit;
    so.capacity_ah = capacity_ah;
    // The surface the daemon gave its sequencer: the cell's, else the bench DAQ's cell_area_m2 the run recorded.
    double bench_cell_area_m2 = DaqConfig{}.cell_area_m2;
    if (const auto bench = config.value("bench", nlohmann::json::object()); bench.is_object()) {
        const auto area = nlohmann::json::json_pointer("/instruments/daq/cell_area_m2");
        if (bench.contains(area) && bench[area].is_number() && bench[area].get<double>() > 0)
            bench_cell_area_m2 = bench[area].get<double>();
    }
    so.area_m2 = cell.surface_or(bench_cell_area_m2);
    NullCycler null_cycler;
    NullChamber null_chamber;
    ReplaySink sink(run);
    sequencer::Sequencer seq(null_cycler, null_chamber, sink, so);
    seq.start(replay_program(program), 0.0);

    // Everything on the run's clock, t_s (the daemon's t_mono minus the run's start: the sequencer's own
    // relative times come out identical).
    double last_t = kNaN, last_v = kNaN, target_c = kNaN;
    for (const auto& seg : program.segments)
        if (const auto* sp = std::get_if<ChamberSetpointSegment>(&seg)) target_c = sp->setpoint_c;
    std::size_t di = 0, ci = 0, ei = 0, fi = 0;
    auto chamber_sample = [](const ChamberSample& r) {
        return sequencer::ChamberSample{r.t_s, r.unix_s, r.ambient_c, r.setpoint_c, r.running.value_or(true), r.alarm_bits};
    };
    auto flush_until = [&](double t) {
        for (;;) {
            // The earliest pending item before t: DAQ, chamber, equilibrium, segment end.
            double best = t;
            int which = -1;
            if (di < daq.size() && daq[di].t_s < best) best = daq[di].t_s, which = 0;
            if (ci < chamber.size() && chamber[ci].t_s < best) best = chamber[ci].t_s, which = 1;
            if (ei < equilibrium_t.size() && equilibrium_t[ei] < best) best = equilibrium_t[ei], which = 2;
            if (fi < finished_t.size() && finished_t[fi] < best) best = finished_t[fi], which = 3;
            if (which < 0) return;
            if (which == 0) {
                const auto& r = daq[di++];
                seq.on_daq({r.t_s, r.unix_s, r.thermopile_v, r.surface_c, r.t1_c, r.t2_c, r.heat_flux_w_per_m2});
            } else if (which == 1) {
                seq.on_chamber(chamber_sample(chamber[ci++]));
            } else if (which == 2) {
                // The stored equilibrium: readings exactly at the set point end the (replay's) wait now.
                const double te = equilibrium_t[ei++];
                if (!std::isfinite(target_c)) continue;
                seq.on_chamber({te, 0.0, target_c, target_c, true, 0});
                // (The first reading starts the hold, the second ends it: hold_s is 0 in the replay.)
                seq.on_daq({te, 0.0, 0.0, target_c, target_c, target_c, 0.0});
                seq.on_daq({te, 0.0, 0.0, target_c, target_c, target_c, 0.0});
            } else {
                // The live reading that said the tester's program finished (not stored when the tester records).
                const double tf = finished_t[fi++];
                sequencer::CyclerSample fin;
                fin.t_mono_s = tf;
                fin.voltage_v = std::isfinite(last_v) ? last_v : 0.0;
                fin.status = "finish";
                fin.covered_by_records = true;
                seq.on_cycler(fin);
            }
        }
    };

    for (const auto& r : cycler) {
        flush_until(r.t_s);
        if (!std::isfinite(last_t) || r.t_s > last_t) last_t = r.t_s;
        if (std::isfinite(r.voltage_v)) last_v = r.voltage_v;
        sequencer::CyclerSample cs;
        cs.t_mono_s = r.t_s;
        cs.t_wall_s = r.unix_s;
        cs.voltage_v = r.voltage_v;
        cs.current_a = r.current_a;
        cs.capacity_ah = r.capacity_ah;
        cs.energy_wh = r.energy_wh;
        cs.step_id = r.step_id;
        cs.cycle_id = r.cycle;
        cs.step_type = r.step_type;
        // Every stored row is part of the recording; the end of a program comes from its event (flush_until),
        // where the daemon saw it.
        cs.status = "working";
        seq.on_cycler(cs);
    }
    flush_until(kNoLimit);
    seq.wait_for_fits();
    sink.take(out);

    if (!out.params) {
        // A run that did not complete (stopped, aborted, interrupted) got no final fit online: fit the replayed
        // recording the same way.
        try {
            const auto c = estimator::characterize({seq.recording()});
            out.params = c.params;
            out.summary = c.summary_json();
        } catch (const std::exception& e) {
            out.params_error = e.what();
        }
    }
    return out;
}

}  // namespace cellbench::daemon
