#include "cellbench/instruments/instrument.hpp"

#include <stdexcept>

#include "cellbench/instruments/registry.hpp"

namespace cellbench::instruments {

namespace {
constexpr std::size_t kRateWindow = 64;  // readings kept for the sample rate
}  // namespace

std::string_view to_string(InstrumentState state) {
    switch (state) {
        case InstrumentState::connecting: return "connecting";
        case InstrumentState::connected: return "connected";
        case InstrumentState::offline: return "offline";
        case InstrumentState::error: return "error";
    }
    return "error";
}

InstrumentState Instrument::state() const {
    std::lock_guard l(m_);
    return state_;
}

std::string Instrument::detail() const {
    std::lock_guard l(m_);
    return detail_;
}

InstrumentStatus Instrument::status(double now_unix_s) const {
    InstrumentStatus s;
    s.name = name_;
    s.kind = kind_;
    {
        std::lock_guard l(m_);
        s.state = state_;
        s.address = address_;
        s.detail = detail_;
        s.simulated = simulated_;
        if (last_reading_unix_s_) s.data_age_s = std::max(0.0, now_unix_s - *last_reading_unix_s_);
        if (reading_times_.size() >= 2 && reading_times_.back() > reading_times_.front())
            s.sample_rate_hz = static_cast<double>(reading_times_.size() - 1) /
                               (reading_times_.back() - reading_times_.front());
        s.reconnects = reconnects_;
        s.faults = faults_;
        s.members = members_;
    }
    s.lost_frames = lost_frames();
    s.sim_requests = sim_requests();
    return s;
}

void Instrument::set_members(std::vector<MemberReading> members) {
    std::lock_guard l(m_);
    members_ = std::move(members);
}

bool Instrument::set_state(InstrumentState state, std::string detail) {
    std::lock_guard l(m_);
    const bool changed = state != state_;
    if (state == InstrumentState::connected && state_ != InstrumentState::connected) {
        if (was_connected_) ++reconnects_;
        was_connected_ = true;
    }
    state_ = state;
    detail_ = std::move(detail);
    return changed;
}

void Instrument::set_detail(std::string detail) {
    std::lock_guard l(m_);
    detail_ = std::move(detail);
}

void Instrument::set_address(std::string address) {
    std::lock_guard l(m_);
    address_ = std::move(address);
}

void Instrument::set_simulated(bool simulated) {
    std::lock_guard l(m_);
    simulated_ = simulated;
}

void Instrument::note_reading(double unix_s, double t_s) {
    std::lock_guard l(m_);
    last_reading_unix_s_ = unix_s;
    last_reading_t_s_ = t_s;
    reading_times_.push_back(unix_s);
    if (reading_times_.size() > kRateWindow) reading_times_.pop_front();
}

std::optional<double> Instrument::last_reading_t_s() const {
    std::lock_guard l(m_);
    return last_reading_t_s_;
}

void Instrument::count_fault(bool lost_answer) {
    std::lock_guard l(m_);
    ++faults_;
    if (lost_answer) ++lost_answers_;
}

std::uint64_t Instrument::lost_answers() const {
    std::lock_guard l(m_);
    return lost_answers_;
}

// ---------------------------------------------------------------------------------------------------------

void InstrumentRegistry::add_impl(std::unique_ptr<Instrument> instrument) {
    if (find(instrument->name())) throw std::invalid_argument("instrument \"" + instrument->name() + "\" added twice");
    items_.push_back(std::move(instrument));
}

Instrument* InstrumentRegistry::find(std::string_view name) const {
    for (const auto& i : items_)
        if (i->name() == name) return i.get();
    return nullptr;
}

bool InstrumentRegistry::all_connected() const {
    if (items_.empty()) return false;
    for (const auto& i : items_)
        if (i->state() != InstrumentState::connected) return false;
    return true;
}

void InstrumentRegistry::start_all() {
    for (const auto& i : items_) i->start();
}

void InstrumentRegistry::stop_all() {
    for (const auto& i : items_) i->stop();
}

}  // namespace cellbench::instruments
