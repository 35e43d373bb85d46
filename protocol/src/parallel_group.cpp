#include "cellbench/protocol/parallel_group.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

namespace cellbench::protocol {
namespace {

using neware::ChannelStatus;

std::string fmt(double v, int decimals) { return neware::format_number(v, decimals); }

std::string member_name(std::size_t index, const neware::InquireEntry& e) {
    return "member " + std::to_string(index + 1) + " (" + e.channel.key() + ")";
}

GroupFault make_fault(GroupFaultKind kind, std::size_t index, const neware::InquireEntry& e, std::string reason) {
    return GroupFault{kind, index, e.channel.key(), member_name(index, e) + ": " + std::move(reason)};
}

ChannelStatus group_status(std::span<const neware::InquireEntry> members) {
    auto any = [&](ChannelStatus s) {
        return std::any_of(members.begin(), members.end(), [&](const auto& m) { return m.workstatus == s; });
    };
    auto all = [&](ChannelStatus s) {
        return std::all_of(members.begin(), members.end(), [&](const auto& m) { return m.workstatus == s; });
    };
    if (any(ChannelStatus::protect)) return ChannelStatus::protect;
    if (any(ChannelStatus::working)) return ChannelStatus::working;
    if (any(ChannelStatus::pause)) return ChannelStatus::pause;
    if (all(ChannelStatus::finish)) return ChannelStatus::finish;
    if (any(ChannelStatus::stop)) return ChannelStatus::stop;
    if (any(ChannelStatus::finish)) return ChannelStatus::finish;
    return ChannelStatus::unknown;
}

}  // namespace

std::string_view to_string(GroupFaultKind kind) {
    switch (kind) {
        case GroupFaultKind::member_protect: return "member_protect";
        case GroupFaultKind::member_stopped: return "member_stopped";
        case GroupFaultKind::voltage_mismatch: return "voltage_mismatch";
        case GroupFaultKind::current_sharing: return "current_sharing";
        case GroupFaultKind::member_missing: return "member_missing";
    }
    return "unknown";
}

void ParallelGroup::reset() {
    fault_.reset();
    pending_.reset();
    pending_count_ = 0;
}

GroupReading ParallelGroup::update(std::span<const neware::InquireEntry> members) {
    GroupReading r;
    r.members = members.size();
    std::optional<GroupFault> immediate, debounced;

    if (members.empty()) {
        immediate = GroupFault{GroupFaultKind::member_missing, 0, "", "no member readings"};
    } else {
        const auto& first = members.front();
        r.step_id = first.step_id;
        r.cycle_id = first.cycle_id;
        r.step_type = first.step_type;
        r.total_time_s = first.total_time_s;
        r.relative_time_s = first.relative_time_s;
        r.status = group_status(members);

        double voltage_sum = 0.0;
        std::size_t voltage_count = 0;
        std::vector<double> voltages;
        for (std::size_t i = 0; i < members.size(); ++i) {
            const auto& m = members[i];
            if (!std::isfinite(m.current_a) || !std::isfinite(m.voltage_v)) {
                if (!immediate)
                    immediate = make_fault(GroupFaultKind::member_missing, i, m, "no current or voltage reading");
                continue;
            }
            r.current_a += m.current_a;
            voltage_sum += m.voltage_v;
            ++voltage_count;
            voltages.push_back(m.voltage_v);
            if (std::isfinite(m.capacity_ah)) r.capacity_ah += m.capacity_ah;
            if (std::isfinite(m.energy_wh)) r.energy_wh += m.energy_wh;
        }
        r.voltage_v = voltage_count ? voltage_sum / static_cast<double>(voltage_count) : std::nan("");

        const bool any_working = std::any_of(members.begin(), members.end(),
                                             [](const auto& m) { return m.workstatus == ChannelStatus::working; });
        // Status: protect at once; a member stopped/finished/paused while another works after debouncing.
        for (std::size_t i = 0; i < members.size() && !immediate; ++i) {
            const auto& m = members[i];
            if (m.workstatus == ChannelStatus::protect)
                immediate = make_fault(GroupFaultKind::member_protect, i, m,
                                       "went to protect" + std::string(members.size() > 1 ? " while the group ran" : ""));
        }
        if (members.size() > 1 && any_working) {
            for (std::size_t i = 0; i < members.size() && !debounced; ++i) {
                const auto& m = members[i];
                if (m.workstatus != ChannelStatus::working && m.workstatus != ChannelStatus::protect)
                    debounced = make_fault(GroupFaultKind::member_stopped, i, m,
                                           "is '" + (m.workstatus_text.empty() ? std::string(neware::to_string(m.workstatus))
                                                                               : m.workstatus_text) +
                                               "' while the other members work");
            }
        }
        // Voltage agreement: distance from the median (robust to the one bad member).
        if (members.size() > 1 && voltages.size() == members.size() && !debounced) {
            std::vector<double> sorted = voltages;
            std::sort(sorted.begin(), sorted.end());
            const std::size_t n = sorted.size();
            const double median = n % 2 ? sorted[n / 2] : 0.5 * (sorted[n / 2 - 1] + sorted[n / 2]);
            std::size_t worst = 0;
            double worst_dev = -1.0;
            for (std::size_t i = 0; i < members.size(); ++i) {
                const double dev = std::fabs(members[i].voltage_v - median);
                if (dev > worst_dev) {
                    worst_dev = dev;
                    worst = i;
                }
            }
            // With two members the median is their midpoint: judge their difference.
            const double spread = n == 2 ? 2.0 * worst_dev : worst_dev;
            if (spread > options_.voltage_tolerance_v)
                debounced = make_fault(GroupFaultKind::voltage_mismatch, worst, members[worst],
                                       "voltage " + fmt(members[worst].voltage_v, 4) + " V differs from the group's " +
                                           fmt(median, 4) + " V by more than " +
                                           fmt(options_.voltage_tolerance_v, 4) + " V");
        }
        // Current sharing while the group works.
        if (members.size() > 1 && r.status == ChannelStatus::working &&
            std::fabs(r.current_a) >= options_.min_current_for_sharing_a && !debounced &&
            voltages.size() == members.size()) {
            const double expected = r.current_a / static_cast<double>(members.size());
            const double allowed = options_.current_share_tolerance * std::fabs(expected) + options_.current_share_tolerance_a;
            std::size_t worst = 0;
            double worst_dev = -1.0;
            for (std::size_t i = 0; i < members.size(); ++i) {
                const double dev = std::fabs(members[i].current_a - expected);
                if (dev > worst_dev) {
                    worst_dev = dev;
                    worst = i;
                }
            }
            if (worst_dev > allowed)
                debounced = make_fault(GroupFaultKind::current_sharing, worst, members[worst],
                                       "carries " + fmt(members[worst].current_a, 3) + " A, expected share " +
                                           fmt(expected, 3) + " A of " + fmt(r.current_a, 3) + " A (tolerance " +
                                           fmt(allowed, 3) + " A)");
        }
    }

    // Debounce: the same kind on the same member for fault_after_samples consecutive updates.
    if (debounced) {
        if (pending_ && pending_->kind == debounced->kind && pending_->member == debounced->member)
            ++pending_count_;
        else
            pending_count_ = 1;
        pending_ = debounced;
    } else {
        pending_.reset();
        pending_count_ = 0;
    }
    if (!fault_) {
        if (immediate) {
            fault_ = immediate;
            r.new_fault = true;
        } else if (pending_ && pending_count_ >= std::max(1, options_.fault_after_samples)) {
            fault_ = pending_;
            r.new_fault = true;
        }
    }
    r.fault = fault_;
    return r;
}

}  // namespace cellbench::protocol
