#pragma once
// A bounded pool of worker threads for the sequencer's fits (issue 14: every fit used to get its own
// std::thread, unbounded). Jobs compute in parallel on at most `threads` workers; each job's result (the
// callable its compute step returns) is delivered only after every earlier job's delivery, so results reach
// their sink in submission order whatever order the computations finish in.
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <thread>
#include <vector>

namespace cellbench::sequencer {

class OrderedWorkerPool {
public:
    // compute() runs on a worker; the callable it returns (may be empty) is the delivery.
    using Job = std::function<std::function<void()>()>;

    explicit OrderedWorkerPool(std::size_t threads = 2);
    ~OrderedWorkerPool();  // finishes and delivers every submitted job, then joins
    OrderedWorkerPool(const OrderedWorkerPool&) = delete;
    OrderedWorkerPool& operator=(const OrderedWorkerPool&) = delete;

    void submit(Job job);
    void wait_idle();  // every job submitted so far computed and delivered
    [[nodiscard]] bool idle();  // nothing queued, computing or undelivered (never blocks on a job)
    [[nodiscard]] std::size_t threads() const { return workers_.size(); }

private:
    void work();
    void deliver_ready_locked(std::unique_lock<std::mutex>& lock);

    std::mutex mutex_;
    std::condition_variable cv_;       // jobs queued / stopping
    std::condition_variable idle_cv_;  // a delivery happened
    std::deque<std::pair<std::uint64_t, Job>> queue_;
    std::map<std::uint64_t, std::function<void()>> ready_;  // computed, waiting for their turn
    std::uint64_t next_serial_ = 0, next_delivery_ = 0;
    bool delivering_ = false;
    bool stop_ = false;
    std::vector<std::thread> workers_;
};

}  // namespace cellbench::sequencer
