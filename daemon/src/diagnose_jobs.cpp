#include "cellbench/daemon/diagnose_jobs.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <iterator>

#include <spdlog/spdlog.h>

#include "cellbench/daemon/api.hpp"
#include "cellbench/estimator/diagnose.hpp"

namespace cellbench::daemon {

using nlohmann::json;

namespace {

double unix_now_s() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

}  // namespace

struct DiagnoseJobs::Job {
    std::int64_t id = 0;
    json info;
    std::vector<std::string> effects;
    Loader load;
    std::string state = "running";  // running | done | failed
    bool started = false;
    double progress = 0.0;
    std::string stage = "waiting";
    double created_unix_s = 0.0;
    double finished_unix_s = NAN;
    double wall_s = NAN;
    std::string error;
    json diagnosis, traces, improved_params;
};

DiagnoseJobs::DiagnoseJobs(DiagnoseJobsOptions options) : opt_(std::move(options)) {
    worker_ = std::thread([this] { loop(); });
}

DiagnoseJobs::~DiagnoseJobs() { stop(); }

void DiagnoseJobs::stop() {
    {
        std::lock_guard l(m_);
        if (stopping_ && !worker_.joinable()) return;
        stopping_ = true;
        for (auto& j : waiting_) {
            j->state = "failed";
            j->error = "cellbenchd stopped before the job started";
            j->finished_unix_s = unix_now_s();
        }
        waiting_.clear();
    }
    cancel_ = true;
    cv_.notify_all();
    if (worker_.joinable() && worker_.get_id() != std::this_thread::get_id()) worker_.join();
}

json DiagnoseJobs::submit(json info, std::vector<std::string> effects, Loader load) {
    std::lock_guard l(m_);
    if (stopping_) throw Unavailable("cellbenchd is shutting down");
    if (waiting_.size() >= opt_.max_waiting)
        throw Conflict("the diagnosis queue is full (" + std::to_string(waiting_.size()) +
                       " jobs waiting behind the running one); try again when one has finished");
    auto job = std::make_shared<Job>();
    job->id = next_id_++;
    job->info = info.is_object() ? std::move(info) : json::object();
    job->effects = std::move(effects);
    job->load = std::move(load);
    job->created_unix_s = unix_now_s();
    waiting_.push_back(job);
    jobs_[job->id] = job;
    cv_.notify_all();
    spdlog::info("diagnosis job {} queued: {}", job->id, job->info.dump(-1, ' ', false, json::error_handler_t::replace));
    return job_json(*job, false);
}

json DiagnoseJobs::get(std::int64_t id) const {
    std::lock_guard l(m_);
    const auto it = jobs_.find(id);
    if (it == jobs_.end())
        throw NotFound("no diagnosis job " + std::to_string(id) + " (only the last " + std::to_string(opt_.keep) +
                       " finished jobs are kept, and none across a restart)");
    return job_json(*it->second, true);
}

json DiagnoseJobs::list() const {
    std::lock_guard l(m_);
    json out = json::array();
    for (auto it = jobs_.rbegin(); it != jobs_.rend(); ++it) out.push_back(job_json(*it->second, false));
    return {{"diagnoses", std::move(out)}};
}

json DiagnoseJobs::job_json(const Job& j, bool results) const {
    json o = j.info;
    o["id"] = j.id;
    o["state"] = j.state;
    o["progress"] = j.progress;
    o["stage"] = j.stage;
    if (j.state == "running") {
        std::size_t ahead = 0;
        const auto it = std::find_if(waiting_.begin(), waiting_.end(), [&](const auto& w) { return w.get() == &j; });
        if (it != waiting_.end()) ahead = static_cast<std::size_t>(it - waiting_.begin()) + (running_ ? 1 : 0);
        o["position"] = ahead;
        if (!j.started) o["stage"] = "waiting (" + std::to_string(ahead) + " ahead)";
    }
    o["effects"] = j.effects;
    o["created_unix_s"] = j.created_unix_s;
    o["finished_unix_s"] = std::isfinite(j.finished_unix_s) ? json(j.finished_unix_s) : json(nullptr);
    o["wall_s"] = std::isfinite(j.wall_s) ? json(j.wall_s) : json(nullptr);
    if (j.state == "failed") o["error"] = j.error;
    if (results && j.state == "done") {
        o["diagnosis"] = j.diagnosis;
        o["traces"] = j.traces;
        o["improved_params"] = j.improved_params;
    }
    return o;
}

void DiagnoseJobs::loop() {
    if (opt_.nice != 0) {
        // Linux: the nice value is per thread and inherited by the threads this one creates (the estimator's).
        errno = 0;
        if (::setpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid)), opt_.nice) != 0)
            spdlog::debug("diagnosis worker: setpriority: {}", std::strerror(errno));
    }
    std::unique_lock l(m_);
    while (true) {
        cv_.wait(l, [&] { return stopping_ || !waiting_.empty(); });
        if (stopping_) return;
        auto job = waiting_.front();
        waiting_.pop_front();
        job->started = true;
        job->stage = "starting";
        running_ = job;
        l.unlock();
        run(job);
        l.lock();
        running_.reset();
        // Forget the oldest finished jobs beyond `keep`.
        std::size_t finished = 0;
        for (auto it = jobs_.rbegin(); it != jobs_.rend();) {
            const bool done = it->second->state != "running";
            if (done && ++finished > opt_.keep) {
                it = std::make_reverse_iterator(jobs_.erase(std::next(it).base()));
            } else {
                ++it;
            }
        }
    }
}

void DiagnoseJobs::run(const std::shared_ptr<Job>& job) {
    const auto t0 = std::chrono::steady_clock::now();
    const auto set_stage = [&](double fraction, std::string_view stage) {
        std::lock_guard l(m_);
        job->progress = std::clamp(fraction, job->progress, 1.0);
        job->stage = std::string(stage);
    };
    std::string error;
    json diagnosis, traces, improved;
    try {
        set_stage(0.0, "reading the recording");
        const DiagnoseInput in = job->load([&](std::string_view stage) { set_stage(0.0, stage); });
        estimator::DiagnoseOptions o;
        o.effects = job->effects;
        o.threads = opt_.threads ? opt_.threads : std::max(1u, std::thread::hardware_concurrency()) - 1;
        if (o.threads == 0) o.threads = 1;
        o.cancel = &cancel_;
        for (const auto& c : in.confirm) o.confirm.push_back(&c);
        // The estimator reports 1.0 when its work is done; the job is done when its results are stored.
        o.progress = [&](double f, std::string_view stage) { set_stage(std::min(f, 0.99), stage); };
        const estimator::Diagnosis d = estimator::diagnose(in.params, in.recording, o);
        set_stage(0.99, "preparing the traces");
        diagnosis = estimator::diagnosis_to_json(d);
        traces = estimator::traces_to_json(estimator::diagnosis_traces(d, in.recording, opt_.max_trace_points));
        improved = d.accepted.empty() ? json(nullptr) : d.improved_params.to_json();
    } catch (const estimator::DiagnoseCancelled&) {
        error = "cancelled: cellbenchd is shutting down";
    } catch (const std::exception& e) {
        error = e.what();
    }
    const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::lock_guard l(m_);
    job->finished_unix_s = unix_now_s();
    job->wall_s = wall;
    job->load = nullptr;  // frees what the loader captured (an uploaded recording)
    if (error.empty()) {
        job->state = "done";
        job->progress = 1.0;
        job->stage = "done";
        job->diagnosis = std::move(diagnosis);
        job->traces = std::move(traces);
        job->improved_params = std::move(improved);
        spdlog::info("diagnosis job {} done in {:.1f} s", job->id, wall);
    } else {
        job->state = "failed";
        job->stage = "failed";
        job->error = error;
        spdlog::warn("diagnosis job {} failed after {:.1f} s: {}", job->id, wall, error);
    }
}

}  // namespace cellbench::daemon
