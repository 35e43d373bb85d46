#include "cellbench/daemon/systemd.hpp"

#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <condition_variable>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <thread>

#include <spdlog/pattern_formatter.h>
#include <spdlog/spdlog.h>

namespace cellbench::daemon::systemd {

namespace {

template <class T>
std::optional<T> parse_unsigned(std::string_view s) {
    T v{};
    const auto r = std::from_chars(s.data(), s.data() + s.size(), v);
    if (r.ec != std::errc() || r.ptr != s.data() + s.size() || s.empty()) return std::nullopt;
    return v;
}

}  // namespace

Notifier Notifier::from_environment() {
    const char* e = std::getenv("NOTIFY_SOCKET");
    if (!e || !*e || (e[0] != '/' && e[0] != '@')) return {};  // vsock: addresses are not supported here
    return Notifier(e);
}

bool Notifier::notify(std::string_view state) const {
    if (address_.empty()) return false;
    sockaddr_un sa{};
    sa.sun_family = AF_UNIX;
    if (address_.size() > sizeof sa.sun_path - (address_[0] == '/' ? 1 : 0)) {
        errno = ENAMETOOLONG;
        return false;
    }
    std::memcpy(sa.sun_path, address_.data(), address_.size());
    socklen_t len = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + address_.size());
    if (address_[0] == '@') sa.sun_path[0] = '\0';  // abstract namespace: no terminating NUL counted
    else len += 1;
    const int fd = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (fd < 0) return false;
    const ssize_t n = ::sendto(fd, state.data(), state.size(), MSG_NOSIGNAL, reinterpret_cast<const sockaddr*>(&sa), len);
    const int err = errno;
    ::close(fd);
    errno = err;
    return n == static_cast<ssize_t>(state.size());
}

std::optional<std::chrono::microseconds> parse_watchdog(const char* usec, const char* pid, pid_t self) {
    if (!usec) return std::nullopt;
    const auto us = parse_unsigned<std::uint64_t>(usec);
    if (!us || *us == 0) return std::nullopt;
    if (pid && *pid) {
        const auto p = parse_unsigned<long long>(pid);
        if (!p || *p != static_cast<long long>(self)) return std::nullopt;  // meant for another process
    }
    return std::chrono::microseconds(*us);
}

std::optional<std::chrono::microseconds> watchdog_timeout() {
    return parse_watchdog(std::getenv("WATCHDOG_USEC"), std::getenv("WATCHDOG_PID"), ::getpid());
}

// ---------------------------------------------------------------------------------------------------------

struct Watchdog::State {
    Notifier notifier;
    std::chrono::microseconds period;
    Probe probe;
    std::mutex m;
    std::condition_variable cv;
    bool stop = false;
    std::uint64_t issued = 0;    // generation of the latest probe
    std::uint64_t answered = 0;  // newest generation whose done() ran
    std::uint64_t pings = 0;
    std::thread thread;
};

Watchdog::Watchdog(Notifier notifier, std::chrono::microseconds period, Probe probe)
    : state_(std::make_shared<State>()) {
    state_->notifier = std::move(notifier);
    state_->period = period;
    state_->probe = std::move(probe);
    state_->thread = std::thread([st = state_.get(), weak = std::weak_ptr<State>(state_)] {
        std::unique_lock lock(st->m);
        while (!st->stop) {
            const std::uint64_t gen = ++st->issued;
            lock.unlock();
            // done() may run after the Watchdog is gone: it holds the state only weakly.
            st->probe([weak, gen] {
                if (auto s = weak.lock()) {
                    std::lock_guard l(s->m);
                    s->answered = std::max(s->answered, gen);
                }
            });
            lock.lock();
            if (st->cv.wait_for(lock, st->period, [&] { return st->stop; })) break;
            if (st->answered == gen) {
                ++st->pings;
                lock.unlock();
                st->notifier.notify("WATCHDOG=1");
                lock.lock();
            } else {
                spdlog::warn("watchdog: the event loop did not run a probe within {} ms: no WATCHDOG=1 ping",
                             std::chrono::duration_cast<std::chrono::milliseconds>(st->period).count());
            }
        }
    });
}

Watchdog::~Watchdog() { stop(); }

void Watchdog::stop() {
    {
        std::lock_guard l(state_->m);
        state_->stop = true;
    }
    state_->cv.notify_all();
    if (state_->thread.joinable()) state_->thread.join();
}

std::uint64_t Watchdog::pings() const {
    std::lock_guard l(state_->m);
    return state_->pings;
}

// ---------------------------------------------------------------------------------------------------------

bool fd_is_journal_stream(int fd) {
    const char* e = std::getenv("JOURNAL_STREAM");
    if (!e) return false;
    const std::string_view v(e);
    const auto colon = v.find(':');
    if (colon == std::string_view::npos) return false;
    const auto dev = parse_unsigned<unsigned long long>(v.substr(0, colon));
    const auto ino = parse_unsigned<unsigned long long>(v.substr(colon + 1));
    struct stat st {};
    if (!dev || !ino || ::fstat(fd, &st) != 0) return false;
    return static_cast<unsigned long long>(st.st_dev) == *dev && static_cast<unsigned long long>(st.st_ino) == *ino;
}

int syslog_priority(spdlog::level::level_enum level) {
    switch (level) {
        case spdlog::level::critical: return 2;  // LOG_CRIT
        case spdlog::level::err: return 3;       // LOG_ERR
        case spdlog::level::warn: return 4;      // LOG_WARNING
        case spdlog::level::info: return 6;      // LOG_INFO
        default: return 7;                       // LOG_DEBUG (trace, debug)
    }
}

namespace {

class PriorityFlag final : public spdlog::custom_flag_formatter {
public:
    void format(const spdlog::details::log_msg& msg, const std::tm&, spdlog::memory_buf_t& dest) override {
        const char digit = static_cast<char>('0' + syslog_priority(msg.level));
        dest.push_back(digit);
    }
    std::unique_ptr<custom_flag_formatter> clone() const override { return std::make_unique<PriorityFlag>(); }
};

}  // namespace

std::unique_ptr<spdlog::formatter> journal_formatter() {
    auto f = std::make_unique<spdlog::pattern_formatter>();
    f->add_flag<PriorityFlag>('*').set_pattern("<%*>%v");
    return f;
}

bool use_journal_format_if_connected() {
    if (!fd_is_journal_stream(STDOUT_FILENO) && !fd_is_journal_stream(STDERR_FILENO)) return false;
    spdlog::set_formatter(journal_formatter());
    return true;
}

}  // namespace cellbench::daemon::systemd
