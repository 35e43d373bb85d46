// An independent BTS 8 client (its own sockets and its own XML reading, none of the project's protocol or
// driver code) runs a whole job on `cellbench sim` the way public BTS 8 clients do: getdevinfo -> start with a
// real BTS Client step file (with <backup> and the stray '"' before </bts>) -> inquire / inquiredf while
// working -> test id (download startpos=0 count=0) -> download -> downloadlog -> downloadStepLayer -> light ->
// clearflag -> stop. Every request must be answered.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kSource = CELLBENCH_SOURCE_DIR;
const fs::path kStepFile = fs::path(CELLBENCH_SHARED_DIR) / "reference/neware/bts-client-2024-step-file.xml";

struct Sim {
    pid_t pid = -1;
    FILE* out = nullptr;
    int port = 0;
};

Sim start_sim(const fs::path& config) {
    int fds[2];
    if (pipe(fds) != 0) return {};
    Sim s;
    s.pid = fork();
    if (s.pid == 0) {
        dup2(fds[1], STDOUT_FILENO);
        close(fds[0]);
        close_range(3, ~0U, 0);
        execl(kBin.c_str(), kBin.c_str(), "-q", "sim", "--config", config.c_str(), "--time-scale", "100", nullptr);
        _exit(127);
    }
    close(fds[1]);
    s.out = fdopen(fds[0], "r");
    char line[512];
    for (int k = 0; k < 3 && fgets(line, sizeof line, s.out); ++k) {
        const std::string text(line);
        if (text.rfind("neware tcp ", 0) == 0) s.port = std::stoi(text.substr(text.rfind(':') + 1));
    }
    return s;
}

// A minimal BTS 8 client: one request, one answer; an answer ends at "</bts>" + optional whitespace + "#\r\n".
class Bts8Client {
public:
    explicit Bts8Client(int port) {
        fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
        timeval tv{5, 0};  // an unanswered request fails the test instead of hanging it
        setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
        sockaddr_in a{};
        a.sin_family = AF_INET;
        a.sin_port = htons(static_cast<std::uint16_t>(port));
        inet_pton(AF_INET, "127.0.0.1", &a.sin_addr);
        connected_ = ::connect(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
    }
    ~Bts8Client() { ::close(fd_); }
    bool connected() const { return connected_; }

    std::string command(const std::string& body, const std::string& terminator = "\n\n#\r\n") {
        const std::string bytes = "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\">" + body + "</bts>" + terminator;
        if (::send(fd_, bytes.data(), bytes.size(), 0) != static_cast<ssize_t>(bytes.size())) return {};
        char buf[8192];
        while (true) {
            const auto end = pending_.find("</bts>");
            if (end != std::string::npos) {
                auto k = end + 6;
                while (k < pending_.size() && (pending_[k] == '\r' || pending_[k] == '\n' || pending_[k] == ' ')) ++k;
                if (pending_.compare(k, 3, "#\r\n") == 0) {
                    std::string frame = pending_.substr(0, end + 6);
                    pending_.erase(0, k + 3);
                    return frame;
                }
            }
            const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
            if (n <= 0) return {};  // timeout or closed: unanswered
            pending_.append(buf, static_cast<std::size_t>(n));
        }
    }

private:
    int fd_ = -1;
    bool connected_ = false;
    std::string pending_;
};

std::string cmd_of(const std::string& frame) {
    std::smatch m;
    return std::regex_search(frame, m, std::regex("<cmd>([^<]*)</cmd>")) ? m[1].str() : std::string();
}

// Attributes of every <tag .../> or <tag ...>text</tag>, in order.
std::vector<std::map<std::string, std::string>> elements(const std::string& frame, const std::string& tag) {
    std::vector<std::map<std::string, std::string>> out;
    const std::regex element("<" + tag + "\\s([^>]*?)/?>(([^<]*)</" + tag + ">)?");
    const std::regex attribute("([A-Za-z_]+)\\s*=\\s*\"([^\"]*)\"");
    for (auto it = std::sregex_iterator(frame.begin(), frame.end(), element); it != std::sregex_iterator(); ++it) {
        std::map<std::string, std::string> attrs;
        const std::string inner = (*it)[1].str();
        for (auto a = std::sregex_iterator(inner.begin(), inner.end(), attribute); a != std::sregex_iterator(); ++a)
            attrs[(*a)[1].str()] = (*a)[2].str();
        attrs["#text"] = (*it)[3].str();
        out.push_back(attrs);
    }
    return out;
}

}  // namespace

TEST(NewareBts8Client, IndependentClientRunsAWholeJobOnCellbenchSim) {
    ASSERT_TRUE(fs::exists(kStepFile)) << kStepFile;
    const fs::path dir = fs::temp_directory_path() / ("cellbench-bts8-" + std::to_string(::getpid()));
    fs::create_directories(dir);
    std::ifstream in(kSource / "config/bench.sim.json");
    auto cfg = nlohmann::json::parse(in);
    cfg["instruments"]["cycler"]["port"] = 0;
    cfg["instruments"]["chamber"]["port"] = 0;
    cfg["instruments"]["daq"]["socket_path"] = (dir / "dewe.sock").string();
    cfg["simulation"]["params"] = (kSource / "config/cells/p45b-thesis.json").string();
    std::ofstream(dir / "bench.json") << cfg.dump(2);
    Sim sim = start_sim(dir / "bench.json");
    // A failed assertion returns early: the simulator process must not outlive the test.
    struct Reaper {
        Sim& s;
        ~Reaper() {
            if (s.pid > 0) {
                ::kill(s.pid, SIGKILL);
                ::waitpid(s.pid, nullptr, 0);
            }
            if (s.out) fclose(s.out);
        }
    } reaper{sim};
    ASSERT_GT(sim.pid, 0);
    ASSERT_GT(sim.port, 0) << "no 'neware tcp' line";

    {
        Bts8Client c(sim.port);
        ASSERT_TRUE(c.connected());
        const auto login = c.command("<cmd>connect</cmd><username>admin</username><password>neware</password><type>bfgs</type>");
        EXPECT_EQ(cmd_of(login), "connect_resp") << login;

        const auto info = c.command("<cmd>getdevinfo</cmd>");
        ASSERT_EQ(cmd_of(info), "getdevinfo_resp") << info;
        EXPECT_EQ(elements(info, "server").size(), 1u) << info;
        const auto channels = elements(info, "channel");
        ASSERT_FALSE(channels.empty()) << info;
        const auto& ch = channels.front();  // the first channel: wired to the simulated cell
        const std::string where = "devtype=\"" + ch.at("devtype") + "\" devid=\"" + ch.at("devid") + "\" subdevid=\"" +
                                  ch.at("subdevid") + "\" chlid=\"" + ch.at("Channelid") + "\"";
        const std::string at = "ip=\"" + ch.at("ip") + "\" " + where;

        // start: the step file's path on the "BTS PC", <backup> in the list, the stray quote before </bts>.
        const auto started = c.command(
            "<cmd>start</cmd><list count = \"1\"><start " + at + " barcode=\"bts8-hil\">" + kStepFile.string() +
            "</start><backup backupdir=\"C:\\Neware data\\\" remotedir=\"\" filenametype=\"0\" customfilename=\"\" "
            "addtimewhenrepeat=\"0\" createdirbydate=\"0\" filetype=\"0\" backupontime=\"1\" backupontimeinterval=\"720\" "
            "backupfree=\"1\" /></list>\"");
        ASSERT_EQ(cmd_of(started), "start_resp") << started;
        ASSERT_EQ(elements(started, "start").at(0).at("#text"), "ok") << started;

        std::this_thread::sleep_for(500ms);  // 50 bench s at time scale 100
        // This one framed without the blank line before '#'.
        const auto live = c.command("<cmd>inquire</cmd><list count = \"1\"><inquire " + at +
                                        " aux=\"0\" barcode=\"1\">true</inquire></list>",
                                    "#\r\n");
        ASSERT_EQ(cmd_of(live), "inquire_resp") << live;
        const auto entry = elements(live, "inquire").at(0);
        EXPECT_EQ(entry.at("workstatus"), "working") << live;
        EXPECT_EQ(entry.at("step_type"), "cc") << live;  // Step 1 of the BTS Client file: CC charge
        EXPECT_EQ(entry.at("step_id"), "1") << live;
        EXPECT_EQ(entry.at("barcode"), "bts8-hil");

        const auto df = c.command("<cmd>inquiredf</cmd><list count = \"1\"><chl " + where + " testid=\"0\" /></list>");
        ASSERT_EQ(cmd_of(df), "inquiredf_resp") << df;
        const auto test = elements(df, "chl").at(0);
        EXPECT_GT(std::stoll(test.at("count")), 0) << df;

        const auto id = c.command("<cmd>download</cmd><download " + where +
                                  " auxid=\"0\" testid=\"0\" startpos=\"0\" count=\"0\"/>");
        ASSERT_EQ(cmd_of(id), "donwload_resp") << id;  // sic, as real servers spell it
        const auto header = elements(id, "download").at(0);
        EXPECT_EQ(header.at("testid"), test.at("testid"));
        EXPECT_TRUE(elements(id, "data").empty());

        const auto rows = c.command("<cmd>download</cmd><download " + where + " auxid=\"0\" testid=\"" + header.at("testid") +
                                    "\" startpos=\"1\" count=\"100\"/>");
        ASSERT_EQ(cmd_of(rows), "donwload_resp") << rows;
        const auto data = elements(rows, "data");
        ASSERT_EQ(data.size(), 100u);
        EXPECT_EQ(data[0].at("seqid"), "1");
        EXPECT_EQ(data[0].at("steptype"), "cc");
        EXPECT_EQ(data[0].at("atime").size(), 19u);  // "YYYY-MM-DD hh:mm:ss"
        EXPECT_GT(std::stod(data[0].at("curr")), 0.0);  // charging
        EXPECT_LE(std::stod(data[0].at("curr")), 0.0225 + 1e-4);  // the file's 22.5 mA (shared by the group)

        const auto log = c.command("<cmd>downloadlog</cmd><download " + where + " testid=\"0\"/>");
        ASSERT_EQ(cmd_of(log), "donwloadlog_resp") << log;
        EXPECT_FALSE(elements(log, "data").empty()) << log;

        const auto layer = c.command("<cmd>downloadStepLayer</cmd><downloadStepLayer " + where + " />");
        ASSERT_EQ(cmd_of(layer), "downloadStepLayer_resp") << layer;
        ASSERT_FALSE(elements(layer, "data").empty()) << layer;
        EXPECT_EQ(elements(layer, "data").at(0).at("stepid"), "1");

        const auto light = c.command("<cmd>light</cmd><list count = \"1\"><light " + at + ">true</light></list>");
        ASSERT_EQ(cmd_of(light), "light_resp") << light;
        EXPECT_EQ(elements(light, "light").at(0).at("#text"), "ok");
        const auto flag = c.command("<cmd>clearflag</cmd><list count = \"1\"><clearflag " + at + ">true</clearflag></list>");
        EXPECT_EQ(cmd_of(flag), "clearflag_resp") << flag;

        const auto stop = c.command("<cmd>stop</cmd><list count = \"1\"><stop " + at + ">true</stop></list>");
        ASSERT_EQ(cmd_of(stop), "stop_resp") << stop;
        EXPECT_EQ(elements(stop, "stop").at(0).at("#text"), "ok");
        const auto after = c.command("<cmd>getchlstatus</cmd><list count = \"1\"><status " + at + ">true</status></list>");
        ASSERT_EQ(cmd_of(after), "getchlstatus_resp") << after;
        EXPECT_EQ(elements(after, "status").at(0).at("#text"), "stop") << after;
        EXPECT_EQ(elements(after, "status").at(0).at("reservepause"), "1");

        // A command the tester does not know is answered, never left hanging.
        const auto unknown = c.command("<cmd>broadcaststop</cmd>");
        EXPECT_EQ(cmd_of(unknown), "broadcaststop_resp") << unknown;
        EXPECT_NE(unknown.find("<error>"), std::string::npos) << unknown;
    }

    ::kill(sim.pid, SIGTERM);
    int st = 0;
    ::waitpid(sim.pid, &st, 0);
    sim.pid = -1;
    EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0) << "cellbench sim must stop cleanly on SIGTERM";
    fs::remove_all(dir);
}
