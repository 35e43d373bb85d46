// Commands to the instruments with their retries: the tester's program start/stop/pause/continue and the
// chamber's set point, and the wait for the safe commands at shutdown.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>
#include "cellbench/protocol/neware_stepfile.hpp"

namespace cellbench::daemon {

void BenchDaemon::Impl::retry_later(int attempt, std::function<void()> fn, std::chrono::milliseconds cap) {
    auto timer = std::make_shared<asio::steady_timer>(io);
    timer->expires_after(std::min(cap, std::chrono::milliseconds(250LL << std::min(attempt, 5))));
    timer->async_wait([this, timer, fn = std::move(fn)](const boost::system::error_code& ec) {
        if (!ec && !stopping) fn();
    });
}

void BenchDaemon::Impl::chamber_setpoint(double c, std::uint64_t gen, int attempt) {
    chamber->set_temperature(c, [this, c, gen, attempt](const std::optional<drivers::ChamberFault>& f) {
        if (!f) {
            if (attempt > 0) spdlog::info("chamber: set point {:.1f} degC taken after {} attempts", c, attempt + 1);
            return recovered("chamber:command");
        }
        if (attempt == 0) instrument_fault("chamber", "set point " + std::to_string(c) + " degC: " + f->message, false);
        if (f->kind == drivers::ChamberFaultKind::rejected || stopping || gen != setpoint_generation) return;
        // Retried at least every second (the safe set point of an abort among them), so a chamber back from a
        // fault takes it within a second; a newer set point (the next run's) supersedes it.
        retry_later(attempt, [this, c, gen, attempt] {
            if (gen == setpoint_generation) chamber_setpoint(c, gen, attempt + 1);
        }, std::chrono::milliseconds(1000));
    });
}

void BenchDaemon::Impl::command_result(const std::string& what, const drivers::NewareCommandResult& r) {
    if (r.ok) {
        spdlog::debug("neware {}: ok", what);
        recovered("neware:command");
        return;
    }
    spdlog::warn("neware {} failed: {}", what, r.error);
    // A cycler that did not take a command: the run cannot be trusted to follow its program.
    instrument_fault("neware", what + " not acknowledged: " + r.error, what == "start" || what == "stop");
}

// A start that never left the daemon (tester unreachable) is sent again with backoff while the cycler's
// loss grace lasts: the tester cannot have acted on it. Any other failure (refused, answer lost: the
// tester may have started) is fatal to the run, as the sequencer cannot trust the program to run.
void BenchDaemon::Impl::cycler_start(const protocol::StepProgram& program, const std::string& barcode, int attempt,
                  std::optional<double> first_try_s) {
    const std::string xml = protocol::compile_step_file(program);
    std::string path;
    if (neware_server) {
        path = "C:\\cellbench\\" + safe_name(barcode) + ".xml";
        neware_server->add_step_file(path, xml);
    } else {
        // A real BTS PC reads the step file by path: write it where that PC can see it.
        std::filesystem::create_directories(step_file_dir);
        const auto p = step_file_dir / (safe_name(barcode) + ".xml");
        std::ofstream(p) << xml;
        path = p.string();
    }
    spdlog::info("neware: starting step program '{}' ({} steps) from {}", program.name, program.steps.size(), path);
    const double t_first = first_try_s.value_or(now_s());
    const std::uint64_t gen = run_generation, stops = stop_serial;
    // Still wanted: the same run, running (not paused, not ended), and no stop sent since.
    auto wanted = [this, gen, stops] {
        if (stopping || gen != run_generation || stops != stop_serial) return false;
        const auto c = active();
        return c && c->seq->state() == sequencer::RunState::Running;
    };
    neware->start_program(path, barcode, [this, program, barcode, attempt, t_first, wanted](const drivers::NewareCommandResult& r) {
        if (r.ok || !r.never_sent) return command_result("start", r);
        if (!wanted()) return;
        if (now_s() - t_first >= grace_for("neware")) return command_result("start", r);
        if (attempt == 0) instrument_fault("neware", "start not sent: " + r.error + "; sending it again", false);
        retry_later(attempt, [this, program, barcode, attempt, t_first, wanted] {
            if (wanted()) cycler_start(program, barcode, attempt + 1, t_first);
        });
    });
}

// Stops the tester's program; a stop the tester did not acknowledge (unreachable, stalled) is sent again
// with backoff until it is, unless a newer run started meanwhile: the cell is never left on a program.
void BenchDaemon::Impl::cycler_stop(const std::string& why, int attempt, std::optional<double> first_cmd) {
    if (attempt == 0) ++stop_serial;  // a start still being retried is no longer wanted
    const double t_cmd = first_cmd.value_or(now_s());
    const std::uint64_t gen = run_generation;
    neware->stop_program([this, t_cmd, why, attempt, gen](const drivers::NewareCommandResult& r) {
        if (!r.ok) {
            if (attempt == 0) {
                command_result("stop", r);
                // Said plainly in the run's record: until the stop gets through, the tester keeps running its
                // step file, guarded only by the file's own protection limits.
                if (auto c = current()) {
                    EventRecord e;
                    e.run_id = c->id;
                    e.unix_s = unix_now_s();
                    e.t_s = c->rel(now_s());
                    e.level = EventLevel::error;
                    e.kind = "cycler";
                    e.message = "stop not acknowledged (" + r.error +
                                "): the tester may still be running its step file, guarded by the file's own "
                                "protection limits; sending the stop again every second until it is acknowledged";
                    e.detail = {{"commanded_t_s", c->rel(t_cmd)}, {"why", why}, {"error", r.error},
                                {"never_sent", r.never_sent}};
                    store->record_event(e);
                }
            }
            if (stopping || gen != run_generation) return;
            spdlog::warn("neware: stop not acknowledged ({}); sending it again", r.error);
            // A safety command: retried at least every second (a stop that cannot leave costs nothing on the
            // wire), so it goes out within a second of the tester becoming reachable again.
            return retry_later(attempt, [this, why, attempt, t_cmd, gen] {
                if (gen == run_generation) cycler_stop(why, attempt + 1, t_cmd);
            }, std::chrono::milliseconds(1000));
        }
        // When the tester confirmed: recorded so the reaction time of a safety stop is visible.
        const double t_ack = now_s();
        if (auto c = current()) {
            EventRecord e;
            e.run_id = c->id;
            e.unix_s = unix_now_s();
            e.t_s = c->rel(t_ack);
            e.kind = "cycler";
            e.message = "current off: the tester acknowledged the stop";
            e.detail = {{"commanded_t_s", c->rel(t_cmd)}, {"acknowledged_t_s", c->rel(t_ack)}, {"why", why},
                        {"attempts", attempt + 1}};
            store->record_event(e);
        }
    });
}

// Waits until the stop request and the safe set point write sent just before have been answered: a probe
// queued behind them on each instrument (the clients answer in order). Bounded by what the configured
// timeouts allow: on the chamber a poll in progress, the write and the probe, each up to (retries + 1)
// attempts of response_timeout_ms; on the cycler the stop and the probe. The probes' callbacks hold the
// shared state, never this frame: one answering after the deadline finds nobody waiting, harmlessly.
void BenchDaemon::Impl::wait_commands() {
    struct Pending {
        std::mutex m;
        std::condition_variable cv;
        int left = 2;
    };
    auto p = std::make_shared<Pending>();
    auto done = [p] {
        std::lock_guard l(p->m);
        --p->left;
        p->cv.notify_all();
    };
    const auto& ch = cfg.faults.chamber;
    const double chamber_s = 3.0 * (ch.retries + 1) * ch.response_timeout_ms / 1e3;
    const double cycler_s = 2.0 * cfg.cycler.response_timeout_ms / 1e3;
    const auto limit = std::chrono::duration<double>(std::max(chamber_s, cycler_s) + 1.0);
    neware->request(protocol::neware::ChannelListRequest{protocol::neware::Command::getchlstatus, cfg.cycler.channels},
                    [done](const auto&, const std::string&) { done(); });
    chamber->read_status([done](const auto&, const auto&) { done(); });
    std::unique_lock l(p->m);
    if (!p->cv.wait_for(l, limit, [&] { return p->left <= 0; }))
        spdlog::warn("shutdown: the instruments did not answer within {:.1f} s; closing the connections", limit.count());
}

}  // namespace cellbench::daemon
