#include <cmath>
#include <cstdio>
#include <utility>

#include <spdlog/spdlog.h>

#include "cellbench/estimator/logger_timing.hpp"
#include "cellbench/estimator/voltage_spikes.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

nlohmann::json metrics_to_json(const estimator::SimulationMetrics& m) {
    auto quantity = [](const estimator::ErrorStats& e, const char* rms_key, const char* max_key) -> nlohmann::json {
        if (!e.rms) return nullptr;
        return {{rms_key, *e.rms}, {max_key, *e.max_abs}};
    };
    return {{"schema", "cellbench.metrics/1"},
            {"samples", m.samples},
            {"voltage", quantity(m.voltage_v, "rms_v", "max_abs_v")},
            {"temperature", quantity(m.temperature_c, "rms_c", "max_abs_c")},
            {"heat_flux", quantity(m.heat_flux_w, "rms_w", "max_abs_w")}};
}

int run_simulate(const SimulateOptions& o) {
    OutputFiles outputs({o.metrics_json, o.output});  // folders checked before the work, all written or none
    const auto params = load_params(o.params);
    auto rec = load_recording(o.recording);
    if (auto reversed = estimator::reversed_current_text(rec); !reversed.empty()) throw InputError(reversed);
    // The recording as `fit` and `diagnose` read it: rows at current steps that read the step's voltage beside the
    // current before it take the next row's current (the model's input), voltage spikes of one to three rows the
    // voltage between the rows either side.
    for (const auto& note : estimator::correct_logging_artifacts(rec)) spdlog::warn("{}", note);
    if (const auto lag = estimator::voltage_lag_text(rec); !lag.empty())
        spdlog::warn("{}: at every current step part of the error is the logger's timing, not the model's", lag);
    if (!o.initial_soc)
        if (const auto warning = estimator::start_outside_ocv_range(params, rec); !warning.empty()) spdlog::warn("{}", warning);
    if (const auto warning = estimator::temperature_outside_characterization(params, rec); !warning.empty())
        spdlog::warn("{}", warning);
    const estimator::CellModel model(params);
    estimator::SimulationOptions so;
    so.initial_soc = o.initial_soc;
    so.ambient_c = o.ambient_c;
    std::string initial_soc_source = o.initial_soc ? "given" : "first row";
    const auto full = o.initial_soc ? std::nullopt : estimator::initial_soc_from_full_charge(params, rec);
    if (full) {
        so.initial_soc = full->soc;
        initial_soc_source = fmt::format("counted back from the full charge ending at {:.0f} s", full->full_time_s);
        spdlog::info("{}: it charges the cell to full at {:.0f} s before any discharge: initial SOC {:.3f} counted back "
                     "from there (the SOC at the end of a full charge is 1, as the fit's), where its first voltage gives "
                     "{:.3f}; give --initial-soc to set it",
                     o.recording, full->full_time_s, full->soc, full->first_row_soc);
    } else if (const auto start = estimator::fit_initial_soc_under_load(model, rec, so)) {
        so.initial_soc = start->soc;
        initial_soc_source = fmt::format("fitted to the first {:.0f} s", start->window_s);
        spdlog::info("{}: it starts under load ({:.3g} A), so its first voltage does not give its SOC: initial SOC "
                     "{:.3f} fitted to its first {:.0f} s ({:.1f} mV RMS there; {:.3f} from that voltage less R0 I, "
                     "{:.1f} mV); give --initial-soc to set it",
                     o.recording, rec.current_a[0], start->soc, start->window_s, 1e3 * start->rms_v, start->guess_soc,
                     1e3 * start->guess_rms_v);
    }
    const auto trace = estimator::simulate(model, rec, so);
    const auto metrics = estimator::compare(params, rec, trace);
    if (const auto warning = estimator::soc_outside_range(params, trace, rec.source); !warning.empty())
        spdlog::warn("{} (--initial-soc sets it)", warning);
    spdlog::info("simulated {} samples ({:.0f} s) from SOC {:.3f}, ambient {:.2f} degC{}", rec.size(),
                 rec.time_s.back() - rec.time_s.front(), trace.initial_soc, trace.ambient_c,
                 rec.has_ambient() ? " (measured)" : " (constant)");

    // A non-finite error (an overflowing input, a diverging model) is never printed as "RMS inf" nor written as
    // null: it is an error saying which quantity.
    for (const auto& [name, e] : {std::pair<const char*, const estimator::ErrorStats*>{"voltage", &metrics.voltage_v},
                                  {"temperature", &metrics.temperature_c},
                                  {"heat flux", &metrics.heat_flux_w}})
        if (e->rms && (!std::isfinite(*e->rms) || !std::isfinite(*e->max_abs)))
            throw InputError(o.recording + ": the " + name +
                             " error of the simulation is not a finite number: the recording holds values the "
                             "model cannot follow (check it for extreme values) or the parameters " +
                             o.params + " make the model unstable");
    auto line = [](const char* name, const estimator::ErrorStats& e, double scale, const char* unit) {
        if (e.rms)
            std::printf("%-12s RMS %8.4f %-4s max |err| %8.4f %s\n", name, *e.rms * scale, unit, *e.max_abs * scale, unit);
        else
            std::printf("%-12s not measured in this recording\n", name);
    };
    std::printf("samples      %zu\n", metrics.samples);
    line("voltage", metrics.voltage_v, 1000.0, "mV");
    line("temperature", metrics.temperature_c, 1.0, "degC");
    line("heat flux", metrics.heat_flux_w, 1.0, "W");

    // Where the voltage error lies: by SOC band and by current band (bias = mean error, simulated minus measured).
    const auto bands = estimator::error_bands(params, rec, trace);
    auto band_lines = [](const char* title, const std::vector<estimator::ErrorBand>& v) {
        if (v.empty()) return;
        std::printf("%s\n", title);
        for (const auto& b : v)
            std::printf("  %-20s %5.1f %% of the time  RMS %8.2f mV  bias %+8.2f mV\n", b.name.c_str(),
                        100 * b.share_of_time, 1e3 * b.voltage_rms_v, 1e3 * b.voltage_mean_v);
    };
    band_lines("voltage error by SOC band (simulated SOC):", bands.by_soc);
    band_lines("voltage error by current band (C-rate of the parameter set's capacity):", bands.by_current);

    if (!o.metrics_json.empty()) {
        auto j = metrics_to_json(metrics);
        auto band_json = [](const std::vector<estimator::ErrorBand>& v) {
            auto a = nlohmann::json::array();
            for (const auto& b : v)
                a.push_back({{"band", b.name}, {"share_of_time", b.share_of_time}, {"voltage_rms_v", b.voltage_rms_v},
                             {"voltage_mean_v", b.voltage_mean_v}});
            return a;
        };
        j["voltage_by_soc_band"] = band_json(bands.by_soc);
        j["voltage_by_current_band"] = band_json(bands.by_current);
        j["initial_soc"] = trace.initial_soc;
        j["initial_soc_source"] = initial_soc_source;
        outputs.write_json(o.metrics_json, j);
    }
    if (!o.output.empty()) {
        std::vector<protocol::ExtraColumn> extra = {
            {"Simulated Voltage / V", &trace.voltage_v},
            {"Simulated Surface Temperature / degC", &trace.temperature_c},
            {"Simulated Heat Flow / W", &trace.heat_flow_out_w},
            {"Simulated SOC / 1", &trace.soc},
            {"Simulated OCV / V", &trace.ocv_v},
        };
        outputs.write(o.output, [&](std::ostream& out) { protocol::write_bdf_csv(out, rec, extra); });
    }
    outputs.commit();
    return 0;
}

}  // namespace cellbench::cli
