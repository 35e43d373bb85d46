#include "cellbench/sequencer/worker_pool.hpp"

#include <algorithm>

namespace cellbench::sequencer {

OrderedWorkerPool::OrderedWorkerPool(std::size_t threads) : max_threads_(std::max<std::size_t>(1, threads)) {}

OrderedWorkerPool::~OrderedWorkerPool() {
    // Every queued job has a worker that takes it before ending (submit starts one whenever fewer than the bound
    // run, and a worker ends only on an empty queue): joining them all finishes and delivers every job.
    // A delivery may submit more work meanwhile: its worker is joined in the next pass.
    for (;;) {
        std::vector<std::thread> batch;
        std::vector<std::thread::id> ids;
        {
            std::lock_guard lock(mutex_);
            if (workers_.empty()) break;
            batch.swap(workers_);
        }
        for (auto& t : batch) {
            ids.push_back(t.get_id());
            if (t.joinable()) t.join();
        }
        std::lock_guard lock(mutex_);
        for (const auto& id : ids) std::erase(ended_, id);
    }
}

std::vector<std::thread> OrderedWorkerPool::take_ended_locked() {
    std::vector<std::thread> done;
    for (auto it = workers_.begin(); it != workers_.end();) {
        if (std::find(ended_.begin(), ended_.end(), it->get_id()) != ended_.end()) {
            std::erase(ended_, it->get_id());
            done.push_back(std::move(*it));
            it = workers_.erase(it);
        } else {
            ++it;
        }
    }
    return done;
}

void OrderedWorkerPool::submit(Job job) {
    std::vector<std::thread> ended;
    {
        std::lock_guard lock(mutex_);
        queue_.emplace_back(next_serial_++, std::move(job));
        ended = take_ended_locked();
        if (running_ < max_threads_) {
            ++running_;
            workers_.emplace_back([this] { work(); });
        }
    }
    for (auto& t : ended) t.join();  // already returned from work(): no wait on a job
}

void OrderedWorkerPool::wait_idle() {
    std::unique_lock lock(mutex_);
    idle_cv_.wait(lock, [&] { return next_delivery_ == next_serial_; });
}

std::size_t OrderedWorkerPool::live_threads() {
    std::lock_guard lock(mutex_);
    return running_;
}

bool OrderedWorkerPool::idle() {
    std::lock_guard lock(mutex_);
    return next_delivery_ == next_serial_;  // counted after each delivery has returned
}

// Delivers, in serial order, every computed job whose turn has come; one thread delivers at a time (outside
// the lock: a delivery may take the sink's locks or submit more jobs).
void OrderedWorkerPool::deliver_ready_locked(std::unique_lock<std::mutex>& lock) {
    if (delivering_) return;
    delivering_ = true;
    for (auto it = ready_.find(next_delivery_); it != ready_.end(); it = ready_.find(next_delivery_)) {
        auto deliver = std::move(it->second);
        ready_.erase(it);
        lock.unlock();
        try {
            if (deliver) deliver();
        } catch (...) {
            // a delivery that throws must not take the pool down; the sink reports its own failures
        }
        lock.lock();
        ++next_delivery_;
        idle_cv_.notify_all();
    }
    delivering_ = false;
}

void OrderedWorkerPool::work() {
    std::unique_lock lock(mutex_);
    while (!queue_.empty()) {
        auto [serial, job] = std::move(queue_.front());
        queue_.pop_front();
        lock.unlock();
        std::function<void()> deliver;
        try {
            deliver = job();
        } catch (...) {
            // compute() reports its own failures through its delivery; nothing to deliver
        }
        lock.lock();
        ready_.emplace(serial, std::move(deliver));
        deliver_ready_locked(lock);
    }
    // The queue is empty under the lock: a later submit sees running_ below the bound and starts a worker.
    --running_;
    ended_.push_back(std::this_thread::get_id());
}

}  // namespace cellbench::sequencer
