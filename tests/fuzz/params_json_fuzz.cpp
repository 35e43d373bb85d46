// libFuzzer target: a parameter set (cellbench.params/1) as a user hands it to `simulate` and `diagnose`
// (`--params FILE`, hand-edited or written by another tool) must load or throw InputError naming its source. One
// that loads must write and read back unchanged, and the model must simulate a short recording with it to errors
// that are finite, or infinite where the simulation diverged (the caller's error), never NaN and never a crash, a
// hang or undefined behaviour (UBSan: a float-to-integer conversion out of range, ...).
// Input: the file's text.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/model.hpp"
#include "cellbench/estimator/params.hpp"
#include "cellbench/estimator/simulate.hpp"
#include "cellbench/protocol/json_input.hpp"

using namespace cellbench;

namespace {

void check(bool condition) {
    if (!condition) __builtin_trap();
}

const std::string kSource = "fuzz.json";

// Three minutes at 1 s: a rest, 1C and 3C discharge pulses of a 3 Ah cell, a charge pulse, rests between them,
// with surface temperature and heat flux: every path of the model and of compare().
const Recording& recording() {
    static const Recording r = [] {
        Recording rec;
        rec.source = "pulses";
        for (int k = 0; k < 180; ++k) {
            const int phase = k / 20;
            const double i = phase == 1 ? -3.0 : phase == 3 ? -9.0 : phase == 5 ? 3.0 : phase == 7 ? -1.5 : 0.0;
            rec.time_s.push_back(k);
            rec.current_a.push_back(i);
            rec.voltage_v.push_back(3.7 + 0.01 * i);
            rec.surface_c.push_back(25.0 + 0.002 * k);
            rec.heat_flux_w_per_m2.push_back(20.0 * std::abs(i));
        }
        rec.pad_optional_channels();
        return rec;
    }();
    return r;
}

void check_error(const InputError& e) {
    const std::string_view what = e.what();
    check(what.substr(0, kSource.size()) == kSource);
}

void check_stats(const estimator::ErrorStats& s) {
    if (!s.rms) return;
    check(!std::isnan(*s.rms) && *s.rms >= 0);
    check(s.max_abs && !std::isnan(*s.max_abs) && *s.max_abs >= 0);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    estimator::ParameterSet p;
    try {
        p = estimator::ParameterSet::from_json(protocol::parse_json_input(text, kSource), kSource);
    } catch (const InputError& e) {
        check_error(e);
        return 0;
    }
    // What loads writes and reads back unchanged.
    const nlohmann::json written = p.to_json();
    check(estimator::ParameterSet::from_json(written, "written.json").to_json() == written);

    const Recording& rec = recording();
    (void)estimator::start_outside_ocv_range(p, rec);
    (void)estimator::temperature_outside_characterization(p, rec);
    (void)estimator::initial_soc_from_full_charge(p, rec);
    const estimator::CellModel model(p);
    const auto trace = estimator::simulate(model, rec);
    check(trace.voltage_v.size() == rec.size());
    (void)estimator::soc_outside_range(p, trace, rec.source);
    const auto metrics = estimator::compare(p, rec, trace);
    check(metrics.voltage_v.rms.has_value());
    check_stats(metrics.voltage_v);
    check_stats(metrics.temperature_c);
    check_stats(metrics.heat_flux_w);
    const auto bands = estimator::error_bands(p, rec, trace);
    for (const auto* v : {&bands.by_soc, &bands.by_current})
        for (const auto& b : *v) check(b.share_of_time >= 0 && b.share_of_time <= 1.0 + 1e-9);
    return 0;
}
