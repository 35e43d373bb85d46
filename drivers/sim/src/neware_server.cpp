#include "cellbench/sim/neware_server.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <ctime>
#include <deque>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <random>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <thread>

#include <utility>  // before Asio: Boost 1.74 awaitable.hpp uses std::exchange without it

#include <boost/asio.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/core/recording.hpp"

namespace cellbench::sim {

namespace asio = boost::asio;
using asio::ip::tcp;
using namespace protocol::neware;

namespace {

constexpr std::size_t kMaxTicksPerFire = 20000;        // bounds one timer callback when the thread lagged
constexpr std::uintmax_t kMaxStepFileBytes = 1u << 20;
// Bytes sent before each answer in garbage mode: junk, a stray terminator, more junk without one.
const std::string kGarbage = std::string("\x01\x02\xff junk #\r\n", 12) + "\n\n#\r\n" + "more junk <b";

struct Member {
    int chlid = 0;
    ChannelStatus status = ChannelStatus::finish;
    bool faulted = false;  // put into protect/stop by inject_member_status: carries no current
    std::string barcode;
    double capacity_ah = 0.0, energy_wh = 0.0;  // of the current step
};

// One recorded point of the group's test (what `download` serves). Member values are derived from it: a
// conducting member carries current/conducting and the members' common step capacity and energy.
struct GroupRecord {
    double test_time_s = 0.0;
    double voltage_v = 0.0, group_current_a = 0.0;
    double member_capacity_ah = 0.0, member_energy_wh = 0.0;
    std::uint32_t faulted_mask = 0;  // bit i: members[i] carried no current
    std::uint16_t conducting = 0;
    std::uint16_t step_id = 0, cycle_id = 0;
    char step_type[8] = {};  // the tester's code: rest, cc, dc, cv
};
// The tester's data memory: the newest rows of the running (or last) test. At 10 rows per bench second this
// is over 8 bench hours; a client that falls further behind gets an answer starting at the oldest row kept.
constexpr std::size_t kMaxRecordedRows = 300000;

}  // namespace

struct NewareServer::Impl {
    class Session;

    Impl(BenchPlant p, std::shared_ptr<const BenchClock> c, NewareServerOptions o)
        : plant(std::move(p)), clock(std::move(c)), options(std::move(o)), cell(*this) {
        if (!clock) clock = std::make_shared<const BenchClock>(1.0, plant.now_s());
        if (options.tick_s <= 0 || !std::isfinite(options.tick_s)) options.tick_s = 0.1;
        options.timer_period_ms = std::clamp(options.timer_period_ms, 1, 1000);
        for (const int chlid : options.cell_channels) {
            if (chlid < 1 || chlid > options.channel_count)
                throw std::runtime_error("neware sim: cell channel " + std::to_string(chlid) + " outside 1.." +
                                         std::to_string(options.channel_count));
            Member m;
            m.chlid = chlid;
            members.push_back(std::move(m));
        }
    }

    // --- everything below runs on the io thread unless noted ---------------------------------------------
    asio::io_context io;  // first: destroyed last (handlers own sessions)
    std::optional<asio::executor_work_guard<asio::io_context::executor_type>> guard;
    tcp::acceptor acceptor{io};
    asio::steady_timer timer{io};
    std::thread thread;
    std::atomic<int> bound_port{0};
    bool stopping = false;

    BenchPlant plant;
    std::shared_ptr<const BenchClock> clock;
    NewareServerOptions options;
    std::vector<Member> members;
    std::optional<ProgramRunner> runner;
    std::uint64_t member_serial = 0;  // runner step serial the member accumulators belong to
    // Recorded data of the latest test: rows seqid first_seqid.. (one per program tick).
    std::int64_t test_id = 0;
    std::int64_t first_seqid = 1;
    // Wall clock of the test's start (unix s) and its bench time: a row's atime is start + its test time.
    double test_start_unix_s = 0.0;
    std::vector<LogEntry> test_log;  // the test's log (downloadlog): start 100000, end 100001
    std::deque<GroupRecord> records;
    std::vector<std::weak_ptr<Session>> sessions;

    std::atomic<bool> stall{false}, malformed{false}, garbage{false};

    // Starved host (set_starved): the io thread waits in hold_while_starved() until released.
    std::mutex starve_mutex;  // any thread
    std::condition_variable starve_cv;
    bool starved = false;
    bool held = false;      // the io thread is inside hold_while_starved()
    bool io_ended = false;  // the io thread has left io.run(): nothing will hold it

    void hold_while_starved() {
        std::unique_lock lock(starve_mutex);
        held = true;
        starve_cv.notify_all();
        starve_cv.wait(lock, [&] { return !starved; });
        held = false;
        starve_cv.notify_all();
    }

    mutable std::mutex files_mutex;  // any thread
    std::map<std::string, std::string> files;

    mutable std::mutex stats_mutex;  // any thread
    NewareServerStats stats;
    NewareRunSnapshot snap;
    std::uint64_t snap_serial = ~0ull;
    std::size_t snap_history_size = 0;

    // The cell behind the group, as the runner sees it: each conducting member carries current/n.
    struct GroupCell : RunnerCell {
        explicit GroupCell(Impl& s) : self(s) {}
        Impl& self;
        double last_until_s = 0.0;
        double share() const {
            const auto n = self.members.size();
            return n ? static_cast<double>(self.conducting()) / static_cast<double>(n) : 0.0;
        }
        double voltage_at(double current_a) override { return self.plant.voltage_at(current_a * share()); }
        CellMeasurement drive(double current_a, double until_s) override {
            const std::size_t conducting = self.conducting();
            const double cell_current = current_a * share();
            // This tick's current, and only up to its end: if this thread lags the clock, the chamber and
            // the DAQ reading the plant meanwhile do not move the cell on with it (plant.hpp, set_current).
            self.plant.set_current(cell_current, until_s);
            self.plant.advance_to(until_s);
            const PlantReading r = self.plant.read();
            const double dt = std::max(0.0, until_s - last_until_s);
            last_until_s = until_s;
            if (self.runner && self.runner->step_serial() != self.member_serial) {
                self.member_serial = self.runner->step_serial();
                for (auto& m : self.members) m.capacity_ah = m.energy_wh = 0.0;
            }
            if (conducting > 0 && self.runner && self.runner->step().type != protocol::StepType::rest) {
                const double member_a = std::fabs(r.current_a) / static_cast<double>(conducting);
                for (auto& m : self.members) {
                    if (m.faulted) continue;
                    m.capacity_ah += member_a * dt / 3600.0;
                    m.energy_wh += member_a * std::fabs(r.terminal_voltage_v) * dt / 3600.0;
                }
            }
            if (self.runner) self.record(until_s, r, conducting);
            return {r.current_a, r.terminal_voltage_v};
        }
    } cell;

    void record(double t_s, const PlantReading& r, std::size_t n_conducting) {
        GroupRecord g;
        // Test time as the tester counts it (pauses excluded), at the end of the tick being driven.
        g.test_time_s = runner->total_time_s() + (t_s - runner->now_s());
        g.voltage_v = r.terminal_voltage_v;
        g.group_current_a = n_conducting > 0 ? r.current_a : 0.0;
        g.conducting = static_cast<std::uint16_t>(n_conducting);
        for (std::size_t i = 0; i < members.size() && i < 32; ++i) {
            if (members[i].faulted) {
                g.faulted_mask |= 1u << i;
            } else {
                g.member_capacity_ah = members[i].capacity_ah;
                g.member_energy_wh = members[i].energy_wh;
            }
        }
        g.step_id = static_cast<std::uint16_t>(runner->step_id());
        g.cycle_id = static_cast<std::uint16_t>(runner->cycle_id());
        const auto code = runner->step_type_code();
        std::copy_n(code.data(), std::min(code.size(), sizeof g.step_type - 1), g.step_type);
        records.push_back(g);
        if (records.size() > kMaxRecordedRows) {
            records.pop_front();
            ++first_seqid;
        }
    }

    std::size_t conducting() const {
        return static_cast<std::size_t>(std::count_if(members.begin(), members.end(), [](const Member& m) {
            return !m.faulted;
        }));
    }

    Member* member(const ChannelAddress& a) {
        if (a.devtype != options.devtype || a.devid != options.devid || a.subdevid != options.subdevid) return nullptr;
        for (auto& m : members)
            if (m.chlid == a.chlid) return &m;
        return nullptr;
    }
    bool exists(const ChannelAddress& a) const {
        return a.devtype == options.devtype && a.devid == options.devid && a.subdevid == options.subdevid &&
               a.chlid >= 1 && a.chlid <= options.channel_count;
    }
    bool run_active() const {
        return runner && (runner->state() == RunState::working || runner->state() == RunState::paused);
    }

    void count(std::uint64_t NewareServerStats::*field, std::uint64_t n = 1) {
        std::lock_guard lock(stats_mutex);
        stats.*field += n;
    }

    // ------------------------------------------------------------------------------------------------------
    // Listening

    void open_acceptor(int port) {
        const tcp::endpoint ep(asio::ip::make_address(options.host), static_cast<unsigned short>(port));
        acceptor.open(ep.protocol());
        acceptor.set_option(tcp::acceptor::reuse_address(true));
        acceptor.bind(ep);
        acceptor.listen();
        bound_port = acceptor.local_endpoint().port();
        accept();
    }

    // Port 0 ("any free port"): a port below the kernel's ephemeral range (20000-32767), not one from it. The
    // refused-connections fault closes the listener and opens it again on the same port; an ephemeral port
    // may meanwhile be handed to any outgoing connection on the machine (the daemon's own reconnect attempts
    // included), and then the listener could not come back while that connection lives.
    void open_acceptor_any() {
        std::random_device seed;
        std::mt19937 pick(seed());
        std::uniform_int_distribution<int> port(20000, 32767);
        for (int attempt = 0; attempt < 64; ++attempt) {
            try {
                open_acceptor(port(pick));
                return;
            } catch (const boost::system::system_error&) {
                boost::system::error_code ignored;
                acceptor.close(ignored);
            }
        }
        open_acceptor(0);
    }

    void accept();
    void close_all();

    // ------------------------------------------------------------------------------------------------------
    // Execution

    void on_timer(const boost::system::error_code& ec) {
        if (ec || stopping) return;
        try {
            advance();
        } catch (const std::exception& e) {
            spdlog::error("neware sim: execution failed: {}", e.what());
        }
        timer.expires_after(std::chrono::milliseconds(options.timer_period_ms));
        timer.async_wait([this](const boost::system::error_code& e) { on_timer(e); });
    }

    void advance() {
        // Run ahead of the clock by one timer period (plus a tick): see the header.
        const double lead_s = clock->time_scale() * options.timer_period_ms / 1000.0 + options.tick_s;
        double target_s = clock->now_s() + lead_s;
        if (runner && runner->state() == RunState::working) {
            const double bounded = runner->now_s() + kMaxTicksPerFire * options.tick_s;
            if (target_s > bounded) {
                spdlog::warn("neware sim: execution lags the bench clock by {:.1f} s; catching up",
                             target_s - runner->now_s());
                target_s = bounded;
            }
            const auto ticks = runner->run_until(target_s, cell);
            count(&NewareServerStats::ticks, ticks);
            if (runner->state() != RunState::working) on_run_ended();
        }
        if (!runner || runner->state() != RunState::working) {
            // Idle (or a partial tick left): the cell rests, the plant still evolves.
            if (!runner || runner->state() != RunState::working) plant.set_current(0.0);
            plant.advance_to(target_s);
        }
        update_snapshot();
    }

    std::int64_t last_seqid() const { return first_seqid + static_cast<std::int64_t>(records.size()) - 1; }

    std::string atime_at(double test_time_s) const {
        const auto t = static_cast<std::time_t>(std::floor(test_start_unix_s + test_time_s));
        std::tm tm{};
        gmtime_r(&t, &tm);
        char buf[32];
        std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", &tm);
        return buf;
    }

    void log_event(int code) {
        const double t = records.empty() ? 0.0 : records.back().test_time_s;
        test_log.push_back({std::max<std::int64_t>(1, last_seqid()), code, atime_at(t)});
    }

    void on_run_ended() {
        plant.set_current(0.0);
        log_event(100001);
        if (runner->state() == RunState::finished) {
            for (auto& m : members)
                if (!m.faulted) m.status = ChannelStatus::finish;
            spdlog::info("neware sim: program '{}' finished at bench {:.1f} s", runner->program().name,
                         runner->now_s());
        }
    }

    void update_snapshot() {
        std::lock_guard lock(stats_mutex);
        snap.has_run = runner.has_value();
        snap.member_status.clear();
        for (const auto& m : members) snap.member_status.push_back(m.status);
        if (!runner) return;
        snap.state = runner->state();
        snap.program_name = runner->program().name;
        snap.step_id = runner->step_id();
        snap.cycle_id = runner->cycle_id();
        snap.step_type = std::string(runner->step_type_code());
        snap.bench_time_s = runner->now_s();
        snap.group_current_a = runner->last().current_a;
        snap.voltage_v = runner->last().voltage_v;
        snap.step_time_s = runner->step_time_s();
        snap.total_time_s = runner->total_time_s();
        snap.step_capacity_ah = runner->step_capacity_ah();
        if (runner->step_serial() != snap_serial || runner->history().size() != snap_history_size) {
            snap_serial = runner->step_serial();
            snap_history_size = runner->history().size();
            snap.history.assign(runner->history().begin(), runner->history().end());
        }
    }

    // ------------------------------------------------------------------------------------------------------
    // Requests

    std::optional<protocol::StepProgram> load_program(const std::string& path, std::string& why) {
        std::string content;
        bool found = false;
        {
            std::lock_guard lock(files_mutex);
            if (const auto it = files.find(path); it != files.end()) {
                content = it->second;
                found = true;
            }
        }
        if (!found) {
            std::filesystem::path p(path);
            if (p.is_relative() && !options.step_file_dir.empty()) p = std::filesystem::path(options.step_file_dir) / p;
            std::error_code ec;
            const auto size = std::filesystem::file_size(p, ec);
            if (ec) {
                why = "step file not found: " + path;
                return std::nullopt;
            }
            if (size > kMaxStepFileBytes) {
                why = "step file too large: " + path;
                return std::nullopt;
            }
            std::ifstream in(p, std::ios::binary);
            std::ostringstream ss;
            ss << in.rdbuf();
            content = ss.str();
        }
        try {
            return protocol::parse_step_file(content);
        } catch (const std::exception& e) {
            why = path + ": " + e.what();
            return std::nullopt;
        }
    }

    Response handle(const Request& request) {
        return std::visit([this](const auto& r) { return handle_one(r); }, request);
    }

    Response handle_one(const ConnectRequest&) { return ConnectResponse{true, "ok"}; }

    Response handle_one(const GetDevInfoRequest&) {
        GetDevInfoResponse r;
        r.servers.push_back({options.ip, 3306});  // the BTS server's database port, as real servers list it
        for (int c = 1; c <= options.channel_count; ++c)
            r.channels.push_back({ChannelAddress{options.ip, options.devtype, options.devid, options.subdevid, c}, true});
        return r;
    }

    Response handle_one(const ChannelListRequest& req) {
        if (req.command == Command::getchlstatus) {
            ChannelStatusResponse r;
            for (const auto& a : req.channels) {
                StatusEntry s;
                s.channel = a;
                s.reserve_pause = true;  // as real BTS 8 servers report
                if (const Member* m = member(a)) {
                    s.status = m->status;
                } else if (exists(a)) {
                    s.status = ChannelStatus::finish;  // no cell, never started: idle channels say finish
                } else {
                    s.status = ChannelStatus::unknown;
                    s.status_text = "false";
                }
                r.channels.push_back(std::move(s));
            }
            return r;
        }
        if (req.command == Command::inquiredf) {
            InquireDfResponse r;
            for (const auto& a : req.channels) {
                TestInfo t;
                t.channel = {"", a.devtype, a.devid, a.subdevid, a.chlid};
                if (member(a) != nullptr) {
                    t.testid = test_id;
                    t.count = test_id > 0 ? std::max<std::int64_t>(0, last_seqid()) : 0;
                }
                t.flag = !(member(a) != nullptr && run_active());  // true: no test running (as the captures show)
                r.channels.push_back(t);
            }
            return r;
        }
        if (req.command == Command::light || req.command == Command::clearflag) {
            ChannelCommandResponse r;
            r.command = req.command;
            for (const auto& a : req.channels) {
                bool ok = exists(a);
                if (req.command == Command::clearflag) {
                    // Clears a protect flag (the channel can be started again); nothing to clear answers false.
                    Member* m = member(a);
                    ok = m != nullptr && m->status == ChannelStatus::protect;
                    if (ok) m->status = ChannelStatus::stop;
                } else if (ok) {
                    spdlog::info("neware sim: channel {} light {}", a.key(), req.on ? "on" : "off");
                }
                r.channels.push_back({a, ok, ok ? "ok" : "false"});
            }
            update_snapshot();
            return r;
        }
        ChannelCommandResponse r;
        r.command = req.command;
        const double now_s = plant.now_s();
        bool group_done = false;  // the group acts once per request
        for (const auto& a : req.channels) {
            bool ok = false;
            if (member(a) != nullptr) {
                switch (req.command) {
                    case Command::stop:
                        if (!group_done && run_active()) {
                            runner->stop();
                            plant.set_current(0.0);
                            log_event(100001);
                            for (auto& m : members)
                                if (!m.faulted) m.status = ChannelStatus::stop;
                            spdlog::info("neware sim: program '{}' stopped at bench {:.1f} s", runner->program().name,
                                         now_s);
                        }
                        ok = true;
                        group_done = true;
                        break;
                    case Command::pause:
                        if (group_done || (runner && runner->state() == RunState::working)) {
                            if (!group_done) {
                                runner->pause();
                                plant.set_current(0.0);
                                for (auto& m : members)
                                    if (!m.faulted) m.status = ChannelStatus::pause;
                            }
                            ok = true;
                            group_done = true;
                        }
                        break;
                    case Command::continue_:
                        if (group_done || (runner && runner->state() == RunState::paused)) {
                            if (!group_done) {
                                runner->resume(std::max(now_s, runner->now_s()));
                                cell.last_until_s = runner->now_s();
                                for (auto& m : members)
                                    if (!m.faulted) m.status = ChannelStatus::working;
                            }
                            ok = true;
                            group_done = true;
                        }
                        break;
                    default: break;
                }
            } else if (exists(a)) {
                ok = req.command == Command::stop;  // stopping an idle channel is harmless
            }
            r.channels.push_back({a, ok, ok ? "ok" : "false"});
        }
        update_snapshot();
        return r;
    }

    Response handle_one(const InquireRequest& req) {
        InquireResponse r;
        const std::size_t n_conducting = conducting();
        for (const auto& a : req.channels) {
            InquireEntry e;
            e.channel = {"", a.devtype, a.devid, a.subdevid, a.chlid};
            e.cycle_id = 1;
            e.step_type = "--";
            if (const Member* m = member(a)) {
                const PlantReading reading = plant.read();  // per member: its own sensor noise
                e.workstatus = m->status;
                e.barcode = req.barcode ? m->barcode : "";
                e.voltage_v = reading.terminal_voltage_v;
                e.current_a = 0.0;
                const bool active = run_active() && !m->faulted;
                if (runner) e.cycle_id = runner->cycle_id();
                if (active) {
                    e.step_id = runner->step_id();
                    e.step_type = std::string(runner->step_type_code());
                    e.total_time_s = runner->total_time_s();
                    e.relative_time_s = runner->step_time_s();
                    e.capacity_ah = m->capacity_ah;
                    e.energy_wh = m->energy_wh;
                    if (runner->state() == RunState::working && n_conducting > 0)
                        e.current_a = reading.current_a / static_cast<double>(n_conducting);
                    e.log_code = 102000;  // seen on working channels in the field
                }
            } else if (exists(a)) {
                e.workstatus = ChannelStatus::finish;  // idle, no cell
                e.voltage_v = 0.0;
            } else {
                e.workstatus = ChannelStatus::unknown;
                e.workstatus_text = "false";
                e.voltage_v = std::nan("");
                e.current_a = std::nan("");
            }
            r.channels.push_back(std::move(e));
        }
        return r;
    }

    Response handle_one(const DownloadRequest& req) {
        DownloadResponse r;
        r.channel = {"", req.channel.devtype, req.channel.devid, req.channel.subdevid, req.channel.chlid};
        r.testid = member(req.channel) != nullptr ? test_id : 0;
        r.count = req.count;
        r.auxid = req.auxid;
        const auto index = static_cast<std::size_t>(
            std::find_if(members.begin(), members.end(), [&](const Member& m) { return m.chlid == req.channel.chlid; }) -
            members.begin());
        if (member(req.channel) == nullptr || (req.testid != 0 && req.testid != test_id) || req.count == 0) {
            r.startpos = req.startpos;
            return r;  // no cell there, a test this tester no longer holds, or the test-id query (count 0)
        }
        const std::int64_t start = std::max(req.startpos, first_seqid);
        r.startpos = start;
        const auto end = first_seqid + static_cast<std::int64_t>(records.size());
        for (std::int64_t seq = start; seq < end && r.records.size() < static_cast<std::size_t>(req.count); ++seq) {
            const GroupRecord& g = records[static_cast<std::size_t>(seq - first_seqid)];
            const bool carried = index < 32 && (g.faulted_mask & (1u << index)) == 0 && g.conducting > 0;
            DownloadRecord d;
            d.seqid = seq;
            d.step_id = g.step_id;
            d.cycle_id = g.cycle_id;
            d.step_type = std::string(g.step_type, strnlen(g.step_type, sizeof g.step_type));
            d.test_time_s = g.test_time_s;
            d.atime = atime_at(g.test_time_s);
            d.voltage_v = g.voltage_v;
            d.current_a = carried ? g.group_current_a / g.conducting : 0.0;
            d.capacity_ah = carried ? g.member_capacity_ah : 0.0;
            d.energy_wh = carried ? g.member_energy_wh : 0.0;
            r.records.push_back(std::move(d));
        }
        return r;
    }

    Response handle_one(const TestRequest& req) {
        const bool ours = member(req.channel) != nullptr && (req.testid == 0 || req.testid == test_id);
        const ChannelAddress ch{"", req.channel.devtype, req.channel.devid, req.channel.subdevid, req.channel.chlid};
        if (req.command == Command::downloadlog) {
            DownloadLogResponse r;
            r.channel = ch;
            r.testid = member(req.channel) != nullptr ? test_id : 0;
            if (ours) r.entries = test_log;
            return r;
        }
        StepLayerResponse r;
        r.channel = ch;
        r.testid = member(req.channel) != nullptr ? test_id : 0;
        if (!ours) return r;
        // The step table: one entry per run of rows of one step execution (step id and cycle).
        const auto index = static_cast<std::size_t>(
            std::find_if(members.begin(), members.end(), [&](const Member& m) { return m.chlid == req.channel.chlid; }) -
            members.begin());
        double previous_end_s = 0.0;
        for (std::size_t k = 0; k < records.size();) {
            std::size_t j = k;
            while (j + 1 < records.size() && records[j + 1].step_id == records[k].step_id &&
                   records[j + 1].cycle_id == records[k].cycle_id)
                ++j;
            const GroupRecord& a = records[k];
            const GroupRecord& b = records[j];
            auto member_current = [&](const GroupRecord& g) {
                const bool carried = index < 32 && (g.faulted_mask & (1u << index)) == 0 && g.conducting > 0;
                return carried ? g.group_current_a / g.conducting : 0.0;
            };
            StepLayerEntry e;
            e.start_seqid = first_seqid + static_cast<std::int64_t>(k);
            e.end_seqid = first_seqid + static_cast<std::int64_t>(j);
            e.step_index = static_cast<int>(r.steps.size()) + 1;
            e.step_id = a.step_id;
            e.cycle_id = a.cycle_id;
            e.step_type = std::string(a.step_type, strnlen(a.step_type, sizeof a.step_type));
            e.step_time_s = b.test_time_s - previous_end_s;
            e.end_atime = atime_at(b.test_time_s);
            e.start_voltage_v = a.voltage_v;
            e.end_voltage_v = b.voltage_v;
            e.start_current_a = member_current(a);
            e.end_current_a = member_current(b);
            e.capacity_ah = b.member_capacity_ah;
            e.energy_wh = b.member_energy_wh;
            previous_end_s = b.test_time_s;
            r.steps.push_back(std::move(e));
            k = j + 1;
        }
        return r;
    }

    Response handle_one(const StartRequest& req) {
        ChannelCommandResponse r;
        r.command = Command::start;
        std::map<std::string, std::optional<protocol::StepProgram>> programs;
        std::optional<protocol::StepProgram> chosen;
        std::string chosen_path, chosen_barcode;
        std::vector<bool> ok(req.entries.size(), false);
        for (std::size_t i = 0; i < req.entries.size(); ++i) {
            const auto& e = req.entries[i];
            if (member(e.channel) == nullptr) {
                spdlog::warn("neware sim: start refused on {}: no cell on that channel", e.channel.key());
                continue;
            }
            if (run_active()) {
                spdlog::warn("neware sim: start refused on {}: the channel is running", e.channel.key());
                continue;
            }
            if (!programs.count(e.step_file_path)) {
                std::string why;
                programs[e.step_file_path] = load_program(e.step_file_path, why);
                if (!programs[e.step_file_path]) spdlog::warn("neware sim: start refused: {}", why);
            }
            const auto& program = programs[e.step_file_path];
            if (!program) continue;
            const double limit_a = options.max_channel_current_a * static_cast<double>(members.size());
            if (program->max_current_a() > limit_a + 1e-9) {
                spdlog::warn("neware sim: start refused: '{}' asks for {} A, the channels give {} A", program->name,
                             program->max_current_a(), limit_a);
                continue;
            }
            if (chosen && chosen_path != e.step_file_path) {
                spdlog::warn("neware sim: start refused on {}: the group was started with {}", e.channel.key(),
                             chosen_path);
                continue;
            }
            if (!chosen) {
                chosen = program;
                chosen_path = e.step_file_path;
                chosen_barcode = e.barcode;
            }
            member(e.channel)->barcode = e.barcode;
            ok[i] = true;
        }
        if (chosen) {
            // A start on any member starts the whole parallel group (BTS parallel mode).
            runner.emplace(std::move(*chosen), plant.now_s(), options.tick_s);
            cell.last_until_s = runner->now_s();
            ++test_id;
            first_seqid = 1;
            records.clear();
            test_start_unix_s = static_cast<double>(std::chrono::duration_cast<std::chrono::seconds>(
                                                        std::chrono::system_clock::now().time_since_epoch())
                                                        .count());
            test_log.clear();
            test_log.push_back({1, 100000, atime_at(0.0)});
            member_serial = 0;
            for (auto& m : members) {
                m.faulted = false;
                m.status = ChannelStatus::working;
                m.capacity_ah = m.energy_wh = 0.0;
                if (m.barcode.empty()) m.barcode = chosen_barcode;
            }
            spdlog::info("neware sim: program '{}' ({} steps) started from {} at bench {:.1f} s", runner->program().name,
                         runner->program().steps.size(), chosen_path, runner->now_s());
        }
        for (std::size_t i = 0; i < req.entries.size(); ++i)
            r.channels.push_back({req.entries[i].channel, ok[i], ok[i] ? "ok" : "false"});
        update_snapshot();
        return r;
    }

    // The bytes to send for a request (empty: no answer).
    std::string answer(std::string_view frame) {
        count(&NewareServerStats::requests);
        Response response;
        try {
            response = handle(parse_request(frame));
        } catch (const ProtocolError& e) {
            // Never silence: a client waits for one answer per request.
            count(&NewareServerStats::malformed_requests);
            std::string cmd;
            try {
                cmd = frame_command(frame);
            } catch (const ProtocolError&) {
                cmd = "unknown";
            }
            spdlog::warn("neware sim: request '{}' answered with an error: {}", cmd.substr(0, 64), e.what());
            response = ErrorResponse{cmd, e.what()};
        }
        if (stall) {
            count(&NewareServerStats::unanswered);
            return {};
        }
        std::string bytes = encode_response(response);
        if (malformed) bytes = bytes.substr(0, bytes.size() / 2) + "</bts>" + std::string(kFrameTerminator);
        if (garbage) bytes = kGarbage + bytes;
        count(&NewareServerStats::responses);
        return bytes;
    }

    // ------------------------------------------------------------------------------------------------------
    // Faults (on the io thread)

    void set_refuse(bool refuse) {
        if (stopping) return;
        if (refuse) {
            boost::system::error_code ec;
            acceptor.close(ec);
            spdlog::info("neware sim: refusing connections");
        } else if (!acceptor.is_open()) {
            reopen(0);
        }
    }

    // Listens again on the same port. A client retrying meanwhile may hold that (ephemeral) port for a moment
    // with its own connecting socket, so a failed bind is retried every 50 ms for up to 5 s.
    void reopen(int attempt) {
        if (stopping || acceptor.is_open()) return;
        try {
            open_acceptor(bound_port);
            spdlog::info("neware sim: accepting connections again on port {}", bound_port.load());
        } catch (const std::exception& e) {
            boost::system::error_code ignored;
            acceptor.close(ignored);
            if (attempt >= 100) {
                spdlog::error("neware sim: cannot listen again on port {}: {}", bound_port.load(), e.what());
                return;
            }
            auto retry = std::make_shared<asio::steady_timer>(io, std::chrono::milliseconds(50));
            retry->async_wait([this, retry, attempt](const boost::system::error_code& ec) {
                if (!ec) reopen(attempt + 1);
            });
        }
    }

    void inject(int chlid, ChannelStatus status) {
        for (auto& m : members) {
            if (m.chlid != chlid) continue;
            m.status = status;
            m.faulted = status == ChannelStatus::protect || status == ChannelStatus::stop;
            spdlog::info("neware sim: channel {} put into {}", chlid, to_string(status));
        }
        if (run_active() && conducting() == 0) {
            runner->stop();
            plant.set_current(0.0);
        }
        update_snapshot();
    }
};

// -------------------------------------------------------------------------------------------------------------
// Sessions: one per connection, all on the io thread.

class NewareServer::Impl::Session : public std::enable_shared_from_this<Session> {
public:
    Session(tcp::socket socket, Impl& server) : socket_(std::move(socket)), server_(server) {}

    void start() { read(); }

    void close() {
        boost::system::error_code ec;
        socket_.shutdown(tcp::socket::shutdown_both, ec);
        socket_.close(ec);
    }

private:
    void read() {
        socket_.async_read_some(asio::buffer(buffer_),
                                [self = shared_from_this()](const boost::system::error_code& ec, std::size_t n) {
                                    self->on_read(ec, n);
                                });
    }

    void on_read(const boost::system::error_code& ec, std::size_t n) {
        if (ec || server_.stopping) {
            close();
            return;
        }
        splitter_.feed(std::string_view(buffer_.data(), n));
        while (true) {
            std::optional<std::string> frame;
            try {
                frame = splitter_.next();
            } catch (const ProtocolError& e) {
                spdlog::warn("neware sim: {}", e.what());
                continue;
            }
            if (!frame) break;
            std::string bytes;
            try {
                bytes = server_.answer(*frame);
            } catch (const std::exception& e) {
                spdlog::error("neware sim: request failed: {}", e.what());
            }
            if (!bytes.empty()) send(std::move(bytes));
        }
        read();
    }

    void send(std::string bytes) {
        out_.push_back(std::move(bytes));
        if (!writing_) write_next();
    }

    void write_next() {
        writing_ = true;
        asio::async_write(socket_, asio::buffer(out_.front()),
                          [self = shared_from_this()](const boost::system::error_code& ec, std::size_t) {
                              self->out_.pop_front();
                              if (ec) {
                                  self->close();
                                  return;
                              }
                              if (self->out_.empty())
                                  self->writing_ = false;
                              else
                                  self->write_next();
                          });
    }

    tcp::socket socket_;
    Impl& server_;
    std::array<char, 16384> buffer_{};
    FrameSplitter splitter_{};
    std::deque<std::string> out_;
    bool writing_ = false;
};

void NewareServer::Impl::accept() {
    acceptor.async_accept([this](const boost::system::error_code& ec, tcp::socket socket) {
        if (stopping) return;
        if (!ec) {
            boost::system::error_code ignored;
            socket.set_option(tcp::no_delay(true), ignored);
            auto session = std::make_shared<Session>(std::move(socket), *this);
            std::erase_if(sessions, [](const auto& w) { return w.expired(); });
            sessions.push_back(session);
            count(&NewareServerStats::connections);
            session->start();
        }
        if (acceptor.is_open()) accept();
    });
}

void NewareServer::Impl::close_all() {
    stopping = true;
    // A tester that is switched off conducts nothing (and holds the plant's time no longer: set_current).
    if (run_active()) plant.set_current(0.0);
    boost::system::error_code ec;
    acceptor.close(ec);
    timer.cancel();
    for (auto& w : sessions)
        if (auto s = w.lock()) s->close();
    sessions.clear();
}

// -------------------------------------------------------------------------------------------------------------

NewareServer::NewareServer(BenchPlant plant, std::shared_ptr<const BenchClock> clock, NewareServerOptions options)
    : impl_(std::make_shared<Impl>(std::move(plant), std::move(clock), std::move(options))) {}

NewareServer::~NewareServer() { stop(); }

void NewareServer::start() {
    if (impl_->thread.joinable()) return;
    try {
        if (impl_->options.port == 0)
            impl_->open_acceptor_any();
        else
            impl_->open_acceptor(impl_->options.port);
    } catch (const std::exception& e) {
        throw std::runtime_error("neware sim: cannot listen on " + impl_->options.host + ":" +
                                 std::to_string(impl_->options.port) + ": " + e.what());
    }
    impl_->stopping = false;
    impl_->guard.emplace(impl_->io.get_executor());
    impl_->timer.expires_after(std::chrono::milliseconds(0));
    impl_->timer.async_wait([impl = impl_.get()](const boost::system::error_code& e) { impl->on_timer(e); });
    {
        std::lock_guard lock(impl_->starve_mutex);
        impl_->io_ended = false;
    }
    impl_->thread = std::thread([impl = impl_.get()] {
        try {
            impl->io.run();
        } catch (const std::exception& e) {
            spdlog::error("neware sim: io thread ended: {}", e.what());
        }
        std::lock_guard lock(impl->starve_mutex);
        impl->io_ended = true;
        impl->starve_cv.notify_all();
    });
    spdlog::info("neware sim: listening on {}", description());
}

void NewareServer::stop() {
    if (!impl_ || !impl_->thread.joinable()) return;
    set_starved(false);  // the io thread must run to close
    asio::post(impl_->io, [impl = impl_.get()] { impl->close_all(); });
    impl_->guard.reset();
    impl_->thread.join();
    impl_->io.restart();
}

int NewareServer::port() const { return impl_->bound_port; }

std::string NewareServer::description() const {
    return "tcp " + impl_->options.host + ":" + std::to_string(impl_->bound_port.load());
}

std::vector<ChannelAddress> NewareServer::cell_channel_addresses() const {
    std::vector<ChannelAddress> out;
    for (const auto& m : impl_->members)
        out.push_back({impl_->options.ip, impl_->options.devtype, impl_->options.devid, impl_->options.subdevid, m.chlid});
    return out;
}

void NewareServer::add_step_file(const std::string& path, std::string content) {
    std::lock_guard lock(impl_->files_mutex);
    impl_->files[path] = std::move(content);
}

void NewareServer::set_refuse_connections(bool refuse) {
    asio::post(impl_->io, [impl = impl_.get(), refuse] { impl->set_refuse(refuse); });
}

void NewareServer::drop_connections() {
    asio::post(impl_->io, [impl = impl_.get()] {
        for (auto& w : impl->sessions)
            if (auto s = w.lock()) s->close();
        spdlog::info("neware sim: dropped all connections");
    });
}

void NewareServer::set_starved(bool starved) {
    Impl& impl = *impl_;
    std::unique_lock lock(impl.starve_mutex);
    if (impl.starved == starved) return;
    impl.starved = starved;
    if (!starved) {
        impl.starve_cv.notify_all();
        spdlog::info("neware sim: the host gets CPU again");
        return;
    }
    spdlog::info("neware sim: the host gets no CPU (starved)");
    if (!impl.thread.joinable()) return;  // not running: nothing to hold
    asio::post(impl.io, [impl = impl_.get()] { impl->hold_while_starved(); });
    // Returns once the io thread is held (or released again by another thread).
    impl.starve_cv.wait(lock, [&] { return impl.held || !impl.starved || impl.io_ended; });
}

void NewareServer::set_stall_responses(bool stall) { impl_->stall = stall; }
void NewareServer::set_malformed_responses(bool malformed) { impl_->malformed = malformed; }
void NewareServer::set_garbage_between_frames(bool garbage) { impl_->garbage = garbage; }

bool NewareServer::inject_member_status(int chlid, ChannelStatus status) {
    const bool known = std::any_of(impl_->members.begin(), impl_->members.end(),
                                   [&](const Member& m) { return m.chlid == chlid; });
    if (!known) return false;
    asio::post(impl_->io, [impl = impl_.get(), chlid, status] { impl->inject(chlid, status); });
    return true;
}

NewareServerStats NewareServer::stats() const {
    std::lock_guard lock(impl_->stats_mutex);
    return impl_->stats;
}

NewareRunSnapshot NewareServer::snapshot() const {
    std::lock_guard lock(impl_->stats_mutex);
    return impl_->snap;
}

}  // namespace cellbench::sim
