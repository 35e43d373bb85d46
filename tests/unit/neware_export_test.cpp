// Neware BTS record export -> Recording.
#include "cellbench/protocol/neware_export.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

namespace {

using cellbench::InputError;
using cellbench::Recording;
using cellbench::protocol::parse_neware_export;

std::string error_of(const std::string& text) {
    try {
        (void)parse_neware_export(text, "rw_neware.csv");
    } catch (const InputError& e) {
        return e.what();
    }
    return "";
}

constexpr const char* kRwHeader =
    "DataPoint,Step Type,Time,Total Time,Current(A),Voltage(V),Capacity(Ah),Energy(Wh),Date,Power(W),Time(s)\r\n";

TEST(NewareExport, ReadsTheBtsRecordExport) {
    const std::string text = std::string(kRwHeader) +
                             "1,Rest,00:00:00,00:00:00,0.0,4.0964,0.0,0.0,2025-05-23 09:35:38,0.0,0.0\r\n"
                             "2,Rest,00:00:00,00:00:00,0.0,4.0964,0.0,0.0,2025-05-23 09:35:39,0.0,0.1\r\n"
                             "3,CC DChg,00:00:00,00:00:00,-4.5001,4.05,0.0,0.0,2025-05-23 09:35:39,-18.2,0.2\r\n"
                             "4,CC DChg,00:00:00,00:00:00,-4.5002,4.04,0.0,0.0,2025-05-23 09:35:39,-18.2,0.3\r\n"
                             "5,CC Chg,00:00:00,00:00:00,4.4999,4.06,0.0,0.0,2025-05-23 09:35:39,18.3,0.4\r\n";
    const Recording rec = parse_neware_export(text, "rw_neware.csv");
    ASSERT_EQ(rec.size(), 5u);
    EXPECT_EQ(rec.source, "rw_neware.csv");
    // Time(s) wins over the 1 s resolution Total Time.
    EXPECT_EQ(rec.time_s, (std::vector<double>{0.0, 0.1, 0.2, 0.3, 0.4}));
    EXPECT_EQ(rec.voltage_v, (std::vector<double>{4.0964, 4.0964, 4.05, 4.04, 4.06}));
    // Sign kept: Neware and BDF both count charging current positive.
    EXPECT_EQ(rec.current_a, (std::vector<double>{0.0, 0.0, -4.5001, -4.5002, 4.4999}));
    EXPECT_EQ(rec.step_type, (std::vector<std::string>{"Rest", "Rest", "CC DChg", "CC DChg", "CC Chg"}));
    EXPECT_EQ(rec.step_count, (std::vector<double>{1, 1, 2, 2, 3}));
    // 2025-05-23 09:35:38 UTC.
    ASSERT_EQ(rec.unix_time_s.size(), 5u);
    EXPECT_EQ(rec.unix_time_s[0], 1747992938.0);
    EXPECT_EQ(rec.unix_time_s[1], 1747992939.0);
    EXPECT_EQ(rec.repaired_timestamps, 0u);
    EXPECT_TRUE(rec.surface_c.empty());
    EXPECT_TRUE(rec.cycle_count.empty());
}

TEST(NewareExport, FallsBackToTotalTimeAndSpreadsItsRepeatedStamps) {
    const std::string text =
        "Step Type,Total Time,Current(A),Voltage(V)\n"
        "Rest,00:02:00,0,4.07\n"
        "Rest,00:02:00,0,4.07\n"
        "Rest,00:02:00,0,4.07\n"
        "Rest,00:02:00,0,4.07\n"
        "Rest,00:02:01,0,4.07\n"
        "Rest,26:00:00.5,0,4.07\n"  // hours beyond a day
        "Rest,93601,0,4.07\n";      // plain seconds
    const Recording rec = parse_neware_export(text, "x");
    ASSERT_EQ(rec.size(), 7u);
    EXPECT_EQ(rec.repaired_timestamps, 3u);
    EXPECT_DOUBLE_EQ(rec.time_s[0], 120.0);
    EXPECT_DOUBLE_EQ(rec.time_s[1], 120.25);
    EXPECT_DOUBLE_EQ(rec.time_s[2], 120.5);
    EXPECT_DOUBLE_EQ(rec.time_s[3], 120.75);
    EXPECT_DOUBLE_EQ(rec.time_s[4], 121.0);
    EXPECT_DOUBLE_EQ(rec.time_s[5], 93600.5);
    EXPECT_DOUBLE_EQ(rec.time_s[6], 93601.0);
}

TEST(NewareExport, RepairsTheBackwardStepArtefactOfTimeSeconds) {
    // rw_30degC_neware.csv around row 1213: Time(s) 121.1 is followed by 121.0 and 121.1 again.
    const std::string text =
        "Step Type,Current(A),Voltage(V),Time(s)\n"
        "Rest,0,4.07,120.9\nRest,0,4.07,121.0\nRest,0,4.07,121.1\nRest,0,4.07,121.0\n"
        "Rest,0,4.07,121.1\nRest,0,4.07,121.2\nRest,0,4.07,121.3\n";
    const Recording rec = parse_neware_export(text, "x");
    EXPECT_EQ(rec.repaired_timestamps, 2u);
    EXPECT_NEAR(rec.time_s[3], 121.1 + 0.1 / 3.0, 1e-12);
    EXPECT_NEAR(rec.time_s[4], 121.1 + 0.2 / 3.0, 1e-12);
    EXPECT_EQ(rec.time_s[5], 121.2);
    EXPECT_EQ(rec.time_s[6], 121.3);
}

TEST(NewareExport, BackwardStepOfOneSecondOrMoreIsAnError) {
    const std::string text = "Step Type,Current(A),Voltage(V),Time(s)\nRest,0,4.07,10\nRest,0,4.07,11\nRest,0,4.07,9.5\n";
    EXPECT_EQ(error_of(text),
              "rw_neware.csv:4: column \"Time(s)\": time steps back by 1.5 s (from 11 s to 9.5 s); only steps back of "
              "less than 1 s are repaired");
}

TEST(NewareExport, ColumnNamesIgnoreCaseAndSpacesAndMilliUnitsAreScaled) {
    const std::string text =
        " step type , TIME (S) ,Current (mA),voltage(mV)\n"
        "CC Chg,0,1500,3700\n"
        "CC Chg,1,-250.5,3710\n";
    const Recording rec = parse_neware_export(text, "x");
    ASSERT_EQ(rec.size(), 2u);
    EXPECT_DOUBLE_EQ(rec.current_a[0], 1.5);
    EXPECT_DOUBLE_EQ(rec.current_a[1], -0.2505);
    EXPECT_DOUBLE_EQ(rec.voltage_v[0], 3.7);
    EXPECT_DOUBLE_EQ(rec.voltage_v[1], 3.71);
    EXPECT_EQ(rec.step_type, (std::vector<std::string>{"CC Chg", "CC Chg"}));
}

TEST(NewareExport, StepIdColumnIsUsedWhenPresent) {
    const std::string text =
        "Step ID,Step Type,Cycle ID,Time(s),Current(A),Voltage(V)\n"
        "4,Rest,2,0,0,4.0\n"
        "5,Rest,2,1,0,4.0\n"
        "7,CC DChg,3,2,-4.5,3.9\n";
    const Recording rec = parse_neware_export(text, "x");
    EXPECT_EQ(rec.step_count, (std::vector<double>{4, 5, 7}));
    EXPECT_EQ(rec.cycle_count, (std::vector<double>{2, 2, 3}));
}

TEST(NewareExport, StepTimeResetSplitsTwoStepsOfTheSameType) {
    const std::string text =
        "Step Type,Time,Time(s),Current(A),Voltage(V)\n"
        "CC DChg,00:00:00,0,-4.5,4.0\n"
        "CC DChg,00:00:01,1,-4.5,4.0\n"
        "CC DChg,00:00:02,2,-4.5,4.0\n"
        "CC DChg,00:00:00,3,-9.0,3.9\n"  // next step, same type, new current
        "CC DChg,00:00:01,4,-9.0,3.9\n"
        "Rest,00:00:00,5,0,4.0\n";
    const Recording rec = parse_neware_export(text, "x");
    EXPECT_EQ(rec.step_count, (std::vector<double>{1, 1, 1, 2, 2, 3}));
}

TEST(NewareExport, DateFormats) {
    const std::string text =
        "Time(s),Current(A),Voltage(V),Date\n"
        "0,0,4,2024/02/29 23:59:59.5\n"
        "1,0,4,2024-03-01T00:00:00\n"
        "2,0,4,\n";
    const Recording rec = parse_neware_export(text, "x");
    ASSERT_EQ(rec.unix_time_s.size(), 3u);
    EXPECT_EQ(rec.unix_time_s[0], 1709251199.5);  // leap day
    EXPECT_EQ(rec.unix_time_s[1], 1709251200.0);
    EXPECT_TRUE(std::isnan(rec.unix_time_s[2]));
    EXPECT_TRUE(rec.step_count.empty()) << "no step information in this export";

    EXPECT_EQ(error_of("Time(s),Current(A),Voltage(V),Date\n0,0,4,2025-02-30 10:00:00\n"),
              "rw_neware.csv:2: column \"Date\": expected a date YYYY-MM-DD hh:mm:ss[.fff], got \"2025-02-30 10:00:00\"");
}

TEST(NewareExport, BadInputIsAnErrorWithLineAndColumn) {
    EXPECT_EQ(error_of("Step Type,Total Time,Current(A),Voltage(V)\nRest,00:61:00,0,4\n"),
              "rw_neware.csv:2: column \"Total Time\": expected a duration hh:mm:ss, h:mm:ss.fff or seconds, got \"00:61:00\"");
    EXPECT_EQ(error_of("Step Type,Time(s),Current(A),Voltage(V)\nRest,0,0,4\nRest,1,zero,4\n"),
              "rw_neware.csv:3: column \"Current(A)\": expected a number, got \"zero\"");
    EXPECT_EQ(error_of("Step Type,Time(s),Current(A),Voltage(V)\nRest,0,,4\n"),
              "rw_neware.csv:2: column \"Current(A)\": expected a number, got an empty cell");

    std::string msg = error_of("Step Type,Time(s),Voltage(V)\nRest,0,4\n");
    EXPECT_EQ(msg.rfind("rw_neware.csv:1: missing required column \"Current(A)\"", 0), 0u) << msg;
    msg = error_of("Step Type,Time,Current(A),Voltage(V)\nRest,00:00:00,0,4\n");
    EXPECT_EQ(msg.rfind("rw_neware.csv:1: no time column: expected \"Time(s)\", \"Total Time\", \"Cumulative Time\"", 0), 0u) << msg;
    msg = error_of("");
    EXPECT_EQ(msg.rfind("rw_neware.csv:1: empty file", 0), 0u) << msg;
    EXPECT_EQ(error_of(kRwHeader), "rw_neware.csv:1: header only: expected data rows after the header");
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Several BTSDA versions and NewareNDA's CSV: the same four rows (0, 1.5, 61 and 3725.25 s) in every layout
// give the same BDF times, and the reader says which layout it found.

namespace {

using cellbench::protocol::NewareExportInfo;
using cellbench::protocol::NewareExportLayout;

const std::vector<double> kTimes{0.0, 1.5, 61.0, 3725.25};

struct Layout {
    const char* name;
    std::string text;
    NewareExportLayout expected;
};

std::vector<Layout> layouts() {
    return {
        {"Time(s) in seconds",
         "DataPoint,Step Type,Time(s),Current(A),Voltage(V)\n1,Rest,0,0,4.1\n2,CC DChg,1.5,-4.5,4.0\n"
         "3,CC DChg,61,-4.5,3.9\n4,Rest,3725.25,0,3.95\n",
         NewareExportLayout::btsda_test_time},
        {"Time(s) as h:mm:ss.ms",
         "DataPoint,Step Type,Time(s),Current(A),Voltage(V)\n1,Rest,0:00:00.000,0,4.1\n2,CC DChg,0:00:01.500,-4.5,4.0\n"
         "3,CC DChg,0:01:01.000,-4.5,3.9\n4,Rest,1:02:05.250,0,3.95\n",
         NewareExportLayout::btsda_test_time},
        {"Total Time hh:mm:ss.ms",
         "DataPoint,Step Type,Time,Total Time,Current(A),Voltage(V)\n1,Rest,00:00:00,00:00:00,0,4.1\n"
         "2,CC DChg,00:00:00,00:00:01.5,-4.5,4.0\n3,CC DChg,00:00:59.5,00:01:01,-4.5,3.9\n"
         "4,Rest,00:00:00,01:02:05.25,0,3.95\n",
         NewareExportLayout::btsda_total_time},
        {"Cumulative Time hh:mm:ss",
         "Record ID,Cycle Index,Step Index,Step Type,Step Time,Cumulative Time,Current(A),Voltage(V)\n"
         "1,1,1,Rest,00:00:00,00:00:00,0,4.1\n2,1,2,CC DChg,00:00:00,00:00:01.500,-4.5,4.0\n"
         "3,1,2,CC DChg,00:00:59.500,00:01:01,-4.5,3.9\n4,1,3,Rest,00:00:00,01:02:05.250,0,3.95\n",
         NewareExportLayout::btsda_cumulative_time},
        {"Realtime wall clock only",
         "DataPoint,Step Type,Current(mA),Voltage(V),Realtime\n1,Rest,0,4.1,2025-05-23 09:35:38\n"
         "2,CC DChg,-4500,4.0,2025-05-23 09:35:39.5\n3,CC DChg,-4500,3.9,2025-05-23 09:36:39\n"
         "4,Rest,0,3.95,2025-05-23 10:37:43.25\n",
         NewareExportLayout::btsda_wall_clock},
        {"NewareNDA CSV",
         "Index,Cycle,Step,Status,Time,Voltage,Current(mA),Charge_Capacity(mAh),Discharge_Capacity(mAh),"
         "Charge_Energy(mWh),Discharge_Energy(mWh),Timestamp\n"
         "1,1,1,Rest,0.0,4.1,0.0,0,0,0,0,2025-05-23 09:35:38\n"
         "2,1,2,CC_DChg,0.0,4.0,-4500.0,0,0,0,0,2025-05-23 09:35:39.500\n"
         "3,1,2,CC_DChg,59.5,3.9,-4500.0,0,74.4,0,0,2025-05-23 09:36:39\n"
         "4,1,3,Rest,0.0,3.95,0.0,0,0,0,0,2025-05-23 10:37:43.250\n",
         NewareExportLayout::newarenda},
    };
}

}  // namespace

TEST(NewareExport, EveryTimeLayoutGivesTheSameBdfTimes) {
    for (const auto& l : layouts()) {
        NewareExportInfo info;
        const Recording rec = parse_neware_export(l.text, "export.csv", &info);
        EXPECT_EQ(info.layout, l.expected) << l.name;
        ASSERT_EQ(rec.size(), 4u) << l.name;
        for (std::size_t k = 0; k < kTimes.size(); ++k) EXPECT_NEAR(rec.time_s[k], kTimes[k], 1e-9) << l.name << " row " << k;
        EXPECT_DOUBLE_EQ(rec.current_a[1], -4.5) << l.name;  // mA columns scaled, the sign kept
        EXPECT_DOUBLE_EQ(rec.voltage_v[3], 3.95) << l.name;
    }
    // NewareNDA: its Time column is the step time (it falls back), never taken as the test time; its Status is
    // the step type, its Step the step count.
    const Recording nda = parse_neware_export(layouts().back().text, "nda.csv");
    EXPECT_EQ(nda.step_type[1], "CC_DChg");
    EXPECT_EQ(nda.step_count, (std::vector<double>{1, 2, 2, 3}));
    ASSERT_EQ(nda.unix_time_s.size(), 4u);
    EXPECT_DOUBLE_EQ(nda.unix_time_s[0], 1747992938.0);
}

TEST(NewareExport, ImpossibleValuesNameTheRow) {
    const std::string head = "DataPoint,Time(s),Current(A),Voltage(V)\n1,0,0,4.1\n";
    EXPECT_NE(error_of(head + "2,1,0,42.0\n").find("rw_neware.csv:3: column \"Voltage(V)\": physically impossible voltage"),
              std::string::npos)
        << error_of(head + "2,1,0,42.0\n");
    EXPECT_NE(error_of(head + "2,1,-20000,4.0\n").find(":3: column \"Current(A)\": physically impossible current"),
              std::string::npos);
    EXPECT_NE(error_of(head + "2,1,0,inf\n").find(":3:"), std::string::npos);
    EXPECT_NE(error_of(head + "2,1,nan,4.0\n").find(":3:"), std::string::npos);
    EXPECT_NE(error_of("DataPoint,Cumulative Time,Current(A),Voltage(V)\n1,00:00:00,0,4.1\n2,yesterday,0,4.1\n")
                  .find(":3: column \"Cumulative Time\": expected a duration"),
              std::string::npos);
    EXPECT_NE(error_of("DataPoint,Current(A),Voltage(V)\n1,0,4.1\n").find("no time column"), std::string::npos);
}

// BTSDA in a decimal-comma locale (or the export opened and saved by a spreadsheet there): ';' between cells,
// "4,0964" and durations "00:00:01,500". Read as the comma export with the same values, and the info says so.
TEST(NewareExportDialect, SemicolonsAndDecimalCommasReadAsTheCommaExport) {
    const std::string comma = std::string(kRwHeader) +
                              "1,Rest,00:00:00.000,00:00:00,0.0,4.0964,0.0,0.0,2025-05-23 09:35:38,0.0,0.0\r\n"
                              "2,CC DChg,00:00:01.500,00:00:01,-4.5001,4.05,-0.0019,0.0,2025-05-23 09:35:39,-18.2,1.5\r\n";
    std::string euro = comma;
    for (char& c : euro) c = c == ',' ? ';' : c == '.' ? ',' : c;
    cellbench::protocol::NewareExportInfo info_comma, info_euro;
    const Recording a = parse_neware_export(comma, "rw_neware.csv", &info_comma);
    const Recording b = parse_neware_export(euro, "rw_neware.csv", &info_euro);
    EXPECT_EQ(b.time_s, a.time_s);
    EXPECT_EQ(b.time_s, (std::vector<double>{0.0, 1.5}));
    EXPECT_EQ(b.voltage_v, a.voltage_v);
    EXPECT_EQ(b.current_a, a.current_a);
    EXPECT_EQ(b.step_type, a.step_type);
    EXPECT_EQ(b.unix_time_s, a.unix_time_s);
    EXPECT_EQ(info_comma.separator, ',');
    EXPECT_EQ(info_euro.separator, ';');
}
