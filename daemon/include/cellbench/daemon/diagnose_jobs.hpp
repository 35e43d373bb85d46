#pragma once
// cellbenchd's diagnosis jobs (POST /runs/{id}/diagnose, POST /diagnose, GET /diagnoses/{job}; api.hpp):
// estimator::diagnose on one worker thread of its own, never on the HTTP I/O threads.
//
// - One job at a time, first come first served; up to max_waiting jobs wait behind it ("state": "running",
//   "stage": "waiting (N ahead)", "position": N). A submit beyond that is refused (Conflict, 409).
// - The last `keep` finished jobs (done or failed) are kept in memory with their results; older ones are
//   forgotten (GET answers 404). Nothing is persisted: a restart forgets every job.
// - The worker runs at a lower CPU priority (nice +10, inherited by the estimator's candidate threads), so a
//   run being recorded keeps the CPU it needs.
// - stop() (daemon shutdown) drops the waiting jobs, asks the running one to give up (estimator
//   DiagnoseOptions::cancel: it ends after the candidate fits under way) and joins the worker.
#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/params.hpp"

namespace cellbench::daemon {

struct DiagnoseJobsOptions {
    std::size_t keep = 8;              // finished jobs kept
    std::size_t max_waiting = 4;       // queued behind the running one
    std::size_t threads = 0;           // estimator worker threads; 0 = cores - 1 (at least 1)
    std::size_t max_trace_points = 2000;
    int nice = 10;                     // added to the worker thread's nice value (Linux); 0 = unchanged
};

// What a job works on, produced on the worker thread (reading a run from the database or parsing an upload
// may take seconds). Throwing (InputError, ...) fails the job with the message.
struct DiagnoseInput {
    estimator::ParameterSet params;
    Recording recording;
    std::vector<Recording> confirm;  // other recordings of the cell the findings must hold on (may be empty)
};

class DiagnoseJobs {
public:
    using Loader = std::function<DiagnoseInput(const std::function<void(std::string_view)>& stage)>;

    explicit DiagnoseJobs(DiagnoseJobsOptions options = {});
    ~DiagnoseJobs();  // stop()
    DiagnoseJobs(const DiagnoseJobs&) = delete;
    DiagnoseJobs& operator=(const DiagnoseJobs&) = delete;

    // Queues a job: `info` (an object: "source", "params", ...) is merged into the job's JSON. Returns the job
    // (api.hpp "Job"). Throws Conflict when max_waiting jobs are waiting, Unavailable after stop().
    nlohmann::json submit(nlohmann::json info, std::vector<std::string> effects, Loader load);

    // The job with its results. Throws NotFound for an unknown or forgotten id.
    [[nodiscard]] nlohmann::json get(std::int64_t id) const;
    // Every job kept, newest first, without the results (diagnosis, traces, improved_params).
    [[nodiscard]] nlohmann::json list() const;

    void stop();

private:
    struct Job;
    void loop();
    void run(const std::shared_ptr<Job>& job);
    nlohmann::json job_json(const Job& job, bool results) const;  // under m_

    DiagnoseJobsOptions opt_;
    mutable std::mutex m_;
    std::condition_variable cv_;
    std::deque<std::shared_ptr<Job>> waiting_;
    std::shared_ptr<Job> running_;  // being worked on
    std::map<std::int64_t, std::shared_ptr<Job>> jobs_;  // every job kept (waiting, running, finished)
    std::int64_t next_id_ = 1;
    bool stopping_ = false;
    std::atomic<bool> cancel_{false};
    std::thread worker_;
};

}  // namespace cellbench::daemon
