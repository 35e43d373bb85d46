#include "cellbench/drivers/can_transport.hpp"

#include <sys/socket.h>
#include <sys/un.h>
#include <sys/stat.h>
#include <unistd.h>
#include <net/if.h>
#include <linux/can.h>
#include <linux/can/raw.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cstddef>
#include <cerrno>
#include <cstring>
#include <deque>
#include <mutex>
#include <vector>

#include <boost/asio/generic/raw_protocol.hpp>
#include <boost/asio/local/datagram_protocol.hpp>
#include <boost/asio/steady_timer.hpp>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/core/recording.hpp"

namespace cellbench::drivers {

namespace asio = boost::asio;
using boost::system::error_code;

namespace {

error_code errno_code(int e) { return error_code(e, boost::system::system_category()); }

// Errors after which a can-dgram peer is gone (its socket closed or its file removed).
bool peer_gone(const error_code& ec) {
    return ec == asio::error::connection_refused || ec == asio::error::connection_reset ||
           ec == asio::error::not_connected || ec == errno_code(ENOENT);
}

// --------------------------------------------------------------------------------------------------------
// SocketCAN: a thin raw socket. struct can_frame is converted field by field, so the records handed on are the
// little-endian layout of protocol/dewe_can.hpp whatever the host.
class SocketCanTransport final : public CanTransport, public std::enable_shared_from_this<SocketCanTransport> {
public:
    SocketCanTransport(asio::io_context& io, std::string interface) : socket_(io), interface_(std::move(interface)) {}

    void open() {
        socket_.open(asio::generic::raw_protocol(PF_CAN, CAN_RAW));
        const unsigned index = if_nametoindex(interface_.c_str());
        if (index == 0)
            throw boost::system::system_error(errno_code(ENODEV), "CAN interface " + interface_);
        sockaddr_can addr{};
        addr.can_family = AF_CAN;
        addr.can_ifindex = static_cast<int>(index);
        socket_.bind(asio::generic::raw_protocol::endpoint(&addr, sizeof addr, CAN_RAW));
        socket_.non_blocking(true);  // send() never blocks; async receives are unaffected
    }

    void async_receive(ReceiveHandler handler) override {
        socket_.async_receive(asio::buffer(&frame_, sizeof frame_),
                              [self = shared_from_this(), handler = std::move(handler)](const error_code& ec, std::size_t n) {
                                  if (ec) return handler(ec, {});
                                  if (n != sizeof(can_frame)) {
                                      handler(ec, std::span<const std::uint8_t>(
                                                      reinterpret_cast<const std::uint8_t*>(&self->frame_), n));
                                      return;
                                  }
                                  protocol::CanFrame f;
                                  f.can_id = self->frame_.can_id;
                                  f.len = self->frame_.len;
                                  f.len8_dlc = self->frame_.len8_dlc;
                                  std::memcpy(f.data.data(), self->frame_.data, protocol::kCanMaxDlen);
                                  protocol::encode_can_record(f, self->record_.data());  // len > 8 kept for the decoder
                                  handler(ec, self->record_);
                              });
    }

    error_code send(const protocol::CanFrame& f) override {
        can_frame native{};
        native.can_id = f.can_id;
        native.len = f.len;
        native.len8_dlc = f.len8_dlc;
        std::memcpy(native.data, f.data.data(), protocol::kCanMaxDlen);
        error_code ec;
        socket_.send(asio::buffer(&native, sizeof native), 0, ec);
        return ec;
    }

    error_code send_record(std::span<const std::uint8_t> bytes) override {
        if (bytes.size() == protocol::kCanRecordBytes) {
            protocol::CanRecordError why{};
            if (auto f = protocol::decode_can_record(bytes, &why)) return send(*f);
        }
        // The kernel only takes well-formed frames of sizeof(struct can_frame); pass the bytes, it refuses them.
        error_code ec;
        socket_.send(asio::buffer(bytes.data(), bytes.size()), 0, ec);
        return ec;
    }

    void close() override {
        error_code ignored;
        socket_.close(ignored);
    }

    std::string description() const override { return "can " + interface_; }

private:
    asio::generic::raw_protocol::socket socket_;
    std::string interface_;
    can_frame frame_{};
    protocol::CanRecord record_{};
};

// --------------------------------------------------------------------------------------------------------
// can-dgram listener: autobound, connected to the hub (so the hub's sends are not limited by the receiver's
// small datagram queue), subscribing with an empty datagram.
class CanDgramListener final : public CanTransport, public std::enable_shared_from_this<CanDgramListener> {
public:
    CanDgramListener(asio::io_context& io, std::string path, std::chrono::milliseconds resubscribe)
        : socket_(io), timer_(io), retry_timer_(io), path_(std::move(path)), resubscribe_(resubscribe) {}

    void open() {
        socket_.open();
        socket_.bind(asio::local::datagram_protocol::endpoint(""));  // autobind: an anonymous abstract address
        socket_.non_blocking(true);
        subscribe();
        arm_resubscribe();
    }

    void async_receive(ReceiveHandler handler) override {
        handler_ = std::move(handler);
        receive();
    }

    error_code send(const protocol::CanFrame& f) override {
        const auto record = protocol::encode_can_record(f);
        return send_record(record);
    }

    error_code send_record(std::span<const std::uint8_t> bytes) override {
        if (!connected_) return asio::error::not_connected;
        error_code ec;
        socket_.send(asio::buffer(bytes.data(), bytes.size()), 0, ec);
        if (peer_gone(ec)) connected_ = false;
        return ec;
    }

    void close() override {
        closed_ = true;
        error_code ignored;
        timer_.cancel();
        retry_timer_.cancel();
        socket_.close(ignored);
    }

    std::string description() const override { return "can-dgram " + path_; }

private:
    void subscribe() {
        if (closed_) return;
        error_code ec;
        if (!connected_) {
            socket_.connect(asio::local::datagram_protocol::endpoint(path_), ec);
            if (ec) return;  // hub not up yet: retried on the next tick
            connected_ = true;
        }
        socket_.send(asio::buffer(static_cast<const void*>(nullptr), 0), 0, ec);
        if (peer_gone(ec)) {
            // The hub restarted: connect to the new socket at the same path right away.
            connected_ = false;
            socket_.connect(asio::local::datagram_protocol::endpoint(path_), ec);
            if (ec) return;
            connected_ = true;
            socket_.send(asio::buffer(static_cast<const void*>(nullptr), 0), 0, ec);
        }
    }

    void arm_resubscribe() {
        timer_.expires_after(resubscribe_);
        timer_.async_wait([self = shared_from_this()](const error_code& ec) {
            if (ec || self->closed_) return;
            self->subscribe();
            self->arm_resubscribe();
        });
    }

    void receive() {
        socket_.async_receive(asio::buffer(buffer_), [self = shared_from_this()](const error_code& ec, std::size_t n) {
            if (!self->handler_) return;
            if (ec && ec != asio::error::operation_aborted && !self->closed_ && peer_gone(ec)) {
                // The hub went away: keep listening, the resubscription reconnects. Retry after a pause so a
                // sticky error cannot spin.
                self->connected_ = false;
                self->retry_timer_.expires_after(std::chrono::milliseconds(50));
                self->retry_timer_.async_wait([self](const error_code& tec) {
                    if (tec || self->closed_) {
                        if (auto h = std::move(self->handler_)) h(asio::error::operation_aborted, {});
                        return;
                    }
                    self->receive();
                });
                return;
            }
            auto h = std::move(self->handler_);
            self->handler_ = nullptr;
            h(ec, std::span<const std::uint8_t>(self->buffer_.data(), ec ? 0 : n));
        });
    }

    asio::local::datagram_protocol::socket socket_;
    asio::steady_timer timer_, retry_timer_;
    std::string path_;
    std::chrono::milliseconds resubscribe_;
    bool connected_ = false;
    std::atomic<bool> closed_{false};
    ReceiveHandler handler_;
    std::array<std::uint8_t, 128> buffer_{};  // larger than a record, so oversize datagrams show as such
};

// --------------------------------------------------------------------------------------------------------
// can-dgram hub: the bus. Every datagram registers its sender as a subscriber; frames go to all subscribers.
//
// A frame sent to a listener stays charged to the hub's send buffer until the listener reads it: with the 1 MiB
// asked for, about 2 700 of the 16-byte records (measured) fit in flight. At x400 the simulated DAQ sends about
// 8 000 frames per second, so a listener off the CPU for a third of a second would lose frames, where a SocketCAN
// socket's receive buffer on a real bench holds them. The hub therefore keeps what a listener could not take yet,
// in order, up to kBacklogFrames per listener (seconds of the fastest stream), and retries every kBacklogRetry;
// only beyond that does the listener lose frames (the oldest first), and send reports it.
class CanDgramHub final : public CanTransport, public std::enable_shared_from_this<CanDgramHub> {
public:
    static constexpr std::size_t kBacklogFrames = 65536;
    static constexpr auto kBacklogRetry = std::chrono::milliseconds(1);

    CanDgramHub(asio::io_context& io, std::string path) : socket_(io), retry_timer_(io), path_(std::move(path)) {}

    void open() {
        struct stat st {};
        if (::lstat(path_.c_str(), &st) == 0) {
            if (!S_ISSOCK(st.st_mode))
                throw boost::system::system_error(errno_code(EEXIST), path_ + " exists and is not a socket");
            ::unlink(path_.c_str());  // stale socket of an earlier run
        }
        socket_.open();
        socket_.bind(asio::local::datagram_protocol::endpoint(path_));
        bound_ = true;
        socket_.non_blocking(true);
        // Room for bursts (a catch-up batch at a high time scale) before slow listeners lose frames.
        error_code ignored;
        socket_.set_option(asio::socket_base::send_buffer_size(1 << 20), ignored);
        receive();
    }

    void async_receive(ReceiveHandler handler) override {
        std::lock_guard lock(mutex_);
        handler_ = std::move(handler);
    }

    error_code send(const protocol::CanFrame& f) override {
        const auto record = protocol::encode_can_record(f);
        return send_record(record);
    }

    // Success when every listener took the frame or holds it in its backlog; would_block when a listener's
    // backlog was full and it lost its oldest frame.
    error_code send_record(std::span<const std::uint8_t> bytes) override {
        std::lock_guard lock(mutex_);
        if (!socket_.is_open()) return asio::error::bad_descriptor;
        error_code result;
        for (auto it = subscribers_.begin(); it != subscribers_.end();) {
            if (it->backlog.empty()) {
                error_code ec;
                switch (try_send(it->endpoint, bytes, ec)) {
                    case Delivery::sent: ++it; continue;
                    case Delivery::gone: it = subscribers_.erase(it); continue;
                    case Delivery::failed: result = ec; ++it; continue;
                    case Delivery::full: break;  // keep it in the backlog
                }
            }
            if (it->backlog.size() >= kBacklogFrames) {
                it->backlog.pop_front();
                if (it->lost++ == 0)
                    spdlog::warn("can-dgram {}: a listener is {} frames behind; it loses frames from now on", path_,
                                 kBacklogFrames);
                result = asio::error::would_block;
            }
            it->backlog.emplace_back(bytes.begin(), bytes.end());
            arm_retry_locked();
            ++it;
        }
        return result;
    }

    void close() override {
        std::lock_guard lock(mutex_);
        error_code ignored;
        retry_timer_.cancel();
        socket_.close(ignored);
        if (bound_) {
            ::unlink(path_.c_str());
            bound_ = false;
        }
        subscribers_.clear();
    }

    std::string description() const override { return "can-dgram " + path_; }

private:
    struct Subscriber {
        asio::local::datagram_protocol::endpoint endpoint;
        std::deque<std::vector<std::uint8_t>> backlog;  // frames it could not take yet, oldest first
        std::uint64_t lost = 0;                          // dropped from a full backlog
    };

    // What became of one record sent to one listener.
    enum class Delivery {
        sent,    // the listener's socket took it
        full,    // its receive queue is full: keep the record and retry
        gone,    // the listener's socket is gone: forget the listener
        failed,  // another error, which retrying will not mend
    };

    Delivery try_send(const asio::local::datagram_protocol::endpoint& to, std::span<const std::uint8_t> bytes,
                      error_code& ec) {
        socket_.send_to(asio::buffer(bytes.data(), bytes.size()), to, 0, ec);
        if (!ec) return Delivery::sent;
        if (peer_gone(ec)) return Delivery::gone;
        if (ec == asio::error::would_block || ec == asio::error::try_again || ec == asio::error::no_buffer_space)
            return Delivery::full;
        return Delivery::failed;
    }

    void arm_retry_locked() {
        if (retry_armed_ || !socket_.is_open()) return;
        retry_armed_ = true;
        retry_timer_.expires_after(kBacklogRetry);
        retry_timer_.async_wait([self = shared_from_this()](const error_code& ec) {
            if (!ec) self->drain_backlogs();
        });
    }

    void drain_backlogs() {
        std::lock_guard lock(mutex_);
        retry_armed_ = false;
        if (!socket_.is_open()) return;
        bool waiting = false;
        for (auto it = subscribers_.begin(); it != subscribers_.end();) {
            auto& q = it->backlog;
            Delivery d = Delivery::sent;
            while (!q.empty()) {
                error_code ec;
                d = try_send(it->endpoint, q.front(), ec);
                if (d == Delivery::sent || d == Delivery::failed) q.pop_front();  // a failure retrying will not mend
                if (d == Delivery::gone || d == Delivery::full) break;
            }
            if (d == Delivery::gone) {
                it = subscribers_.erase(it);
                continue;
            }
            if (q.empty() && it->lost > 0) {
                spdlog::warn("can-dgram {}: a listener caught up after losing {} frames", path_, it->lost);
                it->lost = 0;
            }
            waiting = waiting || !q.empty();
            ++it;
        }
        if (waiting) arm_retry_locked();
    }

    void receive() {
        socket_.async_receive_from(asio::buffer(buffer_), sender_, [self = shared_from_this()](const error_code& ec, std::size_t n) {
            if (ec == asio::error::operation_aborted || !self->socket_.is_open()) {
                ReceiveHandler h;
                {
                    std::lock_guard lock(self->mutex_);
                    h = std::move(self->handler_);
                    self->handler_ = nullptr;
                }
                if (h) h(asio::error::operation_aborted, {});
                return;
            }
            ReceiveHandler h;
            if (!ec) {
                std::lock_guard lock(self->mutex_);
                // An unbound sender (no address) cannot be answered; everyone else subscribes by sending.
                if (self->sender_.size() > offsetof(sockaddr_un, sun_path) &&
                    std::none_of(self->subscribers_.begin(), self->subscribers_.end(),
                                 [&](const Subscriber& s) { return s.endpoint == self->sender_; })) {
                    self->subscribers_.push_back(Subscriber{self->sender_, {}, 0});
                    spdlog::debug("can-dgram {}: subscriber {} joined", self->path_, self->subscribers_.size());
                }
                if (n > 0 && self->handler_) {
                    h = std::move(self->handler_);
                    self->handler_ = nullptr;
                }
            }
            if (h) h(ec, std::span<const std::uint8_t>(self->buffer_.data(), n));
            self->receive();
        });
    }

    asio::local::datagram_protocol::socket socket_;
    asio::steady_timer retry_timer_;
    std::string path_;
    bool bound_ = false;
    bool retry_armed_ = false;
    std::mutex mutex_;  // subscribers_, handler_, the retry timer (send may come from another strand)
    std::vector<Subscriber> subscribers_;
    ReceiveHandler handler_;
    asio::local::datagram_protocol::endpoint sender_;
    std::array<std::uint8_t, 128> buffer_{};
};

}  // namespace

// ------------------------------------------------------------------------------------------------------------

CanEndpoint CanEndpoint::from_json(const nlohmann::json& j, const std::string& source) {
    auto fail = [&](const std::string& path, const std::string& what) -> CanEndpoint {
        throw InputError(source + ": " + path + ": " + what);
    };
    if (!j.is_object()) return fail("$", "expected an object");
    const auto t = j.find("transport");
    if (t == j.end() || !t->is_string()) return fail("$.transport", "expected \"socketcan\" or \"can-dgram\"");
    CanEndpoint e;
    const std::string kind = t->get<std::string>();
    const char* key = nullptr;
    if (kind == "socketcan") {
        e.kind = Kind::socketcan;
        key = "interface";
    } else if (kind == "can-dgram") {
        e.kind = Kind::can_dgram;
        key = "path";
    } else {
        return fail("$.transport", "expected \"socketcan\" or \"can-dgram\", got \"" + kind + "\"");
    }
    auto n = j.find(key);
    if (n == j.end() && e.kind == Kind::can_dgram) {  // the bench config's spelling
        n = j.find("socket_path");
        if (n != j.end()) key = "socket_path";
    }
    if (n == j.end() || !n->is_string() || n->get<std::string>().empty())
        return fail(std::string("$.") + key, "expected a non-empty string");
    e.name = n->get<std::string>();
    return e;
}

nlohmann::json CanEndpoint::to_json() const {
    if (kind == Kind::socketcan) return {{"transport", "socketcan"}, {"interface", name}};
    return {{"transport", "can-dgram"}, {"path", name}};
}

bool socketcan_available(std::string* why) {
    const int fd = ::socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (fd < 0) {
        if (why) *why = std::string("socket(PF_CAN, SOCK_RAW, CAN_RAW) failed: ") + std::strerror(errno);
        return false;
    }
    ::close(fd);
    return true;
}

bool network_interface_exists(const std::string& name) { return if_nametoindex(name.c_str()) != 0; }

std::shared_ptr<CanTransport> open_socketcan(asio::io_context& io, const std::string& interface) {
    auto t = std::make_shared<SocketCanTransport>(io, interface);
    t->open();
    return t;
}

std::shared_ptr<CanTransport> open_can_dgram_listener(asio::io_context& io, const std::string& path,
                                                      std::chrono::milliseconds resubscribe_interval) {
    auto t = std::make_shared<CanDgramListener>(io, path, resubscribe_interval);
    t->open();
    return t;
}

std::shared_ptr<CanTransport> open_can_dgram_hub(asio::io_context& io, const std::string& path) {
    auto t = std::make_shared<CanDgramHub>(io, path);
    t->open();
    return t;
}

std::shared_ptr<CanTransport> open_can_listener(asio::io_context& io, const CanEndpoint& endpoint) {
    return endpoint.kind == CanEndpoint::Kind::socketcan ? open_socketcan(io, endpoint.name)
                                                         : open_can_dgram_listener(io, endpoint.name);
}

std::shared_ptr<CanTransport> open_can_publisher(asio::io_context& io, const CanEndpoint& endpoint) {
    return endpoint.kind == CanEndpoint::Kind::socketcan ? open_socketcan(io, endpoint.name)
                                                         : open_can_dgram_hub(io, endpoint.name);
}

}  // namespace cellbench::drivers
