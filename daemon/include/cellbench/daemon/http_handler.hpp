#pragma once
// The daemon's HTTP request handling without a socket: one parsed request in, the response out, through the
// same router as HttpServer (routes, authentication, validation, JSON errors). For tests and fuzzing
// (tests/fuzz/http_request_fuzz.cpp feeds raw bytes through beast::http::request_parser into it).
//
// What stays with the connection (HttpServer's sessions) is not done here: reading with the header and body
// limits (413/431/400 for requests that do not parse), the shutdown 503, and timeouts.
#include <boost/beast/http/message.hpp>
#include <boost/beast/http/string_body.hpp>

#include "cellbench/daemon/api.hpp"
#include "cellbench/daemon/http_server.hpp"

namespace cellbench::daemon {

using HttpRequest = boost::beast::http::request<boost::beast::http::string_body>;
using HttpResponse = boost::beast::http::response<boost::beast::http::string_body>;

// Answers `request` as HttpServer would: status, headers (Server, Cache-Control, Content-Type, Allow,
// WWW-Authenticate, Location, ...), keep-alive as the request asks, and for HEAD the headers of the GET
// response without its body. A streamed export (GET /runs/{id}/export.bdf.csv) is collected into the body
// (an exception from the backend's cursor propagates: the server would cut the connection there); a static
// dashboard file (options.static_dir) is read into the body. Thread-safe as far as the backend is.
HttpResponse handle_http_request(const HttpRequest& request, ApiBackend& backend, const HttpServerOptions& options);

}  // namespace cellbench::daemon
