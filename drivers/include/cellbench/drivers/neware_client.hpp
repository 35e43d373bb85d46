#pragma once
// Neware BTS API client on Boost.Asio: one TCP connection to the BTS server, one logical channel that is a
// single tester channel or a parallel group of channels (protocol/parallel_group.hpp).
//
//  - All I/O runs on one strand of the given io_context: async_read_some feeds a FrameSplitter; requests go
//    out one at a time (the BTS answers strictly in order) and each answer is matched to its request by
//    command ("inquire" <- "inquire_resp").
//  - Every request has a deadline (request_timeout from when it was queued). A request that cannot be sent
//    in time fails; one that was sent but not answered fails and the connection is re-established (after a
//    lost answer the stream can no longer be trusted). Reconnects back off exponentially.
//  - `inquire` of all members is polled every poll_period; each answer becomes a NewareSample stamped with
//    std::chrono::steady_clock (request and answer instants), aggregated into the group reading.
//  - Recorded data: after a start this client accepted, every poll also downloads what the tester recorded
//    since the last poll (`download`, up to 1000 rows per request, per member) and joins the members' rows by
//    seqid into group rows, delivered with the poll's sample, before it. The tester records at its own
//    interval whatever the polling and the network do, so the science (step edges, pulse fits) uses these
//    rows; the live values are for supervision. A download that fails is retried from the same row next poll.
//  - start/stop/pause/continue go to all members in one request; the result is ok only if every member said ok.
//  - A group fault (a member in protect, current sharing off, voltages disagreeing, ...) is reported once as
//    an event; with stop_on_group_fault the client then stops all members.
//  - Nothing throws across the io_context: failures arrive as events and as the command callbacks' results.
//    Callbacks run on the strand and never after stop() has returned.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>

#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/protocol/parallel_group.hpp"

namespace cellbench::drivers {

struct NewareClientOptions {
    std::string host = "127.0.0.1";
    int port = 502;
    // The logical channel: one channel, or the members of a parallel group (the thesis: three of 20 A).
    std::vector<protocol::neware::ChannelAddress> members;
    std::chrono::milliseconds poll_period{100};
    std::chrono::milliseconds request_timeout{1000};
    std::chrono::milliseconds connect_timeout{1000};
    std::chrono::milliseconds reconnect_initial{100};
    std::chrono::milliseconds reconnect_max{5000};
    std::size_t max_frame_bytes = protocol::neware::kDefaultMaxFrameBytes;
    // Sent first on every connection when set (BTS 8 API login); a refusal drops the connection.
    std::optional<protocol::neware::ConnectRequest> login;
    protocol::ParallelGroupOptions group;
    bool stop_on_group_fault = true;
    // Download the recorded data of tests this client started (see above).
    bool download_records = true;
};

// One poll of the logical channel.
struct NewareSample {
    std::chrono::steady_clock::time_point request_time;  // inquire sent
    std::chrono::steady_clock::time_point time;          // answer received
    protocol::GroupReading group;                        // the logical channel (sum / mean)
    std::vector<protocol::neware::InquireEntry> members; // in the order of options.members
    // Recorded rows of the group (members joined by seqid: currents, capacities and energies summed, voltage
    // averaged) that arrived since the previous sample, oldest first; all of them precede the live values.
    std::vector<protocol::neware::DownloadRecord> records;
    std::int64_t test_id = 0;  // the tester's id of the test the records belong to (0: none yet)
    bool recording = false;    // the tester records this period: records carry it (a test this client started)
};

enum class NewareEventKind {
    connected,       // TCP up (and logged in)
    disconnected,    // connection lost or dropped; a reconnect is scheduled
    connect_failed,  // an attempt failed; a retry is scheduled
    timeout,         // a request got no answer in time
    protocol_error,  // a malformed or unexpected frame, or an answer that does not fit the request
    command_failed,  // start/stop/pause/continue not acknowledged by every member
    group_fault,     // the parallel group misbehaves (fault names the member and the reason)
};
const char* to_string(NewareEventKind kind);

struct NewareEvent {
    std::chrono::steady_clock::time_point time;
    NewareEventKind kind = NewareEventKind::protocol_error;
    std::string message;
    std::optional<protocol::GroupFault> fault;  // group_fault only
};

struct NewareCommandResult {
    bool ok = false;
    std::string error;  // empty when ok
    std::vector<protocol::neware::ChannelResult> channels;
    // The command never left this client (not connected, or the tester busy with other requests until the
    // timeout): the tester cannot have acted on it, so sending it again is safe. After a lost answer it may have.
    bool never_sent = false;
};

class NewareClient {
public:
    using CommandDone = std::function<void(const NewareCommandResult&)>;
    using ResponseDone =
        std::function<void(const std::optional<protocol::neware::Response>& response, const std::string& error)>;

    // Throws std::invalid_argument for an unusable configuration (no members or more than four, a
    // non-positive period or timeout).
    NewareClient(boost::asio::io_context& io, NewareClientOptions options);
    ~NewareClient();  // stops
    NewareClient(const NewareClient&) = delete;
    NewareClient& operator=(const NewareClient&) = delete;

    // Set before start().
    void on_sample(std::function<void(const NewareSample&)> callback);
    void on_event(std::function<void(const NewareEvent&)> callback);

    void start();  // connects and polls (reconnecting as needed)
    void stop();   // closes; thread-safe; no callback runs after it returns

    // Commands to all members. `done` runs on the strand (also on failure: not connected in time, timeout).
    void start_program(std::string step_file_path, std::string barcode, CommandDone done = {});
    void stop_program(CommandDone done = {});
    void pause_program(CommandDone done = {});
    void continue_program(CommandDone done = {});

    // Any request (getchlstatus, getdevinfo, ...), queued like the others.
    void request(protocol::neware::Request request, ResponseDone done);

    // Clears a latched group fault (e.g. after the operator dealt with it).
    void reset_group_fault();

    [[nodiscard]] bool connected() const;  // thread-safe snapshot

private:
    struct Impl;
    std::shared_ptr<Impl> impl_;
};

}  // namespace cellbench::drivers
