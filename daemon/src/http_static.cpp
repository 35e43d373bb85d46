// The dashboard: the files compiled into the daemon (web_assets.hpp) or, with --web-root, a folder served
// without ever leaving it.
#include "http_internal.hpp"

#include <algorithm>
#include <charconv>

#include "cellbench/daemon/web_assets.hpp"

namespace cellbench::daemon::http_detail {

// The dashboard compiled into the daemon (web_assets.hpp). Only the exact embedded names exist (no file
// system behind them, so nothing to traverse); "/" is index.html. Strong ETag with 304 on If-None-Match;
// content-hashed names are cached for a year, index.html is revalidated; gzip when the client takes it.
Reply Router::embedded_file(std::string_view path) {
    const auto assets = web_assets();
    if (assets.empty()) {
        if (path != "/" && path != "/index.html") return not_found();
        Reply r;
        r.res.result(http::status::not_found);
        r.res.set(http::field::content_type, "text/html; charset=utf-8");
        r.res.body() =
            "<!doctype html><meta charset=utf-8><title>cellbenchd: no dashboard</title>"
            "<h1>This cellbenchd was built without its dashboard</h1>"
            "<p>The dashboard is bundled from <code>web/</code> with node and npm when cellbenchd is built. "
            "Install them (<code>make deps</code> installs the Debian packages <code>nodejs npm</code>) and "
            "rebuild (<code>make</code>, or <code>cmake --build build</code>), or serve a built bundle with "
            "<code>cellbenchd --web-root DIR</code>.</p><p>The REST API is under <a href=\"/api/v1/status\">"
            "/api/v1</a>.</p>";
        return r;
    }
    if (!is_get()) return method_not_allowed("GET, HEAD");
    if (path == "/") path = "/index.html";
    const auto it = std::find_if(assets.begin(), assets.end(), [&](const WebAsset& a) { return a.path == path; });
    if (it == assets.end()) return error(http::status::not_found, "not found");
    Reply r;
    // The gzip representation has its own validator ("HASH-gz"); either names the same file content.
    const bool gzip = accepts_gzip();
    const std::string_view hash = it->etag.substr(1, it->etag.size() - 2);  // without the quotes
    r.res.set(http::field::etag, "\"" + std::string(hash) + (gzip ? "-gz\"" : "\""));
    r.res.set(http::field::cache_control, it->immutable ? "public, max-age=31536000, immutable" : "no-cache");
    r.res.set(http::field::vary, "Accept-Encoding");
    r.res.set("X-Content-Type-Options", "nosniff");
    const auto inm = req_[http::field::if_none_match];
    if (!hash.empty() && std::string_view(inm.data(), inm.size()).find(hash) != std::string_view::npos) {
        r.res.result(http::status::not_modified);
        return r;
    }
    r.res.result(http::status::ok);
    r.res.set(http::field::content_type, beast::string_view(it->content_type.data(), it->content_type.size()));
    if (gzip) {
        r.res.set(http::field::content_encoding, "gzip");
        r.res.body().assign(it->gzip);
    } else {
        r.res.body().assign(it->body);
    }
    return r;
}

// Accept-Encoding names gzip (or *) without q=0.
bool Router::accepts_gzip() const {
    const auto field = req_[http::field::accept_encoding];
    for (auto item : split(std::string_view(field.data(), field.size()), ',')) {
        while (!item.empty() && (item.front() == ' ' || item.front() == '\t')) item.remove_prefix(1);
        const auto semi = item.find(';');
        std::string_view name = item.substr(0, semi), params = semi == std::string_view::npos ? "" : item.substr(semi);
        while (!name.empty() && (name.back() == ' ' || name.back() == '\t')) name.remove_suffix(1);
        if (!iequals(name, "gzip") && name != "*") continue;
        const auto q = params.find("q=");
        if (q == std::string_view::npos) return true;
        double v = 1.0;
        std::from_chars(params.data() + q + 2, params.data() + params.size(), v);
        return v > 0.0;
    }
    return false;
}

Reply Router::static_file(std::string_view path) {
    if (st_.static_root.empty()) return embedded_file(path);
    if (!is_get()) return method_not_allowed("GET, HEAD");
    // Decode first: "%2e%2e" must be seen as "..". Then refuse any dot segment, hidden name, backslash
    // or NUL, and finally check the canonical result is inside the root (symlinks cannot lead out).
    const auto decoded = percent_decode(path, false);
    const auto refuse = [&] { return error(http::status::not_found, "not found"); };
    if (!decoded || decoded->find('\0') != std::string::npos || decoded->find('\\') != std::string::npos)
        return refuse();
    fs::path rel;
    for (const auto part : split(*decoded, '/')) {
        if (part.empty()) continue;
        if (part.front() == '.') return refuse();  // ".", "..", ".git", ...
        rel /= std::string(part);
    }
    fs::path file = st_.static_root / rel;
    std::error_code ec;
    if (fs::is_directory(file, ec)) file /= "index.html";
    const fs::path canonical = fs::canonical(file, ec);
    if (ec || !is_within(st_.static_root, canonical) || !fs::is_regular_file(canonical, ec)) return refuse();

    http::file_body::value_type body;
    beast::error_code bec;
    body.open(canonical.c_str(), beast::file_mode::scan, bec);
    if (bec) return refuse();
    Reply r;
    r.file.emplace(std::piecewise_construct, std::make_tuple(std::move(body)),
                   std::make_tuple(http::status::ok, req_.version()));
    r.file->set(http::field::content_type, mime_type(canonical));
    // Dashboard files change with a build and carry no content hash in their names: revalidate.
    r.file->set(http::field::cache_control, "no-cache");
    r.file->set("X-Content-Type-Options", "nosniff");
    return r;
}

}  // namespace cellbench::daemon::http_detail
