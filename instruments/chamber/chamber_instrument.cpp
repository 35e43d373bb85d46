#include "chamber/chamber_instrument.hpp"

namespace cellbench::instruments {

ChamberInstrument::ChamberInstrument(drivers::ChamberClient& client, const sim::ChamberServer* hosted)
    : InstrumentOf("chamber", "chamber"), client_(client), hosted_(hosted) {
    set_simulated(hosted != nullptr);
    client_.on_status([this](const drivers::ChamberStatus& s) { deliver(s); });
}

CommandResult ChamberInstrument::result_of(const std::optional<drivers::ChamberFault>& fault) {
    if (!fault) return {};
    return {fault->kind == drivers::ChamberFaultKind::unreachable ? CommandResult::Outcome::never_sent
                                                                  : CommandResult::Outcome::failed,
            fault->operation + ": " + fault->message};
}

std::optional<std::uint64_t> ChamberInstrument::sim_requests() const {
    if (!hosted_) return std::nullopt;
    return hosted_->stats().requests;
}

}  // namespace cellbench::instruments
