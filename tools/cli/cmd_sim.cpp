// `cellbench sim`: the simulated bench as its own process, the way real instruments are separate boxes (a
// Neware BTS API server, a Modbus TCP chamber and the DEWE-43A CAN stream, sharing one simulated cell and
// chamber air). Prints one line per instrument as soon as it accepts connections; runs until SIGTERM.
#include <utility>  // before Boost.Asio: Boost 1.74 + g++ 12 in C++20 needs std::exchange declared
#include <csignal>
#include <cstdio>

#include <boost/asio.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/daemon/bench_daemon.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/drivers/can_transport.hpp"
#include "cellbench/sim/chamber_server.hpp"
#include "cellbench/sim/dewe_publisher.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/plant.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

int run_sim(const SimOptions& o) {
    const auto cfg = daemon::load_bench_config(o.config);
    if (!cfg.simulation) throw InputError(o.config + ": $.simulation: missing (the simulated bench needs a cell to simulate)");
    const auto& simc = *cfg.simulation;
    const double scale = o.time_scale.value_or(simc.time_scale);
    if (!(scale > 0)) throw InputError("--time-scale: expected a positive number of bench seconds per wall second");
    sim::BenchPlant plant(daemon::simulated_plant_options(cfg, load_params(simc.params_path)));
    auto clock = std::make_shared<sim::BenchClock>(scale);

    boost::asio::io_context io;
    // SIGTERM is ours before the first instrument line: a client may act on that line and stop the bench at once
    // (the hil test did, under load: the signal came before the set existed and killed the process).
    boost::asio::signal_set signals(io, SIGINT, SIGTERM);
    sim::NewareServerOptions no;
    no.host = cfg.cycler.endpoint.host;
    no.port = cfg.cycler.endpoint.port;
    sim::NewareServer neware(plant, clock, no);
    neware.start();
    std::printf("neware %s\n", neware.description().c_str());
    std::fflush(stdout);

    sim::ChamberServerOptions co;
    co.host = cfg.chamber.endpoint.host;
    co.port = cfg.chamber.endpoint.port;
    if (!cfg.chamber.register_map.is_null() && !cfg.chamber.register_map.empty())
        co.map = protocol::ChamberRegisterMap::from_json(cfg.chamber.register_map, o.config + " $.instruments.chamber.register_map");
    sim::ChamberServer chamber(plant, clock, co);
    chamber.start();
    std::printf("chamber %s\n", chamber.description().c_str());
    std::fflush(stdout);

    drivers::CanEndpoint ep;
    ep.kind = cfg.daq.transport == daemon::DaqConfig::Transport::socketcan ? drivers::CanEndpoint::Kind::socketcan
                                                                           : drivers::CanEndpoint::Kind::can_dgram;
    ep.name = ep.kind == drivers::CanEndpoint::Kind::socketcan ? cfg.daq.interface : cfg.daq.socket_path;
    sim::DewePublisherOptions dopt;
    if (!cfg.daq.layout.is_null() && !cfg.daq.layout.empty())
        dopt.layout = protocol::DeweCanLayout::from_json(cfg.daq.layout, o.config + " $.instruments.daq.layout");
    sim::DewePublisher dewe(io, plant, clock, drivers::open_can_publisher(io, ep), dopt);
    dewe.start();
    // INTERFACES.md: "dewe can vcan0", or "dewe can-dgram SOCKET_PATH" where the kernel has no AF_CAN.
    std::printf("dewe %s %s\n", ep.kind == drivers::CanEndpoint::Kind::socketcan ? "can" : "can-dgram", ep.name.c_str());
    std::fflush(stdout);
    spdlog::info("simulated bench running at {}x bench time; SIGTERM stops it", scale);

    signals.async_wait([&](const boost::system::error_code&, int) {
        dewe.stop();
        chamber.stop();
        neware.stop();
        io.stop();
    });
    io.run();
    return 0;
}

}  // namespace cellbench::cli
