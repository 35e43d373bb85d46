#pragma once
// The DEWE-43A data acquisition (heat flux sensor, thermocouples) behind the Instrument interface: the CAN
// stream driver (drivers/dewe_driver) and, when the daemon hosts it, the simulated publisher
// (drivers/sim/dewe_publisher). Readings are the decoded CAN samples.
#include "cellbench/drivers/dewe_driver.hpp"
#include "cellbench/instruments/instrument.hpp"
#include "cellbench/sim/dewe_publisher.hpp"

namespace cellbench::instruments {

class DeweInstrument final : public InstrumentOf<drivers::DeweReading> {
public:
    // hosted: the simulated publisher this process runs, or nullptr.
    DeweInstrument(drivers::DeweDriver& driver, const sim::DewePublisher* hosted);

    void start() override { driver_.start(); }
    void stop() override { driver_.stop(); }
    [[nodiscard]] drivers::DeweDriver& driver() { return driver_; }

protected:
    // CAN frame counter gaps seen by the decoder.
    [[nodiscard]] std::optional<std::uint64_t> lost_frames() const override;

private:
    drivers::DeweDriver& driver_;
};

}  // namespace cellbench::instruments
