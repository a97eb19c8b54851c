// Hostile HTTP framing and connection floods against the real `oxbow serve` (server/http/request_guard.h):
// compressed, chunked and length-less bodies are bounded before they are read or inflated, header floods
// are cut, malformed framing (CRLF floods, two Content-Lengths, Content-Length with Transfer-Encoding,
// negative or overflowing lengths, unknown codings) is answered at once and its connection closed, an API
// key followed by a NUL byte is not a match, idle connections cannot starve a new client and one client
// address cannot hold more than --max-connections-per-client connections. No wall-clock assertions but
// generous bounds that tell "answered at once" from "answered at the request deadline" (30 s here).
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "sift/sift.h"
#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/server_suite.h"

namespace oxbow {
namespace {

using Clock = std::chrono::steady_clock;
using nlohmann::json;
using oxbow::testing::ConnectTo;
using oxbow::testing::SendAll;

// What a raw exchange got back.
struct Reply {
  std::string text;           // every byte the server sent
  bool closed = false;        // the server closed (or reset) the connection before the give-up
  double seconds = 0;         // from the last byte sent to the close (or the give-up)
  int Status() const { return text.rfind("HTTP/1.1 ", 0) == 0 ? std::stoi(text.substr(9, 3)) : 0; }
  size_t Responses() const {
    size_t n = 0;
    for (size_t at = text.find("HTTP/1.1 "); at != std::string::npos; at = text.find("HTTP/1.1 ", at + 1)) {
      n += at == 0 || text[at - 1] == '\n' ? 1 : 0;  // a status line, not a mention in a body
    }
    return n;
  }
  json Body() const {
    const size_t at = text.find("\r\n\r\n");
    return at == std::string::npos ? json() : json::parse(text.substr(at + 4), nullptr, false);
  }
};

// Reads until the server closes the connection or `give_up` passes.
Reply ReadReply(int fd, std::chrono::seconds give_up) {
  Reply reply;
  const auto start = Clock::now();
  const auto until = start + give_up;
  char buf[65536];
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now()).count();
    pollfd p{fd, POLLIN, 0};
    if (left <= 0 || poll(&p, 1, static_cast<int>(left)) <= 0) break;
    const ssize_t n = recv(fd, buf, sizeof buf, 0);
    if (n <= 0) {
      reply.closed = true;
      break;
    }
    reply.text.append(buf, static_cast<size_t>(n));
  }
  reply.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  return reply;
}

// Sends `request` (as much as the server takes: it may answer and close early) on a new connection, keeps
// the connection open for writing (a server waiting for EOF waits) and reads the reply.
Reply Exchange(int port, const std::string& request, std::chrono::seconds give_up = std::chrono::seconds(10)) {
  const int fd = ConnectTo(port);
  if (fd < 0) return {};
  SendAll(fd, request);
  Reply reply = ReadReply(fd, give_up);
  close(fd);
  return reply;
}

// Peak resident memory of process `pid`, bytes (VmHWM).
uint64_t PeakRssBytes(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::stoull(line.substr(6)) * 1024;
  }
  return 0;
}

// A gzip member of `zero_bytes` zeros (a multiple of 258 plus one) as a fixed-Huffman deflate stream: a
// literal zero, then length-258 copies at distance 1 (13 bits each: ~1/160 of the inflated size).
std::string GzipOfZeros(uint64_t zero_bytes) {
  std::string out("\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\x03", 10);
  uint64_t bits = 0;
  int nbits = 0;
  auto put = [&](uint32_t value, int count) {  // LSB-first
    bits |= static_cast<uint64_t>(value) << nbits;
    nbits += count;
    while (nbits >= 8) {
      out.push_back(static_cast<char>(bits & 0xff));
      bits >>= 8;
      nbits -= 8;
    }
  };
  auto put_code = [&](uint32_t code, int count) {  // Huffman codes go most significant bit first
    for (int i = count - 1; i >= 0; --i) put((code >> i) & 1u, 1);
  };
  put(1, 1);                 // BFINAL
  put(1, 2);                 // fixed Huffman
  put_code(0x30, 8);         // literal 0
  for (uint64_t copies = (zero_bytes - 1) / 258; copies > 0; --copies) {
    put_code(0xc5, 8);       // length code 285 = 258
    put_code(0, 5);          // distance code 0 = 1
  }
  put_code(0, 7);            // end of block
  if (nbits > 0) put(0, 8 - nbits);
  std::array<uint32_t, 256> table{};
  for (uint32_t i = 0; i < 256; ++i) {
    uint32_t c = i;
    for (int k = 0; k < 8; ++k) c = (c & 1u) != 0 ? 0xedb88320u ^ (c >> 1) : c >> 1;
    table[i] = c;
  }
  uint32_t crc = 0xffffffffu;
  for (uint64_t i = 0; i < zero_bytes; ++i) crc = table[crc & 0xff] ^ (crc >> 8);
  crc ^= 0xffffffffu;
  for (uint32_t value : {crc, static_cast<uint32_t>(zero_bytes)}) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>((value >> (8 * i)) & 0xff));
  }
  return out;
}

// `data` as a chunked body of `chunk`-byte chunks.
std::string Chunked(const std::string& data, size_t chunk) {
  std::string out;
  for (size_t at = 0; at < data.size(); at += chunk) {
    const std::string part = data.substr(at, chunk);
    char size_line[32];
    std::snprintf(size_line, sizeof size_line, "%zx\r\n", part.size());
    out += size_line + part + "\r\n";
  }
  return out + "0\r\n\r\n";
}

class HostileHttpTest : public oxbow::testing::ServerSuite {
 protected:
  static void SetUpTestSuite() { SetUpServerSuite("oxbow-hostile-http-test"); }
  // A server whose request deadline (30 s) is far above the "at once" bounds of the tests.
  static std::unique_ptr<oxbow::testing::ServerProcess> Start(std::vector<std::string> extra) {
    extra.insert(extra.begin(), {"--request-timeout-s", "30", "--read-timeout-s", "30"});
    return StartServer(extra);
  }
  // Expects one error answer with `status` (any of `statuses`), the JSON error shape and a request id,
  // given at once, and the connection closed after it.
  static void ExpectRefusedAtOnce(const Reply& reply, std::initializer_list<int> statuses, const std::string& what) {
    EXPECT_NE(std::find(statuses.begin(), statuses.end(), reply.Status()), statuses.end()) << what << ":\n" << reply.text;
    EXPECT_TRUE(reply.closed) << what << ": the connection stayed open";
    EXPECT_LT(reply.seconds, 10) << what << ": answered only at the request deadline";
    EXPECT_EQ(reply.Responses(), 1u) << what << ":\n" << reply.text;
    EXPECT_NE(reply.text.find("X-Request-Id: "), std::string::npos) << what;
    EXPECT_TRUE(reply.Body().contains("error")) << what << ":\n" << reply.text;
    EXPECT_FALSE(reply.Body()["error"]["request_id"].get<std::string>().empty()) << what;
  }

};

TEST_F(HostileHttpTest, CompressedBodiesAreRefusedWithoutInflating) {
  auto server = Start({});
  // 256 MiB of zeros in 1.7 MB of gzip: inflated, the body alone would add hundreds of MiB.
  const std::string bomb = GzipOfZeros(258ull * 1040000 + 1);
  const uint64_t peak_before = PeakRssBytes(server->pid());
  for (const char* path : {"/v1/images?id=bomb", "/v1/search"}) {
    const Reply reply = Exchange(server->port(), std::string("POST ") + path +
                                                     " HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                                                     "Content-Encoding: gzip\r\nContent-Length: " +
                                                     std::to_string(bomb.size()) + "\r\n\r\n" + bomb);
    ExpectRefusedAtOnce(reply, {415}, path);
    EXPECT_EQ(reply.Body()["error"]["code"], "unsupported_encoding");
  }
  const uint64_t peak_after = PeakRssBytes(server->pid());
  EXPECT_LT(peak_after, peak_before + (100ull << 20)) << "peak RSS " << peak_before << " -> " << peak_after;
  // Any other coding too; identity is no coding.
  for (const char* coding : {"br", "x-unknown", "deflate"}) {
    ExpectRefusedAtOnce(Exchange(server->port(), std::string("POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Encoding: ") +
                                                     coding + "\r\nContent-Length: 4\r\n\r\nabcd"),
                        {415}, coding);
  }
  const Reply identity = Exchange(server->port(), "POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                                                  "Content-Encoding: identity\r\nConnection: close\r\nContent-Length: " +
                                                      std::to_string(image_.size()) + "\r\n\r\n" + image_);
  EXPECT_EQ(identity.Status(), 200) << identity.text;
  auto record = server->Client().Get("/v1/images/bomb");
  ASSERT_TRUE(record);
  EXPECT_EQ(record->status, 404);
}

TEST_F(HostileHttpTest, ChunkedBodiesAreCutAtTheUploadLimit) {
  auto server = Start({"--max-upload-mb", "1"});
  const std::string head = "POST /v1/images?id=chunked HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\nTransfer-Encoding: chunked\r\n\r\n";
  ExpectRefusedAtOnce(Exchange(server->port(), head + Chunked(std::string(3u << 20, 'x'), 65536)), {413}, "3 MiB in 64 KiB chunks");
  // A chunk size line announcing more than the limit is enough.
  ExpectRefusedAtOnce(Exchange(server->port(), head + "ffffffffffffffff\r\nxx"), {413}, "a 2^64-1 byte chunk");
  // Within the limit a chunked body is read (and the image added).
  const Reply added = Exchange(server->port(), "POST /v1/images?id=chunked HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                                               "Connection: close\r\nTransfer-Encoding: chunked\r\n\r\n" + Chunked(image_, 1000));
  EXPECT_EQ(added.Status(), 201) << added.text;
}

// A body the HTTP library cannot read gets a 400 that says which part of it is wrong.
TEST_F(HostileHttpTest, AnUnreadableBodyIsNamedInTheAnswer) {
  auto server = Start({});
  const std::string multipart = "--XYZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.png\"\r\n\r\nxx";
  const Reply cut = Exchange(server->port(), "POST /v1/images?id=m HTTP/1.1\r\nHost: x\r\nConnection: close\r\n"
                                             "Content-Type: multipart/form-data; boundary=XYZ\r\nContent-Length: " +
                                                 std::to_string(multipart.size()) + "\r\n\r\n" + multipart);
  EXPECT_EQ(cut.Status(), 400) << cut.text;
  EXPECT_NE(cut.Body()["error"]["message"].get<std::string>().find("multipart/form-data body"), std::string::npos) << cut.text;
  const Reply chunked = Exchange(server->port(), "POST /v1/search HTTP/1.1\r\nHost: x\r\nConnection: close\r\n"
                                                 "Content-Type: image/png\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\nxx\r\n0\r\n\r\n");
  EXPECT_EQ(chunked.Status(), 400) << chunked.text;
  EXPECT_NE(chunked.Body()["error"]["message"].get<std::string>().find("chunked body"), std::string::npos) << chunked.text;
  auto client = server->Client();
  EXPECT_EQ(client.Get("/v1/images/m")->status, 404);
}

TEST_F(HostileHttpTest, ARequestWithoutLengthHasNoBody) {
  auto server = Start({});
  // RFC 9112 6.3: no Content-Length and no Transfer-Encoding means no body, not "read until EOF": the
  // answer comes while the client keeps its connection open.
  const Reply reply =
      Exchange(server->port(), "POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\nConnection: close\r\n\r\n");
  EXPECT_EQ(reply.Status(), 400) << reply.text;
  EXPECT_LT(reply.seconds, 10) << "the server waited for the end of the connection";
  EXPECT_EQ(reply.Body()["error"]["code"], "invalid_image") << reply.text;
}

TEST_F(HostileHttpTest, HeaderFloodsGet431) {
  auto server = Start({"--max-header-count", "50", "--max-header-kb", "32"});
  std::string many = "GET /v1/stats HTTP/1.1\r\nHost: x\r\n";
  for (int i = 0; i < 2000; ++i) many += "X-Flood-" + std::to_string(i) + ": " + std::string(100, 'a') + "\r\n";
  ExpectRefusedAtOnce(Exchange(server->port(), many + "\r\n"), {431}, "2000 headers");
  std::string count = "GET /v1/stats HTTP/1.1\r\nHost: x\r\n";
  for (int i = 0; i < 50; ++i) count += "X-H" + std::to_string(i) + ": 1\r\n";
  ExpectRefusedAtOnce(Exchange(server->port(), count + "\r\n"), {431}, "51 short headers");
  std::string bytes = "GET /v1/stats HTTP/1.1\r\nHost: x\r\n";
  for (int i = 0; i < 5; ++i) bytes += "X-Big" + std::to_string(i) + ": " + std::string(8000, 'b') + "\r\n";
  ExpectRefusedAtOnce(Exchange(server->port(), bytes + "\r\n"), {431}, "40 KB of headers");
  ExpectRefusedAtOnce(Exchange(server->port(), "GET /v1/stats HTTP/1.1\r\nX-Long: " + std::string(20000, 'c') + "\r\n\r\n"),
                      {431}, "one 20 KB header line");
  // At the limits a request is served.
  std::string fits = "GET /v1/stats HTTP/1.1\r\nConnection: close\r\n";
  for (int i = 0; i < 49; ++i) fits += "X-H" + std::to_string(i) + ": 1\r\n";
  EXPECT_EQ(Exchange(server->port(), fits + "\r\n").Status(), 200);
}

TEST_F(HostileHttpTest, MalformedFramingIsAnsweredOnceAndClosed) {
  auto server = Start({});
  const int port = server->port();
  // Leftover bytes of a refused request are never parsed as more requests.
  std::string crlf;
  for (int i = 0; i < 3000; ++i) crlf += "\r\n";
  ExpectRefusedAtOnce(Exchange(port, crlf), {400}, "6000 bytes of CRLF");
  ExpectRefusedAtOnce(Exchange(port, "NOT A REQUEST\r\n\r\nGET /healthz HTTP/1.1\r\n\r\n"), {400}, "garbage request line");
  ExpectRefusedAtOnce(Exchange(port, "GET /healthz HTTP/1.1\nHost: x\n\n"), {400}, "bare LF");
  ExpectRefusedAtOnce(Exchange(port, "GET /healthz HTTP/2.0\r\n\r\n"), {505}, "HTTP/2.0");
  ExpectRefusedAtOnce(Exchange(port, "GET /healthz HTTP/1.1\r\nBad Name: x\r\n\r\n"), {400}, "space in a header name");
  ExpectRefusedAtOnce(Exchange(port, "GET /healthz HTTP/1.1\r\nX-A: 1\r\n folded\r\n\r\n"), {400}, "obsolete folding");
  const std::string post = "POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n";
  ExpectRefusedAtOnce(Exchange(port, post + "Content-Length: 4\r\nContent-Length: 40\r\n\r\nabcd"), {400}, "two different Content-Lengths");
  ExpectRefusedAtOnce(Exchange(port, post + "Content-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n"), {400},
                      "Content-Length and Transfer-Encoding");
  ExpectRefusedAtOnce(Exchange(port, post + "Transfer-Encoding: gzip, chunked\r\n\r\n0\r\n\r\n"), {400, 501},
                      "Transfer-Encoding gzip, chunked");
  ExpectRefusedAtOnce(Exchange(port, post + "Transfer-Encoding: chunked\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n"),
                      {400, 501}, "chunked twice");
  ExpectRefusedAtOnce(Exchange(port, post + "Content-Length: -5\r\n\r\n"), {400}, "Content-Length -5");
  ExpectRefusedAtOnce(Exchange(port, post + "Content-Length: 18446744073709551617\r\n\r\n"), {400}, "Content-Length 2^64+1");
  ExpectRefusedAtOnce(Exchange(port, post + "Content-Length: 0x10\r\n\r\n"), {400}, "hexadecimal Content-Length");
  ExpectRefusedAtOnce(Exchange(port, "GET /healthz HTTP/1.1\r\nContent-Length: 5\r\n\r\nGET /"), {400}, "a GET with a body");
  // Two equal Content-Lengths are one; a stray CRLF before a request line is tolerated.
  const Reply equal = Exchange(port, "\r\nGET /healthz HTTP/1.1\r\nContent-Length: 0\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
  EXPECT_EQ(equal.Status(), 200) << equal.text;
  // Keep-alive still works for well-formed requests.
  const Reply two = Exchange(port, "GET /healthz HTTP/1.1\r\nHost: x\r\n\r\nGET /healthz HTTP/1.1\r\nConnection: close\r\n\r\n");
  EXPECT_EQ(two.Responses(), 2u) << two.text;
  const std::string log = server->Log();
  EXPECT_NE(log.find("status=400 refused: malformed HTTP request"), std::string::npos) << log;
}

// A request line of another HTTP version, or of none, gets one answer: one status line, and no other
// bytes a client scanning the reply for "HTTP/1.1 " could take for a second one (the message included).
TEST_F(HostileHttpTest, AnotherHttpVersionGetsOneAnswer) {
  auto server = Start({});
  const std::vector<std::pair<std::string, int>> requests = {
      {"GET /healthz HTTP/2.0\r\n\r\n", 505},
      {"GET /healthz HTTP/2.0\r\nHost: x\r\n\r\n", 505},
      {"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n", 505},  // HTTP/2's connection preface
      {"GET /healthz HTTP/1.2\r\n\r\n", 505},
      {"GET /healthz HTTP/2\r\n\r\n", 400},
      {"GET /healthz\r\n\r\n", 400},
      {"FOO /v1 HTTP/1.1\r\nHost: x\r\n\r\n", 501},  // a method no server route or HTTP library serves
      {"TRACE / HTTP/1.1\r\nHost: x\r\n\r\n", 501},
  };
  for (const auto& [request, status] : requests) {
    const Reply reply = Exchange(server->port(), request);
    ExpectRefusedAtOnce(reply, {status}, request);
    size_t versions = 0;
    for (size_t at = reply.text.find("HTTP/"); at != std::string::npos; at = reply.text.find("HTTP/", at + 1)) ++versions;
    EXPECT_EQ(versions, 1u) << request << ":\n" << reply.text;
  }
}

TEST_F(HostileHttpTest, AnApiKeyFollowedByANulByteIsRefused) {
  auto server = Start({"--api-key", "secret"});
  const int port = server->port();
  const std::string nul_key = std::string("X-API-Key: secret") + '\0' + "junk\r\n";
  const Reply add = Exchange(port, "POST /v1/images?id=nul HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n" + nul_key +
                                       "Content-Length: " + std::to_string(image_.size()) + "\r\n\r\n" + image_);
  EXPECT_TRUE(add.Status() == 400 || add.Status() == 403) << add.text;
  const std::string bearer = std::string("Authorization: Bearer secret") + '\0' + "junk\r\n";
  const Reply add_bearer = Exchange(port, "POST /v1/images?id=nul HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n" + bearer +
                                              "Content-Length: " + std::to_string(image_.size()) + "\r\n\r\n" + image_);
  EXPECT_TRUE(add_bearer.Status() == 400 || add_bearer.Status() == 403) << add_bearer.text;
  auto client = server->Client();
  auto record = client.Get("/v1/images/nul");
  ASSERT_TRUE(record);
  EXPECT_EQ(record->status, 404) << "an image was stored with a NUL-suffixed key";
  // With the right key the same image is added, and a NUL-suffixed key cannot delete it.
  httplib::Headers headers = {{"X-API-Key", "secret"}};
  auto added = client.Post("/v1/images?id=ok", headers, image_, "image/png");
  ASSERT_TRUE(added);
  EXPECT_EQ(added->status, 201) << added->body;
  const Reply del = Exchange(port, "DELETE /v1/images/ok HTTP/1.1\r\nHost: x\r\n" + nul_key + "\r\n");
  EXPECT_TRUE(del.Status() == 400 || del.Status() == 403) << del.text;
  auto kept = client.Get("/v1/images/ok");
  ASSERT_TRUE(kept);
  EXPECT_EQ(kept->status, 200);
}

TEST_F(HostileHttpTest, IdleConnectionsDoNotStarveANewClient) {
  auto server = Start({"--http-workers", "2", "--queue", "2"});
  const int port = server->port();
  std::vector<int> idle;
  idle.reserve(14);
  for (int i = 0; i < 14; ++i) idle.push_back(ConnectTo(port));
  std::this_thread::sleep_for(std::chrono::milliseconds(200));  // all accepted and filed
  // The issue measured 48.8 s for this answer (the 503 thread waited 5 s per idle connection).
  const Reply reply = Exchange(port, "GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
  EXPECT_TRUE(reply.Status() == 200 || reply.Status() == 503) << reply.text;
  EXPECT_LT(reply.seconds, 5) << "the new client waited behind idle connections";
  for (int fd : idle) close(fd);
  // Once the idle ones are gone, requests are served again.
  int status = 0;
  for (const auto until = Clock::now() + std::chrono::seconds(20); status != 200 && Clock::now() < until;) {
    status = Exchange(port, "GET /healthz HTTP/1.1\r\nConnection: close\r\n\r\n").Status();
  }
  EXPECT_EQ(status, 200);
}

// A worker drops an idle keep-alive connection early while others wait, but never one whose request has
// arrived: B and C send at once and wait (one worker, busy with A's idle keep-alive); when A is dropped
// B has waited over the 1 s busy-idle limit with C still queued, and must still be answered. (Found by
// the browser test: a thumbnail request on such a connection was closed unanswered.)
TEST_F(HostileHttpTest, ARequestQueuedBehindAnIdleConnectionIsServed) {
  auto server = Start({"--http-workers", "1", "--queue", "4"});
  const int port = server->port();
  const int a = ConnectTo(port);
  ASSERT_GE(a, 0);
  ASSERT_TRUE(oxbow::testing::SendAll(a, "GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n"));
  std::string first;
  ASSERT_TRUE(oxbow::testing::ReadUntil(a, "\"ok\"}", &first)) << first;  // served; A now idles, kept alive
  std::vector<int> queued;
  queued.reserve(2);
  for (int i = 0; i < 2; ++i) {
    queued.push_back(ConnectTo(port));
    ASSERT_TRUE(oxbow::testing::SendAll(queued.back(), "GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"));
  }
  for (size_t i = 0; i < queued.size(); ++i) {
    const Reply reply = ReadReply(queued[i], std::chrono::seconds(10));
    EXPECT_EQ(reply.Status(), 200) << "queued connection " << i << " was closed unanswered:\n" << reply.text;
    close(queued[i]);
  }
  close(a);
}

TEST_F(HostileHttpTest, OneClientAddressHoldsAtMostItsConnectionLimit) {
  auto server = Start({"--http-workers", "8", "--max-connections-per-client", "3"});
  const int port = server->port();
  std::vector<int> idle;
  idle.reserve(3);
  for (int i = 0; i < 3; ++i) idle.push_back(ConnectTo(port));
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const Reply over = Exchange(port, "GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n");
  ExpectRefusedAtOnce(over, {503}, "a fourth connection");
  EXPECT_NE(over.Body()["error"]["message"].get<std::string>().find("--max-connections-per-client"), std::string::npos)
      << over.text;
  EXPECT_NE(over.text.find("Retry-After: 1"), std::string::npos);
  for (int fd : idle) close(fd);
  int status = 0;
  for (const auto until = Clock::now() + std::chrono::seconds(20); status != 200 && Clock::now() < until;) {
    status = Exchange(port, "GET /healthz HTTP/1.1\r\nConnection: close\r\n\r\n").Status();
  }
  EXPECT_EQ(status, 200) << "closed connections were not given back to their client's count";
}

}  // namespace
}  // namespace oxbow
