#include "cellbench/sim/dewe_publisher.hpp"

#include <algorithm>
#include <atomic>
#include <mutex>

#include <boost/asio/dispatch.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>

namespace cellbench::sim {

namespace asio = boost::asio;
using boost::system::error_code;

namespace {
// Cap of one burst, so a process that was suspended for long catches up without starving the io_context.
constexpr std::uint64_t kMaxBurstSamples = 2000;
// Shortest timer period: at high time scales samples go out in bursts instead of a timer per sample. Each tick
// wakes this thread, the listener's and the daemon's feed (three context switches): at x400 the DAQ's 10 Hz is
// 4 000 samples per wall second. A burst spans at most kMaxBurstBenchS of bench time (well inside a DAQ grace
// and its staleness limit) and kMaxTimerPeriod of wall time.
constexpr auto kMinTimerPeriod = std::chrono::microseconds(500);
constexpr auto kMaxTimerPeriod = std::chrono::milliseconds(2);
constexpr double kMaxBurstBenchS = 0.5;
}  // namespace

struct DewePublisher::Impl : std::enable_shared_from_this<Impl> {
    Impl(asio::io_context& io, BenchPlant p, std::shared_ptr<const BenchClock> c,
         std::shared_ptr<drivers::CanTransport> t, DewePublisherOptions o)
        : strand(asio::make_strand(io)),
          plant(std::move(p)),
          clock(std::move(c)),
          transport(std::move(t)),
          options(std::move(o)),
          timer(strand) {
        options.layout.validate();
        if (!(options.sample_rate_hz > 0)) options.sample_rate_hz = 10.0;
    }

    asio::strand<asio::io_context::executor_type> strand;
    BenchPlant plant;
    std::shared_ptr<const BenchClock> clock;
    std::shared_ptr<drivers::CanTransport> transport;
    DewePublisherOptions options;
    asio::steady_timer timer;
    SampleHook hook;
    std::atomic<bool> silent{false}, stopped{false};

    // Strand-only.
    double t0_s = 0.0;
    std::uint64_t next_counter = 0;
    std::chrono::steady_clock::duration min_period = kMinTimerPeriod;  // see kMaxTimerPeriod
    std::uint64_t drops_pending = 0;
    std::uint64_t garbage_kind = 0;

    mutable std::mutex stats_mutex;
    DewePublisherStats stats;

    double sample_time_s(std::uint64_t k) const { return t0_s + static_cast<double>(k) / options.sample_rate_hz; }

    void start() {
        asio::dispatch(strand, [self = shared_from_this()] {
            self->t0_s = self->clock->now_s();
            // kMaxBurstBenchS of bench time in wall time, within [kMinTimerPeriod, kMaxTimerPeriod].
            const auto burst_wall = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                std::chrono::duration<double>(kMaxBurstBenchS / self->clock->time_scale()));
            self->min_period = std::clamp<std::chrono::steady_clock::duration>(burst_wall, kMinTimerPeriod, kMaxTimerPeriod);
            self->tick();
        });
    }

    void stop() {
        if (stopped.exchange(true)) return;
        asio::dispatch(strand, [self = shared_from_this()] {
            self->timer.cancel();
            self->transport->close();
        });
    }

    void tick() {
        if (stopped) return;
        const double now_s = clock->now_s();
        for (std::uint64_t burst = 0; burst < kMaxBurstSamples && sample_time_s(next_counter) <= now_s; ++burst)
            produce(next_counter++);
        const auto due = clock->wall_at(sample_time_s(next_counter));
        timer.expires_at(std::max(due, std::chrono::steady_clock::now() + min_period));
        timer.async_wait([self = shared_from_this()](const error_code& ec) {
            if (!ec) self->tick();
        });
    }

    void produce(std::uint64_t counter) {
        plant.advance_to(sample_time_s(counter));
        const PlantReading r = plant.read();
        bool sent = false;
        DewePublisherStats delta;
        delta.samples = 1;
        if (drops_pending > 0) {
            --drops_pending;
            delta.samples_dropped = 1;
        } else if (silent) {
            delta.samples_silenced = 1;
        } else {
            const std::array<double, protocol::kDeweChannelCount> values{r.thermopile_v, r.surface_type_t_c,
                                                                         r.terminal_pos_c, r.terminal_neg_c};
            bool all_sent = true;
            for (const auto& frame : protocol::encode_dewe_sample(options.layout, values, counter)) {
                if (transport->send(frame)) all_sent = false;
                else ++delta.frames_sent;
            }
            if (!all_sent) delta.samples_undelivered = 1;
            sent = all_sent;
        }
        add(delta);
        if (hook) hook(counter, r, sent);
    }

    void add(const DewePublisherStats& d) {
        std::lock_guard lock(stats_mutex);
        stats.samples += d.samples;
        stats.frames_sent += d.frames_sent;
        stats.samples_dropped += d.samples_dropped;
        stats.samples_silenced += d.samples_silenced;
        stats.samples_undelivered += d.samples_undelivered;
        stats.garbage_sent += d.garbage_sent;
    }

    // An identifier the layout does not use.
    std::uint32_t unused_id() const {
        for (std::uint32_t id = protocol::kCanSffMask;; --id) {
            const bool used = std::any_of(options.layout.frames.begin(), options.layout.frames.end(),
                                          [&](const auto& f) { return !f.extended && f.can_id == id; });
            if (!used) return id;
        }
    }

    void send_one_garbage() {
        const auto& first = options.layout.frames.front();
        const std::uint32_t first_id = first.extended ? (first.can_id | protocol::kCanEffFlag) : first.can_id;
        const std::array<std::uint8_t, 8> payload{0xDE, 0xAD, 0xBE, 0xEF, 0x01, 0x02, 0x03, 0x04};
        error_code ec;
        switch (garbage_kind++ % 5) {
            case 0:  // an identifier nobody declared
                ec = transport->send(protocol::CanFrame::data_frame(unused_id(), false, payload));
                break;
            case 1: {  // a declared frame too short to hold its fields
                protocol::CanFrame f;
                f.can_id = first_id;
                f.len = 0;
                ec = transport->send(f);
                break;
            }
            case 2: {  // len > 8
                protocol::CanFrame f;
                f.can_id = first_id;
                auto record = protocol::encode_can_record(f);
                record[4] = 15;
                ec = transport->send_record(record);
                break;
            }
            case 3: {  // not a 16-byte record
                const std::array<std::uint8_t, 10> shortrec{0x10, 0x03, 0, 0, 2, 0, 0, 0, 0xAA, 0xBB};
                ec = transport->send_record(shortrec);
                break;
            }
            default: {  // a remote frame asking for the declared identifier
                protocol::CanFrame f;
                f.can_id = first_id | protocol::kCanRtrFlag;
                f.len = 8;
                ec = transport->send(f);
                break;
            }
        }
        if (!ec) {
            DewePublisherStats d;
            d.garbage_sent = 1;
            add(d);
        }
    }
};

DewePublisher::DewePublisher(asio::io_context& io, BenchPlant plant, std::shared_ptr<const BenchClock> clock,
                             std::shared_ptr<drivers::CanTransport> transport, DewePublisherOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(plant), std::move(clock), std::move(transport), std::move(options))) {}

DewePublisher::~DewePublisher() { stop(); }

void DewePublisher::on_sample(SampleHook hook) { impl_->hook = std::move(hook); }
void DewePublisher::start() { impl_->start(); }
void DewePublisher::stop() { impl_->stop(); }
void DewePublisher::set_silent(bool silent) { impl_->silent = silent; }

void DewePublisher::drop_samples(std::uint64_t count) {
    asio::post(impl_->strand, [self = impl_, count] { self->drops_pending += count; });
}

void DewePublisher::send_garbage(std::uint64_t count) {
    asio::post(impl_->strand, [self = impl_, count] {
        for (std::uint64_t i = 0; i < count && !self->stopped; ++i) self->send_one_garbage();
    });
}

DewePublisherStats DewePublisher::stats() const {
    std::lock_guard lock(impl_->stats_mutex);
    return impl_->stats;
}

std::string DewePublisher::description() const { return impl_->transport->description(); }

}  // namespace cellbench::sim
