#include "cellbench/drivers/dewe_driver.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <mutex>

#include <boost/asio/dispatch.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>
#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

namespace cellbench::drivers {

namespace asio = boost::asio;
using boost::system::error_code;
using Clock = std::chrono::steady_clock;

const char* to_string(DeweStreamState state) {
    switch (state) {
        case DeweStreamState::waiting: return "waiting";
        case DeweStreamState::streaming: return "streaming";
        case DeweStreamState::silent: return "silent";
        case DeweStreamState::stopped: return "stopped";
    }
    return "?";
}

struct DeweDriver::Impl : std::enable_shared_from_this<Impl> {
    Impl(asio::io_context& io, std::shared_ptr<CanTransport> t, DeweDriverOptions o)
        : strand(asio::make_strand(io)),
          transport(std::move(t)),
          options(std::move(o)),
          decoder(options.layout),
          health_timer(strand),
          retry_timer(strand) {}

    asio::strand<asio::io_context::executor_type> strand;
    std::shared_ptr<CanTransport> transport;
    DeweDriverOptions options;
    protocol::DeweCanDecoder decoder;
    asio::steady_timer health_timer, retry_timer;
    std::function<void(const DeweReading&)> sample_callback;
    std::function<void(const DeweHealth&)> health_callback;
    std::atomic<bool> stopped{false};

    // Strand-only state.
    DeweHealth health;
    protocol::DeweStreamStats reported;  // counters at the last health report
    Clock::time_point started{};

    mutable std::mutex snapshot_mutex;
    DeweHealth snapshot;

    // A copy of one received record (the transport's buffer is only valid during its handler).
    struct Record {
        std::array<std::uint8_t, protocol::kCanRecordBytes + 1> bytes{};
        std::size_t size = 0;  // sizes beyond the array are clamped to it: still the wrong size
        Clock::time_point time;
    };

    void start() {
        asio::dispatch(strand, [self = shared_from_this()] {
            self->started = Clock::now();
            self->receive();
            self->arm_health();
        });
    }

    void stop() {
        if (stopped.exchange(true)) return;
        asio::dispatch(strand, [self = shared_from_this()] {
            self->health_timer.cancel();
            self->retry_timer.cancel();
            self->transport->close();
            self->health.state = DeweStreamState::stopped;
            self->publish_snapshot();
        });
    }

    void receive() {
        if (stopped) return;
        transport->async_receive([self = shared_from_this()](const error_code& ec, std::span<const std::uint8_t> bytes) {
            Record r;
            r.time = Clock::now();
            r.size = std::min(bytes.size(), r.bytes.size());
            std::copy_n(bytes.begin(), r.size, r.bytes.begin());
            asio::dispatch(self->strand, [self, ec, r] { self->on_record(ec, r); });
        });
    }

    void on_record(const error_code& ec, const Record& r) {
        if (stopped || ec == asio::error::operation_aborted) return;
        if (ec) {
            // The medium failed (e.g. CAN interface down): say so, retry shortly.
            report(fmt::format("receive error on {}: {}", transport->description(), ec.message()));
            retry_timer.expires_after(std::chrono::milliseconds(500));
            retry_timer.async_wait([self = shared_from_this()](const error_code& tec) {
                if (!tec) self->receive();
            });
            return;
        }
        const std::uint64_t frames_before = decoder.stats().frames;
        const double time_s = std::chrono::duration<double>(r.time.time_since_epoch()).count();
        const auto sample = decoder.push_record(std::span<const std::uint8_t>(r.bytes.data(), r.size), time_s);
        health.stats = decoder.stats();
        if (decoder.stats().frames != frames_before) {
            health.last_frame = r.time;
            if (health.state != DeweStreamState::streaming) {
                const bool resumed = health.state == DeweStreamState::silent;
                health.state = DeweStreamState::streaming;
                report(resumed ? "stream resumed" : "stream started");
            }
        }
        if (sample && sample_callback && !stopped) sample_callback(reading_of(*sample, r.time));
        receive();
    }

    DeweReading reading_of(const protocol::DeweSample& s, Clock::time_point time) const {
        DeweReading out;
        out.time = time;
        out.sequence = s.sequence;
        out.thermopile_v = s.thermopile_v();
        out.type_t_c = s.type_t_c();
        out.t1_c = s.t1_c();
        out.t2_c = s.t2_c();
        // Thesis eq. 2.2 with the sensor's own Type-T, then eq. 2.3 over the whole cell surface.
        out.heat_flux_w_per_m2 = protocol::heat_flux_density_w_per_m2(out.thermopile_v, out.type_t_c,
                                                                      options.sensitivity_v_per_w_per_m2);
        out.heat_flow_w = out.heat_flux_w_per_m2 * options.area_m2;
        return out;
    }

    void arm_health() {
        health_timer.expires_after(options.health_interval);
        health_timer.async_wait([self = shared_from_this()](const error_code& ec) {
            if (ec || self->stopped) return;
            self->check_health();
            self->arm_health();
        });
    }

    void check_health() {
        publish_snapshot();  // keep the counters of health() fresh
        const auto now = Clock::now();
        const auto since = health.last_frame == Clock::time_point{} ? started : health.last_frame;
        if (health.state != DeweStreamState::silent && now - since > options.silence_timeout) {
            health.state = DeweStreamState::silent;
            report(fmt::format("no valid frame on {} for {:.1f} s", transport->description(),
                               std::chrono::duration<double>(now - since).count()));
            return;
        }
        const auto& s = health.stats;
        if (s.lost_samples != reported.lost_samples || s.lost_frames != reported.lost_frames ||
            s.garbage != reported.garbage || s.resyncs != reported.resyncs) {
            std::string what;
            auto add = [&](std::uint64_t now_n, std::uint64_t before, const char* name) {
                if (now_n == before) return;
                if (!what.empty()) what += ", ";
                what += fmt::format("{} {}", now_n - before, name);
            };
            add(s.lost_samples, reported.lost_samples, "samples lost");
            add(s.lost_frames, reported.lost_frames, "frames lost");
            add(s.garbage, reported.garbage, "garbage frames");
            add(s.resyncs, reported.resyncs, "counter restarts");
            report(what + " since the last report");
        }
    }

    void report(std::string message) {
        health.message = std::move(message);
        reported = health.stats;
        publish_snapshot();
        spdlog::debug("dewe {}: {} ({})", transport->description(), health.message, to_string(health.state));
        if (health_callback && !stopped) health_callback(health);
    }

    void publish_snapshot() {
        std::lock_guard lock(snapshot_mutex);
        snapshot = health;
    }
};

DeweDriver::DeweDriver(asio::io_context& io, std::shared_ptr<CanTransport> transport, DeweDriverOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(transport), std::move(options))) {}

DeweDriver::~DeweDriver() { stop(); }

void DeweDriver::on_sample(std::function<void(const DeweReading&)> callback) {
    impl_->sample_callback = std::move(callback);
}

void DeweDriver::on_health(std::function<void(const DeweHealth&)> callback) {
    impl_->health_callback = std::move(callback);
}

void DeweDriver::start() { impl_->start(); }

void DeweDriver::stop() { impl_->stop(); }

DeweHealth DeweDriver::health() const {
    std::lock_guard lock(impl_->snapshot_mutex);
    DeweHealth h = impl_->snapshot;
    return h;
}

}  // namespace cellbench::drivers
