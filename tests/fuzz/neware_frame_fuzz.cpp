// libFuzzer target: bytes from the network through FrameSplitter and the BTS frame parsers (and the step-file
// parser, which reads files that come from the BTS PC). Any input must end in frames, ProtocolError or
// InputError: never a crash, a hang, undefined behaviour or unbounded memory.
//
// Not part of the normal build. Build and run, e.g.:
//   clang++ -std=c++20 -g -O1 -fsanitize=fuzzer,address,undefined -I protocol/include -I core/include \
//     tests/fuzz/neware_frame_fuzz.cpp protocol/src/neware_bts.cpp protocol/src/neware_stepfile.cpp \
//     core/src/recording.cpp -o neware_frame_fuzz && ./neware_frame_fuzz -max_len=4096
// or configure with -DCELLBENCH_FUZZ=ON -DCMAKE_CXX_COMPILER=clang++ (target neware_frame_fuzz).
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "cellbench/core/recording.hpp"
#include "cellbench/protocol/neware_bts.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"

using namespace cellbench::protocol;

namespace {

void parse_both(const std::string& frame) {
    try {
        const auto r = neware::parse_response(frame);
        // Whatever parses must encode and parse again.
        (void)neware::parse_response(neware::encode_response(r));
    } catch (const neware::ProtocolError&) {
    }
    try {
        const auto q = neware::parse_request(frame);
        (void)neware::parse_request(neware::encode_request(q));
    } catch (const neware::ProtocolError&) {
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0) return 0;
    const std::string_view bytes(reinterpret_cast<const char*>(data) + 1, size - 1);
    const unsigned mode = data[0];

    if (mode % 8 == 7) {  // a step file
        try {
            const StepProgram p = parse_step_file(bytes);
            (void)parse_step_file(compile_step_file(p));
        } catch (const neware::ProtocolError&) {
        } catch (const cellbench::InputError&) {
        }
        return 0;
    }

    // A stream cut into chunks of a size taken from the first byte; a small frame limit so the
    // oversize path is reached too.
    const std::size_t chunk = 1 + (mode >> 3) * 7;
    neware::FrameSplitter splitter(mode & 1 ? 512 : neware::kDefaultMaxFrameBytes);
    for (std::size_t at = 0; at < bytes.size(); at += chunk) {
        splitter.feed(bytes.substr(at, chunk));
        for (int guard = 0; guard < 100000; ++guard) {
            std::optional<std::string> frame;
            try {
                frame = splitter.next();
            } catch (const neware::ProtocolError&) {
                continue;
            }
            if (!frame) break;
            parse_both(*frame);
        }
    }
    // The whole input as one frame, too (parsers see frames that the splitter would not produce).
    parse_both(std::string(bytes));
    return 0;
}
