// An independent client against `cellbench sim` (its own process, as real instruments are separate boxes):
// raw BTS XML over TCP with garbage between frames, Modbus function 3 and an unsupported function.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <modbus/modbus.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>

namespace fs = std::filesystem;

namespace {

const fs::path kBin = fs::path(CELLBENCH_BIN_DIR) / "cellbench";
const fs::path kSource = CELLBENCH_SOURCE_DIR;
constexpr const char* kTerminator = "\n\n#\r\n";

struct SimProcess {
    pid_t pid = -1;
    FILE* out = nullptr;
    int neware_port = 0, chamber_port = 0;
    std::string dewe;
};

SimProcess start_sim(const fs::path& config) {
    int fds[2];
    if (pipe(fds) != 0) return {};
    SimProcess p;
    p.pid = fork();
    if (p.pid == 0) {
        dup2(fds[1], STDOUT_FILENO);
        close(fds[0]);
        close_range(3, ~0U, 0);  // the test's own sockets stay with the test
        execl(kBin.c_str(), kBin.c_str(), "-q", "sim", "--config", config.c_str(), "--time-scale", "100", nullptr);
        _exit(127);
    }
    close(fds[1]);
    p.out = fdopen(fds[0], "r");
    char line[512];
    for (int k = 0; k < 3 && fgets(line, sizeof line, p.out); ++k) {
        const std::string s(line);
        const auto colon = s.rfind(':');
        if (s.rfind("neware tcp ", 0) == 0) p.neware_port = std::stoi(s.substr(colon + 1));
        if (s.rfind("chamber modbus-tcp ", 0) == 0) p.chamber_port = std::stoi(s.substr(colon + 1));
        if (s.rfind("dewe ", 0) == 0) p.dewe = s.substr(5);
    }
    return p;
}

std::string exchange_frame(int fd, const std::string& bytes) {
    if (::send(fd, bytes.data(), bytes.size(), 0) != static_cast<ssize_t>(bytes.size())) return {};
    std::string got;
    char buf[4096];
    while (got.find(kTerminator) == std::string::npos) {
        const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
        if (n <= 0) break;
        got.append(buf, static_cast<std::size_t>(n));
    }
    return got;
}

std::string request(const std::string& cmd, const std::string& list) {
    return "<?xml version=\"1.0\" encoding=\"UTF-8\" ?>\r\n<bts version=\"1.0\">\r\n<cmd>" + cmd + "</cmd>\r\n" + list +
           "</bts>" + kTerminator;
}

}  // namespace

TEST(SimulatedBench, IndependentClientsTalkToCellbenchSim) {
    const fs::path dir = fs::temp_directory_path() / ("cellbench-sim-" + std::to_string(::getpid()));
    fs::create_directories(dir);
    std::ifstream in(kSource / "config/bench.sim.json");
    auto cfg = nlohmann::json::parse(in);
    cfg["instruments"]["cycler"]["port"] = 0;  // any free port: the process prints the one it bound
    cfg["instruments"]["chamber"]["port"] = 0;
    cfg["instruments"]["daq"]["socket_path"] = (dir / "dewe.sock").string();
    cfg["simulation"]["params"] = (kSource / "config/cells/p45b-thesis.json").string();
    std::ofstream(dir / "bench.json") << cfg.dump(2);

    SimProcess sim = start_sim(dir / "bench.json");
    ASSERT_GT(sim.pid, 0);
    ASSERT_GT(sim.neware_port, 0) << "no 'neware tcp' line";
    ASSERT_GT(sim.chamber_port, 0) << "no 'chamber modbus-tcp' line";
    EXPECT_NE(sim.dewe.find("can-dgram"), std::string::npos);

    // Neware BTS API: garbage before a frame, then getchlstatus and inquire.
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<std::uint16_t>(sim.neware_port));
    inet_pton(AF_INET, "127.0.0.1", &addr.sin_addr);
    ASSERT_EQ(::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
    const std::string chl = "ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"1\"";
    auto status = exchange_frame(fd, "garbage that is not a frame\r\n" +
                                         request("getchlstatus", "<list count=\"1\"><status " + chl + ">true</status></list>\r\n"));
    EXPECT_NE(status.find("<cmd>getchlstatus_resp</cmd>"), std::string::npos) << status;
    EXPECT_TRUE(status.find(">stop<") != std::string::npos || status.find(">finish<") != std::string::npos) << status;
    auto inquire = exchange_frame(
        fd, request("inquire", "<list count=\"1\"><inquire " + chl + " aux=\"0\" barcode=\"1\">true</inquire></list>\r\n"));
    EXPECT_NE(inquire.find("<cmd>inquire_resp</cmd>"), std::string::npos) << inquire;
    const auto v = inquire.find("voltage=\"");
    ASSERT_NE(v, std::string::npos) << inquire;
    const double volts = std::stod(inquire.substr(v + 9));
    EXPECT_GT(volts, 3.9);  // a full P45B at rest
    EXPECT_LT(volts, 4.2);
    ::close(fd);

    // Chamber: Modbus function 3 answers; an unsupported function gets an exception.
    modbus_t* mb = modbus_new_tcp("127.0.0.1", sim.chamber_port);
    ASSERT_NE(mb, nullptr);
    // libmodbus waits 0.5 s for a reply by default: too short for a busy machine (a reply only ever comes late).
    modbus_set_response_timeout(mb, 10, 0);
    ASSERT_EQ(modbus_connect(mb), 0);
    std::uint16_t regs[2] = {};
    EXPECT_EQ(modbus_read_registers(mb, 1, 2, regs), 2) << modbus_strerror(errno);
    std::uint8_t raw[] = {1, 0x11};  // report server id: not implemented by the chamber
    ASSERT_GT(modbus_send_raw_request(mb, raw, sizeof raw), 0);
    std::uint8_t rsp[MODBUS_TCP_MAX_ADU_LENGTH];
    // The reply to a raw request comes back raw: MBAP header (7 bytes), function | 0x80, exception code.
    ASSERT_EQ(modbus_receive_confirmation(mb, rsp), 9);
    EXPECT_EQ(rsp[7], 0x11 | 0x80);
    EXPECT_EQ(rsp[8], MODBUS_EXCEPTION_ILLEGAL_FUNCTION);
    modbus_close(mb);
    modbus_free(mb);

    ::kill(sim.pid, SIGTERM);
    int st = 0;
    ::waitpid(sim.pid, &st, 0);
    EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0) << "cellbench sim must stop cleanly on SIGTERM";
    if (sim.out) fclose(sim.out);
    fs::remove_all(dir);
}
