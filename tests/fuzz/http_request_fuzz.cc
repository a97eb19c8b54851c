// Fuzz target: the HTTP layer end to end. The input is sent as the raw bytes of a request over TCP to a
// real server::HttpServer (server/http/http_server.cc, linked as oxbow_http) on 127.0.0.1, serving an api::Service
// over an index built with the fuzz vocabulary (one image indexed at start). oxbow's connection loop reads
// and checks the request head first (server/http/request_guard.cc: header count and bytes, Content-Length /
// Transfer-Encoding / Content-Encoding framing; the seeds include header floods, chunked and gzip bodies,
// two Content-Lengths, Content-Length with chunked), cuts chunked bodies at the limit, then cpp-httplib parses the
// request line, headers, query string and multipart body; oxbow's routes collect the parameters
// (CollectParams), pick the image part, parse and validate every parameter (bbox, top_k, ids, metadata
// JSON...), decode and search. Checked for every input: the server answers (no crash, no hang: 20 s
// limit), the answer is an HTTP/1.1 status line, every error answer with a JSON body carries
// {"error": {...}}, and no input gets 500 (an internal error). Writes are allowed, so the index changes
// as the run goes on.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>
#include <thread>

#include "api/service.h"
#include "sift/base/binary_io.h"
#include "server/http/http_server.h"
#include "tests/fuzz/fuzz_support.h"

namespace {

using namespace oxbow;

class FuzzServer {
 public:
  FuzzServer() {
    std::signal(SIGPIPE, SIG_IGN);
    const auto dir = fuzz::ScratchDir() / "http-index";
    const auto vocabulary_path = (fuzz::ScratchDir() / "http-vocabulary.oxvoc").string();
    fuzz::CheckSetup(fuzz::FuzzVocabulary().Write(vocabulary_path), "write vocabulary");
    api::ServiceOptions options;
    options.max_image_bytes = 1u << 20;
    options.max_pixels = 4'000'000;
    options.max_image_side_px = 96;
    options.max_concurrent_extractions = 2;
    options.extraction_wait_ms = 5'000;
    options.add_nice = 0;
    index::IndexOptions index_options;
    index_options.num_threads = 1;
    auto service = api::Service::Open(dir.string(), vocabulary_path, options, index_options);
    if (!service) fuzz::CheckSetup(std::unexpected(service.error()), "open service");
    // One indexed image (a real photo) so that /similar, GET and DELETE of "box" reach the index.
    auto photo = io::ReadWholeFile("/usr/share/doc/opencv-doc/examples/data/box.png");
    if (!photo) fuzz::CheckSetup(std::unexpected(photo.error()), "read box.png (opencv-doc)");
    api::AddImageRequest add;
    add.id = "box";
    add.image = *photo;
    add.replace = true;
    if (auto added = (*service)->AddImage(add); !added) fuzz::CheckSetup(std::unexpected(added.error()), "add image");
    server::HttpServerOptions http;
    http.port = 0;
    http.threads = 2;
    http.max_body_bytes = 2u << 20;
    http.read_timeout_s = 2;
    http.write_timeout_s = 2;
    server_ = std::make_unique<server::HttpServer>(http);
    auto port = server_->Bind();
    if (!port) fuzz::CheckSetup(std::unexpected(port.error()), "bind");
    port_ = *port;
    server_->SetService(std::shared_ptr<api::Service>(std::move(*service)));
    thread_ = std::thread([this] { server_->Run(); });
  }
  ~FuzzServer() {
    server_->Shutdown();
    thread_.join();
  }
  int port() const { return port_; }

 private:
  std::unique_ptr<server::HttpServer> server_;
  std::thread thread_;
  int port_ = 0;
};

[[noreturn]] void Bug(const char* what, const std::string& response) {
  std::fprintf(stderr, "http fuzz: %s; response:\n%.2000s\n", what, response.c_str());
  std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static FuzzServer server;
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) std::abort();
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(server.port()));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  // libFuzzer's -timeout runs a SIGALRM timer whose handler does not restart system calls, so every call
  // below may fail with EINTR while the server is still working: retry those, and measure the 20 s from
  // one deadline (an interrupted poll was once taken for "no answer within 20 s" after a few ms). An
  // interrupted connect goes on in the background: wait until the socket is writable, then ask its result.
  if (::connect(fd, reinterpret_cast<const sockaddr*>(&address), sizeof(address)) != 0) {
    if (errno != EINTR) Bug("connect failed", "");
    pollfd p{fd, POLLOUT, 0};
    while (::poll(&p, 1, 20'000) < 0 && errno == EINTR) {
    }
    int error = 0;
    socklen_t length = sizeof(error);
    if (::getsockopt(fd, SOL_SOCKET, SO_ERROR, &error, &length) != 0 || error != 0) Bug("connect failed", "");
  }
  // The server may answer (and close) before reading everything, e.g. for an oversized body: a failed
  // send is then expected, the answer is still read.
  size_t sent = 0;
  while (sent < size) {
    const ssize_t n = ::send(fd, data + sent, size - sent, MSG_NOSIGNAL);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    sent += static_cast<size_t>(n);
  }
  ::shutdown(fd, SHUT_WR);
  std::string response;
  char buffer[65536];
  using Clock = std::chrono::steady_clock;
  const auto deadline = Clock::now() + std::chrono::seconds(20);
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    pollfd p{fd, POLLIN, 0};
    const int ready = ::poll(&p, 1, static_cast<int>(std::max<int64_t>(0, left.count())));
    if (ready < 0 && errno == EINTR) continue;
    if (ready < 0) Bug("poll failed", response);
    if (ready == 0) Bug("no answer within 20 s", response);
    const ssize_t n = ::recv(fd, buffer, sizeof(buffer), 0);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    response.append(buffer, static_cast<size_t>(n));
  }
  ::close(fd);
  if (response.empty()) return 0;  // an incomplete head (the input ended inside it) is closed without an answer
  if (response.rfind("HTTP/1.1 ", 0) != 0) Bug("not an HTTP/1.1 status line", response);
  const int status = std::atoi(response.c_str() + 9);
  if (status < 100 || status > 599) Bug("status code out of range", response);
  // A request, however malformed, is the client's error (4xx) or an overload (503); a 500 means an
  // exception or an internal error inside the server.
  if (status == 500) Bug("internal error answer", response);
  const bool json = response.find("Content-Type: application/json") != std::string::npos;
  // An answer to HEAD has the headers of the error answer but no body (found by this fuzzer: HEAD on a
  // POST-only route, 405 with Content-Length and nothing after the head).
  const size_t head_end = response.find("\r\n\r\n");
  const bool has_body = head_end != std::string::npos && head_end + 4 < response.size();
  if (status >= 400 && json && has_body && response.find("\"error\"") == std::string::npos) {
    Bug("error answer without an error object", response);
  }
  return 0;
}
