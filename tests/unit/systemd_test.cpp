// cellbenchd's systemd integration (daemon/src/systemd.cpp): sd_notify datagrams to a unix datagram socket
// standing in for systemd (path and abstract namespace), WATCHDOG_USEC/WATCHDOG_PID, the watchdog that pings
// only while its probe runs, and the journal's "<N>" priority format.
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <functional>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/systemd.hpp"

namespace sd = cellbench::daemon::systemd;
namespace fs = std::filesystem;

namespace {

// A bound unix datagram socket: what systemd listens on.
class FakeSystemd {
public:
    // `name` starting with '@' binds in the abstract namespace.
    explicit FakeSystemd(const std::string& name) : name_(name) {
        fd_ = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
        if (fd_ < 0) throw std::runtime_error("socket");
        sockaddr_un sa{};
        sa.sun_family = AF_UNIX;
        std::memcpy(sa.sun_path, name.data(), name.size());
        socklen_t len = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + name.size());
        if (name[0] == '@') sa.sun_path[0] = '\0';
        else len += 1, ::unlink(name.c_str());
        if (::bind(fd_, reinterpret_cast<sockaddr*>(&sa), len) != 0) throw std::runtime_error("bind " + name);
    }
    ~FakeSystemd() {
        ::close(fd_);
        if (name_[0] == '/') ::unlink(name_.c_str());
    }
    // The next datagram, waiting at most `wait_ms` (a bound against hanging, not a timing assertion).
    std::optional<std::string> receive(int wait_ms = 10000) {
        pollfd p{fd_, POLLIN, 0};
        if (::poll(&p, 1, wait_ms) <= 0) return std::nullopt;
        char buf[4096];
        const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
        if (n < 0) return std::nullopt;
        return std::string(buf, static_cast<std::size_t>(n));
    }

private:
    std::string name_;
    int fd_ = -1;
};

std::string unique(const std::string& stem) { return stem + "-" + std::to_string(::getpid()); }

}  // namespace

TEST(SdNotify, SendsToFilesystemSocket) {
    const std::string path = (fs::temp_directory_path() / unique("cellbench-notify")).string();
    FakeSystemd systemd(path);
    const sd::Notifier n(path);
    ASSERT_TRUE(n.active());
    ASSERT_TRUE(n.notify("READY=1\nSTATUS=API http://127.0.0.1:8750/api/v1"));
    EXPECT_EQ(systemd.receive(), "READY=1\nSTATUS=API http://127.0.0.1:8750/api/v1");
    ASSERT_TRUE(n.notify("STOPPING=1"));
    EXPECT_EQ(systemd.receive(), "STOPPING=1");
}

TEST(SdNotify, SendsToAbstractNamespaceSocket) {
    const std::string name = "@" + unique("cellbench-notify-abstract");
    FakeSystemd systemd(name);
    ASSERT_TRUE(sd::Notifier(name).notify("READY=1"));
    EXPECT_EQ(systemd.receive(), "READY=1");
    // Not the same as a file of that name.
    std::string as_path = name;
    as_path[0] = '/';
    EXPECT_FALSE(sd::Notifier(as_path).notify("READY=1"));
}

TEST(SdNotify, InactiveOrUnreachable) {
    EXPECT_FALSE(sd::Notifier().active());
    EXPECT_FALSE(sd::Notifier().notify("READY=1"));
    EXPECT_FALSE(sd::Notifier((fs::temp_directory_path() / unique("cellbench-nobody")).string()).notify("READY=1"));
    EXPECT_FALSE(sd::Notifier("/" + std::string(200, 'x')).notify("READY=1"));  // longer than sun_path

    ::unsetenv("NOTIFY_SOCKET");
    EXPECT_FALSE(sd::Notifier::from_environment().active());
    ::setenv("NOTIFY_SOCKET", "@abc", 1);
    EXPECT_EQ(sd::Notifier::from_environment().address(), "@abc");
    ::setenv("NOTIFY_SOCKET", "vsock:2:1234", 1);
    EXPECT_FALSE(sd::Notifier::from_environment().active());
    ::unsetenv("NOTIFY_SOCKET");
}

TEST(SdNotify, WatchdogEnvironment) {
    using std::chrono::microseconds;
    EXPECT_EQ(sd::parse_watchdog("30000000", nullptr, 42), microseconds(30000000));
    EXPECT_EQ(sd::parse_watchdog("30000000", "42", 42), microseconds(30000000));
    EXPECT_EQ(sd::parse_watchdog("30000000", "", 42), microseconds(30000000));
    EXPECT_FALSE(sd::parse_watchdog("30000000", "43", 42));  // for another process
    EXPECT_FALSE(sd::parse_watchdog(nullptr, nullptr, 42));
    EXPECT_FALSE(sd::parse_watchdog("0", nullptr, 42));
    EXPECT_FALSE(sd::parse_watchdog("12s", nullptr, 42));
    EXPECT_FALSE(sd::parse_watchdog("-5", nullptr, 42));
}

// The watchdog pings only after the watched loop has run the probe it posted. The test plays the loop: it
// holds each probe's done() and decides when to run it. No timing is asserted: the order of probes and pings
// is what the watchdog guarantees.
TEST(SdNotify, WatchdogPingsOnlyWhileTheLoopRunsProbes) {
    const std::string path = (fs::temp_directory_path() / unique("cellbench-watchdog")).string();
    FakeSystemd systemd(path);
    std::mutex m;
    std::condition_variable cv;
    std::vector<std::function<void()>> probes;
    sd::Watchdog wd(sd::Notifier(path), std::chrono::milliseconds(5), [&](std::function<void()> done) {
        std::lock_guard l(m);
        probes.push_back(std::move(done));
        cv.notify_all();
    });
    auto wait_probes = [&](std::size_t n) {
        std::unique_lock l(m);
        return cv.wait_for(l, std::chrono::seconds(10), [&] { return probes.size() >= n; });
    };
    // A wedged loop: the first probes never run. By the time the watchdog issues probe 3 it has decided twice.
    ASSERT_TRUE(wait_probes(3));
    EXPECT_EQ(systemd.receive(0), std::nullopt) << "pinged although the loop never ran a probe";
    EXPECT_EQ(wd.pings(), 0u);
    // A stale probe that finally runs does not count for the probe now outstanding...
    std::size_t issued = 0;
    {
        std::lock_guard l(m);
        probes.front()();
        issued = probes.size();
    }
    ASSERT_TRUE(wait_probes(issued + 2));
    EXPECT_EQ(systemd.receive(0), std::nullopt) << "a stale probe made the watchdog ping";
    // ...the latest does: the loop is alive again, so a following decision pings.
    bool pinged = false;
    for (int attempt = 0; attempt < 500 && !pinged; ++attempt) {
        {
            std::lock_guard l(m);
            probes.back()();
        }
        if (auto msg = systemd.receive(100)) {
            EXPECT_EQ(*msg, "WATCHDOG=1");
            pinged = true;
        }
    }
    EXPECT_TRUE(pinged) << "no WATCHDOG=1 although the loop ran the probes";
    wd.stop();
    EXPECT_GE(wd.pings(), 1u);
}

TEST(Journal, PriorityPrefixWithoutTimestamp) {
    EXPECT_EQ(sd::syslog_priority(spdlog::level::critical), 2);
    EXPECT_EQ(sd::syslog_priority(spdlog::level::err), 3);
    EXPECT_EQ(sd::syslog_priority(spdlog::level::warn), 4);
    EXPECT_EQ(sd::syslog_priority(spdlog::level::info), 6);
    EXPECT_EQ(sd::syslog_priority(spdlog::level::debug), 7);

    std::ostringstream out;
    auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(out);
    spdlog::logger log("journal-test", sink);
    log.set_level(spdlog::level::trace);
    log.set_formatter(sd::journal_formatter());
    log.info("cellbenchd: API {}", "http://127.0.0.1:8750/api/v1");
    log.warn("chamber: offline");
    log.error("store: disk full");
    log.debug("detail");
    EXPECT_EQ(out.str(),
              "<6>cellbenchd: API http://127.0.0.1:8750/api/v1\n<4>chamber: offline\n<3>store: disk full\n<7>detail\n");
}

TEST(Journal, DetectsTheJournalStreamByDeviceAndInode) {
    const auto path = fs::temp_directory_path() / unique("cellbench-journal-stream");
    std::FILE* f = std::fopen(path.c_str(), "w");
    ASSERT_NE(f, nullptr);
    struct stat st {};
    ASSERT_EQ(::fstat(::fileno(f), &st), 0);
    const std::string match = std::to_string(st.st_dev) + ":" + std::to_string(st.st_ino);
    ::setenv("JOURNAL_STREAM", match.c_str(), 1);
    EXPECT_TRUE(sd::fd_is_journal_stream(::fileno(f)));
    ::setenv("JOURNAL_STREAM", (std::to_string(st.st_dev) + ":" + std::to_string(st.st_ino + 1)).c_str(), 1);
    EXPECT_FALSE(sd::fd_is_journal_stream(::fileno(f)));  // stderr redirected elsewhere by the unit: not the journal
    ::setenv("JOURNAL_STREAM", "garbage", 1);
    EXPECT_FALSE(sd::fd_is_journal_stream(::fileno(f)));
    ::unsetenv("JOURNAL_STREAM");
    EXPECT_FALSE(sd::fd_is_journal_stream(::fileno(f)));
    std::fclose(f);
    fs::remove(path);
}
