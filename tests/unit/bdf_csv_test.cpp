// BDF CSV reading and writing: the recording format every cellbench command reads and writes.
#include "cellbench/protocol/bdf_csv.hpp"

#include <gtest/gtest.h>

#include <charconv>
#include <cmath>
#include <cstring>
#include <random>
#include <sstream>
#include <string>

namespace {

using cellbench::InputError;
using cellbench::Recording;
using cellbench::protocol::BdfReadReport;
using cellbench::protocol::parse_bdf_csv;
using cellbench::protocol::write_bdf_csv;

// The message of the InputError that parsing `text` throws ("" if it does not throw).
std::string error_of(const std::string& text, const std::string& source = "rw.csv") {
    try {
        (void)parse_bdf_csv(text, source);
    } catch (const InputError& e) {
        return e.what();
    }
    return "";
}

bool same_bits(double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; }

TEST(BdfCsv, ColumnsInAnyOrderUnknownOnesIgnoredAndReported) {
    const std::string text =
        "Current / A,Vendor Capacity / Ah,Test Time / s,Step Type,Voltage / V,Surface Temperature / degC\n"
        "-4.5,0.1,0.0,CC DChg,3.9,29.5\n"
        "0.0,0.2,0.1,Rest,4.0,29.6\n";
    BdfReadReport report;
    const Recording rec = parse_bdf_csv(text, "x.csv", &report);
    ASSERT_EQ(rec.size(), 2u);
    EXPECT_EQ(rec.source, "x.csv");
    EXPECT_EQ(rec.time_s, (std::vector<double>{0.0, 0.1}));
    EXPECT_EQ(rec.voltage_v, (std::vector<double>{3.9, 4.0}));
    EXPECT_EQ(rec.current_a, (std::vector<double>{-4.5, 0.0}));
    EXPECT_EQ(rec.step_type, (std::vector<std::string>{"CC DChg", "Rest"}));
    EXPECT_EQ(rec.surface_c, (std::vector<double>{29.5, 29.6}));
    // Channels the file lacks stay empty.
    EXPECT_TRUE(rec.heat_flux_w_per_m2.empty());
    EXPECT_TRUE(rec.unix_time_s.empty());
    EXPECT_TRUE(rec.t1_c.empty());
    EXPECT_EQ(report.rows, 2u);
    EXPECT_EQ(report.repaired_timestamps, 0u);
    EXPECT_EQ(report.ignored_columns, (std::vector<std::string>{"Vendor Capacity / Ah"}));
}

// One row "1,3.7,2,1700000000.5,3,4,STEP,30,31,32,33[,...]" under the header's names, read into every channel.
void expect_every_channel(const Recording& rec, const std::string& step_type) {
    ASSERT_EQ(rec.size(), 1u);
    EXPECT_EQ(rec.time_s.at(0), 1.0);
    EXPECT_EQ(rec.voltage_v.at(0), 3.7);
    EXPECT_EQ(rec.current_a.at(0), 2.0);
    EXPECT_EQ(rec.unix_time_s.at(0), 1700000000.5);
    EXPECT_EQ(rec.step_count.at(0), 3.0);
    EXPECT_EQ(rec.cycle_count.at(0), 4.0);
    EXPECT_EQ(rec.step_type.at(0), step_type);
    EXPECT_EQ(rec.ambient_c.at(0), 30.0);
    EXPECT_EQ(rec.surface_c.at(0), 31.0);
    EXPECT_EQ(rec.t1_c.at(0), 32.0);
    EXPECT_EQ(rec.t2_c.at(0), 33.0);
}

TEST(BdfCsv, EveryOptionalLabelMapsToItsChannel) {
    const std::string text =
        "Test Time / s,Voltage / V,Current / A,Unix Time / s,Step Count / 1,Cycle Count / 1,Step Type,"
        "Ambient Temperature / degC,Surface Temperature / degC,Temperature T1 / degC,Temperature T2 / degC,"
        "Heat Flux Density / W/m^2\n"
        "1,3.7,2,1700000000.5,3,4,CC Chg,30,31,32,33,12.5\n";
    const Recording rec = parse_bdf_csv(text, "x.csv");
    expect_every_channel(rec, "CC Chg");
    EXPECT_EQ(rec.heat_flux_w_per_m2.at(0), 12.5);
}

// The Battery Data Alliance's reference files key their columns on the ontology's machine-readable names.
TEST(BdfCsv, MachineReadableNamesOfTheBdfOntologyAreRead) {
    const std::string text =
        "test_time_second,voltage_volt,current_ampere,unix_time_second,step_count,cycle_count,step_type,"
        "ambient_temperature_celsius,surface_temperature_celsius,temperature_t1_celsius,temperature_t2_celsius,"
        "net_capacity_ah\n"
        "1,3.7,2,1700000000.5,3,4,CHA,30,31,32,33,0.1\n";
    BdfReadReport report;
    expect_every_channel(parse_bdf_csv(text, "x.csv", &report), "CHA");
    EXPECT_EQ(report.ignored_columns, (std::vector<std::string>{"net_capacity_ah"}));
    // One quantity under both of its names is one column twice.
    EXPECT_EQ(error_of("Test Time / s,voltage_volt,Current / A,Voltage / V\n0,3.7,0,3.7\n"),
              "rw.csv:1: column \"Voltage / V\" appears twice (columns 2 and 4)");
}

// Many cyclers log the schedule's step number (Arbin, BioLogic, Digatron: step_id; Neware, Landt: step_index)
// and no Step Count. The index marks the step boundaries the segmentation needs (a SOC-step discharge followed
// at once by a discharge pulse is two steps): a new step wherever it changes, an empty cell continuing the step.
TEST(BdfCsv, AStepIndexWithoutStepCountCountsTheSteps) {
    for (const char* name : {"step_id", "step_index", "Step Index / 1"}) {
        const std::string text = std::string("test_time_second,voltage_volt,current_ampere,") + name +
                                 "\n0,3.7,0,28\n1,3.6,-2,29\n2,3.6,-2,29\n3,3.5,-10,30\n4,3.5,-10,\n5,3.7,0,28\n";
        BdfReadReport report;
        const Recording rec = parse_bdf_csv(text, "x.csv", &report);
        EXPECT_EQ(rec.step_count, (std::vector<double>{1, 2, 2, 3, 3, 4})) << name;
        EXPECT_TRUE(report.steps_counted_from_index) << name;
        EXPECT_TRUE(report.ignored_columns.empty()) << name;
        // A cell that is no step number is an error naming the column as the file names it.
        const std::string bad = std::string("test_time_second,voltage_volt,current_ampere,") + name + "\n0,3.7,0,x\n";
        EXPECT_NE(error_of(bad).find(std::string("column \"") + name + "\""), std::string::npos) << error_of(bad);
    }
    // A file's own Step Count is what counts; the index beside it is ignored (and listed as such).
    BdfReadReport report;
    const Recording rec =
        parse_bdf_csv("Test Time / s,Voltage / V,Current / A,Step Count / 1,step_id\n0,3.7,0,5,1\n1,3.6,-2,6,1\n",
                      "x.csv", &report);
    EXPECT_EQ(rec.step_count, (std::vector<double>{5, 6}));
    EXPECT_FALSE(report.steps_counted_from_index);
    EXPECT_EQ(report.ignored_columns, (std::vector<std::string>{"step_id"}));
}

TEST(BdfCsv, OtherUnitsOfAQuantityAreConvertedToSi) {
    const std::string text =
        "Test Time / ms,Voltage / mV,Current / mA,Surface Temperature / K,Ambient Temperature / \u00b0C,"
        "Temperature T1 / celsius\n"
        "0,3700,-4500,303.15,30,31\n"
        "1500,3650.5,250,304.15,30,31\n";
    const Recording rec = parse_bdf_csv(text, "x.csv");
    ASSERT_EQ(rec.size(), 2u);
    EXPECT_DOUBLE_EQ(rec.time_s.at(1), 1.5);
    EXPECT_DOUBLE_EQ(rec.voltage_v.at(1), 3.6505);
    EXPECT_DOUBLE_EQ(rec.current_a.at(0), -4.5);
    EXPECT_DOUBLE_EQ(rec.current_a.at(1), 0.25);
    EXPECT_NEAR(rec.surface_c.at(0), 30.0, 1e-12);
    EXPECT_EQ(rec.ambient_c.at(0), 30.0);
    EXPECT_EQ(rec.t1_c.at(0), 31.0);
    const Recording hours = parse_bdf_csv("Test Time / h,Voltage / V,Current / A\n0,3.7,0\n0.5,3.7,0\n", "x.csv");
    EXPECT_DOUBLE_EQ(hours.time_s.at(1), 1800.0);
    // The physical range holds in SI: 20000 mV is 20 V, beyond any cell.
    const std::string msg = error_of("Test Time / s,Voltage / mV,Current / A\n0,20000,0\n");
    EXPECT_NE(msg.find("impossible value \"20000\" (20 V)"), std::string::npos) << msg;
}

TEST(BdfCsv, AUnitTheReaderDoesNotConvertIsAnErrorNotAnIgnoredColumn) {
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / kA\n0,3.7,0\n"),
              "rw.csv:1: column \"Current / kA\": a unit of Current this reader does not convert (it reads A, mA)");
    const std::string msg = error_of("Test Time / s,Voltage / V,Current / A,Surface Temperature / degF\n0,3.7,0,80\n");
    EXPECT_NE(msg.find("a unit of Surface Temperature this reader does not convert"), std::string::npos) << msg;
}

// A test time in ms under a seconds name (seen in a published BDF file): every pulse would read 1000 times too
// long. Exactly 1000 times the wall clock's pace is read as ms, and the report says so; any other pace ahead of
// the wall clock is an error; a test time that pauses while the wall clock runs on is a test that was paused.
TEST(BdfCsv, TestTimeRunningAheadOfTheUnixTimeIsReadAsMsOrRefused) {
    std::string ms = "test_time_second,voltage_volt,current_ampere,unix_time_second\n";
    std::string fast = ms, paused = ms;
    for (int i = 0; i < 200; ++i) {
        ms += std::to_string(1000 * i + (i % 3)) + ",3.7,0," + std::to_string(1700000000 + i) + "\n";
        fast += std::to_string(10 * i) + ",3.7,0," + std::to_string(1700000000 + i) + "\n";
        paused += std::to_string(i) + ",3.7,0," + std::to_string(1700000000 + (i < 100 ? i : i + 3600)) + "\n";
    }
    BdfReadReport report;
    const Recording rec = parse_bdf_csv(ms, "x.csv", &report);
    EXPECT_TRUE(report.time_read_as_ms);
    EXPECT_DOUBLE_EQ(rec.time_s.at(1), 1.001);
    EXPECT_DOUBLE_EQ(rec.time_s.back(), 199.001);
    EXPECT_EQ(report.gap_s, 0.0) << "steps of 1000 ms are no gap";
    const std::string msg = error_of(fast);
    EXPECT_NE(msg.find("Test Time / s advances 10 times as fast as Unix Time / s"), std::string::npos) << msg;
    EXPECT_NE(msg.find("\"Test Time / ms\""), std::string::npos) << "says how to fix it: " << msg;
    BdfReadReport paused_report;
    EXPECT_EQ(parse_bdf_csv(paused, "x.csv", &paused_report).time_s.back(), 199.0);
    EXPECT_FALSE(paused_report.time_read_as_ms);
}

TEST(BdfCsv, BomCrlfWhitespaceQuotesAndLabelCase) {
    const std::string text =
        "\xEF\xBB\xBF\"Test Time / s\" , voltage / v,CURRENT / A,\"Step Type\"\r\n"
        " 0 , \"3.7\",-1.5,\"CC, \"\"fast\"\"\"\r\n"
        "\r\n"  // blank line
        "1\t,3.8,+2,  Rest  \r\n";
    const Recording rec = parse_bdf_csv(text, "x.csv");
    ASSERT_EQ(rec.size(), 2u);
    EXPECT_EQ(rec.time_s, (std::vector<double>{0.0, 1.0}));
    EXPECT_EQ(rec.voltage_v, (std::vector<double>{3.7, 3.8}));
    EXPECT_EQ(rec.current_a, (std::vector<double>{-1.5, 2.0}));
    EXPECT_EQ(rec.step_type, (std::vector<std::string>{"CC, \"fast\"", "Rest"}));
}

TEST(BdfCsv, EmptyOrNanOptionalCellsAreNaNAndInfinityIsRejected) {
    const std::string text =
        "Test Time / s,Voltage / V,Current / A,Surface Temperature / degC,Ambient Temperature / degC\n"
        "0,3.7,0,,\n"
        "1,3.7,0,nan,\n"
        "2,3.7,0,29.5,\n";
    const Recording rec = parse_bdf_csv(text, "x.csv");
    ASSERT_EQ(rec.surface_c.size(), 3u);
    EXPECT_TRUE(std::isnan(rec.surface_c[0]));
    EXPECT_TRUE(std::isnan(rec.surface_c[1]));
    EXPECT_EQ(rec.surface_c[2], 29.5);
    EXPECT_TRUE(rec.has_surface());
    // A column that is present but never filled is a channel without values.
    EXPECT_EQ(rec.ambient_c.size(), 3u);
    EXPECT_FALSE(rec.has_ambient());

    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A,Surface Temperature / degC\n0,3.7,0,inf\n"),
              "rw.csv:2: column \"Surface Temperature / degC\": expected a finite number, got \"inf\"");
}

TEST(BdfCsv, UnparsableNumberNamesFileLineAndColumn) {
    std::string text = "Test Time / s,Voltage / V,Current / A\n0,3.7,0\n0.1,abc,0\n";
    EXPECT_EQ(error_of(text), "rw.csv:3: column \"Voltage / V\": expected a number, got \"abc\"");
    // A number followed by junk is not a number either.
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,3.7,1.5A\n"),
              "rw.csv:2: column \"Current / A\": expected a number, got \"1.5A\"");
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,3.7,1e999\n"),
              "rw.csv:2: column \"Current / A\": number out of range: \"1e999\"");
}

TEST(BdfCsv, LineNumbersCountBlankLinesAndQuotedLineBreaks) {
    const std::string text =
        "Test Time / s,Voltage / V,Current / A,Step Type\n"
        "0,3.7,0,\"two\nlines\"\n"  // lines 2-3
        "\n"                        // line 4
        "1,3.7,x,Rest\n";           // line 5
    EXPECT_EQ(error_of(text), "rw.csv:5: column \"Current / A\": expected a number, got \"x\"");
}

TEST(BdfCsv, RequiredCellsMustHoldFiniteNumbers) {
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,,0\n"),
              "rw.csv:2: column \"Voltage / V\": expected a number, got an empty cell");
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,3.7,NaN\n"),
              "rw.csv:2: column \"Current / A\": expected a number, got \"NaN\"");
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n-inf,3.7,0\n"),
              "rw.csv:2: column \"Test Time / s\": expected a finite number, got \"-inf\"");
}

TEST(BdfCsv, MissingRequiredColumnIsAnError) {
    const std::string msg = error_of("Test Time / s,Voltage / V,Current(A)\n0,3.7,0\n");
    EXPECT_EQ(msg.rfind("rw.csv:1: missing required column \"Current / A\"", 0), 0u) << msg;
    EXPECT_NE(msg.find("\"Current(A)\""), std::string::npos) << "the message shows what the header has: " << msg;
}

TEST(BdfCsv, EmptyFileAndHeaderOnlyAreErrors) {
    for (const std::string empty : {"", "\xEF\xBB\xBF", "\r\n\n  \n"}) {
        const std::string msg = error_of(empty);
        EXPECT_EQ(msg.rfind("rw.csv:1: empty file", 0), 0u) << msg;
    }
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\r\n"),
              "rw.csv:1: header only: expected data rows after the header");
}

TEST(BdfCsv, RaggedRowsAndDuplicateColumnsAreErrors) {
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,3.7,0\n1,3.7\n"),
              "rw.csv:3: expected 3 cells as in the header, got 2");
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,3.7,0,5\n"),
              "rw.csv:2: expected 3 cells as in the header, got 4");
    // A trailing comma is not a ragged row.
    EXPECT_EQ(parse_bdf_csv("Test Time / s,Voltage / V,Current / A,\n0,3.7,0,\n", "x").size(), 1u);
    EXPECT_EQ(parse_bdf_csv("Test Time / s,Voltage / V,Current / A\n0,3.7,0,\n", "x").size(), 1u);
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A,Voltage / V\n0,3.7,0,3.8\n"),
              "rw.csv:1: column \"Voltage / V\" appears twice (columns 2 and 4)");
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,\"3.7,0\n"),
              "rw.csv:2: a quoted cell is never closed (missing '\"')");
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A\n0,\"3.7\"x,0\n"),
              "rw.csv:2: unexpected text after a closing quote (expected ',' or the end of the line)");
}

std::string bdf_with_times(const std::vector<std::string>& times) {
    std::string text = "Test Time / s,Voltage / V,Current / A\n";
    for (const auto& t : times) text += t + ",3.7,0\n";
    return text;
}

TEST(BdfCsv, RepeatedStampsAreSpreadOverTheIntervalToTheNextStamp) {
    BdfReadReport report;
    const Recording rec = parse_bdf_csv(bdf_with_times({"0", "1", "1", "1", "2", "3"}), "x", &report);
    ASSERT_EQ(rec.size(), 6u);
    EXPECT_EQ(rec.repaired_timestamps, 2u);
    EXPECT_EQ(report.repaired_timestamps, 2u);
    EXPECT_DOUBLE_EQ(rec.time_s[0], 0.0);
    EXPECT_DOUBLE_EQ(rec.time_s[1], 1.0);
    EXPECT_DOUBLE_EQ(rec.time_s[2], 1.0 + 1.0 / 3.0);
    EXPECT_DOUBLE_EQ(rec.time_s[3], 1.0 + 2.0 / 3.0);
    EXPECT_EQ(rec.time_s[4], 2.0);  // untouched: no drift
    EXPECT_EQ(rec.time_s[5], 3.0);
}

TEST(BdfCsv, SmallBackwardStepIsRepairedWithoutDrift) {
    // The Neware artefact: 121.1 then 121.0, 121.1 again, then on at 0.1 s.
    const Recording rec =
        parse_bdf_csv(bdf_with_times({"120.9", "121.0", "121.1", "121.0", "121.1", "121.2", "121.3"}), "x");
    ASSERT_EQ(rec.size(), 7u);
    EXPECT_EQ(rec.repaired_timestamps, 2u);
    EXPECT_EQ(rec.time_s[2], 121.1);
    EXPECT_NEAR(rec.time_s[3], 121.1 + 0.1 / 3.0, 1e-12);
    EXPECT_NEAR(rec.time_s[4], 121.1 + 0.2 / 3.0, 1e-12);
    EXPECT_EQ(rec.time_s[5], 121.2);
    EXPECT_EQ(rec.time_s[6], 121.3);
    for (std::size_t i = 1; i < rec.size(); ++i) EXPECT_LT(rec.time_s[i - 1], rec.time_s[i]) << i;
}

TEST(BdfCsv, RunAtTheEndContinuesAtTheTypicalInterval) {
    // Median positive interval is 0.1 s; the last two rows have no later stamp to spread towards.
    const Recording rec = parse_bdf_csv(bdf_with_times({"0", "0.1", "0.2", "0.3", "0.25", "0.3"}), "x");
    EXPECT_EQ(rec.repaired_timestamps, 2u);
    EXPECT_NEAR(rec.time_s[4], 0.4, 1e-12);
    EXPECT_NEAR(rec.time_s[5], 0.5, 1e-12);
}

TEST(BdfCsv, BackwardStepOfOneSecondOrMoreIsAnError) {
    EXPECT_EQ(error_of(bdf_with_times({"0", "1", "2", "1"})),
              "rw.csv:5: column \"Test Time / s\": time steps back by 1 s (from 2 s to 1 s); only steps back of "
              "less than 1 s are repaired");
    // Measured from the latest stamp, not the previous row: two small steps back that add up to 1.1 s.
    const std::string msg = error_of(bdf_with_times({"0", "5", "4.5", "3.9"}));
    EXPECT_EQ(msg.rfind("rw.csv:5: column \"Test Time / s\": time steps back by", 0), 0u) << msg;
    // Just under 1 s is repaired.
    EXPECT_EQ(parse_bdf_csv(bdf_with_times({"0", "5", "4.01", "6"}), "x").repaired_timestamps, 1u);
}

// A cycler that restarts its test clock mid-test (a published Neware export keeps such "non-monotonic total
// time" on purpose, as the Battery Data Alliance's Time_Bug example) while the Unix time runs on: the rows after
// each step back keep their own intervals and follow the row before by the Unix time's interval. Without a Unix
// time, or where it steps back too, it stays an error.
TEST(BdfCsv, ATestTimeThatStepsBackIsPlacedByTheUnixTimeBesideIt) {
    const std::string text =
        "test_time_second,voltage_volt,current_ampere,unix_time_second\n"
        "0,3.7,0,1000\n10,3.7,0,1010\n20,3.7,0,1020\n5,3.6,-1,1031\n15.5,3.6,-1,1041.5\n2,3.7,0,1050\n3,3.7,0,1051\n";
    BdfReadReport report;
    const Recording rec = parse_bdf_csv(text, "x.csv", &report);
    EXPECT_EQ(rec.time_s, (std::vector<double>{0, 10, 20, 31, 41.5, 50, 51}));
    EXPECT_EQ(report.time_jumps_placed_by_unix_time, 2u);
    EXPECT_EQ(report.first_time_jump, "line 5: from 20 s to 5 s");
    const auto messages = cellbench::protocol::describe(report, "x.csv");
    ASSERT_EQ(messages.size(), 1u);
    EXPECT_TRUE(messages[0].warning);
    EXPECT_EQ(messages[0].text, "x.csv: the test time steps back 2 times (first at line 5: from 20 s to 5 s): the rows "
                                "after each step are placed by the Unix time beside them");
    // The Unix time steps back as well: nothing can place the rows.
    EXPECT_EQ(error_of("test_time_second,voltage_volt,current_ampere,unix_time_second\n0,3.7,0,1000\n10,3.7,0,1010\n"
                       "5,3.7,0,1005\n"),
              "rw.csv:4: column \"Test Time / s\": time steps back by 5 s (from 10 s to 5 s); only steps back of less "
              "than 1 s are repaired (the Unix time beside it does not run on there, so it cannot place the rows after "
              "it either)");
    // A Unix time that leaps by centuries (a corrupt stamp; found by the fuzzer, session 42) would place the rows at
    // a test time beyond any test: an error, where it used to give a recording this reader refused to read back.
    EXPECT_EQ(error_of("test_time_second,voltage_volt,current_ampere,unix_time_second\n0,3.7,0,1729695087\n"
                       "12,3.7,0,1729695099\n1,3.75,0,29617591110\n"),
              "rw.csv:4: column \"Test Time / s\": time steps back by 11 s (from 12 s to 1 s); only steps back of less "
              "than 1 s are repaired (placed by the Unix time beside it, its rows would reach a test time of 27887896023 "
              "s: no test runs so long)");
}

// Found by the fuzzer (session 42): after a test time placed by the Unix time across a 100 000 s gap, the last
// rows repeat their stamp. Spread at the recording's only interval (the gap), they ran the test time 3 times as
// fast as the Unix time: a recording this reader refused to read back from the file it wrote. Now an error.
TEST(BdfCsv, RepairedStampsThatWouldRunAheadOfTheUnixTimeAreAnError) {
    EXPECT_EQ(error_of("Test Time / s,Voltage / V,Current / A,Unix Time / s\n5,4.0,0,1747893000\n"
                       "0.1,4.0,0,1747993000.1\n0.1,3.95,-4.5,1747993000.2\n0.035,3.94,-4.5,1747993000.3\n"),
              "rw.csv: column \"Test Time / s\": 2 repeated or backward stamps cannot be repaired in step with the Unix "
              "time beside them (spread at the recording's typical interval, the test time would advance 3 times as "
              "fast): check the time columns");
    // The same stamps at a logger's pace repair as before.
    BdfReadReport report;
    const Recording rec = parse_bdf_csv("Test Time / s,Voltage / V,Current / A,Unix Time / s\n0,4.0,0,1000\n"
                                        "60,4.0,0,1060\n120,4.0,0,1120\n120,4.0,0,1180\n",
                                        "x.csv", &report);
    EXPECT_EQ(rec.time_s, (std::vector<double>{0, 60, 120, 180}));
    EXPECT_EQ(report.repaired_timestamps, 1u);
}

TEST(BdfCsv, TimeThatNeverAdvancesIsAnErrorButOneRowIsFine) {
    EXPECT_EQ(error_of(bdf_with_times({"7", "7", "7"})),
              "rw.csv: column \"Test Time / s\": time never advances (all 3 rows at 7 s)");
    EXPECT_EQ(parse_bdf_csv(bdf_with_times({"7"}), "x").size(), 1u);
}

TEST(BdfCsv, WritesLabelsOfPresentChannelsOnly) {
    Recording rec;
    rec.time_s = {0.0, 0.1, 0.2};
    rec.voltage_v = {3.7, 3.69, 3.68};
    rec.current_a = {-1.5, -1.5, 0.0};
    rec.surface_c = {29.5, cellbench::kNaN, 29.7};
    std::ostringstream out;
    write_bdf_csv(out, rec);
    EXPECT_EQ(out.str(),
              "Test Time / s,Voltage / V,Current / A,Surface Temperature / degC\n"
              "0,3.7,-1.5,29.5\n"
              "0.1,3.69,-1.5,\n"
              "0.2,3.68,0,29.7\n");
}

TEST(BdfCsv, WriteRejectsChannelsOfTheWrongLength) {
    Recording rec;
    rec.time_s = {0.0, 1.0};
    rec.voltage_v = {3.7, 3.7};
    rec.current_a = {0.0, 0.0};
    rec.t1_c = {30.0};
    std::ostringstream out;
    EXPECT_THROW(write_bdf_csv(out, rec), std::invalid_argument);
}

// Values at the writer's resolution (what instruments measure: 0.1 ms, 1 uV, 1 uA, 0.1 mK, 1 mW/m^2) read back
// bit-exactly; finer float noise from arithmetic is written clean (0.30000000000000004 -> 0.3, -0 -> 0).
TEST(BdfCsv, WriteThenParseRoundTripsBitExactlyAtTheResolution) {
    auto at = [](double v, double scale) { return std::round(v * scale) / scale; };
    Recording rec;
    rec.source = "round.bdf.csv";
    const std::size_t n = 2000;
    std::mt19937_64 rng(42);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    for (std::size_t i = 0; i < n; ++i) {
        rec.time_s.push_back(at(static_cast<double>(i) * 0.1, 1e4));  // 0.1 s steps, as the bench records
        rec.voltage_v.push_back(at(3.6 + 0.5 * u(rng), 1e6));
        rec.current_a.push_back(i % 7 == 0 ? 0.0 : at(18.0 * u(rng), 1e6));
        rec.unix_time_s.push_back(at(1747992938.0 + static_cast<double>(i) * 0.1, 1e4));
        rec.step_count.push_back(static_cast<double>(i / 100 + 1));
        rec.cycle_count.push_back(i % 3 == 0 ? cellbench::kNaN : 1.0);
        rec.step_type.push_back(i % 5 == 0 ? "CC, \"odd\"" : (i % 5 == 1 ? "" : (i % 5 == 2 ? " padded " : "Rest")));
        rec.ambient_c.push_back(at(30.0 + u(rng), 1e4));
        rec.surface_c.push_back(i % 11 == 0 ? cellbench::kNaN : at(29.0 + u(rng), 1e4));
        rec.t1_c.push_back(at(100.0 + u(rng) * 199.0, 1e4));  // physically possible (beyond -100..300 degC reads as empty)
        rec.t2_c.push_back(at(25.0 + u(rng), 1e4));
        rec.heat_flux_w_per_m2.push_back(at(u(rng) * 400.0, 1e3));
    }
    std::ostringstream out;
    write_bdf_csv(out, rec);
    BdfReadReport report;
    const Recording back = parse_bdf_csv(out.str(), "round.bdf.csv", &report);
    EXPECT_TRUE(report.ignored_columns.empty());
    EXPECT_EQ(back.repaired_timestamps, 0u);
    ASSERT_EQ(back.size(), n);
    EXPECT_EQ(back.step_type, rec.step_type);
    auto expect_same = [](const std::vector<double>& a, const std::vector<double>& b, const char* what) {
        ASSERT_EQ(a.size(), b.size()) << what;
        for (std::size_t i = 0; i < a.size(); ++i) {
            if (std::isnan(a[i])) {
                EXPECT_TRUE(std::isnan(b[i])) << what << " row " << i;
            } else {
                EXPECT_TRUE(same_bits(a[i], b[i])) << what << " row " << i << ": " << a[i] << " vs " << b[i];
            }
        }
    };
    expect_same(rec.time_s, back.time_s, "time");
    expect_same(rec.voltage_v, back.voltage_v, "voltage");
    expect_same(rec.current_a, back.current_a, "current");
    expect_same(rec.unix_time_s, back.unix_time_s, "unix time");
    expect_same(rec.step_count, back.step_count, "step count");
    expect_same(rec.cycle_count, back.cycle_count, "cycle count");
    expect_same(rec.ambient_c, back.ambient_c, "ambient");
    expect_same(rec.surface_c, back.surface_c, "surface");
    expect_same(rec.t1_c, back.t1_c, "t1");
    expect_same(rec.t2_c, back.t2_c, "t2");
    expect_same(rec.heat_flux_w_per_m2, back.heat_flux_w_per_m2, "heat flux");
}

TEST(BdfCsv, WriterDropsFloatNoiseAndNegativeZero) {
    Recording rec;
    rec.time_s = {0.1 + 0.2, 1.0000000000000002};
    rec.voltage_v = {4.0997000000000003, 3.7000000000000002};
    rec.current_a = {-0.0, 0.1 + 0.2 - 0.3};  // arithmetic noise of 5.6e-17 A, not a current
    rec.surface_c = {30.000000000000004, 29.999999999999996};
    std::ostringstream out;
    write_bdf_csv(out, rec);
    EXPECT_EQ(out.str(),
              "Test Time / s,Voltage / V,Current / A,Surface Temperature / degC\n"
              "0.3,4.0997,0,30\n"
              "1,3.7,0,30\n");
}

// Mangled input must end in a result or an InputError, never a crash or another exception type
// (a cheap stand-in for the libFuzzer target; run it under ASan/UBSan to make it bite harder).
TEST(BdfCsv, MangledInputEitherParsesOrThrowsInputError) {
    const std::string valid =
        "\xEF\xBB\xBF"
        "Test Time / s,Voltage / V,Current / A,Step Type,Surface Temperature / degC\r\n"
        "0,3.7,0,Rest,29.5\r\n0.1,3.7,\"-4.5\",\"CC DChg\",29.6\r\n0.1,3.71,-4.5,CC DChg,\r\n0.2,3.72,-4.5,Rest,29.7\r\n";
    const std::string alphabet = ",\"\r\n .-+e0123456789naif\xEF\xBB\xBF\t/";
    std::mt19937 rng(7);
    std::size_t parsed = 0, rejected = 0;
    for (int trial = 0; trial < 5000; ++trial) {
        std::string text = valid;
        const int edits = 1 + static_cast<int>(rng() % 4);
        for (int e = 0; e < edits && !text.empty(); ++e) {
            const std::size_t at = rng() % text.size();
            switch (rng() % 3) {
                case 0: text[at] = alphabet[rng() % alphabet.size()]; break;
                case 1: text.erase(at, 1 + rng() % 8); break;
                default: text.insert(at, 1, alphabet[rng() % alphabet.size()]); break;
            }
        }
        try {
            const Recording rec = parse_bdf_csv(text, "fuzz");
            ++parsed;
            for (std::size_t i = 1; i < rec.size(); ++i) ASSERT_LT(rec.time_s[i - 1], rec.time_s[i]);
        } catch (const InputError&) {
            ++rejected;
        }
    }
    EXPECT_GT(parsed, 0u);
    EXPECT_GT(rejected, 0u);
}

}  // namespace

TEST(BdfCsv, NumbersReadBitForBitAsFromChars) {
    // The reader's fast path for plain decimals must give exactly what std::from_chars gives (correct rounding),
    // and leave everything else (exponents, more than 15 digits, junk) to it.
    std::mt19937_64 rng(7);
    std::uniform_int_distribution<int> digit(0, 9), len(1, 18), point(0, 19), sign(0, 3);
    for (int k = 0; k < 200000; ++k) {
        std::string cell = sign(rng) == 0 ? "-" : "";
        const int n = len(rng), dot = point(rng);
        for (int j = 0; j < n; ++j) {
            if (j == dot) cell += '.';
            cell += static_cast<char>('0' + digit(rng));
        }
        if (k % 50 == 0) cell += "e-3";
        double want = 0.0, got = 0.0;
        const auto [ptr, ec] = std::from_chars(cell.data(), cell.data() + cell.size(), want);
        ASSERT_TRUE(ec == std::errc{} && ptr == cell.data() + cell.size()) << cell;
        ASSERT_EQ(cellbench::protocol::csv::parse_double(cell, got), cellbench::protocol::csv::NumberStatus::ok) << cell;
        ASSERT_EQ(std::memcmp(&got, &want, sizeof got), 0) << cell << ": " << got << " vs " << want;
    }
    double v = 0.0;
    for (const char* bad : {".", "-", "1.2.3", "1,5", "--1", "1-", "0x10", "1e"})
        EXPECT_NE(cellbench::protocol::csv::parse_double(bad, v), cellbench::protocol::csv::NumberStatus::ok) << bad;
}

// A spreadsheet or a DAQ program in a locale whose decimal mark is the comma writes ';' between cells (or a tab) and
// "3,7125" for a number. Such a file reads as the comma-separated one with the same numbers, and the report says so,
// where it used to be refused for a unit of "Test Time / s;Voltage / V;..." it did not know.
namespace {
const std::string kCommaBdf =
    "Test Time / s,Voltage / V,Current / A,Step Type,Surface Temperature / degC\n"
    "0,4.0964,0,Rest,29.45\n"
    "0.1,4.0512,-4.5,CC DChg,29.46\n"
    "0.2,4.0498,-4.5,CC DChg,\n"
    "1.5e1,4.1,1.25e-3,\"CC, Chg\",29.5\n";

void expect_same_recording(const Recording& a, const Recording& b) {
    EXPECT_EQ(a.time_s, b.time_s);
    EXPECT_EQ(a.voltage_v, b.voltage_v);
    EXPECT_EQ(a.current_a, b.current_a);
    EXPECT_EQ(a.step_type, b.step_type);
    ASSERT_EQ(a.surface_c.size(), b.surface_c.size());
    for (std::size_t k = 0; k < a.surface_c.size(); ++k)
        EXPECT_TRUE(same_bits(a.surface_c[k], b.surface_c[k]) || (std::isnan(a.surface_c[k]) && std::isnan(b.surface_c[k])))
            << "row " << k;
}
}  // namespace

TEST(BdfCsvDialect, SemicolonsAndDecimalCommasReadAsTheCommaFile) {
    const std::string euro =
        "Test Time / s;Voltage / V;Current / A;Step Type;Surface Temperature / degC\r\n"
        "0;4,0964;0;Rest;29,45\r\n"
        "0,1;4,0512;-4,5;CC DChg;29,46\r\n"
        "0,2 ; 4,0498 ;-4,5;CC DChg;\r\n"
        "1,5e1;4,1;1,25e-3;\"CC, Chg\";29,5\r\n";
    BdfReadReport comma_report, report;
    const Recording comma = parse_bdf_csv(kCommaBdf, "x.csv", &comma_report);
    const Recording rec = parse_bdf_csv(euro, "x.csv", &report);
    expect_same_recording(rec, comma);
    // Text keeps its commas: only a cell of digits with one comma is a number.
    EXPECT_EQ(rec.step_type.back(), "CC, Chg");
    EXPECT_EQ(comma_report.separator, ',');
    EXPECT_EQ(report.separator, ';');
    const auto messages = cellbench::protocol::describe(report, "x.csv");
    ASSERT_FALSE(messages.empty());
    EXPECT_NE(messages.front().text.find("semicolon-separated"), std::string::npos) << messages.front().text;
    EXPECT_FALSE(messages.front().warning);
    EXPECT_TRUE(cellbench::protocol::describe(comma_report, "x.csv").empty());
}

TEST(BdfCsvDialect, TabsSeparateCellsAndAreNotTrimmedAway) {
    std::string tabbed = kCommaBdf;
    // Every separator a tab; the quoted cell's comma stays text.
    for (std::size_t k = 0; k < tabbed.size(); ++k)
        if (tabbed[k] == ',' && !(k > 0 && tabbed[k - 1] == 'C' && k + 1 < tabbed.size() && tabbed[k + 1] == ' '))
            tabbed[k] = '\t';
    BdfReadReport report;
    const Recording rec = parse_bdf_csv(tabbed, "x.tsv", &report);
    expect_same_recording(rec, parse_bdf_csv(kCommaBdf, "x.csv"));
    EXPECT_EQ(report.separator, '\t');
    // An empty cell between two tabs is a cell, not trimmed whitespace: the temperature of row 3 is missing.
    EXPECT_TRUE(std::isnan(rec.surface_c.at(2)));
}

TEST(BdfCsvDialect, TheHeaderDecidesAndACommaFileKeepsItsRules) {
    // A comma in the header makes it a comma file: a ';' in a data cell is text there (an error for a number).
    const std::string mixed = "Test Time / s,Voltage / V,Current / A\n0;1,4.0,0\n";
    EXPECT_NE(error_of(mixed).find("Test Time / s"), std::string::npos) << error_of(mixed);
    // In a semicolon file a number with two commas, or a comma and a point, is no number: an error naming the cell.
    const std::string two_commas = "Test Time / s;Voltage / V;Current / A\n0;4,0,1;0\n";
    EXPECT_NE(error_of(two_commas).find("4,0,1"), std::string::npos) << error_of(two_commas);
    const std::string thousands = "Test Time / s;Voltage / V;Current / A\n1.000,5;4,0;0\n";
    EXPECT_NE(error_of(thousands).find("1.000,5"), std::string::npos) << error_of(thousands);
    // Text after a closing quote names the separator the file uses.
    const std::string after_quote = "Test Time / s;Voltage / V;Current / A\n\"0\"x;4,0;0\n";
    EXPECT_NE(error_of(after_quote).find("expected ';'"), std::string::npos) << error_of(after_quote);
}
