#pragma once
// CAN transports behind one interface, carrying the 16-byte `struct can_frame` records of protocol/dewe_can.hpp:
//
//  - SocketCAN: a raw CAN socket (PF_CAN, SOCK_RAW, CAN_RAW) bound to an interface such as vcan0 or can0.
//  - can-dgram (INTERFACES.md): the same records, one per datagram, over a Unix datagram socket, for kernels
//    without AF_CAN. The simulated DAQ is the "hub": it binds SOCKET_PATH. A listener binds an anonymous
//    (autobind) address, connects to SOCKET_PATH and sends an empty datagram to subscribe; the hub then sends
//    every frame to every subscriber, as a bus delivers every frame to every node. Listeners re-send the
//    empty datagram every second, so a restarted hub learns them again. A subscriber that cannot keep up
//    loses frames (the hub never blocks), which the decoder sees as counter gaps, as on a real bus.
//    From a script: s = socket(AF_UNIX, SOCK_DGRAM); s.bind(""); s.connect(PATH); s.send(b""); s.recv(16).
//
// All transports are used from one io_context; open them with the factories below and close() them when done
// (pending handlers then complete with operation_aborted and release the transport).
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>

#include <boost/asio/io_context.hpp>
#include <boost/system/error_code.hpp>
#include <nlohmann/json_fwd.hpp>

#include "cellbench/protocol/dewe_can.hpp"

namespace cellbench::drivers {

class CanTransport {
public:
    // record: the bytes of one received record (normally 16; other sizes are passed on so the decoder can count
    // them as garbage). Valid only during the call.
    using ReceiveHandler = std::function<void(const boost::system::error_code&, std::span<const std::uint8_t> record)>;

    virtual ~CanTransport() = default;

    // Receives one record. One receive at a time. Transient errors of the medium are handled inside; the
    // handler sees records, or operation_aborted after close(), or an error that ends the stream.
    virtual void async_receive(ReceiveHandler handler) = 0;
    // Sends one frame without blocking (would_block when it could not be queued).
    virtual boost::system::error_code send(const protocol::CanFrame& frame) = 0;
    // Sends raw record bytes as they are (fault injection: malformed records). The medium may refuse them.
    virtual boost::system::error_code send_record(std::span<const std::uint8_t> bytes) = 0;
    virtual void close() = 0;
    // "can vcan0" or "can-dgram PATH", as `cellbench sim` prints it.
    [[nodiscard]] virtual std::string description() const = 0;
};

// Where a CAN stream is. JSON: {"transport": "socketcan", "interface": "vcan0"} or
// {"transport": "can-dgram", "path": "/run/cellbench/dewe.sock"} ("socket_path" is accepted for "path").
struct CanEndpoint {
    enum class Kind { socketcan, can_dgram };
    Kind kind = Kind::can_dgram;
    std::string name;  // interface or socket path

    static CanEndpoint from_json(const nlohmann::json& j, const std::string& source = "can endpoint");
    [[nodiscard]] nlohmann::json to_json() const;
};

// Whether this kernel can open a raw CAN socket; *why says why not.
bool socketcan_available(std::string* why = nullptr);
// Whether a network interface of that name exists.
bool network_interface_exists(const std::string& name);

// Throw boost::system::system_error when the socket cannot be opened or bound.
std::shared_ptr<CanTransport> open_socketcan(boost::asio::io_context& io, const std::string& interface);
// The listener side of can-dgram (the daemon's DEWE driver). Opening succeeds even while the hub is not up yet:
// the subscription is retried every resubscribe interval.
std::shared_ptr<CanTransport> open_can_dgram_listener(boost::asio::io_context& io, const std::string& path,
                                                      std::chrono::milliseconds resubscribe_interval = std::chrono::seconds(1));
// The hub side of can-dgram (the simulated DAQ): binds path (replacing a stale socket file, never another kind
// of file) and removes it on close(). async_receive delivers non-empty records that listeners send.
std::shared_ptr<CanTransport> open_can_dgram_hub(boost::asio::io_context& io, const std::string& path);

// Listener for an endpoint: SocketCAN, or the can-dgram listener.
std::shared_ptr<CanTransport> open_can_listener(boost::asio::io_context& io, const CanEndpoint& endpoint);
// Publisher for an endpoint: SocketCAN, or the can-dgram hub.
std::shared_ptr<CanTransport> open_can_publisher(boost::asio::io_context& io, const CanEndpoint& endpoint);

}  // namespace cellbench::drivers
