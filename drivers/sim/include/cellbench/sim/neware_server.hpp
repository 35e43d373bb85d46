#pragma once
// Simulated Neware BTS-4008 with its BTS API server: XML frames over loopback TCP (protocol/neware_bts.hpp),
// many connections (one session each), answering every command of a real BTS 8.0 server's captures
// (../shared/reference/neware/) with the same elements and attributes: connect, getdevinfo, getchlstatus
// (reservepause="1", idle channels `finish` at the cell's voltage), inquire, inquiredf (test id and row count),
// start, stop, pause, continue, download (`donwload_resp`, atime per row, startpos="0" count="0" = the test id
// only), downloadlog (start 100000 / end 100001), downloadStepLayer (one entry per executed step), light and
// clearflag (clears a protect). A command it does not know, or a request it cannot read, gets an error
// answer (<result>false</result><error>why</error>), never silence. Step files are the real BTS Client schema
// (a file written by BTS Client runs here as it is), started from Head_Info Start_Step.
//
// The tester executes started step files itself (ProgramRunner, neware_runner.hpp) on the shared
// BenchPlant. The channels listed in cell_channels are wired to the plant's cell; with more than one they
// form a parallel group (the thesis' 3 x 20 A = 60 A): a start on any member starts the group, each working
// member carries the same share of the program's current and reports its own values (own current and
// voltage readings, its share of capacity and energy). Other channels have no cell (0 V) and refuse start.
//
// Time: bench time from the shared BenchClock (its time scale, e.g. 100 or 1000 bench s per wall s). The
// program advances in ticks of tick_s bench seconds, whatever the scale (see ProgramRunner). The tester runs
// up to one timer period ahead of the clock, so the plant is normally at or beyond the clock's "now" and other
// instruments' advance_to(clock.now) are no-ops. When this server's thread lags the clock (its timer runs late,
// or a loaded host gives it no CPU for a while) they still never integrate the cell with a stale current: each
// tick's current is held only up to the tick's end (BenchPlant::set_current), so the plant waits for the
// tester. Its late tick finds the cell where its previous tick left it (its rows are the cell's under the
// current they record), and its CV phase, cut-offs and step changes run as a real tester's hardware would,
// connected client or not. An idle, paused or stopped tester's 0 A is held for any time.
//
// Step files: `start` names a path on the "BTS PC". It is looked up among files registered with
// add_step_file(), then on disk (relative paths against step_file_dir). devtype 24 (BTS-4008) by default;
// 27 (the captured BTS 8.0 unit) or any other through the options.
//
// Fault switches (thread-safe): refuse connections (the listening socket closes: connect is refused), drop
// every open connection, stall responses (requests are read and carried out, never answered: a lost reply),
// malformed responses (each answer is cut short), garbage between frames (junk and stray terminators before
// each answer), a member's status (protect/stop: that member stops conducting, the others keep their
// share), and a starved host (the server's thread gets no CPU: see set_starved).
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "cellbench/sim/neware_runner.hpp"
#include "cellbench/sim/plant.hpp"

namespace cellbench::sim {

struct NewareServerOptions {
    std::string host = "127.0.0.1";
    int port = 0;  // 0: a free port below the ephemeral range (see port())
    // The unit as the API addresses it.
    std::string ip = "127.0.0.1";
    int devtype = 24, devid = 1, subdevid = 1;
    int channel_count = 8;                 // BTS-4008: 8 channels of 20 A
    std::vector<int> cell_channels{1, 2, 3};  // chlids wired to the cell (2+ = parallel group)
    double max_channel_current_a = 20.0;
    double tick_s = 0.1;                   // bench seconds per program tick
    int timer_period_ms = 5;               // wall period of the execution timer
    std::string step_file_dir;             // base of relative step-file paths
};

struct NewareServerStats {
    std::uint64_t connections = 0;
    std::uint64_t requests = 0;
    std::uint64_t malformed_requests = 0;
    std::uint64_t responses = 0;
    std::uint64_t unanswered = 0;  // stalled
    std::uint64_t ticks = 0;       // program ticks executed
};

// What the tester is doing (for tests and the daemon's status page).
struct NewareRunSnapshot {
    bool has_run = false;
    RunState state = RunState::finished;
    std::string program_name;
    int step_id = 0, cycle_id = 0;
    std::string step_type;
    double bench_time_s = 0.0;       // of the last tick
    double group_current_a = 0.0;    // measured, all conducting members
    double voltage_v = 0.0;
    double step_time_s = 0.0, total_time_s = 0.0;
    double step_capacity_ah = 0.0;
    std::vector<ProgramRunner::StepRecord> history;  // completed steps
    std::vector<protocol::neware::ChannelStatus> member_status;  // per cell channel
};

class NewareServer {
public:
    NewareServer(BenchPlant plant, std::shared_ptr<const BenchClock> clock, NewareServerOptions options = {});
    ~NewareServer();  // stops
    NewareServer(const NewareServer&) = delete;
    NewareServer& operator=(const NewareServer&) = delete;

    // Listens (throws std::runtime_error when it cannot) and starts serving on its own thread.
    void start();
    void stop();
    [[nodiscard]] int port() const;                   // the bound port, after start()
    [[nodiscard]] std::string description() const;    // "tcp 127.0.0.1:15020"
    [[nodiscard]] std::vector<protocol::neware::ChannelAddress> cell_channel_addresses() const;

    // A file on the simulated BTS PC (the daemon or a test puts compiled step files here).
    void add_step_file(const std::string& path, std::string content);

    // Fault switches.
    void set_refuse_connections(bool refuse);
    void drop_connections();
    void set_stall_responses(bool stall);
    void set_malformed_responses(bool malformed);
    void set_garbage_between_frames(bool garbage);
    // The simulated tester's host gets no CPU (what a loaded machine does to this server's thread for a moment):
    // while starved, nothing of the server runs -- no program tick, no answer (requests wait, connections stay
    // open) -- while the bench clock and the other simulated instruments go on. set_starved(true) returns once
    // the server's thread is held (at once when the server is not running); set_starved(false) or stop()
    // releases it, and the server catches up with the clock.
    void set_starved(bool starved);
    // Puts one cell channel into protect (or stop); it stops conducting while the others continue.
    // Returns false if chlid is not a cell channel.
    bool inject_member_status(int chlid, protocol::neware::ChannelStatus status);

    [[nodiscard]] NewareServerStats stats() const;
    [[nodiscard]] NewareRunSnapshot snapshot() const;

private:
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

}  // namespace cellbench::sim
