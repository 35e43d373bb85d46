#pragma once
// A bounded pool of worker threads for the sequencer's fits (issue 14: every fit used to get its own
// std::thread, unbounded). Jobs compute in parallel on at most `threads` workers; each job's result (the
// callable its compute step returns) is delivered only after every earlier job's delivery, so results reach
// their sink in submission order whatever order the computations finish in.
//
// Workers live only while there is work: a submit starts one (up to the bound) and a worker ends when it finds
// the queue empty. An idle pool holds no thread, so nothing of a finished run's fits stays behind in a thread
// (each thread's malloc cache pins the heap pages its chunks sit in until the thread ends, and an idle daemon
// could not give those pages back).
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <condition_variable>
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
    [[nodiscard]] std::size_t threads() const { return max_threads_; }  // the bound
    [[nodiscard]] std::size_t live_threads();  // workers started and not yet ended (0 once idle and drained)

private:
    void work();
    void deliver_ready_locked(std::unique_lock<std::mutex>& lock);
    // Threads whose worker has ended (their ids in ended_), moved out for joining outside the lock.
    std::vector<std::thread> take_ended_locked();

    const std::size_t max_threads_;
    std::mutex mutex_;
    std::condition_variable idle_cv_;  // a delivery happened
    std::deque<std::pair<std::uint64_t, Job>> queue_;
    std::map<std::uint64_t, std::function<void()>> ready_;  // computed, waiting for their turn
    std::uint64_t next_serial_ = 0, next_delivery_ = 0;
    bool delivering_ = false;
    std::size_t running_ = 0;                // workers that have not ended
    std::vector<std::thread> workers_;       // started, not joined yet (running or ended)
    std::vector<std::thread::id> ended_;     // workers that ended, to be joined
};

}  // namespace cellbench::sequencer
