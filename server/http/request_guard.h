// Protection of the HTTP server's worker threads and memory against slow, stalled, greedy and malformed
// clients.
//
// cpp-httplib 0.11 serves each connection on one worker thread, has only per-operation socket timeouts,
// parses request heads leniently (no limit on the header count, a bad request line leaves the connection
// open and its leftover bytes are parsed as more requests, the first of two Content-Lengths wins) and
// reads chunked, length-less and gzip bodies without bound. This file adds what httplib lacks, without
// patching it:
//
//  - GuardedHttpServer replaces httplib's per-connection loop (the overridable
//    Server::process_and_close_socket) with one whose stream enforces a total deadline for reading each
//    request: headers and body must arrive within `request_timeout` of the request's first byte, however
//    they are trickled. A request whose body misses the deadline is answered 408 (the route's error
//    handler asks RequestDeadlineExpired()); one whose headers miss it is closed.
//  - Before httplib sees a request, the loop reads its head itself (ParseRequestHead: at most
//    max_header_count headers and max_head_bytes bytes, strict framing) and refuses what httplib would
//    misread, answering at once and closing the connection: nothing after a refused request is parsed.
//    A chunked body is counted while httplib reads it and cut at max_body_bytes (413).
//  - Connections are scheduled here, not by httplib's thread pool: `threads` workers take accepted
//    connections from a queue of at most `max_queued` (the accept thread only files them), a client
//    address holds at most `max_connections_per_client` open connections, and the connections beyond
//    either limit go to one shedding thread that answers 503. A worker whose keep-alive connection is idle
//    while others wait gives it up after kBusyIdleTimeout instead of keep_alive_timeout; the shedding
//    thread waits at most kShedHeaderTimeout for a request's head and not at all while others wait for it.
//  - UploadBudget bounds the request bodies held in memory by all requests together: a request reserves
//    its Content-Length (a chunked one: the body limit) before its body is read and releases it when its
//    response is done; a request that does not fit is answered 503 with Retry-After, unread.
//  - Closing is "lingering": after the response the server stops writing, discards what the client still
//    sends (at most its declared Content-Length or 1 MiB, for at most 1 s; on the shedding thread 1 MiB
//    for 200 ms, nothing while others wait for it), then closes, so a client whose body was not read still receives its 503/413 instead of a
//    connection reset (larger unread bodies may still see a reset).
//
// Thread safety: UploadBudget is thread-safe. GuardedHttpServer is used as an httplib::Server. The
// thread-local helpers (RequestDeadlineExpired, ReserveUploadForThisRequest, CloseConnectionAfterResponse,
// ChunkedBodyOverLimit) refer to the request the calling worker thread serves.
#pragma once

#include <httplib.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <mutex>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace oxbow::server {

// Header deadline for connections answered by the shedding thread (when no other connection waits for it).
inline constexpr std::chrono::milliseconds kShedHeaderTimeout{500};
// How long a worker keeps an idle connection (no byte of a next request) while other connections wait
// in the queue; otherwise keep_alive_timeout. Counted from the accept for a connection's first request.
inline constexpr std::chrono::milliseconds kBusyIdleTimeout{1000};
// Empty lines tolerated before a request line (RFC 9112 2.2: a stray CRLF after a previous body).
inline constexpr int kMaxLeadingEmptyLines = 2;
// Longest request target (httplib's own limit, answered 414 here) and longest header line.
inline constexpr size_t kMaxTargetBytes = 8192;
inline constexpr size_t kMaxHeaderLineBytes = 8192;

// Limits on a request's head and body, enforced before httplib parses or reads them.
// Like GuardOptions, filled by HttpServer from HttpServerOptions, where the product's defaults live.
struct RequestHeadLimits {
  // Header lines at most, [1, 10000]; more -> 431.
  size_t max_header_count = 0;
  // Request line + headers, bytes at most, [1024, 2^24]; more -> 431 (a single line over
  // kMaxHeaderLineBytes too).
  size_t max_head_bytes = 0;
  // Request body (Content-Length, or the data of a chunked body), bytes at most; more -> 413.
  uint64_t max_body_bytes = 0;
};

// An error answer given by the connection loop itself (before or instead of httplib).
struct Refusal {
  int status = 400;
  std::string code;     // the JSON error code, e.g. "bad_request"
  std::string message;  // for a person
};

// What the loop knows of a request it refuses: the parts of the head read so far (may be empty).
struct RefusedRequest {
  std::string method;
  std::string target;
  std::string request_id;  // the client's X-Request-Id header, as sent
  Refusal refusal;
};

// Fills `res` (status, headers, JSON body) for a refused request, and logs and counts it. The loop adds
// Connection: close and writes it.
using RefusalWriter = std::function<void(const RefusedRequest&, httplib::Response&)>;

// A request head that passed ParseRequestHead.
struct RequestHead {
  std::string method;
  std::string target;
  std::vector<std::pair<std::string, std::string>> headers;  // in order, values without surrounding space
  bool chunked = false;                                      // Transfer-Encoding: chunked
  size_t consumed = 0;     // bytes of the input the head took (leading empty lines included)
  std::string replay;      // the head for httplib: without leading empty lines; a request without a
                           // length gets "Content-Length: 0" (RFC 9112 6.3: no body, not "until EOF")
};

struct HeadParse {
  enum class Kind { kIncomplete, kComplete, kRefused } kind = Kind::kIncomplete;
  RequestHead head;        // kComplete
  RefusedRequest refused;  // kRefused
  uint64_t declared_body_bytes = 0;  // the Content-Length, once the head is complete (also when refused)
};

// Parses the start of `bytes` (what a connection has delivered of its next request) as an HTTP/1.x
// request head. kIncomplete: no verdict yet, more bytes needed (never when `bytes` already breaks a
// limit). kRefused carries the answer: 400 malformed framing (bare LF, bad request line, header name not
// a token, control bytes such as NUL in a value, obsolete line folding, differing Content-Lengths,
// Content-Length with Transfer-Encoding, a non-numeric or overflowing Content-Length, a body on a method
// that takes none), 413 Content-Length over the body limit, 414 target too long, 415 a Content-Encoding
// other than identity (oxbow never inflates request bodies), 431 too many or too large headers, 501 a
// Transfer-Encoding other than chunked, 505 an HTTP version other than 1.0/1.1.
HeadParse ParseRequestHead(std::string_view bytes, const RequestHeadLimits& limits);

// A budget of request-body bytes in memory at once.
class UploadBudget {
 public:
  explicit UploadBudget(uint64_t capacity_bytes) : capacity_(capacity_bytes) {}
  // Takes `bytes` from the budget if they fit; false (nothing taken) otherwise.
  bool TryReserve(uint64_t bytes);
  void Release(uint64_t bytes);
  uint64_t in_use() const;
  uint64_t capacity() const { return capacity_; }

 private:
  const uint64_t capacity_;
  mutable std::mutex mutex_;  // guards in_use_
  uint64_t in_use_ = 0;
};

// No defaults of its own: HttpServer sets every field from HttpServerOptions (the product's defaults and
// their checked ranges), so the two cannot disagree.
struct GuardOptions {
  // Headers and body of a request must arrive within this long of its first byte.
  std::chrono::milliseconds request_timeout{0};
  // Worker threads, [1, 1024]; connections waiting for one at most, [1, 100000]; open connections of
  // one client address at most (served, queued or being refused), [1, 100000].
  int threads = 0;
  int max_queued = 0;
  int max_connections_per_client = 0;
  RequestHeadLimits head;
  UploadBudget* budget = nullptr;  // not owned, may be null: gets back each request's reservation
  RefusalWriter refusal_writer;    // required
};

class ConnectionScheduler;

class GuardedHttpServer : public httplib::Server {
 public:
  explicit GuardedHttpServer(GuardOptions options);

 private:
  friend class ConnectionScheduler;
  // Called by httplib's accept loop for each accepted socket (through the scheduler, on the accept
  // thread): files it with the scheduler.
  bool process_and_close_socket(socket_t sock) override;
  // The per-connection loop, on a worker (or the shedding thread when `shed` holds the reason).
  void ServeConnection(socket_t sock, std::chrono::steady_clock::time_point accepted, const Refusal* shed);

  const GuardOptions options_;
  ConnectionScheduler* scheduler_ = nullptr;  // the one httplib's listen created (owned by httplib)
};

// True when the request this thread serves ran past its read deadline (answer 408).
bool RequestDeadlineExpired();
// True when a read of the request this thread serves waited the whole read timeout for a byte (answer
// 408: its body stopped arriving).
bool RequestReadTimedOut();
// True when the chunked body of the request this thread serves went over max_body_bytes (answer 413).
bool ChunkedBodyOverLimit();
// The connection of the request this thread serves closes after the response (its body may be unread).
void CloseConnectionAfterResponse();
// The socket of the connection this thread serves (-1 when none), for a route handler to notice that its
// client hung up while the request is processed.
int CurrentConnectionSocket();
// Reserves this request's body (Content-Length, or `max_body_bytes` when chunked; capped at
// max_body_bytes) from `budget`; false when it does not fit. Released by GuardedHttpServer after the
// response.
bool ReserveUploadForThisRequest(const httplib::Request& req, UploadBudget* budget, uint64_t max_body_bytes);
// The whole value of header `name` (first occurrence; "" when absent). httplib's get_header_value stops
// at the first NUL byte.
std::string FullHeaderValue(const httplib::Request& req, const char* name);

}  // namespace oxbow::server
