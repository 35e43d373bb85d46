#pragma once
// The bench's instruments, in the order they were added (GET /status lists them in that order). The daemon
// adds one line per instrument; everything that reports on instruments (status, metrics, health, faults)
// iterates the registry instead of naming them.
#include <memory>
#include <string_view>
#include <vector>

#include "cellbench/instruments/instrument.hpp"

namespace cellbench::instruments {

class InstrumentRegistry {
public:
    // Adds an instrument (names are unique: std::invalid_argument otherwise); returns it, typed.
    template <class T>
    T& add(std::unique_ptr<T> instrument) {
        T& ref = *instrument;
        add_impl(std::move(instrument));
        return ref;
    }

    // nullptr when no instrument has that name.
    [[nodiscard]] Instrument* find(std::string_view name) const;
    [[nodiscard]] bool empty() const { return items_.empty(); }
    [[nodiscard]] std::size_t size() const { return items_.size(); }
    // Every instrument reports connected (false when there is none).
    [[nodiscard]] bool all_connected() const;

    void start_all();  // in order
    void stop_all();   // in order

    [[nodiscard]] auto begin() const { return items_.begin(); }
    [[nodiscard]] auto end() const { return items_.end(); }

private:
    void add_impl(std::unique_ptr<Instrument> instrument);
    std::vector<std::unique_ptr<Instrument>> items_;
};

}  // namespace cellbench::instruments
