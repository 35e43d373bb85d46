#pragma once
// systemd integration of cellbenchd without libsystemd (the sd-daemon protocols are small):
//   Notifier   sd_notify(3): one datagram "READY=1", "WATCHDOG=1", "STOPPING=1", "STATUS=..." to the unix
//              datagram socket named by $NOTIFY_SOCKET (a path, or "@name" in the abstract namespace).
//   Watchdog   pings WATCHDOG=1 every period, but only while a probe posted to the watched event loop has run
//              since the previous ping: a wedged io_context stops the pings and systemd restarts the daemon.
//   journal    when stdout/stderr is connected to the journal ($JOURNAL_STREAM), log lines carry the
//              sd-daemon(3) "<N>" syslog priority prefix and no time stamp (the journal stamps them).
#include <sys/types.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include <spdlog/common.h>
#include <spdlog/formatter.h>

namespace cellbench::daemon::systemd {

class Notifier {
public:
    Notifier() = default;  // inactive
    // `address` as $NOTIFY_SOCKET holds it: "/run/systemd/notify" or "@abstract-name". Empty = inactive.
    explicit Notifier(std::string address) : address_(std::move(address)) {}
    // From $NOTIFY_SOCKET (inactive when unset or not a unix socket address).
    static Notifier from_environment();

    [[nodiscard]] bool active() const { return !address_.empty(); }
    [[nodiscard]] const std::string& address() const { return address_; }
    // Sends `state` (newline-separated assignments) as one datagram. True when sent; false when inactive or
    // the socket cannot be reached (errno kept). Thread-safe (a socket per call, as libsystemd does).
    bool notify(std::string_view state) const;

private:
    std::string address_;
};

// The watchdog timeout systemd expects pings within: $WATCHDOG_USEC, when set, positive, and $WATCHDOG_PID
// is unset or names this process.
std::optional<std::chrono::microseconds> watchdog_timeout();
std::optional<std::chrono::microseconds> parse_watchdog(const char* watchdog_usec, const char* watchdog_pid, pid_t self);

class Watchdog {
public:
    // probe(done) must arrange for done() to run on the watched loop (e.g. post it to the io_context).
    // Every `period` the thread sends WATCHDOG=1 if the previous probe's done() has run, then probes again.
    using Probe = std::function<void(std::function<void()> done)>;
    Watchdog(Notifier notifier, std::chrono::microseconds period, Probe probe);
    ~Watchdog();  // stop()
    Watchdog(const Watchdog&) = delete;
    Watchdog& operator=(const Watchdog&) = delete;

    void stop();  // joins the thread; idempotent
    [[nodiscard]] std::uint64_t pings() const;

private:
    struct State;
    std::shared_ptr<State> state_;
};

// True when `fd` is the stream $JOURNAL_STREAM ("DEVICE:INODE") names.
bool fd_is_journal_stream(int fd);
// sd-daemon(3) priority of a spdlog level: trace/debug 7, info 6, warn 4, err 3, critical 2.
int syslog_priority(spdlog::level::level_enum level);
// "<N>message" (no time stamp, no colour).
std::unique_ptr<spdlog::formatter> journal_formatter();
// When stdout or stderr is the journal stream, every logger formats with journal_formatter(). Returns
// whether it did.
bool use_journal_format_if_connected();

}  // namespace cellbench::daemon::systemd
