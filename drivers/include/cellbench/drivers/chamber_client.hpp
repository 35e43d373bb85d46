#pragma once
// Climatic chamber client over Modbus TCP (libmodbus), with the register map of protocol/chamber_modbus.hpp:
// sets the temperature, starts/stops the chamber, polls the process value, set point, run state and alarm bits.
//
// libmodbus calls block, so they run on the client's own worker thread; results and faults are posted to the
// io_context given at construction (callbacks run there, never after stop()).
//
// Faults (instrument faults for the daemon): unreachable (connect failed), timeout (no answer within the
// response timeout), exception_response (the controller answered with a Modbus exception), bad_response
// (malformed or undecodable), alarm (an alarm bit came on), setpoint_not_reached (the process value stayed
// out of tolerance longer than the set point timeout, e.g. a failed heater), rejected (set point outside the
// map's range; nothing is sent). Timeouts, broken connections, malformed answers and the transient exceptions
// (4 server failure, 5 acknowledge, 6 busy) are retried on a fresh connection; 1/2/3 (illegal function,
// address, value) are not, they will not change.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>

#include "cellbench/protocol/chamber_modbus.hpp"

namespace cellbench::drivers {

struct ChamberClientOptions {
    std::string host = "127.0.0.1";
    int port = 502;
    int unit_id = 1;
    protocol::ChamberRegisterMap map = protocol::ChamberRegisterMap::bench_default();
    std::chrono::milliseconds response_timeout{500};
    int retries = 2;  // further attempts after a transient failure
    std::chrono::milliseconds poll_interval{1000};
    double setpoint_tolerance_c = 1.0;
    std::chrono::milliseconds setpoint_timeout{std::chrono::minutes(30)};  // wall time (scale it for simulations)
};

struct ChamberStatus {
    std::chrono::steady_clock::time_point time;  // when the registers were read
    double process_value_c = 0.0;                // chamber air
    double setpoint_c = 0.0;                     // as the controller reports it
    std::optional<bool> running;                 // nullopt: neither the run nor the stop value
    std::uint16_t alarm_word = 0;
    std::vector<std::string> active_alarms;
};

enum class ChamberFaultKind { unreachable, timeout, exception_response, bad_response, alarm, setpoint_not_reached, rejected };
const char* to_string(ChamberFaultKind kind);

struct ChamberFault {
    ChamberFaultKind kind = ChamberFaultKind::timeout;
    std::string operation;   // "read status", "write set point", "write run/stop", "watch set point", ...
    std::string message;     // plain words
    int exception_code = 0;  // for exception_response
    int attempts = 0;        // Modbus attempts made
};

class ChamberClient {
public:
    using Done = std::function<void(const std::optional<ChamberFault>& fault)>;
    using StatusDone = std::function<void(const std::optional<ChamberStatus>&, const std::optional<ChamberFault>&)>;

    ChamberClient(boost::asio::io_context& io, ChamberClientOptions options);
    ~ChamberClient();  // stops
    ChamberClient(const ChamberClient&) = delete;
    ChamberClient& operator=(const ChamberClient&) = delete;

    // Set before start().
    void on_status(std::function<void(const ChamberStatus&)> callback);  // every successful poll
    void on_fault(std::function<void(const ChamberFault&)> callback);    // every fault, polls and commands alike

    void start();  // starts the worker and polling
    void stop();   // joins the worker; no callback runs afterwards

    // Commands (queued on the worker, done runs on the io_context; a fault also goes to on_fault).
    void set_temperature(double setpoint_c, Done done = {});
    void set_running(bool running, Done done = {});
    void read_status(StatusDone done);

private:
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

}  // namespace cellbench::drivers
