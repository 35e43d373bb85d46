#include "cellbench/drivers/neware_client.hpp"
#include "cellbench/drivers/episode_log.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <deque>
#include <mutex>
#include <stdexcept>
#include <string>
#include <string_view>

#include <utility>  // before Asio: Boost 1.74 awaitable.hpp uses std::exchange without it

#include <boost/asio.hpp>
#include <spdlog/spdlog.h>

namespace cellbench::drivers {

namespace asio = boost::asio;
using asio::ip::tcp;
using Clock = std::chrono::steady_clock;
using namespace protocol::neware;

const char* to_string(NewareEventKind kind) {
    switch (kind) {
        case NewareEventKind::connected: return "connected";
        case NewareEventKind::disconnected: return "disconnected";
        case NewareEventKind::connect_failed: return "connect_failed";
        case NewareEventKind::timeout: return "timeout";
        case NewareEventKind::protocol_error: return "protocol_error";
        case NewareEventKind::command_failed: return "command_failed";
        case NewareEventKind::group_fault: return "group_fault";
    }
    return "unknown";
}

namespace {

std::string ms_text(std::chrono::milliseconds ms) { return std::to_string(ms.count()) + " ms"; }

// How the error of a request that expired in the queue begins (NewareCommandResult::never_sent).
constexpr std::string_view kNotSent = "not sent within ";

}  // namespace

struct NewareClient::Impl : std::enable_shared_from_this<Impl> {
    Impl(asio::io_context& io_, NewareClientOptions o)
        : io(io_),
          strand(asio::make_strand(io_)),
          options(std::move(o)),
          resolver(strand),
          socket(strand),
          poll_timer(strand),
          deadline_timer(strand),
          reconnect_timer(strand),
          connect_timer(strand),
          splitter(options.max_frame_bytes),
          group(options.group),
          backoff(options.reconnect_initial) {}

    struct Pending {
        Command command = Command::inquire;
        std::string bytes;
        Clock::time_point deadline;
        Clock::time_point sent;
        ResponseDone done;
    };

    enum class Link { idle, connecting, logging_in, up };

    asio::io_context& io;
    asio::strand<asio::io_context::executor_type> strand;
    NewareClientOptions options;
    tcp::resolver resolver;
    tcp::socket socket;
    asio::steady_timer poll_timer, deadline_timer, reconnect_timer, connect_timer;
    FrameSplitter splitter;
    protocol::ParallelGroup group;
    std::array<char, 16384> buffer{};

    Link link = Link::idle;
    std::uint64_t generation = 0;  // of the connection; handlers of an older one return at once
    std::deque<Pending> queue;
    std::optional<Pending> inflight;
    bool poll_pending = false;
    bool running = false;
    std::chrono::milliseconds backoff;
    Clock::time_point next_poll;
    std::atomic<bool> is_connected{false};

    // Recorded data (options.download_records).
    bool recording = false;               // a test this client started: download its rows
    std::int64_t test_id = 0;             // 0: not known yet (ask for the latest test)
    std::vector<std::int64_t> next_seq;   // per member: the first seqid not downloaded yet
    std::vector<std::deque<DownloadRecord>> unjoined;  // per member: rows not yet matched by every member
    std::optional<NewareSample> held;     // the poll's sample, delivered once the downloads are done
    std::size_t download_member = 0;

    // Callbacks: invoked under cb_mutex and only while not stopped (stop() takes the mutex).
    std::recursive_mutex cb_mutex;
    bool stopped = false;
    std::function<void(const NewareSample&)> sample_cb;
    std::function<void(const NewareEvent&)> event_cb;
    EpisodeLog episode_log;  // one warning per kind of fault in an episode (on the strand)

    // ------------------------------------------------------------------------------------------------------
    // Callback helpers

    template <typename F>
    void deliver(F&& f) {
        std::lock_guard lock(cb_mutex);
        if (stopped) return;
        try {
            f();
        } catch (const std::exception& e) {
            spdlog::error("neware: a callback threw: {}", e.what());
        }
    }

    void emit(NewareEventKind kind, std::string message, std::optional<protocol::GroupFault> fault = std::nullopt) {
        if (kind == NewareEventKind::connected)
            spdlog::info("neware {}:{}: {}", options.host, options.port, message);
        else
            spdlog::log(episode_log.level(to_string(kind), spdlog::level::warn), "neware {}:{}: {}: {}", options.host,
                        options.port, to_string(kind), message);
        deliver([&] {
            if (event_cb) event_cb(NewareEvent{Clock::now(), kind, message, std::move(fault)});
        });
    }

    void complete(ResponseDone& done, const std::optional<Response>& response, const std::string& error) {
        if (!done) return;
        deliver([&] { done(response, error); });
    }

    // ------------------------------------------------------------------------------------------------------
    // Connection

    void connect() {
        if (!running) return;
        link = Link::connecting;
        const auto gen = ++generation;
        resolver.async_resolve(
            options.host, std::to_string(options.port),
            [self = shared_from_this(), gen](const boost::system::error_code& ec, tcp::resolver::results_type results) {
                if (gen != self->generation || !self->running) return;
                if (ec) return self->connect_failed("cannot resolve " + self->options.host + ": " + ec.message());
                self->connect_timer.expires_after(self->options.connect_timeout);
                self->connect_timer.async_wait([self, gen](const boost::system::error_code& e) {
                    if (e || gen != self->generation || self->link != Link::connecting) return;
                    boost::system::error_code ignored;
                    self->socket.close(ignored);  // the connect handler then sees operation_aborted
                });
                asio::async_connect(self->socket, results,
                                    [self, gen](const boost::system::error_code& e, const tcp::endpoint&) {
                                        self->connect_timer.cancel();
                                        if (gen != self->generation || !self->running) return;
                                        if (e)
                                            return self->connect_failed(
                                                e == asio::error::operation_aborted
                                                    ? "connect timed out after " + ms_text(self->options.connect_timeout)
                                                    : e.message());
                                        // A TCP self-connection: with nothing listening on a loopback port in
                                        // the ephemeral range, the connect can bind that very port and
                                        // "connect" to itself (simultaneous open), which would also keep the
                                        // tester from listening there again. Not a tester: drop it.
                                        boost::system::error_code le, re;
                                        const auto local = self->socket.local_endpoint(le);
                                        const auto remote = self->socket.remote_endpoint(re);
                                        if (!le && !re && local == remote)
                                            return self->connect_failed("connected to itself (nothing listens on " +
                                                                        self->options.host + ":" +
                                                                        std::to_string(self->options.port) + ")");
                                        self->on_connected(gen);
                                    });
            });
    }

    void connect_failed(const std::string& why) {
        link = Link::idle;
        boost::system::error_code ignored;
        socket.close(ignored);
        emit(NewareEventKind::connect_failed,
             options.host + ":" + std::to_string(options.port) + ": " + why + "; retrying in " + ms_text(backoff));
        schedule_reconnect();
    }

    void schedule_reconnect() {
        if (!running) return;
        reconnect_timer.expires_after(backoff);
        backoff = std::min(backoff * 2, options.reconnect_max);
        reconnect_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
            if (!ec && self->running && self->link == Link::idle) self->connect();
        });
    }

    void on_connected(std::uint64_t gen) {
        boost::system::error_code ignored;
        socket.set_option(tcp::no_delay(true), ignored);
        splitter.clear();
        read(gen);
        if (options.login) {
            link = Link::logging_in;
            Pending p;
            p.command = Command::connect;
            p.bytes = encode_request(*options.login);
            p.deadline = Clock::now() + options.request_timeout;
            // Completions wait in the queue, inside this Impl: they hold it weakly (a strong hold would keep an Impl
            // whose io_context stopped before stop()'s clean-up ran alive for ever; LeakSanitizer, `make sanitize`).
            p.done = [weak = weak_from_this(), gen](const std::optional<Response>& r, const std::string& error) {
                const auto self = weak.lock();
                if (!self || gen != self->generation) return;
                const auto* resp = r ? std::get_if<ConnectResponse>(&*r) : nullptr;
                if (resp && resp->ok) return self->link_up();
                self->connection_lost("login refused: " + (resp ? resp->result : error));
            };
            queue.push_front(std::move(p));
            pump();
        } else {
            link_up();
        }
    }

    void link_up() {
        link = Link::up;
        is_connected = true;
        backoff = options.reconnect_initial;
        emit(NewareEventKind::connected, "connected to " + options.host + ":" + std::to_string(options.port));
        pump();
    }

    void connection_lost(const std::string& why) {
        if (link == Link::idle) return;
        const bool was_up = link == Link::up;
        link = Link::idle;
        is_connected = false;
        ++generation;  // stale read/write handlers of this connection return at once
        if (held) {    // the poll's downloads end here; its rows are asked for again on the next connection
            held.reset();
            poll_pending = false;
        }
        boost::system::error_code ignored;
        socket.shutdown(tcp::socket::shutdown_both, ignored);
        socket.close(ignored);
        if (inflight) {
            auto p = std::move(*inflight);
            inflight.reset();
            if (p.command == Command::inquire) poll_pending = false;
            complete(p.done, std::nullopt, "connection lost before the answer: " + why);
        }
        // The login of a lost connection is not sent on the next one (it queues its own).
        std::erase_if(queue, [](const Pending& p) { return p.command == Command::connect; });
        emit(was_up ? NewareEventKind::disconnected : NewareEventKind::connect_failed,
             why + "; reconnecting in " + ms_text(backoff));
        schedule_reconnect();
        arm_deadline();
    }

    // ------------------------------------------------------------------------------------------------------
    // Reading

    void read(std::uint64_t gen) {
        socket.async_read_some(asio::buffer(buffer), [self = shared_from_this(), gen](const boost::system::error_code& ec,
                                                                                      std::size_t n) {
            if (gen != self->generation || !self->running) return;
            if (ec) {
                return self->connection_lost(ec == asio::error::eof ? "the tester closed the connection"
                                                                   : ec.message());
            }
            self->splitter.feed(std::string_view(self->buffer.data(), n));
            while (gen == self->generation) {
                std::optional<std::string> frame;
                try {
                    frame = self->splitter.next();
                } catch (const ProtocolError& e) {
                    self->emit(NewareEventKind::protocol_error, e.what());
                    continue;
                }
                if (!frame) break;
                self->on_frame(*frame);
            }
            if (gen == self->generation) self->read(gen);
        });
    }

    void on_frame(const std::string& frame) {
        const auto received = Clock::now();
        std::optional<Response> response;
        try {
            response = parse_response(frame);
        } catch (const ProtocolError& e) {
            // One request, one answer: a malformed frame is (most likely) the answer to the request in flight.
            emit(NewareEventKind::protocol_error, std::string("malformed frame: ") + e.what());
            if (inflight) finish_inflight(std::nullopt, std::string("malformed answer: ") + e.what(), received);
            return;
        }
        if (const auto* error = std::get_if<ErrorResponse>(&*response)) {
            emit(NewareEventKind::protocol_error, "the tester answered " + error->command + " with an error: " + error->message);
            if (inflight) finish_inflight(std::nullopt, "tester error: " + error->message, received);
            return;
        }
        const Command cmd = response_command(*response);
        if (!inflight || inflight->command != cmd) {
            emit(NewareEventKind::protocol_error,
                 "unexpected " + std::string(command_name(cmd)) + "_resp" +
                     (inflight ? " while waiting for " + std::string(command_name(inflight->command)) + "_resp"
                               : std::string(" with no request outstanding")) +
                     "; ignored");
            return;
        }
        finish_inflight(std::move(response), "", received);
    }

    void finish_inflight(std::optional<Response> response, const std::string& error, Clock::time_point received) {
        auto p = std::move(*inflight);
        inflight.reset();
        arm_deadline();
        if (p.command == Command::inquire && poll_pending && !p.done) {
            poll_pending = false;
            on_poll_answer(response, error, p.sent, received);
        } else {
            complete(p.done, response, error);
        }
        pump();
    }

    // ------------------------------------------------------------------------------------------------------
    // Sending

    void enqueue(Command command, std::string bytes, ResponseDone done) {
        Pending p;
        p.command = command;
        p.bytes = std::move(bytes);
        p.deadline = Clock::now() + options.request_timeout;
        p.done = std::move(done);
        queue.push_back(std::move(p));
        arm_deadline();
        pump();
    }

    void pump() {
        if (inflight || queue.empty() || !socket.is_open()) return;
        // Only the login may go out before the link is up.
        if (link == Link::logging_in ? queue.front().command != Command::connect : link != Link::up) return;
        inflight = std::move(queue.front());
        queue.pop_front();
        inflight->sent = Clock::now();
        auto bytes = std::make_shared<std::string>(inflight->bytes);
        const auto gen = generation;
        asio::async_write(socket, asio::buffer(*bytes),
                          [self = shared_from_this(), bytes, gen](const boost::system::error_code& ec, std::size_t) {
                              if (gen != self->generation || !self->running) return;
                              if (ec) self->connection_lost("send failed: " + ec.message());
                          });
        arm_deadline();
    }

    // One timer for all deadlines: the earliest of the request in flight and the queued ones.
    void arm_deadline() {
        std::optional<Clock::time_point> earliest;
        if (inflight) earliest = inflight->deadline;
        for (const auto& p : queue)
            if (!earliest || p.deadline < *earliest) earliest = p.deadline;
        if (!earliest) {
            deadline_timer.cancel();
            return;
        }
        deadline_timer.expires_at(*earliest);
        deadline_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
            if (!ec && self->running) self->on_deadline();
        });
    }

    void on_deadline() {
        const auto now = Clock::now();
        // Queued requests that could not even be sent in time.
        std::deque<Pending> expired;
        for (auto it = queue.begin(); it != queue.end();) {
            if (it->deadline <= now) {
                expired.push_back(std::move(*it));
                it = queue.erase(it);
            } else {
                ++it;
            }
        }
        for (auto& p : expired) {
            if (p.command == Command::inquire && !p.done) {
                poll_pending = false;
                continue;  // a poll that never went out: the next one will
            }
            const std::string why = std::string(kNotSent) + ms_text(options.request_timeout) +
                                    (link == Link::up ? " (tester busy)" : " (not connected)");
            emit(NewareEventKind::timeout, std::string(command_name(p.command)) + ": " + why);
            complete(p.done, std::nullopt, why);
        }
        if (inflight && inflight->deadline <= now) {
            auto p = std::move(*inflight);
            inflight.reset();
            if (p.command == Command::inquire && !p.done) poll_pending = false;
            const std::string why = "no answer to " + std::string(command_name(p.command)) + " within " +
                                    ms_text(options.request_timeout);
            emit(NewareEventKind::timeout, why);
            complete(p.done, std::nullopt, why);
            // A late answer would be taken for the next request's: start over on a fresh connection.
            connection_lost(why);
            return;
        }
        arm_deadline();
    }

    // ------------------------------------------------------------------------------------------------------
    // Polling and the group

    void schedule_poll() {
        const auto now = Clock::now();
        next_poll += options.poll_period;
        if (next_poll <= now) next_poll = now + options.poll_period;  // fell behind: skip, do not burst
        poll_timer.expires_at(next_poll);
        poll_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
            if (ec || !self->running) return;
            self->poll();
            self->schedule_poll();
        });
    }

    void poll() {
        if (link != Link::up || poll_pending || options.members.empty()) return;
        poll_pending = true;
        enqueue(Command::inquire, encode_request(InquireRequest{options.members, false, true}), {});
    }

    // Member i's entry: by position when the tester answered every channel (field testers sometimes garble
    // the address, e.g. subdevid), otherwise by address.
    std::optional<std::vector<InquireEntry>> match_members(const InquireResponse& r, std::string& error) const {
        std::vector<InquireEntry> out;
        if (r.channels.size() == options.members.size()) {
            for (std::size_t i = 0; i < r.channels.size(); ++i) {
                if (!r.channels[i].channel.same_channel(options.members[i]))
                    spdlog::debug("neware: inquire entry {} is {}, asked for {}", i, r.channels[i].channel.key(),
                                  options.members[i].key());
                out.push_back(r.channels[i]);
            }
            return out;
        }
        for (const auto& m : options.members) {
            const auto it = std::find_if(r.channels.begin(), r.channels.end(),
                                         [&](const InquireEntry& e) { return e.channel.same_channel(m); });
            if (it == r.channels.end()) {
                error = "inquire_resp has no entry for channel " + m.key();
                return std::nullopt;
            }
            out.push_back(*it);
        }
        return out;
    }

    void on_poll_answer(const std::optional<Response>& response, const std::string& error, Clock::time_point sent,
                        Clock::time_point received) {
        if (!response) return;  // already reported (timeout, malformed frame, lost connection)
        const auto* inquire = std::get_if<InquireResponse>(&*response);
        if (inquire == nullptr) return;
        std::string why;
        auto members = match_members(*inquire, why);
        if (!members) {
            emit(NewareEventKind::protocol_error, why);
            return;
        }
        NewareSample sample;
        sample.request_time = sent;
        sample.time = received;
        sample.group = group.update(*members);
        sample.members = std::move(*members);
        if (sample.group.new_fault && sample.group.fault) {
            emit(NewareEventKind::group_fault, sample.group.fault->reason, sample.group.fault);
            if (options.stop_on_group_fault && sample.group.status != ChannelStatus::finish &&
                sample.group.status != ChannelStatus::stop) {
                spdlog::warn("neware: stopping all members after the group fault");
                send_channel_command(Command::stop, {});
            }
        }
        if (options.download_records && recording && link == Link::up) {
            held = std::move(sample);
            poll_pending = true;  // the downloads belong to this poll
            download_member = 0;
            download_next();
            return;
        }
        sample.recording = false;
        episode_log.end("neware " + options.host + ":" + std::to_string(options.port));
        deliver([&] {
            if (sample_cb) sample_cb(sample);
        });
    }

    // Downloads member download_member's new rows (repeating while full answers come back), then the next
    // member's; after the last, joins and delivers the held sample.
    void download_next() {
        if (download_member >= options.members.size()) {
            deliver_held();
            return;
        }
        DownloadRequest r;
        r.channel = options.members[download_member];
        r.testid = test_id;
        r.startpos = next_seq[download_member];
        r.count = kMaxDownloadCount;
        enqueue(Command::download, encode_request(r),
                [weak = weak_from_this(), member = download_member, gen = generation](
                    const std::optional<Response>& response, const std::string& error) {
                    if (const auto self = weak.lock()) self->on_download(member, gen, response, error);
                });
    }

    void on_download(std::size_t member, std::uint64_t gen, const std::optional<Response>& response,
                     const std::string& error) {
        if (!held || gen != generation || member != download_member) return;  // stale (reconnected, restarted)
        const auto* d = response ? std::get_if<DownloadResponse>(&*response) : nullptr;
        if (d == nullptr) {
            if (response) emit(NewareEventKind::protocol_error, "download: unexpected answer");
            else spdlog::debug("neware: download failed ({}); retried next poll", error);
            deliver_held();
            return;
        }
        if (d->testid != test_id) {
            // test_id 0 asked for the latest test from its first row: these rows are it. Otherwise the tester
            // now holds another test than the one we were reading: start over with its rows.
            const bool fresh = test_id == 0;
            test_id = d->testid;
            if (!fresh) {
                emit(NewareEventKind::protocol_error,
                     "download: the tester holds test " + std::to_string(d->testid) + ", not the one started here");
                std::fill(next_seq.begin(), next_seq.end(), 1);
                for (auto& u : unjoined) u.clear();
                download_member = 0;
                download_next();
                return;
            }
        }
        for (const auto& rec : d->records) {
            if (rec.seqid < next_seq[member]) continue;  // already have it
            unjoined[member].push_back(rec);
            next_seq[member] = rec.seqid + 1;
        }
        if (d->records.size() >= static_cast<std::size_t>(kMaxDownloadCount)) {
            download_next();  // more waiting on this member
            return;
        }
        ++download_member;
        download_next();
    }

    // Group rows: every member's row of a seqid (rows a member lacks wait for the next poll).
    std::vector<DownloadRecord> join() {
        std::vector<DownloadRecord> out;
        const std::size_t n = unjoined.size();
        while (true) {
            bool all = n > 0;
            for (const auto& u : unjoined) all = all && !u.empty();
            if (!all) break;
            std::int64_t seq = unjoined[0].front().seqid;
            for (const auto& u : unjoined) seq = std::max(seq, u.front().seqid);
            bool aligned = true;
            for (auto& u : unjoined) {
                while (!u.empty() && u.front().seqid < seq) u.pop_front();  // a row a member never had
                aligned = aligned && !u.empty();
            }
            if (!aligned) break;
            DownloadRecord g = unjoined[0].front();
            g.voltage_v = g.current_a = g.capacity_ah = g.energy_wh = 0.0;
            for (auto& u : unjoined) {
                const auto& r = u.front();
                g.voltage_v += r.voltage_v / static_cast<double>(n);
                g.current_a += r.current_a;
                g.capacity_ah += r.capacity_ah;
                g.energy_wh += r.energy_wh;
                u.pop_front();
            }
            out.push_back(std::move(g));
        }
        return out;
    }

    void deliver_held() {
        poll_pending = false;
        if (!held) return;
        NewareSample sample = std::move(*held);
        held.reset();
        sample.records = join();
        sample.test_id = test_id;
        // The tester records while its test runs; rows of a test that just ended arrive with this sample.
        sample.recording = !sample.records.empty() || sample.group.status == ChannelStatus::working ||
                           sample.group.status == ChannelStatus::pause;
        episode_log.end("neware " + options.host + ":" + std::to_string(options.port));
        deliver([&] {
            if (sample_cb) sample_cb(sample);
        });
    }

    // A start this client made: read the new test's records from its first row.
    void begin_recording() {
        recording = options.download_records;
        test_id = 0;
        next_seq.assign(options.members.size(), 1);
        unjoined.assign(options.members.size(), {});
    }

    // ------------------------------------------------------------------------------------------------------
    // Commands

    static NewareCommandResult command_result(Command command, const std::vector<ChannelAddress>& members,
                                              const std::optional<Response>& response, const std::string& error) {
        NewareCommandResult result;
        if (!response) {
            result.error = error;
            result.never_sent = error.starts_with(kNotSent);
            return result;
        }
        const auto* r = std::get_if<ChannelCommandResponse>(&*response);
        if (r == nullptr || r->command != command) {
            result.error = "unexpected answer";
            return result;
        }
        result.channels = r->channels;
        std::string failed;
        for (std::size_t i = 0; i < members.size(); ++i) {
            const ChannelResult* c = nullptr;
            if (r->channels.size() == members.size()) {
                c = &r->channels[i];
            } else {
                const auto it = std::find_if(r->channels.begin(), r->channels.end(),
                                             [&](const ChannelResult& x) { return x.channel.same_channel(members[i]); });
                if (it != r->channels.end()) c = &*it;
            }
            if (c == nullptr)
                failed += (failed.empty() ? "" : ", ") + members[i].key() + " (no answer)";
            else if (!c->ok)
                failed += (failed.empty() ? "" : ", ") + members[i].key() + " (" + c->text + ")";
        }
        if (!failed.empty()) {
            result.error = std::string(command_name(command)) + " refused by " + failed;
            return result;
        }
        result.ok = true;
        return result;
    }

    void send_channel_command(Command command, CommandDone done, std::string path = {}, std::string barcode = {}) {
        std::string bytes;
        if (command == Command::start) {
            StartRequest r;
            for (const auto& m : options.members) r.entries.push_back({m, path, barcode, ""});
            bytes = encode_request(r);
        } else {
            bytes = encode_request(ChannelListRequest{command, options.members});
        }
        enqueue(command, std::move(bytes),
                [weak = weak_from_this(), command, done = std::move(done)](const std::optional<Response>& response,
                                                                           const std::string& error) {
                    const auto self = weak.lock();
                    if (!self) return;  // the client is gone: nobody waits for the answer
                    auto result = command_result(command, self->options.members, response, error);
                    if (result.ok && command == Command::start) {
                        self->group.reset();  // a new run
                        self->begin_recording();
                    }
                    if (!result.ok) self->emit(NewareEventKind::command_failed, result.error);
                    if (done) done(result);  // (already inside deliver())
                });
    }
};

// -------------------------------------------------------------------------------------------------------------

NewareClient::NewareClient(boost::asio::io_context& io, NewareClientOptions options) {
    // Configuration errors are the caller's, at construction (never later, across the io_context).
    if (options.members.empty() || options.members.size() > 4)
        throw std::invalid_argument("neware: a logical channel has 1 to 4 member channels (BTS parallels up to "
                                    "four), got " + std::to_string(options.members.size()));
    if (options.poll_period <= std::chrono::milliseconds::zero() ||
        options.request_timeout <= std::chrono::milliseconds::zero() ||
        options.connect_timeout <= std::chrono::milliseconds::zero() ||
        options.reconnect_initial <= std::chrono::milliseconds::zero() ||
        options.reconnect_max < options.reconnect_initial)
        throw std::invalid_argument("neware: periods and timeouts must be positive (reconnect_max >= reconnect_initial)");
    impl_ = std::make_shared<Impl>(io, std::move(options));
}

NewareClient::~NewareClient() { stop(); }

void NewareClient::on_sample(std::function<void(const NewareSample&)> callback) {
    std::lock_guard lock(impl_->cb_mutex);
    impl_->sample_cb = std::move(callback);
}

void NewareClient::on_event(std::function<void(const NewareEvent&)> callback) {
    std::lock_guard lock(impl_->cb_mutex);
    impl_->event_cb = std::move(callback);
}

void NewareClient::start() {
    asio::post(impl_->strand, [self = impl_] {
        if (self->running) return;
        {
            std::lock_guard lock(self->cb_mutex);
            if (self->stopped) return;
        }
        self->running = true;
        self->next_poll = Clock::now();
        self->connect();
        self->schedule_poll();
    });
}

void NewareClient::stop() {
    {
        std::lock_guard lock(impl_->cb_mutex);  // waits for a callback in progress on another thread
        if (impl_->stopped) return;
        impl_->stopped = true;
    }
    asio::post(impl_->strand, [self = impl_] {
        self->running = false;
        self->is_connected = false;
        ++self->generation;
        boost::system::error_code ignored;
        self->resolver.cancel();
        self->socket.shutdown(tcp::socket::shutdown_both, ignored);
        self->socket.close(ignored);
        self->poll_timer.cancel();
        self->deadline_timer.cancel();
        self->reconnect_timer.cancel();
        self->connect_timer.cancel();
        self->queue.clear();
        self->inflight.reset();
    });
}

void NewareClient::start_program(std::string step_file_path, std::string barcode, CommandDone done) {
    asio::post(impl_->strand, [self = impl_, path = std::move(step_file_path), barcode = std::move(barcode),
                               done = std::move(done)]() mutable {
        self->send_channel_command(Command::start, std::move(done), std::move(path), std::move(barcode));
    });
}

void NewareClient::stop_program(CommandDone done) {
    asio::post(impl_->strand,
               [self = impl_, done = std::move(done)]() mutable { self->send_channel_command(Command::stop, std::move(done)); });
}

void NewareClient::pause_program(CommandDone done) {
    asio::post(impl_->strand,
               [self = impl_, done = std::move(done)]() mutable { self->send_channel_command(Command::pause, std::move(done)); });
}

void NewareClient::continue_program(CommandDone done) {
    asio::post(impl_->strand, [self = impl_, done = std::move(done)]() mutable {
        self->send_channel_command(Command::continue_, std::move(done));
    });
}

void NewareClient::request(Request request, ResponseDone done) {
    asio::post(impl_->strand, [self = impl_, request = std::move(request), done = std::move(done)]() mutable {
        std::string bytes;
        try {
            bytes = encode_request(request);
        } catch (const ProtocolError& e) {
            self->complete(done, std::nullopt, e.what());
            return;
        }
        self->enqueue(request_command(request), std::move(bytes), std::move(done));
    });
}

void NewareClient::reset_group_fault() {
    asio::post(impl_->strand, [self = impl_] { self->group.reset(); });
}

bool NewareClient::connected() const { return impl_->is_connected; }

}  // namespace cellbench::drivers
