#include "cellbench/sequencer/worker_pool.hpp"

#include <algorithm>

namespace cellbench::sequencer {

OrderedWorkerPool::OrderedWorkerPool(std::size_t threads) {
    threads = std::max<std::size_t>(1, threads);
    workers_.reserve(threads);
    for (std::size_t k = 0; k < threads; ++k) workers_.emplace_back([this] { work(); });
}

OrderedWorkerPool::~OrderedWorkerPool() {
    {
        std::lock_guard lock(mutex_);
        stop_ = true;  // workers drain the queue first
    }
    cv_.notify_all();
    for (auto& t : workers_)
        if (t.joinable()) t.join();
}

void OrderedWorkerPool::submit(Job job) {
    {
        std::lock_guard lock(mutex_);
        queue_.emplace_back(next_serial_++, std::move(job));
    }
    cv_.notify_one();
}

void OrderedWorkerPool::wait_idle() {
    std::unique_lock lock(mutex_);
    idle_cv_.wait(lock, [&] { return next_delivery_ == next_serial_; });
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
    while (true) {
        cv_.wait(lock, [&] { return stop_ || !queue_.empty(); });
        if (queue_.empty()) return;  // stopping and drained
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
}

}  // namespace cellbench::sequencer
