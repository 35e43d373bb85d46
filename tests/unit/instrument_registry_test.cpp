// The Instrument interface's common bookkeeping (state, reconnects, data age, sample rate, faults) and the
// registry the daemon iterates for /status, /metrics and /health.
#include <gtest/gtest.h>

#include <memory>
#include <string>
#include <vector>

#include "cellbench/instruments/registry.hpp"
#include "neware/neware_instrument.hpp"

namespace {

using cellbench::instruments::CommandResult;
using cellbench::instruments::InstrumentOf;
using cellbench::instruments::InstrumentRegistry;
using cellbench::instruments::InstrumentState;

struct FakeReading {
    double value = 0.0;
};

class FakeInstrument final : public InstrumentOf<FakeReading> {
public:
    FakeInstrument(std::string name, std::vector<std::string>* log) : InstrumentOf(std::move(name), "fake"), log_(log) {}
    void start() override { log_->push_back("start " + name()); }
    void stop() override { log_->push_back("stop " + name()); }
    void emit(double v) { deliver(FakeReading{v}); }

private:
    std::vector<std::string>* log_;
};

TEST(Instrument, ReconnectsCountReturnsToConnectedAfterHavingBeenConnected) {
    std::vector<std::string> log;
    FakeInstrument i("a", &log);
    EXPECT_EQ(i.state(), InstrumentState::connecting);
    EXPECT_TRUE(i.set_state(InstrumentState::connected, ""));
    EXPECT_FALSE(i.set_state(InstrumentState::connected, ""));  // no change, no reconnect
    EXPECT_EQ(i.status(0.0).reconnects, 0u);
    EXPECT_TRUE(i.set_state(InstrumentState::offline, "link down"));
    EXPECT_EQ(i.detail(), "link down");
    EXPECT_TRUE(i.set_state(InstrumentState::connected, ""));
    EXPECT_EQ(i.status(0.0).reconnects, 1u);
    EXPECT_EQ(cellbench::instruments::to_string(i.state()), "connected");
}

TEST(Instrument, StatusCarriesDataAgeSampleRateAndFaults) {
    std::vector<std::string> log;
    FakeInstrument i("a", &log);
    EXPECT_FALSE(i.status(100.0).data_age_s.has_value());
    EXPECT_FALSE(i.last_reading_t_s().has_value());
    // 10 Hz for 1 s of wall time; on the daemon's clock (a simulated bench at x100) 100 s
    for (int k = 0; k <= 10; ++k) i.note_reading(100.0 + 0.1 * k, 5000.0 + 10.0 * k);
    ASSERT_TRUE(i.last_reading_t_s().has_value());
    EXPECT_DOUBLE_EQ(*i.last_reading_t_s(), 5100.0);  // what the simulated bench's pacer waits on
    const auto s = i.status(102.0);
    ASSERT_TRUE(s.data_age_s.has_value());
    EXPECT_NEAR(*s.data_age_s, 1.0, 1e-9);
    EXPECT_NEAR(s.sample_rate_hz, 10.0, 1e-6);
    EXPECT_DOUBLE_EQ(*i.status(50.0).data_age_s, 0.0);  // never negative
    i.count_fault(true);
    i.count_fault(false);
    EXPECT_EQ(i.status(0.0).faults, 2u);
    EXPECT_FALSE(i.status(0.0).lost_frames.has_value());  // the base knows no frames
}

TEST(Instrument, ReadingsReachTheTypedCallback) {
    std::vector<std::string> log;
    FakeInstrument i("a", &log);
    double got = 0.0;
    i.on_reading([&](const FakeReading& r) { got = r.value; });
    i.emit(4.2);
    EXPECT_DOUBLE_EQ(got, 4.2);
}

TEST(InstrumentRegistry, KeepsOrderStartsAndStopsInOrderAndRefusesDuplicates) {
    std::vector<std::string> log;
    InstrumentRegistry reg;
    EXPECT_FALSE(reg.all_connected());
    auto& a = reg.add(std::make_unique<FakeInstrument>("a", &log));
    auto& b = reg.add(std::make_unique<FakeInstrument>("b", &log));
    EXPECT_THROW(reg.add(std::make_unique<FakeInstrument>("a", &log)), std::invalid_argument);
    EXPECT_EQ(reg.size(), 2u);
    EXPECT_EQ(reg.find("b"), &b);
    EXPECT_EQ(reg.find("c"), nullptr);
    std::vector<std::string> names;
    for (const auto& i : reg) names.push_back(i->name());
    EXPECT_EQ(names, (std::vector<std::string>{"a", "b"}));
    reg.start_all();
    reg.stop_all();
    EXPECT_EQ(log, (std::vector<std::string>{"start a", "start b", "stop a", "stop b"}));
    a.set_state(InstrumentState::connected, "");
    EXPECT_FALSE(reg.all_connected());
    b.set_state(InstrumentState::connected, "");
    EXPECT_TRUE(reg.all_connected());
}

TEST(CommandResult, SaysWhetherANewareCommandWasNeverSent) {
    using cellbench::instruments::NewareInstrument;
    cellbench::drivers::NewareCommandResult r;
    r.ok = true;
    EXPECT_TRUE(NewareInstrument::result_of(r).ok());
    r.ok = false;
    r.error = "not connected";
    r.never_sent = true;
    const auto never = NewareInstrument::result_of(r);
    EXPECT_FALSE(never.ok());
    EXPECT_FALSE(never.sent());
    EXPECT_EQ(never.message, "not connected");
    r.never_sent = false;
    EXPECT_TRUE(NewareInstrument::result_of(r).sent());
    EXPECT_EQ(NewareInstrument::result_of(r).outcome, CommandResult::Outcome::failed);
}

}  // namespace
