#include "cellbench/core/recording.hpp"

#include <algorithm>

namespace cellbench {

bool Recording::has_values(const std::vector<double>& channel) {
    return std::any_of(channel.begin(), channel.end(), [](double v) { return std::isfinite(v); });
}

namespace {
template <typename T>
std::vector<T> sub(const std::vector<T>& v, std::size_t b, std::size_t e) {
    if (v.empty()) return {};
    return std::vector<T>(v.begin() + static_cast<std::ptrdiff_t>(b), v.begin() + static_cast<std::ptrdiff_t>(e));
}
template <typename T>
void pad(std::vector<T>& v, std::size_t n, const T& fill) {
    if (!v.empty() && v.size() < n) v.resize(n, fill);
}
}  // namespace

Recording Recording::slice(std::size_t begin, std::size_t end) const {
    end = std::min(end, size());
    begin = std::min(begin, end);
    Recording r;
    r.source = source;
    r.time_s = sub(time_s, begin, end);
    r.voltage_v = sub(voltage_v, begin, end);
    r.current_a = sub(current_a, begin, end);
    r.unix_time_s = sub(unix_time_s, begin, end);
    r.step_count = sub(step_count, begin, end);
    r.cycle_count = sub(cycle_count, begin, end);
    r.step_type = sub(step_type, begin, end);
    r.ambient_c = sub(ambient_c, begin, end);
    r.surface_c = sub(surface_c, begin, end);
    r.t1_c = sub(t1_c, begin, end);
    r.t2_c = sub(t2_c, begin, end);
    r.heat_flux_w_per_m2 = sub(heat_flux_w_per_m2, begin, end);
    return r;
}

void Recording::pad_optional_channels() {
    const auto n = size();
    for (auto* ch : {&unix_time_s, &step_count, &cycle_count, &ambient_c, &surface_c, &t1_c, &t2_c,
                     &heat_flux_w_per_m2})
        pad(*ch, n, kNaN);
    pad(step_type, n, std::string{});
}

bool Recording::take_t1_as_surface() {
    if (has_surface() || !has_values(t1_c)) return false;
    surface_c = t1_c;
    return true;
}

}  // namespace cellbench
