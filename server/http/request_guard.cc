#include "server/http/request_guard.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <limits>
#include <string>

namespace oxbow::server {
namespace {

using Clock = std::chrono::steady_clock;

thread_local bool t_shedding_thread = false;
thread_local bool t_deadline_expired = false;
thread_local uint64_t t_reserved_bytes = 0;
thread_local int t_socket = -1;

// Waits until `fd` is ready for `events` or `timeout_ms` passes; retries on EINTR.
bool PollFor(int fd, short events, int timeout_ms) {
  pollfd p{fd, events, 0};
  for (;;) {
    const int n = ::poll(&p, 1, std::max(0, timeout_ms));
    if (n >= 0) return n > 0;
    if (errno != EINTR) return false;
  }
}

// Milliseconds from now until `t`, clamped to [0, INT_MAX] (0: passed or less than 1 ms away).
int MsUntil(Clock::time_point t) {
  const auto now = Clock::now();
  if (t <= now) return 0;
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(t - now).count();
  return static_cast<int>(std::min<int64_t>(ms, std::numeric_limits<int>::max()));
}

// A socket stream (what httplib's SocketStream does) whose reads stop at a deadline set per request.
// Reads are buffered: httplib reads header lines one byte at a time.
class DeadlineStream : public httplib::Stream {
 public:
  DeadlineStream(socket_t sock, int read_timeout_ms, int write_timeout_ms)
      : sock_(sock), read_timeout_ms_(read_timeout_ms), write_timeout_ms_(write_timeout_ms) {}

  void SetDeadline(Clock::time_point deadline) { deadline_ = deadline; }
  bool HasBufferedBytes() const { return begin_ < end_; }

  bool is_readable() const override {
    return HasBufferedBytes() || PollFor(sock_, POLLIN, std::min(read_timeout_ms_, MsUntil(deadline_)));
  }
  bool is_writable() const override { return PollFor(sock_, POLLOUT, write_timeout_ms_); }

  ssize_t read(char* ptr, size_t size) override {
    if (!HasBufferedBytes()) {
      const int wait_ms = std::min(read_timeout_ms_, MsUntil(deadline_));
      if (wait_ms <= 0 || !PollFor(sock_, POLLIN, wait_ms)) {
        if (MsUntil(deadline_) <= 0) t_deadline_expired = true;
        return -1;
      }
      if (size >= sizeof buffer_) return Receive(ptr, size);  // large reads bypass the buffer
      const ssize_t n = Receive(buffer_, sizeof buffer_);
      if (n <= 0) return n;
      begin_ = 0;
      end_ = static_cast<size_t>(n);
    }
    const size_t n = std::min(size, end_ - begin_);
    std::memcpy(ptr, buffer_ + begin_, n);
    begin_ += n;
    return static_cast<ssize_t>(n);
  }

  ssize_t write(const char* ptr, size_t size) override {
    if (!is_writable()) return -1;
    for (;;) {
      const ssize_t n = ::send(sock_, ptr, size, MSG_NOSIGNAL);
      if (n >= 0 || errno != EINTR) return n;
    }
  }

  void get_remote_ip_and_port(std::string& ip, int& port) const override { Address(true, ip, port); }
  void get_local_ip_and_port(std::string& ip, int& port) const override { Address(false, ip, port); }
  socket_t socket() const override { return sock_; }

 private:
  ssize_t Receive(char* ptr, size_t size) {
    for (;;) {
      const ssize_t n = ::recv(sock_, ptr, size, 0);
      if (n >= 0 || errno != EINTR) return n;
    }
  }
  void Address(bool peer, std::string& ip, int& port) const {
    sockaddr_storage address{};
    socklen_t length = sizeof address;
    const int rc = peer ? ::getpeername(sock_, reinterpret_cast<sockaddr*>(&address), &length)
                        : ::getsockname(sock_, reinterpret_cast<sockaddr*>(&address), &length);
    if (rc != 0) return;
    char text[INET6_ADDRSTRLEN] = {};
    if (address.ss_family == AF_INET) {
      const auto* v4 = reinterpret_cast<const sockaddr_in*>(&address);
      ::inet_ntop(AF_INET, &v4->sin_addr, text, sizeof text);
      port = ntohs(v4->sin_port);
    } else if (address.ss_family == AF_INET6) {
      const auto* v6 = reinterpret_cast<const sockaddr_in6*>(&address);
      ::inet_ntop(AF_INET6, &v6->sin6_addr, text, sizeof text);
      port = ntohs(v6->sin6_port);
    }
    ip = text;
  }

  const socket_t sock_;
  const int read_timeout_ms_;
  const int write_timeout_ms_;
  Clock::time_point deadline_ = Clock::time_point::max();
  char buffer_[4096];
  size_t begin_ = 0, end_ = 0;
};

// Stop sending; when the client has sent bytes the server did not read (a body refused unread), discard
// what it still sends (at most 1 MiB, for at most `linger`); then close. The client then gets the
// response instead of a reset. A connection with nothing unread (an idle keep-alive one) closes at once.
void LingeringClose(socket_t sock, std::chrono::milliseconds linger) {
  ::shutdown(sock, SHUT_WR);
  if (!PollFor(sock, POLLIN, 0)) {
    ::close(sock);
    return;
  }
  const auto until = Clock::now() + linger;
  char sink[16384];
  for (size_t discarded = 0; discarded < (1u << 20);) {
    if (!PollFor(sock, POLLIN, MsUntil(until))) break;
    const ssize_t n = ::recv(sock, sink, sizeof sink, 0);
    if (n <= 0) break;
    discarded += static_cast<size_t>(n);
  }
  ::close(sock);
}

}  // namespace

bool UploadBudget::TryReserve(uint64_t bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (bytes > capacity_ - in_use_) return false;
  in_use_ += bytes;
  return true;
}

void UploadBudget::Release(uint64_t bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  in_use_ -= std::min(bytes, in_use_);
}

uint64_t UploadBudget::in_use() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return in_use_;
}

void MarkSheddingThread() { t_shedding_thread = true; }

bool RequestDeadlineExpired() { return t_deadline_expired; }

int CurrentConnectionSocket() { return t_socket; }

bool ReserveUploadForThisRequest(const httplib::Request& req, UploadBudget* budget, uint64_t max_body_bytes) {
  if (budget == nullptr) return true;
  uint64_t bytes = 0;
  if (req.has_header("Content-Length")) {
    const std::string text = req.get_header_value("Content-Length");
    bytes = max_body_bytes;
    if (!text.empty() && text.size() <= 19 && std::all_of(text.begin(), text.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      bytes = std::min<uint64_t>(std::stoull(text), max_body_bytes);
    }
  } else if (req.has_header("Transfer-Encoding")) {
    bytes = max_body_bytes;
  }
  if (bytes == 0) return true;
  if (!budget->TryReserve(bytes)) return false;
  t_reserved_bytes += bytes;
  return true;
}

// The per-connection loop of httplib 0.11 (keep-alive: wait for the next request, serve it), with a
// stream that enforces the per-request read deadline.
bool GuardedHttpServer::process_and_close_socket(socket_t sock) {
  DeadlineStream stream(sock, static_cast<int>(read_timeout_sec_ * 1000 + read_timeout_usec_ / 1000),
                        static_cast<int>(write_timeout_sec_ * 1000 + write_timeout_usec_ / 1000));
  const auto timeout = t_shedding_thread ? std::chrono::duration_cast<std::chrono::milliseconds>(kShedHeaderTimeout)
                                         : request_timeout_;
  bool ok = false;
  t_socket = sock;
  for (size_t remaining = keep_alive_max_count_; remaining > 0; --remaining) {
    // Idle until the next request starts: at most keep_alive_timeout, and not past stop().
    const auto idle_until = Clock::now() + std::chrono::seconds(keep_alive_timeout_sec_);
    bool readable = stream.HasBufferedBytes();
    while (!readable && svr_sock_ != INVALID_SOCKET && Clock::now() < idle_until) {
      readable = PollFor(sock, POLLIN, std::min(50, MsUntil(idle_until)));
    }
    if (!readable) break;
    stream.SetDeadline(Clock::now() + timeout);
    t_deadline_expired = false;
    bool connection_closed = false;
    const bool close_connection = remaining == 1 || t_shedding_thread || svr_sock_ == INVALID_SOCKET;
    ok = process_request(stream, close_connection, connection_closed, nullptr);
    if (budget_ != nullptr) budget_->Release(t_reserved_bytes);
    t_reserved_bytes = 0;
    if (!ok || connection_closed || close_connection) break;
  }
  t_socket = -1;
  // The shedding thread lingers briefly: it must keep up with a flood.
  LingeringClose(sock, std::chrono::milliseconds(t_shedding_thread ? 200 : 1000));
  return ok;
}

}  // namespace oxbow::server
