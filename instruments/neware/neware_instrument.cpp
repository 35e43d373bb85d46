#include "neware/neware_instrument.hpp"

namespace cellbench::instruments {

NewareInstrument::NewareInstrument(drivers::NewareClient& client, const sim::NewareServer* hosted)
    : InstrumentOf("neware", "cycler"), client_(client), hosted_(hosted) {
    set_simulated(hosted != nullptr);
    client_.on_sample([this](const drivers::NewareSample& s) { deliver(s); });
}

CommandResult NewareInstrument::result_of(const drivers::NewareCommandResult& r) {
    if (r.ok) return {};
    return {r.never_sent ? CommandResult::Outcome::never_sent : CommandResult::Outcome::failed, r.error};
}

std::optional<std::uint64_t> NewareInstrument::sim_requests() const {
    if (!hosted_) return std::nullopt;
    return hosted_->stats().requests;
}

}  // namespace cellbench::instruments
