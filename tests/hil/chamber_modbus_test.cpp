// Climatic chamber client against the simulated chamber over loopback Modbus TCP (libmodbus on both sides):
// the set point is written and the air follows it within the ramp limit, plain function 3 reads work, other
// functions get a Modbus exception, and timeouts, exception responses, alarms and a failed heater surface as
// instrument faults.
#include <gtest/gtest.h>

#include <modbus.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <future>
#include <mutex>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>

#include "cellbench/drivers/chamber_client.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/sim/chamber_server.hpp"
#include "cellbench/sim/plant.hpp"

namespace {

namespace asio = boost::asio;
using namespace cellbench;
using namespace std::chrono_literals;
using drivers::ChamberFault;
using drivers::ChamberFaultKind;
using drivers::ChamberStatus;

estimator::ParameterSet thesis_params() {
    std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
    return estimator::ParameterSet::from_json(nlohmann::json::parse(in), "p45b-thesis.json");
}

template <typename Pred>
bool eventually(Pred pred, std::chrono::milliseconds deadline = 15s) {
    const auto end = std::chrono::steady_clock::now() + deadline;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(5ms);
    }
    return pred();
}

// Simulated chamber (bench time 300x wall time) and a client whose callbacks run on a background io thread.
class ChamberBench {
public:
    explicit ChamberBench(drivers::ChamberClientOptions options = {}, double time_scale = 300.0) {
        sim::PlantOptions o;
        o.cell = thesis_params();
        o.chamber_ripple_c = 0.0;  // the ramp check below reads the bare dynamics
        plant_ = std::make_unique<sim::BenchPlant>(o);
        clock_ = std::make_shared<sim::BenchClock>(time_scale);
        server_ = std::make_unique<sim::ChamberServer>(*plant_, clock_);
        server_->start();

        options.port = server_->port();
        options.poll_interval = 40ms;
        options.response_timeout = 150ms;
        options.retries = 1;
        client_ = std::make_unique<drivers::ChamberClient>(io_, options);
        client_->on_status([this](const ChamberStatus& s) {
            std::lock_guard lock(mutex_);
            statuses_.push_back(s);
        });
        client_->on_fault([this](const ChamberFault& f) {
            std::lock_guard lock(mutex_);
            faults_.push_back(f);
        });
        thread_ = std::thread([this] { io_.run(); });
        client_->start();
    }

    ~ChamberBench() {
        client_->stop();
        server_->stop();
        work_.reset();
        io_.stop();
        thread_.join();
    }

    std::vector<ChamberStatus> statuses() {
        std::lock_guard lock(mutex_);
        return statuses_;
    }
    std::size_t status_count() {
        std::lock_guard lock(mutex_);
        return statuses_.size();
    }
    std::optional<ChamberStatus> last_status() {
        std::lock_guard lock(mutex_);
        if (statuses_.empty()) return std::nullopt;
        return statuses_.back();
    }
    std::optional<ChamberFault> fault_of(ChamberFaultKind kind) {
        std::lock_guard lock(mutex_);
        for (const auto& f : faults_)
            if (f.kind == kind) return f;
        return std::nullopt;
    }
    std::optional<ChamberFault> fault_with_code(int code) {
        std::lock_guard lock(mutex_);
        for (const auto& f : faults_)
            if (f.kind == ChamberFaultKind::exception_response && f.exception_code == code) return f;
        return std::nullopt;
    }

    // Runs a command and waits for its completion.
    std::optional<ChamberFault> set_temperature(double c) {
        std::promise<std::optional<ChamberFault>> done;
        client_->set_temperature(c, [&](const std::optional<ChamberFault>& f) { done.set_value(f); });
        return done.get_future().get();
    }
    std::optional<ChamberFault> set_running(bool running) {
        std::promise<std::optional<ChamberFault>> done;
        client_->set_running(running, [&](const std::optional<ChamberFault>& f) { done.set_value(f); });
        return done.get_future().get();
    }

    sim::ChamberServer& server() { return *server_; }
    sim::BenchPlant& plant() { return *plant_; }
    const sim::BenchClock& clock() const { return *clock_; }
    drivers::ChamberClient& client() { return *client_; }

private:
    asio::io_context io_;
    asio::executor_work_guard<asio::io_context::executor_type> work_{io_.get_executor()};
    std::unique_ptr<sim::BenchPlant> plant_;
    std::shared_ptr<sim::BenchClock> clock_;
    std::unique_ptr<sim::ChamberServer> server_;
    std::unique_ptr<drivers::ChamberClient> client_;
    std::thread thread_;
    std::mutex mutex_;
    std::vector<ChamberStatus> statuses_;
    std::vector<ChamberFault> faults_;
};

TEST(ChamberModbus, SetPointIsWrittenAndTheAirFollowsWithinTheRampLimit) {
    ChamberBench bench;
    ASSERT_TRUE(eventually([&] { return bench.status_count() > 0; }));
    EXPECT_NEAR(bench.last_status()->process_value_c, 30.0, 0.05);
    EXPECT_EQ(bench.last_status()->running, true);

    // 50 degC above the air: a plain first-order chamber (tau 120 s) would start at 25 degC/min.
    EXPECT_FALSE(bench.set_temperature(80.0));
    bench.plant().advance_to(bench.clock().now_s());
    EXPECT_DOUBLE_EQ(bench.plant().read().chamber_setpoint_c, 80.0) << "the write reached the chamber";

    ASSERT_TRUE(eventually([&] { return bench.last_status()->process_value_c >= 79.6; }))
        << "the air reaches the set point";
    const auto statuses = bench.statuses();
    EXPECT_DOUBLE_EQ(statuses.back().setpoint_c, 80.0) << "set point read back";

    // Bench time of each read, from the wall time the client read it at.
    std::size_t intermediate = 0;
    for (std::size_t i = 0; i < statuses.size(); ++i) {
        const double ti = bench.clock().at(statuses[i].time);
        if (statuses[i].process_value_c > 32.0 && statuses[i].process_value_c < 78.0) ++intermediate;
        for (std::size_t j = i + 1; j < statuses.size(); ++j) {
            const double dt = bench.clock().at(statuses[j].time) - ti;
            if (dt < 60.0) continue;
            // 7 degC/min, plus the 0.1 degC register resolution and up to 10 bench s (33 ms wall) of difference
            // in read latency; a chamber without the limit would rise 20 degC in the first minute.
            EXPECT_LE(statuses[j].process_value_c - statuses[i].process_value_c, 7.0 / 60.0 * (dt + 10.0) + 0.2)
                << "between reads " << i << " and " << j << " (" << dt << " bench s apart)";
        }
    }
    EXPECT_GE(intermediate, 3u) << "the air ramps, it does not jump";
    EXPECT_FALSE(bench.fault_of(ChamberFaultKind::setpoint_not_reached));
    EXPECT_FALSE(bench.fault_of(ChamberFaultKind::timeout));
}

TEST(ChamberModbus, RunStopAndOutOfRangeSetPoints) {
    ChamberBench bench;
    EXPECT_FALSE(bench.set_running(false));
    bench.plant().advance_to(bench.clock().now_s());
    EXPECT_FALSE(bench.plant().read().chamber_running);
    ASSERT_TRUE(eventually([&] { auto s = bench.last_status(); return s && s->running == false; }));
    EXPECT_FALSE(bench.set_running(true));

    const auto rejected = bench.set_temperature(250.0);
    ASSERT_TRUE(rejected);
    EXPECT_EQ(rejected->kind, ChamberFaultKind::rejected);
    EXPECT_EQ(rejected->attempts, 0) << "nothing was sent";
}

// A plain libmodbus client, as any Modbus tool would talk to the chamber.
class RawClient {
public:
    explicit RawClient(int port) : ctx_(modbus_new_tcp("127.0.0.1", port)) {
        modbus_set_response_timeout(ctx_, 10, 0);  // a busy machine answers late, not never (exceptions come at once)
        connected_ = modbus_connect(ctx_) == 0;
    }
    ~RawClient() {
        modbus_close(ctx_);
        modbus_free(ctx_);
    }
    bool connected() const { return connected_; }
    modbus_t* get() { return ctx_; }

    // Sends a raw PDU (unit id first) and returns the response PDU (function code onwards).
    std::vector<std::uint8_t> raw(std::vector<std::uint8_t> request) {
        if (modbus_send_raw_request(ctx_, request.data(), static_cast<int>(request.size())) == -1) return {};
        std::uint8_t rsp[MODBUS_TCP_MAX_ADU_LENGTH];
        const int n = modbus_receive_confirmation(ctx_, rsp);
        const int hl = modbus_get_header_length(ctx_);
        if (n <= hl) return {};
        return {rsp + hl, rsp + n};
    }

private:
    modbus_t* ctx_;
    bool connected_ = false;
};

TEST(ChamberModbus, FunctionThreeReadsTheRegistersAndOtherFunctionsGetAnException) {
    ChamberBench bench;
    RawClient raw(bench.server().port());
    ASSERT_TRUE(raw.connected());

    std::uint16_t regs[2] = {};
    ASSERT_EQ(modbus_read_registers(raw.get(), 1, 2, regs), 2) << modbus_strerror(errno);
    EXPECT_NEAR(static_cast<std::int16_t>(regs[0]) * 0.1, 30.0, 0.15) << "process value in 0.1 degC";
    EXPECT_EQ(regs[1], 300) << "set point 30.0 degC";

    // Report server id (0x11), read device identification (0x2B/0x0E), read coils (0x01): not a chamber's.
    EXPECT_EQ(raw.raw({1, 0x11}), (std::vector<std::uint8_t>{0x91, MODBUS_EXCEPTION_ILLEGAL_FUNCTION}));
    EXPECT_EQ(raw.raw({1, 0x2B, 0x0E, 0x01, 0x00}), (std::vector<std::uint8_t>{0xAB, MODBUS_EXCEPTION_ILLEGAL_FUNCTION}));
    EXPECT_EQ(raw.raw({1, 0x01, 0x00, 0x00, 0x00, 0x01}), (std::vector<std::uint8_t>{0x81, MODBUS_EXCEPTION_ILLEGAL_FUNCTION}));

    // Writes: the process value is read-only, set points outside the range are refused, registers beyond the
    // map do not exist.
    EXPECT_EQ(modbus_write_register(raw.get(), 1, 500), -1);
    EXPECT_EQ(errno, EMBXILADD);
    EXPECT_EQ(modbus_write_register(raw.get(), 2, 2500), -1);
    EXPECT_EQ(errno, EMBXILVAL);
    EXPECT_EQ(modbus_read_registers(raw.get(), 100, 1, regs), -1);
    EXPECT_EQ(errno, EMBXILADD);

    // The connection still works after all that, and function 16 writes the set point.
    const std::uint16_t sp[1] = {425};
    EXPECT_EQ(modbus_write_registers(raw.get(), 2, 1, sp), 1);
    bench.plant().advance_to(bench.clock().now_s());
    EXPECT_DOUBLE_EQ(bench.plant().read().chamber_setpoint_c, 42.5);
}

TEST(ChamberModbus, TimeoutsSurfaceAndPollingRecovers) {
    ChamberBench bench;
    ASSERT_TRUE(eventually([&] { return bench.status_count() > 0; }));
    bench.server().set_unresponsive(true);
    ASSERT_TRUE(eventually([&] { return bench.fault_of(ChamberFaultKind::timeout).has_value(); }));
    const auto fault = *bench.fault_of(ChamberFaultKind::timeout);
    EXPECT_EQ(fault.operation, "read status");
    EXPECT_EQ(fault.attempts, 2) << "retried once";

    bench.server().set_unresponsive(false);
    const std::size_t before = bench.status_count();
    EXPECT_TRUE(eventually([&] { return bench.status_count() > before + 2; })) << "polling resumes";
}

TEST(ChamberModbus, ExceptionResponsesSurfaceTransientOnesAreRetried) {
    ChamberBench bench;
    ASSERT_TRUE(eventually([&] { return bench.status_count() > 0; }));
    bench.server().set_exception_response(MODBUS_EXCEPTION_SLAVE_OR_SERVER_BUSY);
    ASSERT_TRUE(eventually([&] { return bench.fault_with_code(6).has_value(); }));
    EXPECT_EQ(bench.fault_with_code(6)->attempts, 2) << "busy is worth a retry";

    bench.server().set_exception_response(MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
    const auto fault = bench.set_temperature(40.0);
    ASSERT_TRUE(fault);
    EXPECT_EQ(fault->kind, ChamberFaultKind::exception_response);
    EXPECT_EQ(fault->exception_code, 2);
    EXPECT_EQ(fault->attempts, 1) << "an illegal address will not get better";
    EXPECT_EQ(fault->operation, "write set point");

    bench.server().set_exception_response(std::nullopt);
    EXPECT_FALSE(bench.set_temperature(40.0));
}

TEST(ChamberModbus, AlarmsSurface) {
    ChamberBench bench;
    ASSERT_TRUE(eventually([&] { return bench.status_count() > 0; }));
    EXPECT_TRUE(bench.server().set_alarm("high_temperature", true));
    EXPECT_FALSE(bench.server().set_alarm("no_such_alarm", true));
    ASSERT_TRUE(eventually([&] { return bench.fault_of(ChamberFaultKind::alarm).has_value(); }));
    EXPECT_NE(bench.fault_of(ChamberFaultKind::alarm)->message.find("high_temperature"), std::string::npos);
    ASSERT_TRUE(eventually([&] { return !bench.last_status()->active_alarms.empty(); }));
    EXPECT_EQ(bench.last_status()->active_alarms, std::vector<std::string>{"high_temperature"});

    bench.server().set_alarm("high_temperature", false);
    EXPECT_TRUE(eventually([&] { return bench.last_status()->active_alarms.empty(); }));
}

TEST(ChamberModbus, FailedHeaterIsReportedAsSetPointNotReached) {
    drivers::ChamberClientOptions options;
    options.setpoint_timeout = 600ms;  // 180 bench s at 300x: a healthy chamber heats 10 degC in ~100 s
    options.setpoint_tolerance_c = 1.0;
    ChamberBench bench(options);
    bench.server().set_heater_failed(true);
    EXPECT_FALSE(bench.set_temperature(40.0));
    ASSERT_TRUE(eventually([&] { return bench.fault_of(ChamberFaultKind::setpoint_not_reached).has_value(); }));
    EXPECT_NE(bench.fault_of(ChamberFaultKind::setpoint_not_reached)->message.find("40.0"), std::string::npos);
    EXPECT_LT(bench.last_status()->process_value_c, 31.0) << "the air never warmed";
}

TEST(ChamberModbus, UnreachableChamberIsAFault) {
    // A port nobody listens on.
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
    socklen_t len = sizeof addr;
    ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
    ::close(fd);

    asio::io_context io;
    auto work = asio::make_work_guard(io);
    drivers::ChamberClientOptions options;
    options.port = ntohs(addr.sin_port);
    options.retries = 0;
    drivers::ChamberClient client(io, options);
    std::optional<ChamberFault> fault;
    client.read_status([&](const auto& status, const auto& f) {
        EXPECT_FALSE(status);
        fault = f;
    });
    client.start();
    for (const auto end = std::chrono::steady_clock::now() + 10s; !fault && std::chrono::steady_clock::now() < end;)
        io.run_one_for(100ms);
    ASSERT_TRUE(fault);
    EXPECT_EQ(fault->kind, ChamberFaultKind::unreachable);
    client.stop();
}

}  // namespace

namespace {

// Issue 14: the chamber's callbacks ran on whichever io thread was free, so two status callbacks could run at
// once (and out of order) in a daemon running its io_context on several threads. They run on a strand now.
TEST(ChamberModbus, CallbacksRunOneAtATimeAndInOrderOnAMultiThreadedIoContext) {
    sim::PlantOptions o;
    o.cell = thesis_params();
    sim::BenchPlant plant(o);
    auto clock = std::make_shared<sim::BenchClock>(300.0);
    sim::ChamberServer server(plant, clock);
    server.start();
    asio::io_context io;
    auto work = asio::make_work_guard(io);
    drivers::ChamberClientOptions options;
    options.port = server.port();
    options.poll_interval = 1ms;  // statuses arrive faster than the callback below handles them
    drivers::ChamberClient client(io, options);
    std::atomic<int> inside{0}, most{0}, count{0};
    std::mutex m;
    std::vector<std::chrono::steady_clock::time_point> times;
    client.on_status([&](const ChamberStatus& s) {
        const int now = ++inside;
        int seen = most.load();
        while (now > seen && !most.compare_exchange_weak(seen, now)) {}
        std::this_thread::sleep_for(3ms);
        {
            std::lock_guard l(m);
            times.push_back(s.time);
        }
        --inside;
        ++count;
    });
    std::vector<std::thread> threads;
    for (int k = 0; k < 4; ++k) threads.emplace_back([&] { io.run(); });
    client.start();
    const auto end = std::chrono::steady_clock::now() + 20s;  // bounds a broken test only
    while (count < 100 && std::chrono::steady_clock::now() < end) std::this_thread::sleep_for(5ms);
    client.stop();
    work.reset();
    io.stop();
    for (auto& t : threads) t.join();
    server.stop();
    EXPECT_GE(count.load(), 100);
    EXPECT_EQ(most.load(), 1) << "status callbacks ran concurrently";
    std::lock_guard l(m);
    EXPECT_TRUE(std::is_sorted(times.begin(), times.end())) << "status callbacks ran out of order";
}

}  // namespace
