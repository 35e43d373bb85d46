#pragma once
// The dashboard's static files (web/: uPlot + our code, bundled by esbuild at build time), compiled into
// cellbenchd. The HTTP server serves them at / unless it is given a folder (HttpServerOptions::static_dir,
// `cellbenchd --web-root DIR`) to serve instead.
//
// Why embedded rather than read from the build tree: an installed or copied daemon (systemd unit, another
// machine) has no build tree, and a dashboard that cannot drift from the daemon's API version is one thing
// less to deploy. The bundle is ~60 kB gzipped, so the binary barely grows. --web-root stays for working on
// the dashboard without relinking.
//
// Built without node/npm (or with -DCELLBENCH_WEB=OFF) the list is empty and / says how to build it.
#include <span>
#include <string_view>

namespace cellbench::daemon {

struct WebAsset {
    std::string_view path;          // "/index.html", "/app-5GQ2....js"
    std::string_view content_type;  // "text/javascript; charset=utf-8"
    std::string_view etag;          // strong validator, quoted: "\"3f2a...\""
    bool immutable = false;         // content-hashed name: cacheable for a year
    std::string_view body;          // the file
    std::string_view gzip;          // the same, gzip-compressed (served on Accept-Encoding: gzip)
};

// Every embedded file; empty when the daemon was built without the dashboard.
std::span<const WebAsset> web_assets();

}  // namespace cellbench::daemon
