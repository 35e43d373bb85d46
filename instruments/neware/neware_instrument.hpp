#pragma once
// The Neware BTS battery tester (the cycler) behind the Instrument interface: the BTS 7.6 client
// (drivers/neware_client) and, when the daemon hosts it, the simulated tester (drivers/sim/neware_server).
// Readings are the channel samples of each poll.
#include "cellbench/drivers/neware_client.hpp"
#include "cellbench/instruments/instrument.hpp"
#include "cellbench/sim/neware_server.hpp"

namespace cellbench::instruments {

class NewareInstrument final : public InstrumentOf<drivers::NewareSample> {
public:
    // hosted: the simulated tester this process runs, or nullptr (a real tester or `cellbench sim`).
    NewareInstrument(drivers::NewareClient& client, const sim::NewareServer* hosted);

    void start() override { client_.start(); }
    void stop() override { client_.stop(); }
    [[nodiscard]] drivers::NewareClient& client() { return client_; }

    [[nodiscard]] static CommandResult result_of(const drivers::NewareCommandResult& r);

protected:
    // Answers lost (timeouts) or malformed.
    [[nodiscard]] std::optional<std::uint64_t> lost_frames() const override { return lost_answers(); }
    [[nodiscard]] std::optional<std::uint64_t> sim_requests() const override;

private:
    drivers::NewareClient& client_;
    const sim::NewareServer* hosted_;
};

}  // namespace cellbench::instruments
