// Three tester channels in parallel as one 60 A channel: sums, agreement, and faults that name the member.
#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "cellbench/protocol/parallel_group.hpp"

using namespace cellbench::protocol;
using neware::ChannelStatus;
using neware::InquireEntry;

namespace {

InquireEntry member(int chlid, double current_a, double voltage_v, ChannelStatus status = ChannelStatus::working) {
    InquireEntry e;
    e.channel = {"", 24, 1, 1, chlid};
    e.current_a = current_a;
    e.voltage_v = voltage_v;
    e.workstatus = status;
    e.step_id = 4;
    e.cycle_id = 1;
    e.step_type = "dc";
    e.capacity_ah = std::fabs(current_a) * 10.0 / 3600.0;
    e.energy_wh = e.capacity_ah * voltage_v;
    e.relative_time_s = 10.0;
    e.total_time_s = 700.0;
    return e;
}

std::vector<InquireEntry> three(double i1, double i2, double i3, double v1 = 3.60, double v2 = 3.601,
                                double v3 = 3.599) {
    return {member(1, i1, v1), member(2, i2, v2), member(3, i3, v3)};
}

}  // namespace

TEST(ParallelGroup, ThreeMembersAreOneSixtyAmpChannel) {
    ParallelGroup g;
    const auto r = g.update(three(-20.01, -19.99, -20.0));
    EXPECT_NEAR(r.current_a, -60.0, 1e-9);
    EXPECT_NEAR(r.voltage_v, 3.6, 1e-9);
    EXPECT_NEAR(r.capacity_ah, 60.0 * 10.0 / 3600.0, 1e-9);
    EXPECT_EQ(r.status, ChannelStatus::working);
    EXPECT_EQ(r.step_id, 4);
    EXPECT_EQ(r.step_type, "dc");
    EXPECT_EQ(r.members, 3u);
    EXPECT_FALSE(r.fault);
    EXPECT_FALSE(r.new_fault);
}

TEST(ParallelGroup, MemberInProtectIsAFaultAtOnce) {
    ParallelGroup g;
    g.update(three(-20, -20, -20));
    auto members = three(-20, 0, -20);
    members[1].workstatus = ChannelStatus::protect;
    members[1].workstatus_text = "protect";
    const auto r = g.update(members);
    ASSERT_TRUE(r.fault);
    EXPECT_TRUE(r.new_fault);
    EXPECT_EQ(r.fault->kind, GroupFaultKind::member_protect);
    EXPECT_EQ(r.fault->member, 1u);
    EXPECT_EQ(r.fault->member_key, "24-1-1-2");
    EXPECT_NE(r.fault->reason.find("member 2 (24-1-1-2)"), std::string::npos) << r.fault->reason;
    EXPECT_NE(r.fault->reason.find("protect"), std::string::npos) << r.fault->reason;
    EXPECT_EQ(r.status, ChannelStatus::protect);
    EXPECT_NEAR(r.current_a, -40.0, 1e-9);  // what the cell really gets
}

TEST(ParallelGroup, CurrentSharingOffAfterDebounce) {
    ParallelGroup g;  // fault_after_samples = 2
    const auto uneven = three(-20, -20, -12);  // member 3 carries too little
    auto r = g.update(uneven);
    EXPECT_FALSE(r.fault) << "one sample may be a step edge";
    r = g.update(uneven);
    ASSERT_TRUE(r.fault);
    EXPECT_TRUE(r.new_fault);
    EXPECT_EQ(r.fault->kind, GroupFaultKind::current_sharing);
    EXPECT_EQ(r.fault->member, 2u);
    EXPECT_NE(r.fault->reason.find("member 3"), std::string::npos) << r.fault->reason;
    EXPECT_NE(r.fault->reason.find("-12"), std::string::npos) << r.fault->reason;
    // Latched: a good reading does not clear it, reset() does.
    r = g.update(three(-20, -20, -20));
    ASSERT_TRUE(r.fault);
    EXPECT_FALSE(r.new_fault);
    g.reset();
    EXPECT_FALSE(g.update(three(-20, -20, -20)).fault);
}

TEST(ParallelGroup, OneSampleGlitchIsNoFault) {
    ParallelGroup g;
    g.update(three(-20, -20, -20));
    g.update(three(-20, -20, -5));  // one odd sample
    const auto r = g.update(three(-20, -20, -20));
    EXPECT_FALSE(r.fault);
}

TEST(ParallelGroup, SharingNotJudgedAtRestOrLowCurrent) {
    ParallelGroup g;
    for (int k = 0; k < 5; ++k) {
        const auto r = g.update(three(0.01, -0.02, 0.0));
        EXPECT_FALSE(r.fault);
    }
}

TEST(ParallelGroup, VoltageDisagreementNamesTheOddMember) {
    ParallelGroup g;
    const auto members = three(-20, -20, -20, 3.60, 3.75, 3.601);
    g.update(members);
    const auto r = g.update(members);
    ASSERT_TRUE(r.fault);
    EXPECT_EQ(r.fault->kind, GroupFaultKind::voltage_mismatch);
    EXPECT_EQ(r.fault->member, 1u);
    EXPECT_NE(r.fault->reason.find("3.75"), std::string::npos) << r.fault->reason;
}

TEST(ParallelGroup, MemberStoppedWhileOthersWork) {
    ParallelGroupOptions o;
    o.fault_after_samples = 1;
    ParallelGroup g(o);
    auto members = three(-30, 0, -30);
    members[1].workstatus = ChannelStatus::stop;
    const auto r = g.update(members);
    ASSERT_TRUE(r.fault);
    EXPECT_EQ(r.fault->kind, GroupFaultKind::member_stopped);
    EXPECT_EQ(r.fault->member, 1u);
    EXPECT_NE(r.fault->reason.find("'stop' while the other members work"), std::string::npos) << r.fault->reason;
}

TEST(ParallelGroup, AllFinishedOrStoppedTogetherIsFine) {
    ParallelGroup g;
    for (const auto s : {ChannelStatus::finish, ChannelStatus::stop, ChannelStatus::pause}) {
        std::vector<InquireEntry> m{member(1, 0, 3.3, s), member(2, 0, 3.3, s), member(3, 0, 3.3, s)};
        for (int k = 0; k < 3; ++k) {
            const auto r = g.update(m);
            EXPECT_FALSE(r.fault);
            EXPECT_EQ(r.status, s);
        }
    }
}

TEST(ParallelGroup, SingleChannelIsPassThrough) {
    ParallelGroup g;
    const std::vector<InquireEntry> one{member(5, 4.5, 4.0)};
    const auto r = g.update(one);
    EXPECT_DOUBLE_EQ(r.current_a, 4.5);
    EXPECT_DOUBLE_EQ(r.voltage_v, 4.0);
    EXPECT_FALSE(r.fault);
}

TEST(ParallelGroup, MissingReadingIsAFault) {
    ParallelGroup g;
    auto members = three(-20, -20, -20);
    members[2].voltage_v = std::nan("");
    const auto r = g.update(members);
    ASSERT_TRUE(r.fault);
    EXPECT_EQ(r.fault->kind, GroupFaultKind::member_missing);
    EXPECT_EQ(r.fault->member, 2u);
    EXPECT_TRUE(g.update({}).fault);
}
