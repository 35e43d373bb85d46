#pragma once
// Simulated climatic chamber: a Modbus TCP server (libmodbus) serving the register map of
// protocol/chamber_modbus.hpp from the plant's chamber air. Reads (functions 3 and 4) see the plant at the
// shared bench clock's "now"; writes (6, 16) of the set point and run/stop go to the plant; every other
// function gets the Modbus exception "illegal function", writes elsewhere "illegal data address", and set
// points outside the map's range "illegal data value".
//
// Runs on its own thread (libmodbus is blocking); serves several clients at once.
//
// Fault switches (thread-safe): unresponsive (requests are read and never answered: client timeouts),
// exception responses (every request answered with a given exception code), alarm bits, and a failed
// heater (the set point is not reached: the air cannot rise above the lab temperature).
#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "cellbench/protocol/chamber_modbus.hpp"
#include "cellbench/sim/plant.hpp"

namespace cellbench::sim {

struct ChamberServerOptions {
    std::string host = "127.0.0.1";
    int port = 0;  // 0: any free port (see port())
    protocol::ChamberRegisterMap map = protocol::ChamberRegisterMap::bench_default();
};

struct ChamberServerStats {
    std::uint64_t requests = 0;
    std::uint64_t exceptions_sent = 0;
    std::uint64_t unanswered = 0;
    std::uint64_t connections = 0;
};

class ChamberServer {
public:
    ChamberServer(BenchPlant plant, std::shared_ptr<const BenchClock> clock, ChamberServerOptions options = {});
    ~ChamberServer();  // stops
    ChamberServer(const ChamberServer&) = delete;
    ChamberServer& operator=(const ChamberServer&) = delete;

    // Listens (throws std::runtime_error when it cannot) and starts serving.
    void start();
    void stop();
    [[nodiscard]] int port() const;  // the bound port, after start()
    [[nodiscard]] std::string description() const;  // "modbus-tcp 127.0.0.1:15021"

    // Fault switches.
    void set_unresponsive(bool unresponsive);
    void set_exception_response(std::optional<std::uint8_t> exception_code);  // nullopt: normal answers
    // Sets or clears a named alarm bit of the map (false if the map has no such alarm).
    bool set_alarm(const std::string& name, bool active);
    void set_alarm_word(std::uint16_t word);
    void set_heater_failed(bool failed);

    [[nodiscard]] ChamberServerStats stats() const;

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace cellbench::sim
