#pragma once
// Deterministic random streams: one per (seed, purpose), so that adding an effect or a recording never shifts the
// numbers another part of the plant draws.
#include <cmath>
#include <cstdint>
#include <random>

namespace cellbench::plant {

inline std::uint64_t splitmix64(std::uint64_t x) {
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

class Rng {
public:
    Rng(std::uint64_t seed, std::uint64_t stream) : engine_(splitmix64(splitmix64(seed) ^ (stream * 0xD1B54A32D192ED03ull))) {}
    // Own conversions (not std::uniform_real_distribution), so the numbers do not depend on the standard library.
    double uniform01() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
    double uniform(double lo, double hi) { return lo + (hi - lo) * uniform01(); }
    std::size_t index(std::size_t n) { return static_cast<std::size_t>(uniform01() * static_cast<double>(n)) % n; }
    double normal() {  // Box-Muller, one value per call
        double u1 = uniform01();
        while (u1 <= 0.0) u1 = uniform01();
        const double u2 = uniform01();
        return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586 * u2);
    }

private:
    std::mt19937_64 engine_;
};

}  // namespace cellbench::plant
