#pragma once
// What the HTTP layer (http_server.hpp) needs from the daemon: the REST/JSON API of INTERFACES.md as an
// abstract backend. The server owns transport, routing, limits and authentication; the backend owns the
// bench. Keeping this seam abstract lets the server be tested over real sockets with a fake backend.
//
// Threading: the server calls the backend from several io_context threads at once (one call per
// connection at a time), so every method must be thread-safe. Calls should return quickly (milliseconds):
// they run on the daemon's I/O threads. Long work (a run) is started, not awaited.
//
// Errors: throw one of the ApiError types below; the server maps them to the HTTP status and a JSON body
// {"error": what()}. Any other exception becomes 500 with a generic message (details only in the log).
//
// JSON shapes (consumed by `cellbench status|runs|start|stop|export` and the future dashboard). Times are
// seconds: `*_unix_s` wall clock (UTC, fractional), `test_time_s` since the run started. Unknown or not
// measured values are null. Fields may be added; none of those documented here may be dropped or renamed.
//
//   Run  (one element of GET /runs, the body of GET /runs/{id}, POST /runs and POST /runs/{id}/...):
//     {"id": 3, "program": "hppc", "cell": "p45b",
//      "state": "running",            // "starting" | "running" | "paused" | "completed" | "stopped" | "failed"
//      "created_unix_s": 1.7e9, "started_unix_s": 1.7e9 | null, "ended_unix_s": null,
//      "samples": 12345,              // rows recorded so far
//      "step": Step | null,           // the current step while active, else null
//      "error": null | "why the run failed",
//      "outcome": null | "completed" | "stopped" | "aborted" | "interrupted"}
//                                     // how a finished run ended: "failed" is "aborted" (a fault or a safety
//                                     // limit ended it) or "interrupted" (the daemon died while it was live;
//                                     // marked at restart, with a "recovery" event; it never continues)
//   Step:
//     {"index": 12, "count": 140,     // 1-based index into the program's steps, and how many there are
//      "type": "CC discharge",        // step kind as the program names it (Rest, CC charge, CV charge, ...)
//      "elapsed_s": 3.5}              // time spent in this step
//   Live values (latest sample of the bench; null when the instrument does not measure it / is offline):
//     {"time_unix_s": 1.7e9, "test_time_s": 812.4 | null, "voltage_v": 3.712, "current_a": -3.82,
//      "soc": 0.621,                  // fraction 0..1 (Coulomb-counted estimate of the active run)
//      "surface_c": 30.4, "ambient_c": 30.0, "t1_c": 30.9, "t2_c": 30.7, "heat_flux_w_per_m2": 41.2}
//
// Terminal run states are "completed", "stopped" (by the operator) and "failed" (see "error").
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace cellbench::daemon {

// The text of an API answer: compact JSON; backend strings may carry invalid UTF-8 (instrument text), which is
// replaced rather than failing the response.
inline std::string api_json_text(const nlohmann::json& j) {
    return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

// Base of the errors the server maps to a status; what() is the message shown to the client.
class ApiError : public std::runtime_error {
public:
    ApiError(int status, const std::string& message) : std::runtime_error(message), status_(status) {}
    [[nodiscard]] int status() const { return status_; }

private:
    int status_;
};
// 404: unknown run id (or other missing resource).
struct NotFound : ApiError {
    explicit NotFound(const std::string& m) : ApiError(404, m) {}
};
// 400: a request the backend cannot accept as given (unknown program or cell name, bad range, ...).
struct BadRequest : ApiError {
    explicit BadRequest(const std::string& m) : ApiError(400, m) {}
};
// 409: the request conflicts with the bench's state (a run is already active, the run is not paused, ...).
struct Conflict : ApiError {
    explicit Conflict(const std::string& m) : ApiError(409, m) {}
};
// 503: the daemon cannot serve this now (instruments offline, database unavailable, shutting down).
struct Unavailable : ApiError {
    explicit Unavailable(const std::string& m) : ApiError(503, m) {}
};

using RunId = std::int64_t;

// GET /runs/{id}/samples?from=&to=&max_points= ; the server validates the numbers (400 when malformed).
struct SampleQuery {
    std::optional<double> from_s;  // test time, inclusive; absent = from the start
    std::optional<double> to_s;    // test time, inclusive; absent = to the latest sample
    std::size_t max_points = 2000;  // 1..kMaxSamplePoints; above it the backend decimates
};
inline constexpr std::size_t kDefaultSamplePoints = 2000;
inline constexpr std::size_t kMaxSamplePoints = 100000;

// POST /runs body: {"program": "hppc", "cell": "p45b", "parameters": {"c_rate": 2}} (names of files under
// config/). The server checks that both names are non-empty strings and that "parameters", when present, is an
// object; the values go to the program loader unchanged (it reports unknown names, wrong types and values out
// of the declared range all at once: a 400, nothing started). `body` is the whole request object.
struct StartRequest {
    std::string program;
    std::string cell;
    nlohmann::json body;
    std::map<std::string, nlohmann::json> parameters{};  // = daemon::ProgramOverrides (last: {program, cell, body} still reads)
};

// POST /runs/{id}/diagnose body {"params": NAME, "effects": [...]} and POST /diagnose?params=NAME&effects=a,b.
// NAME: a parameter set under config/cells/ (a cell name stands for the cell's parameter set), or "run" = the
// run's own fitted parameter set. effects: candidate effect ids (INTERFACES.md), empty = the whole catalogue.
// The server checks the shape (non-empty plain name, effects strings); the backend checks the names.
struct DiagnoseRequest {
    std::string params;
    std::vector<std::string> effects;
    // Other ended runs of the cell every finding must not make worse (estimator DiagnoseOptions::confirm).
    std::vector<std::int64_t> confirm_runs;
    nlohmann::json body;  // the request object (empty object for an upload)
};
// The most runs a diagnosis request may name to confirm its findings on (each is read from the database).
inline constexpr std::size_t kMaxConfirmRuns = 8;
// The largest recording POST /diagnose accepts (HttpServerOptions::max_upload_bytes defaults to it).
inline constexpr std::size_t kMaxUploadBytes = 64 * 1024 * 1024;

// A BDF CSV export being streamed. Pull-based so the server can write each chunk asynchronously with
// backpressure (a slow client never makes the backend buffer a whole run in memory).
class ExportCursor {
public:
    virtual ~ExportCursor() = default;
    // The next piece of the CSV (the header row first), or std::nullopt at the end. Aim for 16-256 KiB per
    // call. Called sequentially (never concurrently), possibly from different threads. An exception after
    // the first chunk aborts the transfer (the client sees a truncated chunked response, not a short file).
    virtual std::optional<std::string> next() = 0;
};

// An ExportCursor over text already in memory (small runs, tests); hands it out in 64 KiB pieces.
class StringExportCursor final : public ExportCursor {
public:
    explicit StringExportCursor(std::string text) : text_(std::move(text)) {}
    std::optional<std::string> next() override {
        if (pos_ >= text_.size()) return std::nullopt;
        const std::size_t n = std::min<std::size_t>(64 * 1024, text_.size() - pos_);
        std::string piece = text_.substr(pos_, n);
        pos_ += n;
        return piece;
    }

private:
    std::string text_;
    std::size_t pos_ = 0;
};

class ApiBackend {
public:
    virtual ~ApiBackend() = default;

    // GET /api/v1/health -> {"status": "ok" | "degraded", "version": "0.1.0", "uptime_s": 12.5}
    // Cheap; must not touch instruments. "degraded" when an instrument is offline (still 200).
    virtual nlohmann::json health() = 0;

    // GET /api/v1/status ->
    //   {"version": "0.1.0", "uptime_s": 12.5,
    //    "instruments": [{"name": "neware", "kind": "cycler" | "chamber" | "daq",
    //                     "state": "connected" | "connecting" | "offline" | "error",
    //                     "address": "127.0.0.1:15020", "detail": "" }],
    //    "run": Run | null,             // the active (running or paused) run, else null
    //    "live": Live values}
    virtual nlohmann::json status() = 0;

    // GET /api/v1/runs -> {"runs": [Run, ...]}  newest first.
    virtual nlohmann::json list_runs() = 0;

    // GET /api/v1/runs/{id} -> Run. NotFound for an unknown id.
    virtual nlohmann::json get_run(RunId id) = 0;

    // GET /api/v1/runs/{id}/samples ->
    //   {"run_id": 3, "from_s": 0.0, "to_s": 3600.0, "max_points": 2000,
    //    "decimated": false,
    //    "time_s": [...],                                      // test time of each row
    //    "series": {"voltage_v": [...], "current_a": [...], "soc": [...], "surface_c": [...],
    //               "ambient_c": [...], "t1_c": [...], "t2_c": [...], "heat_flux_w_per_m2": [...]}}
    // When the range holds more than max_points rows, "decimated": true and the range is cut into at most
    // max_points / 2 equal buckets: "bucket_s" is their width, "time_s" their start, and each series is
    // {"min": [...], "max": [...]} per bucket (so a plot keeps every peak). Empty buckets are omitted.
    // A series the bench does not measure is absent. NotFound for an unknown id.
    virtual nlohmann::json samples(RunId id, const SampleQuery& query) = 0;
    // The same answer serialized: the body GET /runs/{id}/samples sends. A backend may keep it while nothing new
    // is stored (the daemon does); by default it is api_json_text(samples()).
    virtual std::shared_ptr<const std::string> samples_body(RunId id, const SampleQuery& query) {
        return std::make_shared<const std::string>(api_json_text(samples(id, query)));
    }

    // GET /api/v1/runs/{id}/events ->
    //   {"run_id": 3, "events": [{"time_unix_s": 1.7e9, "test_time_s": 12.0,
    //                             "level": "info" | "warning" | "error",
    //                             "kind": "step_started" | "limit" | "instrument" | ...,
    //                             "step": 12 | null, "message": "plain words"}]}
    virtual nlohmann::json events(RunId id) = 0;

    // GET /api/v1/runs/{id}/fits -> one entry per completed HPPC pulse set (INTERFACES.md):
    //   {"run_id": 3, "fits": [{"pulse_set": 1, "test_time_s": 4200.0, "soc": 0.9, "ocv_v": 4.05,
    //     "discharge": {"r0_ohm": 0.0, "r1_ohm": 0.0, "c1_f": 0.0, "r2_ohm": 0.0, "c2_f": 0.0} | null,
    //     "charge":    {"r0_ohm": 0.0, "r1_ohm": 0.0, "c1_f": 0.0, "r2_ohm": 0.0, "c2_f": 0.0} | null}]}
    virtual nlohmann::json fits(RunId id) = 0;

    // GET /api/v1/runs/{id}/steps -> the steps the tester ran, in order (an addition to INTERFACES.md):
    //   {"run_id": 3, "steps": [{"index": 1, "segment": 2, "step_id": 8, "cycle": 3, "type": "dc",
    //     "started_s": 4200.0, "ended_s": 4230.0 | null, "capacity_ah": 0.0375 | null, "energy_wh": ... | null,
    //     "end_reason": "time"}]}
    // The default says the backend does not keep steps (404).
    virtual nlohmann::json steps(RunId id) { throw NotFound("no steps are kept for run " + std::to_string(id)); }

    // GET /api/v1/runs/{id}/export.bdf.csv -> the run as BDF CSV (INTERFACES.md), streamed.
    // Throw NotFound here (before any data) for an unknown id, so the client gets a proper 404.
    virtual std::unique_ptr<ExportCursor> export_bdf_csv(RunId id) = 0;

    // POST /api/v1/runs -> 201 with the new Run (state "starting" or "running").
    // Conflict when a run is already active; BadRequest for an unknown program or cell (say where the
    // files are looked for); Unavailable when the instruments are not ready.
    virtual nlohmann::json start_run(const StartRequest& request) = 0;

    // POST /api/v1/runs/{id}/stop|pause|resume -> Run after the change (stop: "stopped" or still
    // "running" while the safe shutdown step runs). NotFound for an unknown id; Conflict when the run is
    // not in a state that allows it (stop of a finished run, resume of a run that is not paused).
    virtual nlohmann::json stop_run(RunId id) = 0;
    virtual nlohmann::json pause_run(RunId id) = 0;
    virtual nlohmann::json resume_run(RunId id) = 0;

    // -- Diagnosis jobs (an addition to INTERFACES.md; the dashboard's Diagnosis page). `estimator::diagnose`
    // takes seconds to minutes of CPU: the backend runs it on its own worker thread, one job at a time, and
    // answers at once. Job:
    //   {"id": 4, "state": "running" | "done" | "failed", "progress": 0.0..1.0, "stage": "round 1 candidates 3/10",
    //    "position": 0,                 // while running: jobs ahead of it in the queue (0 = it is being worked on)
    //    "source": {"kind": "run", "run_id": 3, "program": "hppc", "cell": "p45b"}
    //            | {"kind": "upload", "bytes": N, "name": "file name given with ?name= or empty"},
    //    "params": "p45b" (as asked), "params_used": "p45b-thesis" (the file, or "run 3"), "effects": [...],
    //    "created_unix_s": 1.7e9, "finished_unix_s": null | 1.7e9, "wall_s": null | 12.5,
    //    "error": "why it failed",                        // failed only
    //    "diagnosis": {cellbench.diagnosis/1},            // done only (INTERFACES.md, `diagnose --json`)
    //    "traces": estimator::traces_to_json(...),        // done only: decimated measured/simulated time series
    //    "improved_params": {cellbench.params/1} | null}  // done only: base + accepted extensions (null: none)
    // POST /runs/{id}/diagnose -> 202 Job. NotFound: unknown run; Conflict: the run is still active or the
    // queue is full; BadRequest: unknown parameter set or effect, no fitted set for "run".
    virtual nlohmann::json diagnose_run(RunId id, const DiagnoseRequest& request) {
        (void)request;
        throw NotFound("diagnosis is not available for run " + std::to_string(id));
    }
    // POST /diagnose?params=NAME -> 202 Job; `csv` is a BDF CSV recording (INTERFACES.md). BadRequest for a
    // recording that does not parse (header and first rows are checked at once; a later bad row fails the job).
    virtual nlohmann::json diagnose_recording(const DiagnoseRequest& request, std::string csv) {
        (void)request;
        (void)csv;
        throw NotFound("diagnosis of uploaded recordings is not available");
    }
    // GET /diagnoses/{job} -> Job. NotFound: unknown or expired (the last few finished jobs are kept).
    virtual nlohmann::json diagnosis(std::int64_t job) { throw NotFound("no diagnosis job " + std::to_string(job)); }
    // GET /diagnoses -> {"diagnoses": [Job without diagnosis/traces/improved_params, ...]} newest first.
    virtual nlohmann::json list_diagnoses() { return {{"diagnoses", nlohmann::json::array()}}; }
    // GET /cells -> what POST /runs and the diagnosis can name under config/:
    //   {"cells": [{"name": "p45b", "description": "...", "params": "p45b-thesis" | null}],
    //    "parameter_sets": [{"name": "p45b-thesis", "cell": "Molicel INR-21700-P45B ...", "capacity_ah": 4.0}],
    //    "programs": ["cc", "hppc", ...]}
    virtual nlohmann::json cells() {
        return {{"cells", nlohmann::json::array()}, {"parameter_sets", nlohmann::json::array()},
                {"programs", nlohmann::json::array()}};
    }

    // GET /metrics: the backend's Prometheus text exposition (format 0.0.4), one "# HELP"/"# TYPE" pair
    // per family, e.g. `cellbench_cell_voltage_volts 3.712`. The server appends its own HTTP counters.
    virtual std::string metrics_text() { return {}; }
};

}  // namespace cellbench::daemon
