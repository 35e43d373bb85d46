// The fuzz build's stand-in for the dashboard bundle (web/ builds the real one with node): two small files, so
// the fuzzer reaches the embedded-file routes (ETag, gzip, 304). http_request_fuzz switches them off and on.
#include <array>

#include "cellbench/daemon/web_assets.hpp"

namespace cellbench::fuzz {
bool web_assets_enabled = true;
}

namespace cellbench::daemon {

std::span<const WebAsset> web_assets() {
    static const std::array<WebAsset, 2> assets{{
        {"/index.html", "text/html; charset=utf-8", "\"0123abcd\"", false,
         "<!doctype html><title>cellbench</title><script src=/app-0123abcd.js></script>", "\x1f\x8b gzip bytes"},
        {"/app-0123abcd.js", "text/javascript; charset=utf-8", "\"4567ef01\"", true, "console.log('cellbench');",
         "\x1f\x8b more gzip bytes"},
    }};
    if (!fuzz::web_assets_enabled) return {};
    return assets;
}

}  // namespace cellbench::daemon
