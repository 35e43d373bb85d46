// DEWE-43A driver against the simulated DAQ over can-dgram (a Unix datagram socket in a temp folder), and the
// same over SocketCAN vcan0 where the kernel has AF_CAN (skipped otherwise): samples arrive, the heat flux is
// the plant's, and injected silence, dropped samples and garbage frames are reported.
#include <gtest/gtest.h>

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>

#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/drivers/dewe_driver.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/heat_flux.hpp"
#include "cellbench/sim/dewe_publisher.hpp"
#include "cellbench/sim/plant.hpp"

namespace {

namespace asio = boost::asio;
using namespace cellbench;
using namespace std::chrono_literals;

estimator::ParameterSet thesis_params() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    return estimator::ParameterSet::from_json(nlohmann::json::parse(in), "p45b-thesis.json");
}

// Waits (polling) until pred holds or the deadline passes; the deadline only bounds a broken test's runtime.
template <typename Pred>
bool eventually(Pred pred, std::chrono::milliseconds deadline = 10s) {
    const auto end = std::chrono::steady_clock::now() + deadline;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(5ms);
    }
    return pred();
}

// One simulated bench (plant + DAQ) and one driver on an io_context run by a background thread.
class DeweBench {
public:
    enum class Medium { can_dgram, socketcan };

    explicit DeweBench(Medium medium, drivers::DeweDriverOptions driver_options = {}) {
        sim::PlantOptions o;
        o.cell = thesis_params();
        o.initial_soc = 0.9;
        o.chamber_ripple_c = 0.0;
        o.temperature_noise_c = 0.0;
        o.thermopile_noise_v = 0.0;
        o.chamber_setpoint_c = 25.0;  // the air cools from 30 degC: heat flows out of the cell
        plant_ = std::make_unique<sim::BenchPlant>(o);
        plant_->set_current(-20.0);   // and the cell heats itself
        area_m2_ = o.cell.thermal.area_m2;
        clock_ = std::make_shared<sim::BenchClock>(20.0);

        std::shared_ptr<drivers::CanTransport> hub, listener;
        if (medium == Medium::can_dgram) {
            static std::atomic<int> serial{0};
            path_ = (std::filesystem::temp_directory_path() /
                     ("cellbench-dewe-" + std::to_string(::getpid()) + "-" + std::to_string(serial++) + ".sock"))
                        .string();
            hub = drivers::open_can_dgram_hub(io_, path_);
            listener = drivers::open_can_dgram_listener(io_, path_, 100ms);
        } else {
            hub = drivers::open_socketcan(io_, "vcan0");
            listener = drivers::open_socketcan(io_, "vcan0");
        }
        sim::DewePublisherOptions po;
        po.sample_rate_hz = 20.0;  // bench time: 400 samples per wall second at scale 20
        publisher_ = std::make_unique<sim::DewePublisher>(io_, *plant_, clock_, hub, po);
        publisher_->on_sample([this](std::uint64_t counter, const sim::PlantReading& r, bool) {
            std::lock_guard lock(mutex_);
            published_[counter] = r;
        });
        driver_options_ = driver_options;
        driver_ = std::make_unique<drivers::DeweDriver>(io_, listener, driver_options);
        driver_->on_sample([this](const drivers::DeweReading& r) {
            std::lock_guard lock(mutex_);
            readings_.push_back(r);
        });
        driver_->on_health([this](const drivers::DeweHealth& h) {
            std::lock_guard lock(mutex_);
            health_reports_.push_back(h);
        });
        driver_->start();
        publisher_->start();
        thread_ = std::thread([this] { io_.run(); });
    }

    ~DeweBench() {
        driver_->stop();
        publisher_->stop();
        std::this_thread::sleep_for(20ms);  // let the closes run
        work_.reset();
        io_.stop();
        thread_.join();
        if (!path_.empty()) std::filesystem::remove(path_);
    }

    std::size_t reading_count() {
        std::lock_guard lock(mutex_);
        return readings_.size();
    }
    std::vector<drivers::DeweReading> readings() {
        std::lock_guard lock(mutex_);
        return readings_;
    }
    std::map<std::uint64_t, sim::PlantReading> published() {
        std::lock_guard lock(mutex_);
        return published_;
    }
    std::vector<drivers::DeweHealth> health_reports() {
        std::lock_guard lock(mutex_);
        return health_reports_;
    }
    bool reported(const std::function<bool(const drivers::DeweHealth&)>& pred) {
        std::lock_guard lock(mutex_);
        return std::any_of(health_reports_.begin(), health_reports_.end(), pred);
    }

    sim::DewePublisher& publisher() { return *publisher_; }
    drivers::DeweDriver& driver() { return *driver_; }
    double area_m2() const { return area_m2_; }
    const std::string& path() const { return path_; }

private:
    asio::io_context io_;
    asio::executor_work_guard<asio::io_context::executor_type> work_{io_.get_executor()};
    std::unique_ptr<sim::BenchPlant> plant_;
    std::shared_ptr<sim::BenchClock> clock_;
    std::unique_ptr<sim::DewePublisher> publisher_;
    std::unique_ptr<drivers::DeweDriver> driver_;
    drivers::DeweDriverOptions driver_options_;
    std::thread thread_;
    std::string path_;
    double area_m2_ = 0.0;

    std::mutex mutex_;
    std::map<std::uint64_t, sim::PlantReading> published_;
    std::vector<drivers::DeweReading> readings_;
    std::vector<drivers::DeweHealth> health_reports_;
};

// The driver's samples are the plant's, converted back with eq. 2.2.
void expect_samples_match_the_plant(DeweBench& bench, std::size_t at_least) {
    ASSERT_TRUE(eventually([&] { return bench.reading_count() >= at_least; }))
        << "only " << bench.reading_count() << " samples arrived";
    const auto readings = bench.readings();
    const auto published = bench.published();
    std::size_t compared = 0;
    for (std::size_t i = 0; i < readings.size(); ++i) {
        const auto& r = readings[i];
        if (i > 0) {
            EXPECT_GE(r.time, readings[i - 1].time) << "monotonic time stamps";
            EXPECT_GT(r.sequence, readings[i - 1].sequence);
        }
        const auto it = published.find(r.sequence);
        ASSERT_NE(it, published.end()) << "sample " << r.sequence << " was never published";
        const auto& p = it->second;
        EXPECT_NEAR(r.thermopile_v, p.thermopile_v, 1e-9 + 1e-6 * std::abs(p.thermopile_v));  // float32
        EXPECT_NEAR(r.type_t_c, p.surface_type_t_c, 0.006);                                     // 0.01 degC steps
        EXPECT_NEAR(r.t1_c, p.terminal_pos_c, 0.006);
        EXPECT_NEAR(r.t2_c, p.terminal_neg_c, 0.006);
        // Sensor noise is off: the converted flux is the plant's true heat flux.
        EXPECT_NEAR(r.heat_flux_w_per_m2, p.heat_flux_w_per_m2, 0.01 + 1e-4 * std::abs(p.heat_flux_w_per_m2));
        EXPECT_NEAR(r.heat_flow_w, r.heat_flux_w_per_m2 * bench.area_m2(), 1e-12);
        ++compared;
    }
    EXPECT_GE(compared, at_least);
    EXPECT_GT(readings.back().heat_flux_w_per_m2, 5.0) << "the test exercised a real heat flux";
}

TEST(DeweCanDgram, SamplesArriveAndHeatFluxMatchesThePlant) {
    DeweBench bench(DeweBench::Medium::can_dgram);
    expect_samples_match_the_plant(bench, 600);
    ASSERT_TRUE(eventually([&] { return bench.driver().health().stats.samples >= 600; }));
    const auto h = bench.driver().health();
    EXPECT_EQ(h.state, drivers::DeweStreamState::streaming);
    EXPECT_EQ(h.stats.garbage, 0u);
    EXPECT_TRUE(eventually([&] {
        return bench.driver().health().stats.lost_samples == bench.publisher().stats().samples_undelivered;
    })) << "nothing lost but what the socket refused";
    EXPECT_TRUE(bench.reported([](const auto& r) { return r.message == "stream started"; }));
}

TEST(DeweCanDgram, InjectedDropsGarbageAndSilenceAreReported) {
    drivers::DeweDriverOptions options;
    options.silence_timeout = 300ms;
    options.health_interval = 50ms;
    DeweBench bench(DeweBench::Medium::can_dgram, options);
    ASSERT_TRUE(eventually([&] { return bench.reading_count() >= 50; }));

    // Dropped samples: counter gaps, counted exactly (plus whatever a slow socket refused).
    bench.publisher().drop_samples(7);
    ASSERT_TRUE(eventually([&] { return bench.publisher().stats().samples_dropped == 7; }));
    ASSERT_TRUE(eventually([&] {
        return bench.reported([](const auto& r) { return r.stats.lost_samples >= 7; });
    })) << "the loss is reported through the health callback";
    EXPECT_TRUE(eventually([&] {
        return bench.driver().health().stats.lost_samples == 7 + bench.publisher().stats().samples_undelivered;
    })) << "lost " << bench.driver().health().stats.lost_samples;
    EXPECT_TRUE(bench.reported([](const auto& r) { return r.message.find("samples lost") != std::string::npos; }));

    // Garbage: every kind counted, none decoded, the stream goes on.
    bench.publisher().send_garbage(10);
    ASSERT_TRUE(eventually([&] { return bench.publisher().stats().garbage_sent == 10; }));
    ASSERT_TRUE(eventually([&] { return bench.reported([](const auto& r) { return r.stats.garbage >= 10; }); }));
    const auto g = bench.driver().health().stats;
    EXPECT_EQ(g.garbage, 10u);
    EXPECT_EQ(g.unknown_id, 2u);
    EXPECT_EQ(g.bad_length, 4u);  // too short for the layout, and len > 8
    EXPECT_EQ(g.wrong_size, 2u);
    EXPECT_EQ(g.not_data, 2u);
    EXPECT_TRUE(bench.reported([](const auto& r) { return r.message.find("garbage frames") != std::string::npos; }));
    const std::size_t before = bench.reading_count();
    ASSERT_TRUE(eventually([&] { return bench.reading_count() > before + 50; })) << "samples keep coming";

    // Silence: reported after the timeout; the stream resumes when frames come back.
    bench.publisher().set_silent(true);
    ASSERT_TRUE(eventually([&] { return bench.driver().health().state == drivers::DeweStreamState::silent; }));
    EXPECT_TRUE(bench.reported([](const auto& r) {
        return r.state == drivers::DeweStreamState::silent && r.message.find("no valid frame") != std::string::npos;
    }));
    bench.publisher().set_silent(false);
    ASSERT_TRUE(eventually([&] { return bench.driver().health().state == drivers::DeweStreamState::streaming; }));
    EXPECT_TRUE(bench.reported([](const auto& r) { return r.message == "stream resumed"; }));
    // The DAQ kept counting while the bus was silent: the gap is lost samples.
    ASSERT_TRUE(eventually([&] {
        const auto s = bench.publisher().stats();
        return bench.driver().health().stats.lost_samples == 7 + s.samples_silenced + s.samples_undelivered;
    })) << "lost " << bench.driver().health().stats.lost_samples << ", silenced "
        << bench.publisher().stats().samples_silenced;
}

TEST(DeweCanDgram, ListenerStartedBeforeTheHubSubscribesLater) {
    boost::asio::io_context io;
    const std::string path = (std::filesystem::temp_directory_path() /
                              ("cellbench-dewe-late-" + std::to_string(::getpid()) + ".sock"))
                                 .string();
    auto listener = drivers::open_can_dgram_listener(io, path, 20ms);
    std::optional<protocol::CanFrame> got;
    listener->async_receive([&](const boost::system::error_code& ec, std::span<const std::uint8_t> rec) {
        if (!ec) got = protocol::decode_can_record(rec);
    });
    io.run_for(50ms);  // no hub yet: the subscription fails quietly
    auto hub = drivers::open_can_dgram_hub(io, path);
    io.run_for(100ms);  // the listener re-subscribes
    const std::array<std::uint8_t, 2> payload{0xCA, 0xFE};
    const auto frame = protocol::CanFrame::data_frame(0x123, false, payload);
    EXPECT_FALSE(hub->send(frame));
    io.run_for(100ms);
    ASSERT_TRUE(got);
    EXPECT_EQ(*got, frame);
    listener->close();
    hub->close();
    io.run_for(20ms);
    EXPECT_FALSE(std::filesystem::exists(path)) << "the hub removes its socket file";
}

TEST(DeweSocketCan, SamplesArriveOverVcan0) {
    std::string why;
    if (!drivers::socketcan_available(&why))
        GTEST_SKIP() << "SocketCAN not available on this kernel (" << why << "); the can-dgram tests cover the driver";
    if (!drivers::network_interface_exists("vcan0"))
        GTEST_SKIP() << "no vcan0 interface (modprobe vcan && ip link add dev vcan0 type vcan && ip link set up vcan0)";
    DeweBench bench(DeweBench::Medium::socketcan);
    expect_samples_match_the_plant(bench, 200);
}

}  // namespace

// The hub's send buffer holds about 2 700 frames in flight; a listener off the CPU longer than that lasts at a
// high time scale (the simulated DAQ catching up) gets the burst late and in order, not lost. Before the hub kept
// a backlog, 17 269 of these 20 000 frames were refused.
TEST(DeweCanDgram, ABurstTheListenerCannotTakeYetArrivesLateInOrderNotLost) {
    boost::asio::io_context io;
    const std::string path = (std::filesystem::temp_directory_path() /
                              ("cellbench-dewe-burst-" + std::to_string(::getpid()) + ".sock"))
                                 .string();
    auto hub = drivers::open_can_dgram_hub(io, path);
    auto listener = drivers::open_can_dgram_listener(io, path, 20ms);
    std::vector<std::uint32_t> got;
    std::function<void()> arm = [&] {
        listener->async_receive([&](const boost::system::error_code& ec, std::span<const std::uint8_t> rec) {
            if (ec) return;
            if (const auto f = protocol::decode_can_record(rec)) {
                std::uint32_t k = 0;
                std::memcpy(&k, f->data.data(), sizeof k);
                got.push_back(k);
            }
            arm();
        });
    };
    arm();
    // Subscribed once the first frame arrives.
    const std::array<std::uint8_t, 4> hello{0xFF, 0xFF, 0xFF, 0xFF};
    for (int i = 0; i < 100 && got.empty(); ++i) {
        EXPECT_FALSE(hub->send(protocol::CanFrame::data_frame(0x100, false, hello)));
        io.run_for(10ms);
    }
    ASSERT_EQ(got.size(), 1u) << "the listener never subscribed";
    got.clear();
    constexpr std::uint32_t kBurst = 20000;  // 7 x what the socket buffer holds
    std::size_t refused = 0;
    for (std::uint32_t k = 0; k < kBurst; ++k) {
        std::array<std::uint8_t, 4> payload{};
        std::memcpy(payload.data(), &k, sizeof k);
        if (hub->send(protocol::CanFrame::data_frame(0x100, false, payload))) ++refused;
    }
    EXPECT_EQ(refused, 0u) << "frames refused while the listener was busy";
    const auto deadline = std::chrono::steady_clock::now() + 30s;  // generous: the machine may be busy
    while (got.size() < kBurst && std::chrono::steady_clock::now() < deadline) io.run_for(20ms);
    ASSERT_EQ(got.size(), kBurst);
    for (std::uint32_t k = 0; k < kBurst; ++k) ASSERT_EQ(got[k], k) << "out of order at " << k;
    listener->close();
    hub->close();
    io.run_for(20ms);
}
