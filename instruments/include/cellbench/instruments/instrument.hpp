#pragma once
// One interface for every instrument of the bench (after libsigrok's struct sr_dev_driver): a name and a kind,
// start/stop, a state, a status snapshot, a typed reading callback, and command results that say whether a
// command was never sent. The daemon keeps its instruments in an InstrumentRegistry and iterates it for
// GET /status, GET /metrics and fault bookkeeping, so a new instrument is one folder under instruments/ and
// one registry line.
//
// The base class keeps what every instrument reports alike (state and its detail, address, data age, sample
// rate, reconnects, faults); it is thread-safe (one leaf mutex). Subclasses adapt one driver (and its hosted
// simulator, when simulated) and add what only they know (lost frames, simulator requests).
#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace cellbench::instruments {

// The API's instrument states (INTERFACES.md, GET /status instruments[].state).
enum class InstrumentState { connecting, connected, offline, error };
[[nodiscard]] std::string_view to_string(InstrumentState state);

// One channel of an instrument made of several (a cycler's channels wired in parallel as one), as it reported
// itself in the newest reading.
struct MemberReading {
    std::string channel;  // "devtype-devid-subdevid-chlid"
    double voltage_v = 0.0, current_a = 0.0;  // + = charge
    std::string status;
};

// What GET /status and GET /metrics show of one instrument.
struct InstrumentStatus {
    std::string name;  // "neware", "chamber", "dewe"
    std::string kind;  // "cycler", "chamber", "daq"
    InstrumentState state = InstrumentState::connecting;
    std::string address;  // where the driver talks to it ("127.0.0.1:15020", "can-dgram /tmp/...")
    std::string detail;   // the last thing it said about its state, in plain words
    bool simulated = false;
    std::optional<double> data_age_s;  // wall seconds since the newest reading; none before the first
    double sample_rate_hz = 0.0;       // readings per wall second recently (0 without history)
    std::uint64_t reconnects = 0;      // returns to "connected" after having been connected
    std::uint64_t faults = 0;          // fault reports since start (every report, not only episode openings)
    // Frames lost on the way (DAQ CAN frame counter gaps; cycler answers lost or malformed); none when the
    // instrument has no such counter.
    std::optional<std::uint64_t> lost_frames;
    std::optional<std::uint64_t> sim_requests;  // requests the hosted simulator answered, when simulated
    std::vector<MemberReading> members;         // its channels, when it is made of several (newest reading)
};

// The outcome of a command to an instrument. never_sent: it never left the driver (not connected, queue
// timed out), so the instrument cannot have acted on it and sending it again is safe.
struct CommandResult {
    enum class Outcome { done, failed, never_sent };
    Outcome outcome = Outcome::done;
    std::string message;  // empty when done
    [[nodiscard]] bool ok() const { return outcome == Outcome::done; }
    [[nodiscard]] bool sent() const { return outcome != Outcome::never_sent; }
};

class Instrument {
public:
    Instrument(std::string name, std::string kind) : name_(std::move(name)), kind_(std::move(kind)) {}
    virtual ~Instrument() = default;
    Instrument(const Instrument&) = delete;
    Instrument& operator=(const Instrument&) = delete;

    [[nodiscard]] const std::string& name() const { return name_; }
    [[nodiscard]] const std::string& kind() const { return kind_; }

    // Connects (and keeps reconnecting) / disconnects the driver; no reading callback runs after stop().
    virtual void start() = 0;
    virtual void stop() = 0;

    [[nodiscard]] InstrumentState state() const;
    [[nodiscard]] std::string detail() const;
    // The snapshot at wall time now_unix_s (for the data age).
    [[nodiscard]] InstrumentStatus status(double now_unix_s) const;

    // -- bookkeeping, called by whoever interprets the driver's events (the daemon) ---------------------------
    // Sets the state and its detail; returns whether the state changed. A return to connected after having
    // been connected counts as a reconnect.
    bool set_state(InstrumentState state, std::string detail);
    void set_detail(std::string detail);
    void set_address(std::string address);
    void set_simulated(bool simulated);
    // A reading taken at wall time unix_s (data age, sample rate) and t_s on the daemon's clock (bench time, the
    // clock the run's silence graces and the simulated bench's pacer count in).
    void note_reading(double unix_s, double t_s);
    // The daemon-clock time of the last reading (nullopt: none yet).
    [[nodiscard]] std::optional<double> last_reading_t_s() const;
    // The channels of an instrument made of several, as the newest reading gave them.
    void set_members(std::vector<MemberReading> members);
    // A fault report; lost_answer: an answer that never came or could not be read (timeout, protocol error).
    void count_fault(bool lost_answer);

protected:
    // What only the subclass knows (called without the base's lock held).
    [[nodiscard]] virtual std::optional<std::uint64_t> lost_frames() const { return std::nullopt; }
    [[nodiscard]] virtual std::optional<std::uint64_t> sim_requests() const { return std::nullopt; }
    // Answers lost (count_fault(true)) so far: the cycler reports them as its lost frames.
    [[nodiscard]] std::uint64_t lost_answers() const;

private:
    const std::string name_, kind_;
    mutable std::mutex m_;  // leaf
    InstrumentState state_ = InstrumentState::connecting;
    std::string detail_, address_;
    bool simulated_ = false;
    bool was_connected_ = false;
    std::uint64_t reconnects_ = 0, faults_ = 0, lost_answers_ = 0;
    std::optional<double> last_reading_unix_s_, last_reading_t_s_;
    std::deque<double> reading_times_;  // the last readings' wall times, for the sample rate
    std::vector<MemberReading> members_;
};

// An instrument whose readings are of type Reading: one typed callback, set before start().
template <class Reading>
class InstrumentOf : public Instrument {
public:
    using Instrument::Instrument;
    using ReadingCallback = std::function<void(const Reading&)>;
    void on_reading(ReadingCallback callback) { on_reading_ = std::move(callback); }

protected:
    void deliver(const Reading& reading) const {
        if (on_reading_) on_reading_(reading);
    }

private:
    ReadingCallback on_reading_;
};

}  // namespace cellbench::instruments
