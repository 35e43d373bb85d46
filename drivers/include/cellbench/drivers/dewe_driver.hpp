#pragma once
// DEWE-43A driver: reads the DAQ's CAN stream (any CanTransport), decodes it with the channel layout, converts
// the thermopile voltage to heat flux with the one FHF05 conversion (protocol/heat_flux.hpp, corrected with the
// sensor's own Type-T), and reports samples and stream health through callbacks.
//
// Callbacks run on the driver's strand of the io_context given at construction. Health is reported when the
// stream state changes (waiting -> streaming -> silent -> streaming ...) and, at most once per health interval,
// when samples or frames were lost or garbage arrived since the last report.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include <boost/asio/io_context.hpp>

#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/protocol/dewe_can.hpp"
#include "cellbench/protocol/heat_flux.hpp"

namespace cellbench::drivers {

struct DeweDriverOptions {
    protocol::DeweCanLayout layout = protocol::DeweCanLayout::bench_default();
    double sensitivity_v_per_w_per_m2 = protocol::kFhf05ThesisSensitivityVPerWPerM2;  // S at 20 degC (certificate)
    double area_m2 = 5.3109e-3;  // A_tot, the whole cell surface (heat flow = q * A), as thermal.area_m2
    std::chrono::milliseconds silence_timeout{1000};  // no valid frame for this long = silent
    std::chrono::milliseconds health_interval{200};   // how often silence and counters are checked
};

struct DeweReading {
    std::chrono::steady_clock::time_point time;  // monotonic receive time of the sample's last frame
    std::uint64_t sequence = 0;                  // unwrapped DAQ sample counter
    double thermopile_v = 0.0;
    double type_t_c = 0.0;                       // Type-T inside the heat flux sensor
    double t1_c = 0.0, t2_c = 0.0;               // Type-K at the terminals (NaN if the layout lacks them)
    double heat_flux_w_per_m2 = 0.0;             // + = leaving the cell surface
    double heat_flow_w = 0.0;                    // heat_flux * area
};

enum class DeweStreamState { waiting, streaming, silent, stopped };
const char* to_string(DeweStreamState state);

struct DeweHealth {
    DeweStreamState state = DeweStreamState::waiting;
    protocol::DeweStreamStats stats;
    std::chrono::steady_clock::time_point last_frame{};  // last valid frame (epoch if none yet)
    std::string message;  // what changed, in plain words
};

class DeweDriver {
public:
    DeweDriver(boost::asio::io_context& io, std::shared_ptr<CanTransport> transport, DeweDriverOptions options = {});
    ~DeweDriver();  // stops
    DeweDriver(const DeweDriver&) = delete;
    DeweDriver& operator=(const DeweDriver&) = delete;

    // Set before start().
    void on_sample(std::function<void(const DeweReading&)> callback);
    void on_health(std::function<void(const DeweHealth&)> callback);

    void start();
    // Closes the transport; no callback runs after the io_context has run the resulting cancellations.
    void stop();

    [[nodiscard]] DeweHealth health() const;  // thread-safe snapshot

private:
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

}  // namespace cellbench::drivers
