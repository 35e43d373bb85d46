// The 22 responses captured from a real BTS 8.0 server (../shared/reference/neware/bts8-captured-responses.txt):
// every one parses to the right structs, and the simulated tester answers the request behind each one with
// the same elements and attributes (names; values differ: another tester, another cell). All but
// get_devinfo_bad_response (a server with no channels; the simulated tester always has its 8).
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <thread>

#include <arpa/inet.h>
#include <sys/socket.h>
#include <unistd.h>

#include <boost/property_tree/ptree.hpp>
#include <boost/property_tree/xml_parser.hpp>
#include <nlohmann/json.hpp>

#include "cellbench/estimator/params.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/sim/neware_server.hpp"
#include "cellbench/sim/plant.hpp"

using namespace cellbench;
using namespace cellbench::protocol::neware;
using namespace std::chrono_literals;

namespace {

const std::string kShared = CELLBENCH_SHARED_DIR;

// name -> exact bytes (CRLF kept) of each "=== name" block.
std::map<std::string, std::string> captures() {
    std::ifstream in(kShared + "/reference/neware/bts8-captured-responses.txt", std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    const std::string text = ss.str();
    std::map<std::string, std::string> out;
    std::size_t pos = text.find("=== ");
    while (pos != std::string::npos) {
        const std::size_t eol = text.find('\n', pos);
        std::string name = text.substr(pos + 4, eol - pos - 4);
        while (!name.empty() && (name.back() == '\r' || name.back() == ' ')) name.pop_back();
        const std::size_t next = text.find("=== ", eol);
        std::string body = text.substr(eol + 1, next == std::string::npos ? std::string::npos : next - eol - 1);
        while (!body.empty() && (body.back() == '\n' || body.back() == '\r' || body.back() == ' ')) body.pop_back();
        out[name] = body;
        pos = next;
    }
    return out;
}

template <typename T>
T parsed_as(const std::string& frame) {
    const Response r = parse_response(frame);
    EXPECT_TRUE(std::holds_alternative<T>(r)) << frame.substr(0, 200);
    return std::holds_alternative<T>(r) ? std::get<T>(r) : T{};
}

ChannelAddress addr(int devid, int sub, int chl, int devtype = 27) { return {"127.0.0.1", devtype, devid, sub, chl}; }

}  // namespace

TEST(NewareCaptures, AllTwentyTwoAreThere) {
    const auto c = captures();
    EXPECT_EQ(c.size(), 22u);
    for (const auto& [name, body] : c) {
        EXPECT_NO_THROW((void)parse_response(body)) << name;
        // And framed as a real server frames them, with and without the blank line before '#'.
        for (const std::string term : {"\n\n#\r\n", "#\r\n", "\r\n#\r\n"}) {
            FrameSplitter s;
            s.feed(body + term + body + term);
            const auto a = s.next();
            const auto b = s.next();
            ASSERT_TRUE(a && b) << name;
            EXPECT_EQ(*a, body) << name;
        }
    }
}

TEST(NewareCaptures, ConnectAndDevInfo) {
    const auto c = captures();
    EXPECT_TRUE(parsed_as<ConnectResponse>(c.at("connect_response")).ok);
    const auto info = parsed_as<GetDevInfoResponse>(c.at("get_devinfo_response"));
    ASSERT_EQ(info.servers.size(), 1u);
    EXPECT_EQ(info.servers[0].ip, "127.0.0.1");
    EXPECT_EQ(info.servers[0].port, 3306);
    ASSERT_EQ(info.channels.size(), 16u);
    EXPECT_EQ(info.channels[0].channel, addr(21, 1, 1));
    EXPECT_TRUE(info.channels[0].online);
    EXPECT_FALSE(info.channels[1].online);
    EXPECT_EQ(info.channels[15].channel, addr(21, 2, 8));
    const auto none = parsed_as<GetDevInfoResponse>(c.at("get_devinfo_bad_response"));
    EXPECT_TRUE(none.channels.empty());
    EXPECT_EQ(none.servers.size(), 1u);
}

TEST(NewareCaptures, ChannelStatusWithReservePause) {
    const auto c = captures();
    const auto all = parsed_as<ChannelStatusResponse>(c.at("get_status_all_response"));
    ASSERT_EQ(all.channels.size(), 16u);
    EXPECT_EQ(all.channels[0].status, ChannelStatus::finish);
    EXPECT_EQ(all.channels[1].status, ChannelStatus::working);
    EXPECT_TRUE(all.channels[1].reserve_pause);
    EXPECT_EQ(all.channels[12].channel, addr(21, 2, 5));
    const auto one = parsed_as<ChannelStatusResponse>(c.at("get_status_21_1_1_response"));
    ASSERT_EQ(one.channels.size(), 1u);
    EXPECT_EQ(one.channels[0].channel, addr(21, 1, 1));
    EXPECT_EQ(one.channels[0].status, ChannelStatus::finish);
}

TEST(NewareCaptures, InquireLiveValuesAndRealStepTypes) {
    const auto c = captures();
    const auto all = parsed_as<InquireResponse>(c.at("inquire_all_response"));
    ASSERT_EQ(all.channels.size(), 16u);
    std::set<std::string> types;
    for (const auto& e : all.channels) types.insert(e.step_type);
    EXPECT_EQ(types, (std::set<std::string>{"--", "cc", "cv", "dc"}));
    const auto& idle = all.channels[0];
    EXPECT_EQ(idle.channel.key(), "27-21-1-1");
    EXPECT_EQ(idle.step_id, 0);  // idle channels omit step_id
    EXPECT_EQ(idle.workstatus, ChannelStatus::finish);
    EXPECT_DOUBLE_EQ(idle.voltage_v, 3.8834);  // the cell's voltage, not 0
    EXPECT_EQ(idle.barcode, "251203_kigr_gen17_01");
    const auto two = parsed_as<InquireResponse>(c.at("inquire_21_1_2_response"));
    ASSERT_EQ(two.channels.size(), 1u);
    const auto& w = two.channels[0];
    EXPECT_EQ(w.cycle_id, 44);
    EXPECT_EQ(w.step_id, 4);
    EXPECT_EQ(w.step_type, "dc");
    EXPECT_EQ(w.workstatus, ChannelStatus::working);
    EXPECT_DOUBLE_EQ(w.current_a, -0.0003);
    EXPECT_DOUBLE_EQ(w.voltage_v, 4.6947);
    EXPECT_DOUBLE_EQ(w.total_time_s, 3189199.3);
    EXPECT_DOUBLE_EQ(w.relative_time_s, 12319);
    EXPECT_EQ(w.log_code, 102000);
    // The count="1" of a two-entry list is not trusted: both entries are read.
    EXPECT_EQ(parsed_as<InquireResponse>(c.at("inquire_21_1_1_and_2_response")).channels.size(), 2u);
    EXPECT_EQ(parsed_as<InquireResponse>(c.at("inquire_21_1_1_response")).channels.size(), 1u);
    EXPECT_DOUBLE_EQ(parsed_as<InquireResponse>(c.at("inquire_21_1_4_response")).channels.at(0).voltage_v, 0.5741);
}

TEST(NewareCaptures, InquireDfGivesTestIdAndRowCount) {
    const auto c = captures();
    const auto all = parsed_as<InquireDfResponse>(c.at("inquiredf_all_response"));
    ASSERT_EQ(all.channels.size(), 16u);
    EXPECT_EQ(all.channels[0].channel, (ChannelAddress{"", 27, 21, 1, 1}));
    EXPECT_EQ(all.channels[0].testid, 143);
    EXPECT_EQ(all.channels[0].count, 219585);
    EXPECT_TRUE(all.channels[0].flag);
    EXPECT_FALSE(all.channels[1].flag);
    EXPECT_EQ(all.channels[15].testid, 109);
    const auto one = parsed_as<InquireDfResponse>(c.at("inquiredf_21_1_1_response"));
    ASSERT_EQ(one.channels.size(), 1u);
    EXPECT_EQ(one.channels[0].count, 219585);
}

TEST(NewareCaptures, ChannelCommandResults) {
    const auto c = captures();
    const auto start = parsed_as<ChannelCommandResponse>(c.at("start_21_1_1_response"));
    EXPECT_EQ(start.command, Command::start);
    ASSERT_EQ(start.channels.size(), 1u);
    EXPECT_TRUE(start.channels[0].ok);
    EXPECT_EQ(start.channels[0].channel, addr(21, 1, 1));
    const auto refused = parsed_as<ChannelCommandResponse>(c.at("start_21_1_4_bad_response"));
    EXPECT_FALSE(refused.channels.at(0).ok);
    EXPECT_EQ(refused.channels.at(0).text, "false");
    EXPECT_TRUE(parsed_as<ChannelCommandResponse>(c.at("stop_21_1_1_response")).channels.at(0).ok);
    const auto both = parsed_as<ChannelCommandResponse>(c.at("stop_21_1_1_and_21_1_2_response"));
    ASSERT_EQ(both.channels.size(), 2u);
    EXPECT_EQ(both.channels[1].channel, addr(21, 1, 2));
    EXPECT_FALSE(parsed_as<ChannelCommandResponse>(c.at("stop_21_1_4_bad_reponse")).channels.at(0).ok);
    const auto flag = parsed_as<ChannelCommandResponse>(c.at("clear_flag_response"));
    EXPECT_EQ(flag.command, Command::clearflag);
    EXPECT_FALSE(flag.channels.at(0).ok);
    const auto light = parsed_as<ChannelCommandResponse>(c.at("light_response"));
    EXPECT_EQ(light.command, Command::light);
    EXPECT_TRUE(light.channels.at(0).ok);
}

TEST(NewareCaptures, DownloadRespSpelledDonwload) {
    const auto c = captures();
    const auto d = parsed_as<DownloadResponse>(c.at("download_21_1_1_repsonse"));
    EXPECT_EQ(d.channel, (ChannelAddress{"", 27, 21, 1, 1}));
    EXPECT_EQ(d.testid, 143);
    EXPECT_EQ(d.startpos, 219576);
    EXPECT_EQ(d.count, 1000);
    EXPECT_EQ(d.auxid, 0);
    ASSERT_EQ(d.records.size(), 10u);
    const auto& r = d.records[2];
    EXPECT_EQ(r.seqid, 219578);
    EXPECT_EQ(r.step_id, 24);
    EXPECT_EQ(r.cycle_id, 29);
    EXPECT_EQ(r.step_type, "dc");
    EXPECT_DOUBLE_EQ(r.test_time_s, 36080.3);  // testtime is in ms
    EXPECT_EQ(r.atime, "2025-12-28 22:29:15");
    EXPECT_DOUBLE_EQ(r.voltage_v, 3.65737199783325);
    EXPECT_DOUBLE_EQ(r.current_a, -0.000295052188448608);
    EXPECT_DOUBLE_EQ(r.capacity_ah, 0.00295712845399976);
    EXPECT_EQ(d.records.back().seqid, 219585);
}

TEST(NewareCaptures, DownloadLogAndStepLayer) {
    const auto c = captures();
    const auto log = parsed_as<DownloadLogResponse>(c.at("downloadlog_21_1_1_response"));
    EXPECT_EQ(log.testid, 143);
    EXPECT_EQ(log.log_level, 0);
    ASSERT_EQ(log.entries.size(), 5u);
    EXPECT_EQ(log.entries[0].seqid, 1);
    EXPECT_EQ(log.entries[0].log_code, 100000);
    EXPECT_EQ(log.entries[4].log_code, 100001);
    EXPECT_EQ(log.entries[4].atime, "2025-12-28 22:30:11");
    const auto layer = parsed_as<StepLayerResponse>(c.at("download_step_layer_21_1_1_response"));
    EXPECT_EQ(layer.testid, 143);
    ASSERT_EQ(layer.steps.size(), 3u);
    EXPECT_EQ(layer.steps[0].step_type, "rest");
    EXPECT_DOUBLE_EQ(layer.steps[0].step_time_s, 43200.0);
    EXPECT_EQ(layer.steps[1].start_seqid, 4322);
    EXPECT_EQ(layer.steps[1].end_seqid, 7518);
    EXPECT_EQ(layer.steps[2].step_type, "cv");
    EXPECT_DOUBLE_EQ(layer.steps[2].end_voltage_v, 4.899825390625);
    EXPECT_EQ(layer.steps[2].end_atime, "2025-12-04 14:39:33");
}

TEST(NewareCaptures, EncoderWritesTheRealSpellings) {
    DownloadResponse d;
    d.channel = {"", 27, 21, 1, 1};
    EXPECT_NE(encode_response(d).find("<cmd>donwload_resp</cmd>"), std::string::npos);
    EXPECT_NE(encode_response(DownloadLogResponse{}).find("<cmd>donwloadlog_resp</cmd>"), std::string::npos);
    EXPECT_NE(encode_response(StepLayerResponse{}).find("<cmd>downloadStepLayer_resp</cmd>"), std::string::npos);
    // And read back what they write.
    EXPECT_TRUE(std::holds_alternative<DownloadResponse>(parse_response(encode_response(d))));
}

// ---------------------------------------------------------------------------------------------------------
// The simulated tester answers like the real one: same elements and attribute names per capture.

namespace {

namespace pt = boost::property_tree;

// "path@attr,attr|text" for every element (a set: list entries of one shape collapse to one string).
void shape_of(const pt::ptree& node, const std::string& path, std::set<std::string>& out) {
    std::set<std::string> attrs;
    if (const auto a = node.get_child_optional("<xmlattr>"))
        for (const auto& [k, v] : *a) attrs.insert(k);
    std::string s = path + "@";
    for (const auto& a : attrs) s += a + ",";
    bool has_children = false;
    for (const auto& [k, child] : node)
        if (k != "<xmlattr>") has_children = true;
    std::string text = node.data();
    text.erase(std::remove_if(text.begin(), text.end(), [](char ch) { return std::isspace(static_cast<unsigned char>(ch)); }),
               text.end());
    if (!has_children && !text.empty()) s += "|text";
    out.insert(s);
    for (const auto& [k, child] : node)
        if (k != "<xmlattr>") shape_of(child, path + "/" + k, out);
}

std::set<std::string> shape(const std::string& frame) {
    std::istringstream in(normalize_vendor_xml(frame));
    pt::ptree tree;
    pt::read_xml(in, tree);
    std::set<std::string> out;
    shape_of(tree, "", out);
    return out;
}

class SimTester {
public:
    SimTester() {
        std::ifstream in(std::string(CELLBENCH_SOURCE_DIR) + "/config/cells/p45b-thesis.json");
        sim::PlantOptions po;
        po.cell = estimator::ParameterSet::from_json(nlohmann::json::parse(in), "p45b-thesis.json");
        po.initial_soc = 0.5;
        plant_.emplace(po);
        clock_ = std::make_shared<const sim::BenchClock>(100.0, 0.0);
        sim::NewareServerOptions o;
        o.devtype = 27;  // the captured server's
        o.devid = 21;
        o.cell_channels = {1};
        server_ = std::make_unique<sim::NewareServer>(*plant_, clock_, o);
        server_->start();
        fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
        sockaddr_in a{};
        a.sin_family = AF_INET;
        a.sin_port = htons(static_cast<std::uint16_t>(server_->port()));
        inet_pton(AF_INET, "127.0.0.1", &a.sin_addr);
        if (::connect(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) fd_ = -1;
    }
    ~SimTester() {
        if (fd_ >= 0) ::close(fd_);
        server_->stop();
    }
    sim::NewareServer& server() { return *server_; }
    std::string ask(const Request& r) { return ask_bytes(encode_request(r)); }
    std::string ask_bytes(const std::string& bytes) {
        if (fd_ < 0 || ::send(fd_, bytes.data(), bytes.size(), 0) != static_cast<ssize_t>(bytes.size())) return {};
        char buf[65536];
        while (true) {
            if (auto f = splitter_.next()) return *f;
            const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
            if (n <= 0) return {};
            splitter_.feed(std::string_view(buf, static_cast<std::size_t>(n)));
        }
    }

private:
    std::optional<sim::BenchPlant> plant_;
    std::shared_ptr<const sim::BenchClock> clock_;
    std::unique_ptr<sim::NewareServer> server_;
    int fd_ = -1;
    FrameSplitter splitter_;
};

}  // namespace

TEST(NewareCaptures, SimulatorAnswersWithTheCapturedStructure) {
    const auto c = captures();
    SimTester sim;
    const ChannelAddress cell{"127.0.0.1", 27, 21, 1, 1};
    const ChannelAddress empty{"127.0.0.1", 27, 21, 1, 4};  // no cell: refuses start and stop like 21-1-4
    auto expect_same = [&](const std::string& capture, const std::string& answer) {
        ASSERT_FALSE(answer.empty()) << capture << ": no answer";
        EXPECT_EQ(shape(answer), shape(c.at(capture))) << capture << "\n--- simulator:\n" << answer;
    };
    expect_same("connect_response", sim.ask(ConnectRequest{}));
    expect_same("get_devinfo_response", sim.ask(GetDevInfoRequest{}));
    expect_same("get_status_21_1_1_response", sim.ask(ChannelListRequest{Command::getchlstatus, {cell}}));
    expect_same("inquire_21_1_1_response", sim.ask(InquireRequest{{cell}}));  // idle: no step_id
    expect_same("inquiredf_21_1_1_response", sim.ask(ChannelListRequest{Command::inquiredf, {cell}}));

    // A real BTS Client step file, started the way public clients start it.
    const std::string step_file = kShared + "/reference/neware/bts-client-2024-step-file.xml";
    const std::string start =
        "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>start</cmd><list count = \"1\">"
        "<start ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"1\" barcode=\"cell-01\">" +
        step_file +
        "</start><backup backupdir=\"C:\\Neware data\\\" remotedir=\"\" filenametype=\"0\" customfilename=\"\" "
        "addtimewhenrepeat=\"0\" createdirbydate=\"0\" filetype=\"0\" backupontime=\"1\" backupontimeinterval=\"720\" "
        "backupfree=\"1\" /></list>\"</bts>\n\n#\r\n";
    const std::string started = sim.ask_bytes(start);
    expect_same("start_21_1_1_response", started);
    EXPECT_NE(started.find(">ok</start>"), std::string::npos) << started;
    StartRequest refused;
    refused.entries.push_back({empty, step_file, "x", ""});
    expect_same("start_21_1_4_bad_response", sim.ask(refused));

    // Working: some rows recorded.
    for (int k = 0; k < 100 && sim.server().snapshot().total_time_s < 30.0; ++k) std::this_thread::sleep_for(20ms);
    expect_same("inquire_21_1_2_response", sim.ask(InquireRequest{{cell}}));  // working: with step_id
    expect_same("inquire_21_1_4_response", sim.ask(InquireRequest{{empty}}));  // idle, no cell
    // Working and idle channels in one answer (the captured "all" answers mix both shapes).
    expect_same("inquire_all_response", sim.ask(InquireRequest{{cell, empty}}));
    expect_same("inquire_21_1_1_and_2_response", sim.ask(InquireRequest{{empty, cell}}));
    std::vector<ChannelAddress> all;
    for (int k = 1; k <= 8; ++k) all.push_back({"127.0.0.1", 27, 21, 1, k});
    expect_same("get_status_all_response", sim.ask(ChannelListRequest{Command::getchlstatus, all}));
    expect_same("inquiredf_all_response", sim.ask(ChannelListRequest{Command::inquiredf, all}));
    const std::string inquired = sim.ask(InquireRequest{{cell}});
    EXPECT_NE(inquired.find("step_type=\"cc\""), std::string::npos) << inquired;  // real code of step 1 (CC Chg)
    DownloadRequest dl;
    dl.channel = cell;
    dl.startpos = 1;
    dl.count = 5;
    expect_same("download_21_1_1_repsonse", sim.ask(dl));
    TestRequest log{Command::downloadlog, cell, 0};
    TestRequest layer{Command::downloadStepLayer, cell, 0};
    expect_same("download_step_layer_21_1_1_response", sim.ask(layer));
    expect_same("clear_flag_response", sim.ask(ChannelListRequest{Command::clearflag, {cell}}));
    expect_same("light_response", sim.ask(ChannelListRequest{Command::light, {cell}}));
    expect_same("stop_21_1_1_response", sim.ask(ChannelListRequest{Command::stop, {cell}}));
    expect_same("downloadlog_21_1_1_response", sim.ask(log));  // start and end logged
    expect_same("stop_21_1_4_bad_reponse", sim.ask(ChannelListRequest{Command::stop, {ChannelAddress{"127.0.0.1", 27, 21, 1, 9}}}));

    // The test-id query: startpos 0, count 0.
    DownloadRequest id;
    id.channel = cell;
    id.startpos = 0;
    id.count = 0;
    const auto answer = parse_response(sim.ask(id));
    ASSERT_TRUE(std::holds_alternative<DownloadResponse>(answer));
    EXPECT_EQ(std::get<DownloadResponse>(answer).testid, 1);
    EXPECT_TRUE(std::get<DownloadResponse>(answer).records.empty());

    // An unknown command gets an error answer, not silence.
    const std::string unknown =
        sim.ask_bytes("<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>broadcaststop</cmd></bts>\n\n#\r\n");
    const auto err = parse_response(unknown);
    ASSERT_TRUE(std::holds_alternative<ErrorResponse>(err)) << unknown;
    EXPECT_EQ(std::get<ErrorResponse>(err).command, "broadcaststop");
    EXPECT_NE(std::get<ErrorResponse>(err).message.find("unknown command"), std::string::npos);
}
