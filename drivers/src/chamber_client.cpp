#include "cellbench/drivers/chamber_client.hpp"
#include "cellbench/drivers/episode_log.hpp"

#include <modbus.h>

#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>
#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

namespace cellbench::drivers {

namespace asio = boost::asio;
using Clock = std::chrono::steady_clock;
using protocol::RegisterTable;

const char* to_string(ChamberFaultKind kind) {
    switch (kind) {
        case ChamberFaultKind::unreachable: return "unreachable";
        case ChamberFaultKind::timeout: return "timeout";
        case ChamberFaultKind::exception_response: return "exception_response";
        case ChamberFaultKind::bad_response: return "bad_response";
        case ChamberFaultKind::alarm: return "alarm";
        case ChamberFaultKind::setpoint_not_reached: return "setpoint_not_reached";
        case ChamberFaultKind::rejected: return "rejected";
    }
    return "?";
}

namespace {

// Modbus exception code of a libmodbus errno (EMBXILFUN..EMBXGTAR), 0 otherwise.
int exception_code_of(int err) {
    const int code = err - MODBUS_ENOBASE;
    return code >= 1 && code <= 11 ? code : 0;
}

bool transient_exception(int code) { return code == 4 || code == 5 || code == 6; }

const char* exception_name(int code) {
    switch (code) {
        case 1: return "illegal function";
        case 2: return "illegal data address";
        case 3: return "illegal data value";
        case 4: return "server device failure";
        case 5: return "acknowledge";
        case 6: return "server device busy";
        case 8: return "memory parity error";
        case 10: return "gateway path unavailable";
        case 11: return "gateway target failed to respond";
        default: return "exception";
    }
}

}  // namespace

struct ChamberClient::Impl : std::enable_shared_from_this<Impl> {
    Impl(asio::io_context& io, ChamberClientOptions o)
        : user(asio::make_strand(io)), options(std::move(o)), poll_timer(worker) {
        options.map.validate();
    }
    ~Impl() { shutdown(); }

    // Callbacks (status, faults, command completions) run on a strand of the user's io_context: one at a
    // time and in the order the worker produced them, however many threads run that io_context.
    asio::strand<asio::io_context::executor_type> user;
    ChamberClientOptions options;
    asio::io_context worker;
    asio::executor_work_guard<asio::io_context::executor_type> work{worker.get_executor()};
    asio::steady_timer poll_timer;
    std::thread thread;
    std::shared_ptr<std::atomic<bool>> alive = std::make_shared<std::atomic<bool>>(true);
    std::function<void(const ChamberStatus&)> status_callback;
    std::function<void(const ChamberFault&)> fault_callback;
    EpisodeLog episode_log;  // one warning per kind of fault in an episode (on the worker)

    // Worker-only state.
    modbus_t* ctx = nullptr;
    bool connected = false;
    std::uint16_t last_alarm_word = 0;
    std::optional<Clock::time_point> out_of_tolerance_since;
    bool setpoint_fault_reported = false;

    void start() {
        if (thread.joinable()) return;
        asio::post(worker, [this] { poll(); });
        thread = std::thread([this] { worker.run(); });
    }

    void shutdown() {
        alive->store(false);
        work.reset();
        worker.stop();
        if (thread.joinable()) thread.join();
        if (ctx) {
            modbus_close(ctx);
            modbus_free(ctx);
            ctx = nullptr;
        }
    }

    // Runs f on the user's io_context unless the client was stopped meanwhile.
    template <typename F>
    void to_user(F f) {
        asio::post(user, [alive = alive, f = std::move(f)]() mutable {
            if (alive->load()) f();
        });
    }

    void report(const ChamberFault& fault) {
        spdlog::log(episode_log.level(fault.operation + " " + to_string(fault.kind), spdlog::level::warn),
                    "chamber {}:{}: {} ({}): {}", options.host, options.port, fault.operation, to_string(fault.kind),
                    fault.message);
        if (fault_callback) to_user([cb = fault_callback, fault] { cb(fault); });
    }

    // ---- libmodbus on the worker thread.

    void disconnect() {
        if (ctx && connected) modbus_close(ctx);
        connected = false;
    }

    std::optional<ChamberFault> ensure_connected(const std::string& operation) {
        if (!ctx) {
            ctx = modbus_new_tcp(options.host.c_str(), options.port);
            if (!ctx) return ChamberFault{ChamberFaultKind::unreachable, operation, "modbus_new_tcp failed: " + std::string(modbus_strerror(errno)), 0, 0};
            modbus_set_slave(ctx, options.unit_id);
            const auto us = std::chrono::duration_cast<std::chrono::microseconds>(options.response_timeout).count();
            modbus_set_response_timeout(ctx, static_cast<std::uint32_t>(us / 1000000), static_cast<std::uint32_t>(us % 1000000));
        }
        if (connected) return std::nullopt;
        if (modbus_connect(ctx) == -1) {
            return ChamberFault{ChamberFaultKind::unreachable, operation,
                                fmt::format("cannot connect to {}:{}: {}", options.host, options.port, modbus_strerror(errno)), 0, 0};
        }
        connected = true;
        return std::nullopt;
    }

    // Runs one Modbus operation (f returns -1 with errno set on failure) with the retry policy.
    template <typename F>
    std::optional<ChamberFault> attempt(const std::string& operation, F f) {
        std::optional<ChamberFault> fault;
        for (int attempt = 1; attempt <= 1 + std::max(0, options.retries); ++attempt) {
            if (auto connect_fault = ensure_connected(operation)) {
                fault = connect_fault;
                fault->attempts = attempt;
                continue;
            }
            if (f() != -1) return std::nullopt;
            const int err = errno;
            const int code = exception_code_of(err);
            if (code != 0) {
                fault = ChamberFault{ChamberFaultKind::exception_response, operation,
                                     fmt::format("Modbus exception {} ({})", code, exception_name(code)), code, attempt};
                if (!transient_exception(code)) return fault;
                continue;  // the connection is fine, the controller asks to try again
            }
            if (err == ETIMEDOUT) {
                fault = ChamberFault{ChamberFaultKind::timeout, operation,
                                     fmt::format("no answer within {} ms", options.response_timeout.count()), 0, attempt};
            } else if (err == EMBBADDATA || err == EMBMDATA || err == EMBBADCRC || err == EMBBADEXC ||
                       err == EMBUNKEXC || err == EMBBADSLAVE) {
                fault = ChamberFault{ChamberFaultKind::bad_response, operation, modbus_strerror(err), 0, attempt};
            } else {
                fault = ChamberFault{ChamberFaultKind::unreachable, operation,
                                     fmt::format("connection lost: {}", modbus_strerror(err)), 0, attempt};
            }
            // A late answer or a half-read frame would poison the next request: start on a fresh connection.
            disconnect();
            spdlog::debug("chamber {}: attempt {} failed: {}", operation, attempt, fault->message);
        }
        return fault;
    }

    std::pair<std::optional<ChamberStatus>, std::optional<ChamberFault>> read_status_now() {
        std::vector<protocol::RegisterBlock> blocks;
        std::optional<ChamberFault> fault = attempt("read status", [&] {
            blocks.clear();
            for (const auto& range : options.map.read_plan()) {
                protocol::RegisterBlock block{range.table, range.start, std::vector<std::uint16_t>(range.count)};
                const int rc = range.table == RegisterTable::holding
                                   ? modbus_read_registers(ctx, range.start, range.count, block.values.data())
                                   : modbus_read_input_registers(ctx, range.start, range.count, block.values.data());
                if (rc == -1) return -1;
                if (rc != range.count) {
                    errno = EMBBADDATA;
                    return -1;
                }
                blocks.push_back(std::move(block));
            }
            return 0;
        });
        if (fault) return {std::nullopt, fault};
        std::string error;
        const auto state = options.map.decode(blocks, &error);
        if (!state) return {std::nullopt, ChamberFault{ChamberFaultKind::bad_response, "read status", error, 0, 1}};
        ChamberStatus s;
        s.time = Clock::now();
        s.process_value_c = state->process_value_c;
        s.setpoint_c = state->setpoint_c;
        s.running = state->running;
        s.alarm_word = state->alarm_word;
        s.active_alarms = state->active_alarms;
        return {s, std::nullopt};
    }

    // Alarm edges and the set point watch, on every status read.
    void supervise(const ChamberStatus& s) {
        const std::uint16_t new_bits = s.alarm_word & static_cast<std::uint16_t>(~last_alarm_word);
        last_alarm_word = s.alarm_word;
        if (new_bits != 0) {
            auto names = options.map.alarm_names(new_bits);
            std::string list;
            for (const auto& n : names) list += (list.empty() ? "" : ", ") + n;
            if (list.empty()) list = fmt::format("unnamed alarm bits 0x{:04X}", new_bits);
            report({ChamberFaultKind::alarm, "read status", "chamber alarm: " + list, 0, 0});
        }
        const bool running = s.running.value_or(false);
        if (!running || std::abs(s.process_value_c - s.setpoint_c) <= options.setpoint_tolerance_c) {
            out_of_tolerance_since.reset();
            setpoint_fault_reported = false;
            return;
        }
        if (!out_of_tolerance_since) out_of_tolerance_since = s.time;
        if (!setpoint_fault_reported && s.time - *out_of_tolerance_since > options.setpoint_timeout) {
            setpoint_fault_reported = true;
            report({ChamberFaultKind::setpoint_not_reached, "watch set point",
                    fmt::format("air at {:.1f} degC, set point {:.1f} degC not reached within {:.0f} s",
                                s.process_value_c, s.setpoint_c,
                                std::chrono::duration<double>(options.setpoint_timeout).count()),
                    0, 0});
        }
    }

    void poll() {
        auto [status, fault] = read_status_now();
        if (fault) report(*fault);
        if (status) {
            episode_log.end("chamber " + options.host + ":" + std::to_string(options.port));
            supervise(*status);
            if (status_callback) to_user([cb = status_callback, s = *status] { cb(s); });
        }
        poll_timer.expires_after(options.poll_interval);
        poll_timer.async_wait([this](const boost::system::error_code& ec) {
            if (!ec) poll();
        });
    }

    std::optional<ChamberFault> write_registers(const std::string& operation, std::uint16_t address,
                                                const std::vector<std::uint16_t>& values) {
        return attempt(operation, [&] {
            const int rc = values.size() == 1 ? modbus_write_register(ctx, address, values[0])
                                              : modbus_write_registers(ctx, address, static_cast<int>(values.size()), values.data());
            return rc == -1 ? -1 : 0;
        });
    }

    void finish(const std::optional<ChamberFault>& fault, Done done) {
        if (fault) report(*fault);
        if (done) to_user([done = std::move(done), fault] { done(fault); });
    }
};

ChamberClient::ChamberClient(asio::io_context& io, ChamberClientOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(options))) {}

ChamberClient::~ChamberClient() { stop(); }

void ChamberClient::on_status(std::function<void(const ChamberStatus&)> callback) { impl_->status_callback = std::move(callback); }
void ChamberClient::on_fault(std::function<void(const ChamberFault&)> callback) { impl_->fault_callback = std::move(callback); }
void ChamberClient::start() { impl_->start(); }
void ChamberClient::stop() { impl_->shutdown(); }

void ChamberClient::set_temperature(double setpoint_c, Done done) {
    asio::post(impl_->worker, [impl = impl_.get(), setpoint_c, done = std::move(done)]() mutable {
        const auto registers = impl->options.map.encode_setpoint(setpoint_c);
        if (!registers) {
            impl->finish(ChamberFault{ChamberFaultKind::rejected, "write set point",
                                      fmt::format("set point {} degC outside {}..{} degC", setpoint_c,
                                                  impl->options.map.setpoint_min_c, impl->options.map.setpoint_max_c),
                                      0, 0},
                         std::move(done));
            return;
        }
        const auto fault = impl->write_registers("write set point", impl->options.map.setpoint.address, *registers);
        if (!fault) {
            impl->out_of_tolerance_since = Clock::now();  // the chamber gets the full timeout to get there
            impl->setpoint_fault_reported = false;
        }
        impl->finish(fault, std::move(done));
    });
}

void ChamberClient::set_running(bool running, Done done) {
    asio::post(impl_->worker, [impl = impl_.get(), running, done = std::move(done)]() mutable {
        const auto& run = impl->options.map.run;
        const auto fault = impl->write_registers("write run/stop", run.address, {running ? run.run_value : run.stop_value});
        impl->finish(fault, std::move(done));
    });
}

void ChamberClient::read_status(StatusDone done) {
    asio::post(impl_->worker, [impl = impl_.get(), done = std::move(done)]() mutable {
        auto [status, fault] = impl->read_status_now();
        if (fault) impl->report(*fault);
        if (status) impl->supervise(*status);
        if (done) impl->to_user([done = std::move(done), status = status, fault = fault] { done(status, fault); });
    });
}

}  // namespace cellbench::drivers
