// Protection of the HTTP server's worker threads and memory against slow, stalled and greedy clients.
//
// cpp-httplib 0.11 serves each connection on one worker thread and only has per-operation socket
// timeouts: a client that sends one byte every few seconds (headers or body) never trips the read
// timeout and holds its worker for as long as it likes; `threads` such clients stop the server. This
// file adds what httplib lacks, without patching it:
//
//  - GuardedHttpServer replaces httplib's per-connection loop (the overridable
//    Server::process_and_close_socket) with one whose stream enforces a total deadline for reading each
//    request: headers and body must arrive within `request_timeout` of the request's first byte, however
//    they are trickled. A request whose body misses the deadline is answered 408 (the route's error
//    handler asks RequestDeadlineExpired()); one whose headers miss it is closed. Idle keep-alive
//    connections are closed after keep_alive_timeout as before, and on stop() within ~50 ms.
//  - Connections answered by the shedding thread (queue full) get a short header deadline
//    (kShedHeaderTimeout), so a stalled client cannot block shedding either.
//  - UploadBudget bounds the request bodies held in memory by all requests together: a request reserves
//    its Content-Length (a chunked one: the body limit) before its body is read and releases it when its
//    response is done; a request that does not fit is answered 503 with Retry-After, unread.
//  - Closing is "lingering": after the response the server stops writing, discards what the client still
//    sends (at most 1 MiB, for at most 1 s; 200 ms on the shedding thread), then closes, so a client whose
//    body was not read still receives its 503/413 instead of a connection reset (larger unread bodies may
//    still see a reset).
//
// Thread safety: UploadBudget is thread-safe. GuardedHttpServer is used as an httplib::Server. The
// thread-local helpers (MarkSheddingThread, RequestDeadlineExpired, ReserveUploadForThisRequest) refer to
// the request the calling worker thread serves.
#pragma once

#include <httplib.h>

#include <chrono>
#include <cstdint>
#include <mutex>

namespace oxbow::server {

// Header deadline for connections answered by the shedding thread.
inline constexpr std::chrono::seconds kShedHeaderTimeout{2};

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

class GuardedHttpServer : public httplib::Server {
 public:
  // `budget` (not owned, may be null) gets back this thread's reservation after each request.
  GuardedHttpServer(std::chrono::milliseconds request_timeout, UploadBudget* budget)
      : request_timeout_(request_timeout), budget_(budget) {}

 private:
  bool process_and_close_socket(socket_t sock) override;

  const std::chrono::milliseconds request_timeout_;
  UploadBudget* budget_;
};

// Called once by the shedding thread of the server's task queue: its connections get kShedHeaderTimeout.
void MarkSheddingThread();
// True when the request this thread serves ran past its read deadline (answer 408).
bool RequestDeadlineExpired();
// The socket of the connection this thread serves (-1 when none), for a route handler to notice that its
// client hung up while the request is processed.
int CurrentConnectionSocket();
// Reserves this request's body (Content-Length, or `max_body_bytes` when chunked or unknown; capped at
// max_body_bytes) from `budget`; false when it does not fit. Released by GuardedHttpServer after the
// response.
bool ReserveUploadForThisRequest(const httplib::Request& req, UploadBudget* budget, uint64_t max_body_bytes);

}  // namespace oxbow::server
