#pragma once
// Several tester channels wired in parallel to one cell (the thesis bench: three 20 A channels of the
// BTS-4008 -> one 60 A channel). Each member still reports its own values; this turns the members' inquire
// results into one logical channel and watches that they behave as one.
//
// Pure logic: readings in, one reading (and possibly a fault) out.
//  - current = sum of the members' currents; capacity and energy = sums.
//  - voltage = mean of the members' voltages. All members sense the same cell, so they must agree: a member
//    farther than voltage_tolerance_v from the median is a fault (a loose sense lead or a member measuring
//    something else).
//  - current sharing: while the group works and carries at least min_current_for_sharing_a, each member must
//    carry total/n within current_share_tolerance (relative to total/n) plus current_share_tolerance_a.
//  - status: a member in protect, or stopped/finished while another member works, is a fault.
// Faults on readings that can be transient at a step edge (sharing, voltage, stop) must persist for
// fault_after_samples consecutive updates; protect is a fault at once. A fault latches until reset().
#include <cstddef>
#include <optional>
#include <span>
#include <string>

#include "cellbench/protocol/neware_bts.hpp"

namespace cellbench::protocol {

struct ParallelGroupOptions {
    double voltage_tolerance_v = 0.05;
    double current_share_tolerance = 0.10;   // relative to the expected share total/n
    double current_share_tolerance_a = 0.2;  // absolute slack (noise, small currents)
    double min_current_for_sharing_a = 1.0;  // below this total, sharing is not judged
    int fault_after_samples = 2;
};

enum class GroupFaultKind { member_protect, member_stopped, voltage_mismatch, current_sharing, member_missing };
std::string_view to_string(GroupFaultKind kind);

struct GroupFault {
    GroupFaultKind kind = GroupFaultKind::member_protect;
    std::size_t member = 0;  // index into the members passed to update()
    std::string member_key;  // "devtype-devid-subdevid-chlid"
    std::string reason;      // plain words, names the member and the numbers
};

struct GroupReading {
    double current_a = 0.0;  // sum, + = charge
    double voltage_v = 0.0;  // mean
    double capacity_ah = 0.0;
    double energy_wh = 0.0;
    neware::ChannelStatus status = neware::ChannelStatus::unknown;
    int step_id = 0, cycle_id = 0;
    std::string step_type;
    double total_time_s = 0.0, relative_time_s = 0.0;
    std::size_t members = 0;
    std::optional<GroupFault> fault;  // the latched fault, if any
    bool new_fault = false;           // the fault was raised by this update
};

class ParallelGroup {
public:
    explicit ParallelGroup(ParallelGroupOptions options = {}) : options_(options) {}

    // Members in a fixed order (the group's configuration order). A single member is a plain channel (no
    // sharing or agreement checks). An empty span or a NaN voltage/current of a member raises member_missing.
    GroupReading update(std::span<const neware::InquireEntry> members);

    void reset();  // clears the latched fault and the debounce counters
    [[nodiscard]] const std::optional<GroupFault>& fault() const { return fault_; }
    [[nodiscard]] const ParallelGroupOptions& options() const { return options_; }

private:
    ParallelGroupOptions options_;
    std::optional<GroupFault> fault_;
    std::optional<GroupFault> pending_;  // a debounced candidate
    int pending_count_ = 0;
};

}  // namespace cellbench::protocol
