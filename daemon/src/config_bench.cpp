// The bench configuration (cellbench.bench/1): instruments, simulation, safety limits, fault policies,
// database and API. See config.hpp and config/README.md.
#include "config_reader.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <set>

#include "cellbench/protocol/chamber_modbus.hpp"
#include "cellbench/protocol/dewe_can.hpp"

namespace cellbench::daemon {

using namespace config_read;

BenchConfig parse_bench_config(const json& j, const std::string& source, const fs::path& base_dir) {
    Ctx ctx{source, {}};
    BenchConfig b;
    b.source = source;
    b.config_dir = base_dir;
    b.document = j;

    Obj root(ctx, &j, "$");
    check_schema(root, kBenchSchema);
    b.name = root.string("name", false, false).value_or("");
    b.token_env = root.string("token_env", false).value_or(b.token_env);
    if (root.has("token_env") && !valid_env_name(b.token_env))
        ctx.add("$.token_env", "expected an environment variable name (A-Z, 0-9, _), got \"" + b.token_env + "\"");
    if (const auto listen = root.string("listen", false)) {
        const auto e = parse_endpoint(*listen);
        if (!e || e->port == 0) ctx.add("$.listen", "expected \"HOST:PORT\" with a port 1..65535, got \"" + *listen + "\"");
        else b.listen = *e;
    }

    Obj inst(ctx, root.get("instruments", true), "$.instruments");

    // Cycler.
    {
        Obj c(ctx, inst.get("cycler", true), "$.instruments.cycler");
        if (c.ok()) {
            auto& cy = b.cycler;
            cy.mode = c.choice("mode", true, {"simulated", "tcp"}).value_or(0) == 0 ? CyclerConfig::Mode::simulated
                                                                                  : CyclerConfig::Mode::tcp;
            if (auto e = endpoint_of(c, cy.mode == CyclerConfig::Mode::simulated)) cy.endpoint = *e;
            cy.poll_period_ms = static_cast<int>(c.integer_or("poll_period_ms", 100, 10, 60000));
            cy.response_timeout_ms = static_cast<int>(c.integer_or("response_timeout_ms", 2000, 50, 60000));
            cy.channel_max_current_a = c.number_or("channel_max_current_a", 20.0, Range::positive());
            const json* chans = c.get("channels", true);
            if (chans && (!chans->is_array() || chans->empty())) {
                ctx.add(c.child("channels"), "expected a non-empty array of channel addresses (the parallel group), " + got(*chans));
            } else if (chans) {
                for (std::size_t i = 0; i < chans->size(); ++i) {
                    Obj a(ctx, &(*chans)[i], c.child("channels") + "[" + std::to_string(i) + "]");
                    if (!a.ok()) continue;
                    protocol::neware::ChannelAddress addr;
                    addr.ip = a.string("ip", true).value_or("");
                    addr.devtype = static_cast<int>(a.integer("devtype", true, 0, 255).value_or(0));
                    addr.devid = static_cast<int>(a.integer("devid", true, 0, 65535).value_or(0));
                    addr.subdevid = static_cast<int>(a.integer("subdevid", true, 0, 65535).value_or(0));
                    addr.chlid = static_cast<int>(a.integer("chlid", true, 0, 65535).value_or(0));
                    a.finish();
                    for (const auto& other : cy.channels)
                        if (other == addr) ctx.add(a.path(), "duplicate channel (each member of the group once)");
                    cy.channels.push_back(addr);
                }
                if (cy.channels.size() > 4)
                    ctx.add(c.child("channels"), "expected at most 4 members (Neware parallels up to four channels), got " +
                                                    std::to_string(cy.channels.size()));
            }
            Obj g(ctx, c.get("group"), c.child("group"));
            auto& go = cy.group;
            go.voltage_tolerance_v = g.number_or("voltage_tolerance_v", go.voltage_tolerance_v, Range::positive());
            go.current_share_tolerance = g.number_or("current_share_tolerance", go.current_share_tolerance, Range{0, 1, true, false});
            go.current_share_tolerance_a = g.number_or("current_share_tolerance_a", go.current_share_tolerance_a, Range::non_negative());
            go.min_current_for_sharing_a = g.number_or("min_current_for_sharing_a", go.min_current_for_sharing_a, Range::non_negative());
            go.fault_after_samples = static_cast<int>(g.integer_or("fault_after_samples", go.fault_after_samples, 1, 100));
            g.finish();
        }
        c.finish();
    }

    // DAQ.
    {
        Obj d(ctx, inst.get("daq", true), "$.instruments.daq");
        if (d.ok()) {
            auto& dq = b.daq;
            dq.mode = d.choice("mode", true, {"simulated", "can"}).value_or(0) == 0 ? DaqConfig::Mode::simulated
                                                                                 : DaqConfig::Mode::can;
            dq.transport = d.choice("transport", true, {"can-dgram", "socketcan"}).value_or(0) == 0
                               ? DaqConfig::Transport::can_dgram
                               : DaqConfig::Transport::socketcan;
            if (dq.transport == DaqConfig::Transport::can_dgram) {
                dq.socket_path = d.string("socket_path", true).value_or("");
                if (dq.socket_path.size() >= 108)  // sizeof(sockaddr_un::sun_path)
                    ctx.add(d.child("socket_path"), "expected a path shorter than 108 bytes (Unix socket limit)");
                if (d.has("interface")) ctx.add(d.child("interface"), "only for transport \"socketcan\" (this one is \"can-dgram\")");
                d.get("interface");
            } else {
                dq.interface = d.string("interface", true).value_or("");
                if (dq.interface.size() >= 16)  // IFNAMSIZ
                    ctx.add(d.child("interface"), "expected an interface name shorter than 16 bytes");
                if (d.has("socket_path")) ctx.add(d.child("socket_path"), "only for transport \"can-dgram\" (this one is \"socketcan\")");
                d.get("socket_path");
            }
            if (const json* layout = d.get("layout")) {
                try {
                    dq.layout = protocol::DeweCanLayout::from_json(*layout, kNestedMarker).to_json();
                } catch (const InputError& e) {
                    ctx.add_nested(d.child("layout"), kNestedMarker, e.what());
                }
            } else {
                dq.layout = protocol::DeweCanLayout::bench_default().to_json();
            }
            // Sensitivity of a thermopile heat flux sensor: microvolts per W/m^2 (the thesis' FHF05: 17.39e-6).
            dq.sensitivity_v_per_w_per_m2 =
                d.number("sensitivity_v_per_w_per_m2", true, Range{0.0, 1e-3, true, false}).value_or(dq.sensitivity_v_per_w_per_m2);
            dq.sensor_area_m2 = d.number("sensor_area_m2", true, Range{0.0, 1.0, true, false}).value_or(dq.sensor_area_m2);
            dq.cell_area_m2 = d.number("cell_area_m2", true, Range{0.0, 1.0, true, false}).value_or(dq.cell_area_m2);
            dq.stale_after_s = d.number_or("stale_after_s", dq.stale_after_s, Range::positive());
        }
        d.finish();
    }

    // Chamber.
    {
        Obj c(ctx, inst.get("chamber", true), "$.instruments.chamber");
        if (c.ok()) {
            auto& ch = b.chamber;
            ch.mode = c.choice("mode", true, {"simulated", "modbus-tcp"}).value_or(0) == 0 ? ChamberConfig::Mode::simulated
                                                                                        : ChamberConfig::Mode::modbus_tcp;
            if (auto e = endpoint_of(c, ch.mode == ChamberConfig::Mode::simulated)) ch.endpoint = *e;
            ch.unit_id = static_cast<int>(c.integer_or("unit_id", 1, 0, 247));
            ch.poll_period_ms = static_cast<int>(c.integer_or("poll_period_ms", 1000, 50, 60000));
            bool map_ok = true;
            protocol::ChamberRegisterMap map = protocol::ChamberRegisterMap::bench_default();
            if (const json* rm = c.get("register_map")) {
                try {
                    map = protocol::ChamberRegisterMap::from_json(*rm, kNestedMarker);
                } catch (const InputError& e) {
                    ctx.add_nested(c.child("register_map"), kNestedMarker, e.what());
                    map_ok = false;
                }
            }
            ch.register_map = map.to_json();
            ch.setpoint_min_c = map.setpoint_min_c;
            ch.setpoint_max_c = map.setpoint_max_c;
            if (const auto safe = c.number("safe_setpoint_c", true)) {
                ch.safe_setpoint_c = *safe;
                if (map_ok && (*safe < ch.setpoint_min_c || *safe > ch.setpoint_max_c))
                    ctx.add(c.child("safe_setpoint_c"), "expected a set point the chamber accepts (" +
                                                            format_number(ch.setpoint_min_c) + ".." +
                                                            format_number(ch.setpoint_max_c) + " degC), got " + format_number(*safe));
            }
        }
        c.finish();
    }
    inst.finish();

    // Simulation (needed as soon as one instrument is simulated).
    if (const json* sj = root.get("simulation")) {
        Obj s(ctx, sj, "$.simulation");
        SimulationConfig sim;
        sim.time_scale = s.number_or("time_scale", 1.0, Range{0.0, 100000.0, true, false});
        sim.seed = static_cast<std::uint32_t>(s.integer_or("seed", 1, 0, 4294967295LL));
        if (const auto p = s.string("params", true)) {
            sim.params_path = resolve(base_dir, *p);
            check_params_file(ctx, s.child("params"), sim.params_path);
        }
        sim.initial_soc = s.number_or("initial_soc", 1.0, Range::closed(0.0, 1.0));
        sim.initial_temperature_c = s.number_or("initial_temperature_c", 25.0, Range::closed(-40.0, 80.0));
        if (const json* h = s.get("hidden")) {
            if (!h->is_object()) ctx.add(s.child("hidden"), "expected an object of hidden effects, " + got(*h));
            else sim.hidden = *h;
        }
        s.finish();
        b.simulation = sim;
    } else if (b.any_simulated()) {
        ctx.add("$.simulation", "missing (required when an instrument's mode is \"simulated\")");
    }

    // Safety limits.
    {
        Obj s(ctx, root.get("safety", true), "$.safety");
        auto& l = b.safety;
        const auto tmax = s.number("max_temperature_c", true, Range::closed(-40.0, 150.0));
        l.max_temperature_c = tmax.value_or(l.max_temperature_c);
        // Limits against each other: a run that ends or aborts sends the chamber to safe_setpoint_c, and the
        // simulated chamber starts at initial_temperature_c; either at or above the limit aborts every run at
        // once and heats the cell past its maximum on the way out.
        if (tmax && *tmax <= b.chamber.safe_setpoint_c)
            ctx.add("$.safety.max_temperature_c", "expected above the chamber's safe_setpoint_c (" +
                                                      format_number(b.chamber.safe_setpoint_c) + " degC), got " +
                                                      format_number(*tmax) + " degC");
        if (tmax && b.simulation && b.chamber.mode == ChamberConfig::Mode::simulated &&
            *tmax <= b.simulation->initial_temperature_c)
            ctx.add("$.safety.max_temperature_c", "expected above the simulated chamber's initial_temperature_c (" +
                                                      format_number(b.simulation->initial_temperature_c) + " degC), got " +
                                                      format_number(*tmax) + " degC");
        const auto vmin = s.number("min_voltage_v", true, Range{0.0, 10.0, false, false});
        const auto vmax = s.number("max_voltage_v", true, Range{0.0, 10.0, true, false});
        if (vmin) l.min_voltage_v = *vmin;
        if (vmax) l.max_voltage_v = *vmax;
        if (vmin && vmax && !(*vmin < *vmax))
            ctx.add("$.safety", "expected min_voltage_v < max_voltage_v, got " + format_number(*vmin) + " and " + format_number(*vmax));
        l.max_current_a = s.number("max_current_a", true, Range::positive()).value_or(l.max_current_a);
        l.chamber_deviation_c = s.number_or("chamber_deviation_c", l.chamber_deviation_c, Range::positive());
        l.instrument_loss_grace_s = s.number_or("instrument_loss_grace_s", l.instrument_loss_grace_s, Range::positive());
        s.finish();
        if (b.cycler.channels.size() > 0 && l.max_current_a > b.cycler.group_max_current_a() * 1.0000001)
            ctx.add("$.safety.max_current_a", "expected at most what the cycler group can carry (" +
                                                  format_number(b.cycler.group_max_current_a()) + " A = " +
                                                  std::to_string(b.cycler.channels.size()) + " x channel_max_current_a), got " +
                                                  format_number(l.max_current_a));
    }

    // Fault policy (optional): per instrument; every grace defaults to safety.instrument_loss_grace_s.
    {
        auto& fp = b.faults;
        const double grace = b.safety.instrument_loss_grace_s;
        fp.cycler.grace_s = fp.chamber.grace_s = fp.daq.grace_s = grace;
        Obj p(ctx, root.get("fault_policy"), "$.fault_policy");
        {
            Obj c(ctx, p.get("cycler"), "$.fault_policy.cycler");
            fp.cycler.grace_s = c.number_or("grace_s", grace, Range::positive());
            const auto lo = c.integer("reconnect_initial_ms", false, 1, 600000);
            const auto hi = c.integer("reconnect_max_ms", false, 1, 600000);
            if (lo) fp.cycler.reconnect_initial_ms = static_cast<int>(*lo);
            if (hi) fp.cycler.reconnect_max_ms = static_cast<int>(*hi);
            if (fp.cycler.reconnect_max_ms < fp.cycler.reconnect_initial_ms)
                ctx.add(c.path(), "expected reconnect_initial_ms <= reconnect_max_ms, got " +
                                      std::to_string(fp.cycler.reconnect_initial_ms) + " and " +
                                      std::to_string(fp.cycler.reconnect_max_ms));
            c.finish();
        }
        {
            Obj c(ctx, p.get("chamber"), "$.fault_policy.chamber");
            auto& ch = fp.chamber;
            ch.grace_s = c.number_or("grace_s", grace, Range::positive());
            ch.response_timeout_ms = static_cast<int>(c.integer_or("response_timeout_ms", ch.response_timeout_ms, 10, 60000));
            ch.retries = static_cast<int>(c.integer_or("retries", ch.retries, 0, 10));
            if (const auto a = c.choice("exception_response", false, {"reconnect", "abort"}))
                ch.exception_response = *a == 0 ? FaultAction::reconnect : FaultAction::abort;
            ch.setpoint_tolerance_c = c.number_or("setpoint_tolerance_c", ch.setpoint_tolerance_c, Range::positive());
            ch.setpoint_timeout_s = c.number_or("setpoint_timeout_s", ch.setpoint_timeout_s, Range::positive());
            if (const auto a = c.choice("setpoint_not_reached", false, {"event", "abort"}))
                ch.setpoint_not_reached = *a == 0 ? SetpointAction::event : SetpointAction::abort;
            c.finish();
        }
        {
            Obj d(ctx, p.get("daq"), "$.fault_policy.daq");
            fp.daq.grace_s = d.number_or("grace_s", grace, Range::positive());
            fp.daq.loss_event_interval_s = d.number_or("loss_event_interval_s", fp.daq.loss_event_interval_s, Range::positive());
            d.finish();
            // The stream is declared silent after stale_after_s; a grace shorter than that could never see it.
            if (b.daq.stale_after_s > fp.daq.grace_s)
                ctx.add("$.fault_policy.daq.grace_s", "expected at least instruments.daq.stale_after_s (" +
                                                          format_number(b.daq.stale_after_s) + " s), got " +
                                                          format_number(fp.daq.grace_s));
        }
        p.finish();
    }

    // Database.
    {
        Obj d(ctx, root.get("database", true), "$.database");
        if (const auto p = d.string("path", true)) b.database.path = *p;
        // The flush period bounds what kill -9 can lose; the reliability goal is at most 1 s.
        b.database.flush_period_ms = static_cast<int>(d.integer_or("flush_period_ms", 200, 10, 500));
        b.database.queue_capacity_samples =
            static_cast<std::size_t>(d.integer_or("queue_capacity_samples", 500000, 1000, 100000000));
        d.finish();
    }
    root.finish();

    ctx.throw_if_any();
    return b;
}

BenchConfig parse_bench_config_text(std::string_view text, const std::string& source, const fs::path& base_dir) {
    return parse_bench_config(parse_json_text(text, source), source, base_dir);
}

BenchConfig load_bench_config(const fs::path& file) {
    const std::string text = read_text_file(file);
    fs::path dir = file.parent_path();
    if (dir.empty()) dir = ".";
    return parse_bench_config_text(text, file.string(), dir);
}

}  // namespace cellbench::daemon
