#include "dewe/dewe_instrument.hpp"

namespace cellbench::instruments {

DeweInstrument::DeweInstrument(drivers::DeweDriver& driver, const sim::DewePublisher* hosted)
    : InstrumentOf("dewe", "daq"), driver_(driver) {
    set_simulated(hosted != nullptr);
    driver_.on_sample([this](const drivers::DeweReading& r) { deliver(r); });
}

std::optional<std::uint64_t> DeweInstrument::lost_frames() const { return driver_.health().stats.lost_frames; }

}  // namespace cellbench::instruments
