#pragma once
// The climate chamber behind the Instrument interface: the Modbus client (drivers/chamber_client) and, when
// the daemon hosts it, the simulated chamber (drivers/sim/chamber_server). Readings are the status polls.
#include "cellbench/drivers/chamber_client.hpp"
#include "cellbench/instruments/instrument.hpp"
#include "cellbench/sim/chamber_server.hpp"

namespace cellbench::instruments {

class ChamberInstrument final : public InstrumentOf<drivers::ChamberStatus> {
public:
    // hosted: the simulated chamber this process runs, or nullptr.
    ChamberInstrument(drivers::ChamberClient& client, const sim::ChamberServer* hosted);

    void start() override { client_.start(); }
    void stop() override { client_.stop(); }
    [[nodiscard]] drivers::ChamberClient& client() { return client_; }

    // A command's outcome (nullopt = done); an unreachable chamber never got the command.
    [[nodiscard]] static CommandResult result_of(const std::optional<drivers::ChamberFault>& fault);

protected:
    [[nodiscard]] std::optional<std::uint64_t> sim_requests() const override;

private:
    drivers::ChamberClient& client_;
    const sim::ChamberServer* hosted_;
};

}  // namespace cellbench::instruments
