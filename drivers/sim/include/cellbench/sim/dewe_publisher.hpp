#pragma once
// Simulated DEWE-43A: samples the plant's heat flux sensor (thermopile voltage, Type-T) and the two Type-K
// thermocouples at a fixed rate in bench time and sends them as CAN frames with the channel layout, over any
// CanTransport (the can-dgram hub where the kernel has no AF_CAN, SocketCAN where it has).
//
// Sample k is taken at bench time t0 + k / rate and carries counter k (wrapped by the layout). Wall time
// follows the shared BenchClock; when the process falls behind, due samples are sent in a burst.
//
// Fault switches (thread-safe): silence (no frames; the DAQ keeps counting, as when the bus is cut), dropped
// samples (counter gaps), garbage records (unknown identifier, too short for the layout, len > 8, wrong
// record size, remote frame, in turn).
#include <cstdint>
#include <functional>
#include <memory>

#include <boost/asio/io_context.hpp>

#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/protocol/dewe_can.hpp"
#include "cellbench/sim/plant.hpp"

namespace cellbench::sim {

struct DewePublisherOptions {
    protocol::DeweCanLayout layout = protocol::DeweCanLayout::bench_default();
    double sample_rate_hz = 10.0;  // in bench time
};

struct DewePublisherStats {
    std::uint64_t samples = 0;              // taken from the plant
    std::uint64_t frames_sent = 0;
    std::uint64_t samples_dropped = 0;      // by the drop fault
    std::uint64_t samples_silenced = 0;     // while silent
    std::uint64_t samples_undelivered = 0;  // a frame of the sample could not be sent (listener too slow)
    std::uint64_t garbage_sent = 0;         // garbage records the medium accepted
};

class DewePublisher {
public:
    // Called for every sample taken (sent or not) with its counter and the plant reading it encodes.
    using SampleHook = std::function<void(std::uint64_t counter, const PlantReading& reading, bool sent)>;

    DewePublisher(boost::asio::io_context& io, BenchPlant plant, std::shared_ptr<const BenchClock> clock,
                  std::shared_ptr<drivers::CanTransport> transport, DewePublisherOptions options = {});
    ~DewePublisher();  // stops
    DewePublisher(const DewePublisher&) = delete;
    DewePublisher& operator=(const DewePublisher&) = delete;

    void on_sample(SampleHook hook);  // set before start()
    void start();
    void stop();  // closes the transport

    // Fault switches.
    void set_silent(bool silent);
    void drop_samples(std::uint64_t count);    // the next `count` samples are not sent
    void send_garbage(std::uint64_t count);    // `count` malformed records, sent soon on the publisher's strand

    [[nodiscard]] DewePublisherStats stats() const;
    [[nodiscard]] std::string description() const;  // the transport's, e.g. "can-dgram /tmp/dewe.sock"

private:
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

}  // namespace cellbench::sim
