#include "cellbench/sim/chamber_server.hpp"

#include <modbus.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

namespace cellbench::sim {

using protocol::RegisterTable;

namespace {

// The span [start, end) of one table that the map uses (empty if none).
struct Span {
    int start = 0, end = 0;
    void add(int address, int count) {
        if (start == end) {
            start = address;
            end = address + count;
        } else {
            start = std::min(start, address);
            end = std::max(end, address + count);
        }
    }
};

}  // namespace

struct ChamberServer::Impl {
    Impl(BenchPlant p, std::shared_ptr<const BenchClock> c, ChamberServerOptions o)
        : plant(std::move(p)), clock(std::move(c)), options(std::move(o)) {
        options.map.validate();
    }
    ~Impl() { stop(); }

    BenchPlant plant;
    std::shared_ptr<const BenchClock> clock;
    ChamberServerOptions options;

    modbus_t* ctx = nullptr;
    modbus_mapping_t* mapping = nullptr;
    int listen_fd = -1;
    int bound_port = 0;
    std::vector<int> clients;
    std::thread thread;
    std::atomic<bool> running{false};

    std::atomic<bool> unresponsive{false};
    std::atomic<int> exception_code{0};
    std::atomic<std::uint16_t> alarm_word{0};

    mutable std::mutex stats_mutex;
    ChamberServerStats stats;

    void start() {
        if (running) return;
        const auto& m = options.map;
        Span holding, input;
        auto add = [&](RegisterTable t, int address, int count) { (t == RegisterTable::holding ? holding : input).add(address, count); };
        add(m.process_value.table, m.process_value.address, static_cast<int>(m.process_value.width_registers()));
        add(m.setpoint.table, m.setpoint.address, static_cast<int>(m.setpoint.width_registers()));
        add(RegisterTable::holding, m.run.address, 1);
        if (m.alarms) add(m.alarms->table, m.alarms->address, 1);
        // Registers outside these spans answer "illegal data address" (libmodbus checks the ranges).
        mapping = modbus_mapping_new_start_address(0, 0, 0, 0, static_cast<unsigned>(holding.start),
                                                   static_cast<unsigned>(holding.end - holding.start),
                                                   static_cast<unsigned>(input.start),
                                                   static_cast<unsigned>(input.end - input.start));
        if (!mapping) throw std::runtime_error(std::string("chamber server: modbus_mapping_new: ") + modbus_strerror(errno));
        ctx = modbus_new_tcp(options.host.c_str(), options.port);
        if (!ctx) throw std::runtime_error(std::string("chamber server: modbus_new_tcp: ") + modbus_strerror(errno));
        // A client that sends half a request must not hold the server forever.
        modbus_set_byte_timeout(ctx, 0, 500000);
        listen_fd = modbus_tcp_listen(ctx, 8);
        if (listen_fd == -1)
            throw std::runtime_error("chamber server: cannot listen on " + options.host + ":" + std::to_string(options.port) +
                                     ": " + modbus_strerror(errno));
        sockaddr_in addr{};
        socklen_t len = sizeof addr;
        ::getsockname(listen_fd, reinterpret_cast<sockaddr*>(&addr), &len);
        bound_port = ntohs(addr.sin_port);
        refresh();
        running = true;
        thread = std::thread([this] { serve(); });
    }

    void stop() {
        if (running.exchange(false) && thread.joinable()) thread.join();
        if (thread.joinable()) thread.join();
        for (int fd : clients) ::close(fd);
        clients.clear();
        if (listen_fd != -1) {
            ::close(listen_fd);
            listen_fd = -1;
        }
        if (ctx) {
            modbus_free(ctx);
            ctx = nullptr;
        }
        if (mapping) {
            modbus_mapping_free(mapping);
            mapping = nullptr;
        }
    }

    // ---- on the server thread.

    std::uint16_t* holding_register(std::uint16_t address) {
        const int i = static_cast<int>(address) - static_cast<int>(mapping->start_registers);
        return i >= 0 && i < mapping->nb_registers ? mapping->tab_registers + i : nullptr;
    }
    std::uint16_t* input_register(std::uint16_t address) {
        const int i = static_cast<int>(address) - static_cast<int>(mapping->start_input_registers);
        return i >= 0 && i < mapping->nb_input_registers ? mapping->tab_input_registers + i : nullptr;
    }
    std::uint16_t* register_at(RegisterTable t, std::uint16_t address) {
        return t == RegisterTable::holding ? holding_register(address) : input_register(address);
    }

    void store(const protocol::RegisterValueSpec& spec, double value) {
        const auto words = protocol::encode_register_value(spec, value);
        if (!words) return;  // not representable: keep the last value, as a controller display would
        for (std::size_t i = 0; i < words->size(); ++i)
            if (auto* r = register_at(spec.table, static_cast<std::uint16_t>(spec.address + i))) *r = (*words)[i];
    }

    // The registers from the plant at bench "now".
    void refresh() {
        plant.advance_to(clock->now_s());
        const PlantReading r = plant.read();
        const auto& m = options.map;
        store(m.process_value, r.chamber_air_c);
        store(m.setpoint, r.chamber_setpoint_c);
        if (auto* run = holding_register(m.run.address)) *run = r.chamber_running ? m.run.run_value : m.run.stop_value;
        if (m.alarms)
            if (auto* a = register_at(m.alarms->table, m.alarms->address)) *a = alarm_word.load();
    }

    void count(std::uint64_t ChamberServerStats::*field) {
        std::lock_guard lock(stats_mutex);
        ++(stats.*field);
    }

    void reply_exception(const std::uint8_t* query, unsigned code) {
        modbus_reply_exception(ctx, query, code);
        count(&ChamberServerStats::exceptions_sent);
    }

    void handle(const std::uint8_t* query, int length) {
        count(&ChamberServerStats::requests);
        if (unresponsive) {
            count(&ChamberServerStats::unanswered);
            return;
        }
        if (const int code = exception_code.load(); code != 0) return reply_exception(query, static_cast<unsigned>(code));
        const int hl = modbus_get_header_length(ctx);
        if (length < hl + 1) return;
        const std::uint8_t function = query[hl];
        auto u16 = [&](int at) { return static_cast<std::uint16_t>(query[at] << 8 | query[at + 1]); };
        switch (function) {
            case MODBUS_FC_READ_HOLDING_REGISTERS:
            case MODBUS_FC_READ_INPUT_REGISTERS:
                refresh();
                modbus_reply(ctx, query, length, mapping);
                return;
            case MODBUS_FC_WRITE_SINGLE_REGISTER:
                if (length < hl + 5) return reply_exception(query, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
                return write(query, length, u16(hl + 1), {u16(hl + 3)});
            case MODBUS_FC_WRITE_MULTIPLE_REGISTERS: {
                if (length < hl + 6) return reply_exception(query, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
                const std::uint16_t address = u16(hl + 1), n = u16(hl + 3);
                const int bytes = query[hl + 5];
                if (n < 1 || n > MODBUS_MAX_WRITE_REGISTERS || bytes != 2 * n || hl + 6 + bytes > length)
                    return reply_exception(query, MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE);
                std::vector<std::uint16_t> values(n);
                for (int i = 0; i < n; ++i) values[static_cast<std::size_t>(i)] = u16(hl + 6 + 2 * i);
                return write(query, length, address, values);
            }
            default:
                // The chamber's controller implements registers only (libmodbus would answer coils, report
                // server id, ... on its own, so those are refused here).
                skip_rest_of_request(query, length);
                return reply_exception(query, MODBUS_EXCEPTION_ILLEGAL_FUNCTION);
        }
    }

    // libmodbus does not know the length of functions it does not implement and stops reading after the
    // function code. The MBAP header does know it: read the rest of this request (and nothing of the next one,
    // which modbus_flush could swallow) so the next request parses.
    void skip_rest_of_request(const std::uint8_t* query, int length) {
        const int total = 6 + (query[4] << 8 | query[5]);  // MBAP: 6 bytes + unit id and PDU
        int remaining = std::min(total, MODBUS_TCP_MAX_ADU_LENGTH) - length;
        const int fd = modbus_get_socket(ctx);
        std::uint8_t sink[MODBUS_TCP_MAX_ADU_LENGTH];
        while (remaining > 0) {
            pollfd p{fd, POLLIN, 0};
            if (::poll(&p, 1, 100) <= 0) return;  // a sender that lies about the length: give up quietly
            const auto n = ::recv(fd, sink, static_cast<std::size_t>(remaining), 0);
            if (n <= 0) return;
            remaining -= static_cast<int>(n);
        }
    }

    void write(const std::uint8_t* query, int length, std::uint16_t address, const std::vector<std::uint16_t>& values) {
        refresh();
        protocol::RegisterBlock image{RegisterTable::holding, static_cast<std::uint16_t>(mapping->start_registers),
                                      std::vector<std::uint16_t>(mapping->tab_registers,
                                                                 mapping->tab_registers + mapping->nb_registers)};
        const auto result = options.map.apply_write(image, address, values);
        if (result.exception_code != 0) {
            spdlog::debug("simulated chamber: write at {} refused: {}", address, result.reason);
            return reply_exception(query, result.exception_code);
        }
        // The plant first: once the client has its answer, the chamber must already be heading there.
        if (result.setpoint_c) plant.set_chamber_setpoint(*result.setpoint_c);
        if (result.running) plant.set_chamber_running(*result.running);
        modbus_reply(ctx, query, length, mapping);  // stores the values and echoes the request
    }

    void close_client(std::size_t i) {
        ::close(clients[i]);
        clients.erase(clients.begin() + static_cast<std::ptrdiff_t>(i));
    }

    void serve() {
        std::vector<std::uint8_t> query(MODBUS_TCP_MAX_ADU_LENGTH);
        while (running) {
            std::vector<pollfd> fds;
            fds.push_back({listen_fd, POLLIN, 0});
            for (int fd : clients) fds.push_back({fd, POLLIN, 0});
            const int n = ::poll(fds.data(), fds.size(), 50);  // wake up regularly to notice stop()
            if (n <= 0) continue;
            // Clients first (indices match fds[1..]); walk backwards so closing one keeps the others' indices.
            for (std::size_t i = clients.size(); i-- > 0;) {
                const short ev = fds[i + 1].revents;
                if (ev == 0) continue;
                if (ev & (POLLERR | POLLNVAL)) {
                    close_client(i);
                    continue;
                }
                modbus_set_socket(ctx, clients[i]);
                const int rc = modbus_receive(ctx, query.data());
                if (rc > 0) handle(query.data(), rc);
                else if (rc == -1) close_client(i);  // closed by the peer or a malformed frame
            }
            if (fds[0].revents & POLLIN) {
                const int fd = ::accept(listen_fd, nullptr, nullptr);
                if (fd >= 0) {
                    clients.push_back(fd);
                    count(&ChamberServerStats::connections);
                }
            }
        }
    }
};

ChamberServer::ChamberServer(BenchPlant plant, std::shared_ptr<const BenchClock> clock, ChamberServerOptions options)
    : impl_(std::make_unique<Impl>(std::move(plant), std::move(clock), std::move(options))) {}

ChamberServer::~ChamberServer() = default;

void ChamberServer::start() { impl_->start(); }
void ChamberServer::stop() { impl_->stop(); }
int ChamberServer::port() const { return impl_->bound_port; }
std::string ChamberServer::description() const {
    return "modbus-tcp " + impl_->options.host + ":" + std::to_string(impl_->bound_port);
}

void ChamberServer::set_unresponsive(bool unresponsive) { impl_->unresponsive = unresponsive; }
void ChamberServer::set_exception_response(std::optional<std::uint8_t> code) { impl_->exception_code = code.value_or(0); }

bool ChamberServer::set_alarm(const std::string& name, bool active) {
    const auto bit = impl_->options.map.alarm_bit(name);
    if (!bit) return false;
    const auto mask = static_cast<std::uint16_t>(1u << *bit);
    std::uint16_t word = impl_->alarm_word.load();
    while (!impl_->alarm_word.compare_exchange_weak(word, active ? static_cast<std::uint16_t>(word | mask)
                                                                 : static_cast<std::uint16_t>(word & ~mask))) {
    }
    return true;
}

void ChamberServer::set_alarm_word(std::uint16_t word) { impl_->alarm_word = word; }
void ChamberServer::set_heater_failed(bool failed) { impl_->plant.set_chamber_heater_failed(failed); }

ChamberServerStats ChamberServer::stats() const {
    std::lock_guard lock(impl_->stats_mutex);
    return impl_->stats;
}

}  // namespace cellbench::sim
