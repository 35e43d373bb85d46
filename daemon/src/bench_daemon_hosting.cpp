// Hosting the simulated instruments (the plant and its servers, on ephemeral ports and a per-process socket)
// and connecting the drivers to them or to the real instruments.
#include "bench_daemon_impl.hpp"

#include <algorithm>
#include <boost/asio/post.hpp>

namespace cellbench::daemon {

void BenchDaemon::Impl::host_simulation() {
    if (!cfg.any_simulated()) return;
    if (!cfg.simulation) throw InputError(cfg.source.string() + ": $.simulation: missing (simulated instruments need a cell)");
    const auto& simc = *cfg.simulation;
    const sim::PlantOptions po = simulated_plant_options(cfg, load_param_file(simc.params_path));
    plant.emplace(po);

    if (cfg.cycler.mode == CyclerConfig::Mode::simulated) {
        sim::NewareServerOptions no;
        // Hosted: an ephemeral port (the configured one is for a tester outside the daemon), so two
        // daemons, or a daemon beside `cellbench sim`, never collide.
        no.host = cfg.cycler.endpoint.host;
        no.port = 0;
        no.max_channel_current_a = cfg.cycler.channel_max_current_a;
        no.cell_channels.clear();
        for (const auto& ch : cfg.cycler.channels) no.cell_channels.push_back(ch.chlid);
        if (!cfg.cycler.channels.empty()) {
            const auto& a = cfg.cycler.channels.front();
            no.ip = a.ip;
            no.devtype = a.devtype;
            no.devid = a.devid;
            no.subdevid = a.subdevid;
        }
        // The tester's execution bursts (time_scale x timer period of bench time) bound how close to a
        // current step the first reading after it can be: keep them near the poll period.
        no.timer_period_ms = static_cast<int>(std::clamp<std::int64_t>(
            wall_period(cfg.cycler.poll_period_ms, scale).count(), 1, 5));
        neware_server = std::make_unique<sim::NewareServer>(*plant, clock, no);
        neware_server->start();
        spdlog::info("simulated neware (hosted) listening on {}", neware_server->description());
    }
    if (cfg.chamber.mode == ChamberConfig::Mode::simulated) {
        sim::ChamberServerOptions co;
        co.host = cfg.chamber.endpoint.host;
        co.port = 0;  // hosted: an ephemeral port (see the cycler)
        if (!cfg.chamber.register_map.is_null() && !cfg.chamber.register_map.empty())
            co.map = protocol::ChamberRegisterMap::from_json(cfg.chamber.register_map,
                                                             cfg.source.string() + " $.instruments.chamber.register_map");
        chamber_server = std::make_unique<sim::ChamberServer>(*plant, clock, co);
        chamber_server->start();
        spdlog::info("simulated chamber (hosted) listening on {}", chamber_server->description());
    }
    if (cfg.daq.mode == DaqConfig::Mode::simulated) {
        drivers::CanEndpoint ep = daq_endpoint();
        sim::DewePublisherOptions dopt;
        if (!cfg.daq.layout.is_null() && !cfg.daq.layout.empty())
            dopt.layout = protocol::DeweCanLayout::from_json(cfg.daq.layout, cfg.source.string() + " $.instruments.daq.layout");
        if (opt.daq_sample_rate_hz) dopt.sample_rate_hz = *opt.daq_sample_rate_hz;
        dewe_publisher = std::make_unique<sim::DewePublisher>(io, *plant, clock, drivers::open_can_publisher(io, ep), dopt);
        dewe_publisher->start();
        spdlog::info("simulated dewe (hosted) sending to {}", dewe_publisher->description());
    }
}

drivers::CanEndpoint BenchDaemon::Impl::daq_endpoint() const {
    drivers::CanEndpoint ep;
    ep.kind = cfg.daq.transport == DaqConfig::Transport::socketcan ? drivers::CanEndpoint::Kind::socketcan
                                                                   : drivers::CanEndpoint::Kind::can_dgram;
    ep.name = ep.kind == drivers::CanEndpoint::Kind::socketcan ? cfg.daq.interface
                                                               : opt.daq_socket_path.value_or(cfg.daq.socket_path);
    // A hosted simulated DAQ on a datagram socket: a path of this process (the configured one is for a
    // publisher outside the daemon), so two daemons never take each other's socket.
    if (ep.kind == drivers::CanEndpoint::Kind::can_dgram && cfg.daq.mode == DaqConfig::Mode::simulated &&
        !opt.daq_socket_path)
        ep.name = hosted_daq_path;
    return ep;
}

void BenchDaemon::Impl::connect_drivers() {
    // Cycler.
    drivers::NewareClientOptions no;
    no.host = cfg.cycler.endpoint.host;
    no.port = neware_server ? neware_server->port() : cfg.cycler.endpoint.port;
    no.members = cfg.cycler.channels;
    no.poll_period = wall_period(cfg.cycler.poll_period_ms, scale);  // poll periods are bench time
    no.request_timeout = std::chrono::milliseconds(cfg.cycler.response_timeout_ms);
    no.reconnect_initial = std::chrono::milliseconds(cfg.faults.cycler.reconnect_initial_ms);
    no.reconnect_max = std::chrono::milliseconds(cfg.faults.cycler.reconnect_max_ms);
    no.group = cfg.cycler.group;
    neware = std::make_unique<drivers::NewareClient>(io, no);
    cycler_instrument = &instruments.add(std::make_unique<instruments::NewareInstrument>(*neware, neware_server.get()));
    cycler_instrument->set_address(no.host + ":" + std::to_string(no.port));
    cycler_instrument->on_reading([this](const drivers::NewareSample& s) { on_neware_sample(s); });
    neware->on_event([this](const drivers::NewareEvent& e) { on_neware_event(e); });

    // Chamber.
    drivers::ChamberClientOptions co;
    co.host = cfg.chamber.endpoint.host;
    co.port = chamber_server ? chamber_server->port() : cfg.chamber.endpoint.port;
    co.unit_id = cfg.chamber.unit_id;
    if (!cfg.chamber.register_map.is_null() && !cfg.chamber.register_map.empty())
        co.map = protocol::ChamberRegisterMap::from_json(cfg.chamber.register_map,
                                                         cfg.source.string() + " $.instruments.chamber.register_map");
    co.poll_interval = wall_period(cfg.chamber.poll_period_ms, scale);
    // Modbus answer timeout and retries are wall time (the link's, not the bench's); the set point watch is
    // bench time.
    co.response_timeout = std::chrono::milliseconds(cfg.faults.chamber.response_timeout_ms);
    co.retries = cfg.faults.chamber.retries;
    co.setpoint_tolerance_c = cfg.faults.chamber.setpoint_tolerance_c;
    co.setpoint_timeout = std::chrono::milliseconds(static_cast<std::int64_t>(
        std::max(1.0, cfg.faults.chamber.setpoint_timeout_s * 1e3 / scale)));
    chamber = std::make_unique<drivers::ChamberClient>(io, co);
    chamber_instrument = &instruments.add(std::make_unique<instruments::ChamberInstrument>(*chamber, chamber_server.get()));
    chamber_instrument->set_address(co.host + ":" + std::to_string(co.port));
    chamber_instrument->on_reading([this](const drivers::ChamberStatus& s) { on_chamber_status(s); });
    chamber->on_fault([this](const drivers::ChamberFault& f) { on_chamber_fault(f); });

    // DAQ.
    const auto ep = daq_endpoint();
    drivers::DeweDriverOptions dopt;
    if (!cfg.daq.layout.is_null() && !cfg.daq.layout.empty())
        dopt.layout = protocol::DeweCanLayout::from_json(cfg.daq.layout, cfg.source.string() + " $.instruments.daq.layout");
    dopt.sensitivity_v_per_w_per_m2 = cfg.daq.sensitivity_v_per_w_per_m2;
    dopt.area_m2 = cfg.daq.cell_area_m2;
    // At least 1 s of wall time: a loaded host (or the simulated DAQ's timer at a high time scale) can hold a
    // healthy stream back for a few hundred ms, which must not read as silence (faults' grace floors at 3 s).
    dopt.silence_timeout = std::chrono::milliseconds(static_cast<std::int64_t>(
        std::max(1000.0, 1000.0 * cfg.daq.stale_after_s / scale)));
    std::shared_ptr<drivers::CanTransport> transport =
        ep.kind == drivers::CanEndpoint::Kind::can_dgram
            ? drivers::open_can_dgram_listener(io, ep.name, std::chrono::milliseconds(200))
            : drivers::open_can_listener(io, ep);
    dewe = std::make_unique<drivers::DeweDriver>(io, transport, dopt);
    daq_instrument = &instruments.add(std::make_unique<instruments::DeweInstrument>(*dewe, dewe_publisher.get()));
    daq_instrument->set_address((ep.kind == drivers::CanEndpoint::Kind::socketcan ? "can " : "can-dgram ") + ep.name);
    daq_instrument->on_reading([this](const drivers::DeweReading& r) { on_dewe_sample(r); });
    dewe->on_health([this](const drivers::DeweHealth& h) { on_dewe_health(h); });

    // Started once all are registered: a driver's first callbacks may already look instruments up.
    instruments.start_all();
}

}  // namespace cellbench::daemon
