// GET /metrics: the Prometheus text exposition format 0.0.4 written by daemon/src/metrics.cpp.
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "cellbench/daemon/metrics.hpp"

using namespace cellbench::daemon;
using namespace cellbench::daemon::metrics;

namespace {

std::vector<std::string> lines_of(const std::string& text) {
    std::vector<std::string> out;
    std::istringstream in(text);
    for (std::string l; std::getline(in, l);) out.push_back(l);
    return out;
}

// The metric name of a sample line: up to '{' or ' '.
std::string sample_name(const std::string& line) { return line.substr(0, line.find_first_of("{ ")); }

// Checks the structure a Prometheus scraper relies on: every family has "# HELP" then "# TYPE" once, before
// its samples, and its samples are contiguous. Returns family -> type.
std::map<std::string, std::string> check_structure(const std::string& text) {
    EXPECT_FALSE(text.empty());
    EXPECT_EQ(text.back(), '\n');
    std::map<std::string, std::string> types;
    std::set<std::string> helped;
    std::string current;
    for (const auto& l : lines_of(text)) {
        EXPECT_FALSE(l.empty()) << "blank line in the exposition";
        if (l.rfind("# HELP ", 0) == 0) {
            const std::string name = l.substr(7, l.find(' ', 7) - 7);
            EXPECT_TRUE(helped.insert(name).second) << "HELP twice for " << name;
            current.clear();
        } else if (l.rfind("# TYPE ", 0) == 0) {
            std::istringstream in(l.substr(7));
            std::string name, type;
            in >> name >> type;
            EXPECT_TRUE(helped.count(name)) << "TYPE before HELP for " << name;
            EXPECT_TRUE(type == "counter" || type == "gauge") << l;
            EXPECT_TRUE(types.emplace(name, type).second) << "TYPE twice for " << name;
            current = name;
        } else {
            EXPECT_NE(l[0], '#') << l;
            EXPECT_EQ(sample_name(l), current) << "sample outside its family: " << l;
        }
    }
    return types;
}

// The value of the sample line that starts with `series` followed by a space, or NaN when absent.
double value_of(const std::string& text, const std::string& series) {
    for (const auto& l : lines_of(text))
        if (l.rfind(series + " ", 0) == 0) return std::stod(l.substr(series.size() + 1));
    return std::numeric_limits<double>::quiet_NaN();
}

}  // namespace

TEST(MetricsFormat, EscapesLabelValuesAndHelp) {
    EXPECT_EQ(escape_label_value("plain"), "plain");
    EXPECT_EQ(escape_label_value("a\\b\"c\nd"), "a\\\\b\\\"c\\nd");
    EXPECT_EQ(escape_help("x \\ y\nz \"q\""), "x \\\\ y\\nz \"q\"");  // quotes stay in help text
}

TEST(MetricsFormat, ValuesRoundTripAndSpecials) {
    EXPECT_EQ(format_value(1.0), "1");
    EXPECT_EQ(format_value(0.1), "0.1");
    EXPECT_EQ(format_value(-3.82), "-3.82");
    EXPECT_EQ(std::stod(format_value(1.0 / 3.0)), 1.0 / 3.0);
    EXPECT_EQ(format_value(std::numeric_limits<double>::quiet_NaN()), "NaN");
    EXPECT_EQ(format_value(std::numeric_limits<double>::infinity()), "+Inf");
    EXPECT_EQ(format_value(-std::numeric_limits<double>::infinity()), "-Inf");
}

TEST(MetricsFormat, NamesAreChecked) {
    EXPECT_TRUE(valid_metric_name("cellbench_run_active"));
    EXPECT_TRUE(valid_metric_name("ns:sub_total"));
    EXPECT_FALSE(valid_metric_name(""));
    EXPECT_FALSE(valid_metric_name("1abc"));
    EXPECT_FALSE(valid_metric_name("a-b"));
    EXPECT_TRUE(valid_label_name("instrument"));
    EXPECT_FALSE(valid_label_name("__reserved"));
    EXPECT_FALSE(valid_label_name("a:b"));
    EXPECT_FALSE(valid_label_name("0a"));
}

TEST(MetricsFormat, FamilyHasHelpTypeAndLabelledSamples) {
    Exposition x;
    x.family("cellbench_things_total", MetricType::counter, "Things, by \"kind\".\nSecond line \\ slash.")
        .sample(std::uint64_t{3}, {{"kind", "a\"b"}, {"where", "x\\y\nz"}})
        .sample(std::uint64_t{0}, {{"kind", "c"}, {"where", ""}});
    x.gauge("cellbench_level", "A gauge.", -1.5);
    EXPECT_EQ(x.text(),
              "# HELP cellbench_things_total Things, by \"kind\".\\nSecond line \\\\ slash.\n"
              "# TYPE cellbench_things_total counter\n"
              "cellbench_things_total{kind=\"a\\\"b\",where=\"x\\\\y\\nz\"} 3\n"
              "cellbench_things_total{kind=\"c\",where=\"\"} 0\n"
              "# HELP cellbench_level A gauge.\n"
              "# TYPE cellbench_level gauge\n"
              "cellbench_level -1.5\n");
    const auto types = check_structure(x.text());
    EXPECT_EQ(types.at("cellbench_things_total"), "counter");
    EXPECT_EQ(types.at("cellbench_level"), "gauge");
}

TEST(MetricsFormat, CountersVersusGaugesAreEnforced) {
    Exposition x;
    EXPECT_THROW(x.sample(1.0), std::logic_error);  // no family yet
    EXPECT_THROW(x.family("cellbench_frames", MetricType::counter, "no _total suffix"), std::invalid_argument);
    x.family("cellbench_frames_total", MetricType::counter, "ok");
    EXPECT_THROW(x.sample(-1.0), std::invalid_argument);
    EXPECT_THROW(x.sample(std::numeric_limits<double>::quiet_NaN()), std::invalid_argument);
    EXPECT_THROW(x.sample(1.0, {{"bad-label", "v"}}), std::invalid_argument);
    EXPECT_THROW(x.family("cellbench_frames_total", MetricType::counter, "again"), std::invalid_argument);
    EXPECT_THROW(x.family("bad name", MetricType::gauge, "h"), std::invalid_argument);
    x.family("cellbench_temperature_celsius", MetricType::gauge, "gauges may go down and be NaN");
    EXPECT_NO_THROW(x.sample(-5.0));
    EXPECT_NO_THROW(x.sample(std::numeric_limits<double>::quiet_NaN(), {{"sensor", "t1"}}));
}

TEST(MetricsRate, SlidingWindowRate) {
    RateMeter m(10.0);
    EXPECT_EQ(m.rate(0.0, 0.0), 0.0);  // no history
    m.observe(0.0, 0.0);
    EXPECT_EQ(m.rate(0.1, 5.0), 0.0);  // too little history to say
    for (int t = 1; t <= 30; ++t) m.observe(t, 100.0 * t);  // 100 per second
    EXPECT_DOUBLE_EQ(m.rate(30.0, 3000.0), 100.0);
    // The rate follows a change within a window: 20 per second from t = 30 on.
    for (int t = 31; t <= 45; ++t) m.observe(t, 3000.0 + 20.0 * (t - 30));
    EXPECT_DOUBLE_EQ(m.rate(45.0, 3300.0), 20.0);
    // Nothing arrives: the rate falls to zero.
    EXPECT_DOUBLE_EQ(m.rate(80.0, 3300.0), 0.0);
}

TEST(MetricsBench, SnapshotExposesInstrumentsStreamStoreAndRun) {
    BenchSnapshot s;
    s.uptime_s = 12.5;
    s.version = "1.2.3";
    s.git = "abc1234-dirty";
    s.instruments = {{"neware", "cycler", "connected", true, 42, 5, 2, 3},
                     {"chamber", "chamber", "offline", false, std::nullopt, 1, 0, std::nullopt},
                     {"dewe", "daq", "connected", true, std::nullopt, 0, 1, 7}};
    cellbench::protocol::DeweStreamStats d;
    d.frames = 1000;
    d.lost_frames = 7;
    d.samples = 250;
    d.lost_samples = 2;
    s.daq_stream = d;
    StoreStats st;
    st.samples_queued = 123;
    st.batches = 9;
    st.failed_batches = 1;
    st.samples_written = 5000;
    st.cycler_samples_accepted = 4000;
    st.daq_samples_accepted = 900;
    st.chamber_samples_accepted = 100;
    st.cycler_samples_per_s = 10.0;
    st.last_batch_ms = 4.0;
    s.store = st;
    RunSnapshot r;
    r.id = 3;
    r.state = "running";
    r.active = true;
    r.step_index = 12;
    r.step_count = 140;
    s.run = r;
    s.voltage_v = 3.712;

    const std::string text = format_bench_metrics(s);
    const auto types = check_structure(text);
    for (const auto& [name, type] : types) {
        EXPECT_EQ(name.rfind("cellbench_", 0), 0u) << name;
        EXPECT_EQ(type == "counter", name.size() > 6 && name.ends_with("_total")) << name << " is a " << type;
    }
    EXPECT_EQ(types.at("cellbench_daq_can_lost_frames_total"), "counter");
    EXPECT_EQ(types.at("cellbench_store_queue_samples"), "gauge");
    EXPECT_EQ(types.at("cellbench_samples_ingested_per_second"), "gauge");

    EXPECT_EQ(value_of(text, "cellbench_instrument_connected{instrument=\"neware\",kind=\"cycler\",mode=\"simulated\"}"), 1);
    EXPECT_EQ(value_of(text, "cellbench_instrument_connected{instrument=\"chamber\",kind=\"chamber\",mode=\"real\"}"), 0);
    EXPECT_EQ(value_of(text, "cellbench_instrument_state{instrument=\"chamber\",state=\"offline\"}"), 1);
    EXPECT_EQ(value_of(text, "cellbench_instrument_state{instrument=\"chamber\",state=\"connected\"}"), 0);
    EXPECT_EQ(value_of(text, "cellbench_sim_requests_total{instrument=\"neware\"}"), 42);
    EXPECT_EQ(value_of(text, "cellbench_build_info{version=\"1.2.3\",git=\"abc1234-dirty\"}"), 1);
    EXPECT_EQ(value_of(text, "cellbench_instrument_faults_total{instrument=\"neware\"}"), 5);
    EXPECT_EQ(value_of(text, "cellbench_instrument_faults_total{instrument=\"dewe\"}"), 0);
    EXPECT_EQ(value_of(text, "cellbench_instrument_reconnects_total{instrument=\"neware\"}"), 2);
    EXPECT_EQ(value_of(text, "cellbench_instrument_lost_frames_total{instrument=\"neware\"}"), 3);
    EXPECT_EQ(value_of(text, "cellbench_instrument_lost_frames_total{instrument=\"dewe\"}"), 7);
    // The chamber has no frame counter: no lost-frames sample that would read as "none lost".
    EXPECT_EQ(text.find("cellbench_instrument_lost_frames_total{instrument=\"chamber\"}"), std::string::npos);
    // Rows of a run are counted by the store (cellbench_store_samples_written_total), not per run.
    EXPECT_EQ(text.find("cellbench_run_samples"), std::string::npos);
    EXPECT_EQ(value_of(text, "cellbench_daq_can_frames_total"), 1000);
    EXPECT_EQ(value_of(text, "cellbench_daq_can_lost_frames_total"), 7);
    EXPECT_EQ(value_of(text, "cellbench_daq_lost_samples_total"), 2);
    EXPECT_EQ(value_of(text, "cellbench_samples_ingested_total{source=\"daq\"}"), 900);
    EXPECT_EQ(value_of(text, "cellbench_samples_ingested_per_second{source=\"cycler\"}"), 10);
    EXPECT_EQ(value_of(text, "cellbench_store_queue_samples"), 123);
    EXPECT_EQ(value_of(text, "cellbench_store_batches_total{result=\"committed\"}"), 9);
    EXPECT_EQ(value_of(text, "cellbench_store_batches_total{result=\"failed\"}"), 1);
    EXPECT_DOUBLE_EQ(value_of(text, "cellbench_store_last_batch_seconds"), 0.004);
    EXPECT_EQ(value_of(text, "cellbench_run_active"), 1);
    EXPECT_EQ(value_of(text, "cellbench_run_state{run=\"3\",state=\"running\"}"), 1);
    EXPECT_EQ(value_of(text, "cellbench_run_state{run=\"3\",state=\"aborted\"}"), 0);
    EXPECT_EQ(value_of(text, "cellbench_run_state{run=\"3\",state=\"waiting_equilibrium\"}"), 0);
    EXPECT_EQ(value_of(text, "cellbench_run_step"), 12);
    EXPECT_EQ(value_of(text, "cellbench_run_steps"), 140);
    EXPECT_DOUBLE_EQ(value_of(text, "cellbench_cell_voltage_volts"), 3.712);
    EXPECT_TRUE(std::isnan(value_of(text, "cellbench_cell_current_amperes")));  // no reading: no sample
}

TEST(MetricsBench, EmptyBenchStillValid) {
    BenchSnapshot s;  // nothing connected yet, no store, no run
    const std::string text = format_bench_metrics(s);
    check_structure(text);
    EXPECT_EQ(value_of(text, "cellbench_run_active"), 0);
    EXPECT_EQ(text.find("cellbench_run_state{"), std::string::npos);
}
