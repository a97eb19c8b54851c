#include "server/http/request_guard.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <limits>
#include <map>
#include <optional>
#include <string>
#include <thread>

namespace oxbow::server {
namespace {

using Clock = std::chrono::steady_clock;

thread_local bool t_shedding_thread = false;
thread_local bool t_deadline_expired = false;
thread_local bool t_read_timed_out = false;
thread_local bool t_chunked_over_limit = false;
thread_local bool t_close_after_response = false;
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

// Follows the chunk framing of a chunked body as httplib reads it and counts its data bytes, so that the
// body is cut once over the limit (httplib 0.11 reads chunked bodies without one). Malformed framing is
// left to httplib's parser, which then answers 400.
class ChunkedBodyMeter {
 public:
  explicit ChunkedBodyMeter(uint64_t max_data_bytes) : max_(max_data_bytes) {}

  // False once the data bytes seen exceed the limit (a chunk size line announcing that is enough).
  bool Feed(const char* data, size_t size) {
    for (size_t i = 0; i < size && state_ != State::kDone;) {
      if (state_ == State::kData) {
        const size_t n = static_cast<size_t>(std::min<uint64_t>(chunk_left_, size - i));
        chunk_left_ -= n;
        i += n;
        if (chunk_left_ == 0) state_ = State::kDataEnd;
        continue;
      }
      const char c = data[i++];
      switch (state_) {
        case State::kSize:
          if (c == '\n') {
            seen_ += chunk_left_;
            state_ = chunk_left_ == 0 ? State::kDone : State::kData;
            in_extension_ = false;
          } else if (!in_extension_ && std::isxdigit(static_cast<unsigned char>(c)) != 0) {
            const uint64_t digit = static_cast<uint64_t>(std::isdigit(static_cast<unsigned char>(c)) != 0 ? c - '0' : (c | 0x20) - 'a' + 10);
            if (chunk_left_ > (max_ - seen_) / 16) return Over();
            chunk_left_ = chunk_left_ * 16 + digit;
            if (chunk_left_ > max_ - seen_) return Over();
          } else {
            in_extension_ = true;  // extensions and the CR before the LF are httplib's to judge
          }
          break;
        case State::kDataEnd:
          if (c == '\n') {
            state_ = State::kSize;
            chunk_left_ = 0;
          }
          break;
        case State::kData:
        case State::kDone: break;
      }
    }
    return true;
  }

 private:
  enum class State { kSize, kData, kDataEnd, kDone };
  bool Over() {
    state_ = State::kDone;
    return false;
  }

  const uint64_t max_;
  State state_ = State::kSize;
  uint64_t chunk_left_ = 0;  // the size being read (kSize) or the data left of the chunk (kData)
  uint64_t seen_ = 0;        // data bytes of the completed size lines
  bool in_extension_ = false;  // past the digits of a size line
};

// A socket stream (what httplib's SocketStream does) whose reads stop at a deadline set per request.
// Reads are buffered: httplib reads header lines one byte at a time, and the loop reads a request's head
// before httplib does, then hands httplib the checked head (Replay) followed by the rest of the bytes.
class DeadlineStream : public httplib::Stream {
 public:
  DeadlineStream(socket_t sock, int read_timeout_ms, int write_timeout_ms)
      : sock_(sock), read_timeout_ms_(read_timeout_ms), write_timeout_ms_(write_timeout_ms) {}

  void SetDeadline(Clock::time_point deadline) { deadline_ = deadline; }
  bool HasBufferedBytes() const { return begin_ < buffer_.size(); }
  std::string_view Buffered() const { return std::string_view(buffer_).substr(begin_); }

  // Appends what the socket delivers next to the buffer; false at EOF, on an error or at the deadline.
  bool ReadMore() {
    if (!WaitReadable()) return false;
    buffer_.erase(0, begin_);
    begin_ = 0;
    const size_t old_size = buffer_.size();
    buffer_.resize(old_size + kChunk);
    const ssize_t n = Receive(buffer_.data() + old_size, kChunk);
    buffer_.resize(old_size + static_cast<size_t>(std::max<ssize_t>(n, 0)));
    return n > 0;
  }

  // Replaces the first `consumed` buffered bytes (a checked head) with `head`; when `chunked_limit` is
  // set, the body that follows the head is metered against it.
  void Replay(size_t consumed, const std::string& head, std::optional<uint64_t> chunked_limit) {
    buffer_ = head + buffer_.substr(begin_ + consumed);
    begin_ = 0;
    head_left_ = head.size();
    meter_.reset();
    if (chunked_limit) meter_.emplace(*chunked_limit);
  }

  bool is_readable() const override {
    return HasBufferedBytes() || PollFor(sock_, POLLIN, std::min(read_timeout_ms_, MsUntil(deadline_)));
  }
  bool is_writable() const override { return PollFor(sock_, POLLOUT, write_timeout_ms_); }

  ssize_t read(char* ptr, size_t size) override {
    ssize_t n = 0;
    if (HasBufferedBytes()) {
      n = static_cast<ssize_t>(std::min(size, buffer_.size() - begin_));
      std::memcpy(ptr, buffer_.data() + begin_, static_cast<size_t>(n));
      begin_ += static_cast<size_t>(n);
    } else {
      if (!WaitReadable()) return -1;
      if (size >= kChunk) {
        n = Receive(ptr, size);  // large reads bypass the buffer
      } else {
        buffer_.resize(kChunk);
        const ssize_t got = Receive(buffer_.data(), kChunk);
        if (got <= 0) return got;
        buffer_.resize(static_cast<size_t>(got));
        begin_ = 0;
        return read(ptr, size);
      }
    }
    if (n > 0 && !Meter(ptr, static_cast<size_t>(n))) {
      t_chunked_over_limit = true;
      return -1;
    }
    return n;
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

 private:
  static constexpr size_t kChunk = 16384;

  bool WaitReadable() const {
    const int wait_ms = std::min(read_timeout_ms_, MsUntil(deadline_));
    if (wait_ms > 0 && PollFor(sock_, POLLIN, wait_ms)) return true;
    if (MsUntil(deadline_) <= 0) {
      t_deadline_expired = true;
    } else {
      t_read_timed_out = true;
    }
    return false;
  }
  ssize_t Receive(char* ptr, size_t size) {
    for (;;) {
      const ssize_t n = ::recv(sock_, ptr, size, 0);
      if (n >= 0 || errno != EINTR) return n;
    }
  }
  // Feeds the body bytes among the `size` just read to the chunk meter; false when over its limit.
  bool Meter(const char* ptr, size_t size) {
    const size_t head = std::min(head_left_, size);
    head_left_ -= head;
    return !meter_ || meter_->Feed(ptr + head, size - head);
  }

  const socket_t sock_;
  const int read_timeout_ms_;
  const int write_timeout_ms_;
  Clock::time_point deadline_ = Clock::time_point::max();
  std::string buffer_;
  size_t begin_ = 0;
  size_t head_left_ = 0;                     // bytes of the replayed head httplib has not read yet
  std::optional<ChunkedBodyMeter> meter_;    // for a chunked request
};

// Stop sending; when the client has sent or is sending bytes the server did not read (`body_unread`: a
// body refused unread), discard what it still sends (at most `max_bytes`, for at most `linger`); then
// close. The client then gets the response instead of a reset. A connection with nothing unread (an
// idle keep-alive one) closes at once.
void LingeringClose(socket_t sock, std::chrono::milliseconds linger, uint64_t max_bytes, bool body_unread) {
  ::shutdown(sock, SHUT_WR);
  if (!body_unread && !PollFor(sock, POLLIN, 0)) {
    ::close(sock);
    return;
  }
  const auto until = Clock::now() + linger;
  char sink[16384];
  for (uint64_t discarded = 0; discarded < max_bytes;) {
    if (!PollFor(sock, POLLIN, MsUntil(until))) break;
    const ssize_t n = ::recv(sock, sink, sizeof sink, 0);
    if (n <= 0) break;
    discarded += static_cast<size_t>(n);
  }
  ::close(sock);
}

// ---- Request heads

bool IsTokenChar(unsigned char c) {
  return std::isalnum(c) != 0 || std::strchr("!#$%&'*+-.^_`|~", c) != nullptr;
}

bool IsToken(std::string_view text) {
  return !text.empty() && std::all_of(text.begin(), text.end(), [](char c) { return c != 0 && IsTokenChar(static_cast<unsigned char>(c)); });
}

bool EqualsIgnoreCase(std::string_view a, std::string_view b) {
  return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), [](char x, char y) {
           return std::tolower(static_cast<unsigned char>(x)) == std::tolower(static_cast<unsigned char>(y));
         });
}

std::string_view TrimSpace(std::string_view text) {
  while (!text.empty() && (text.front() == ' ' || text.front() == '\t')) text.remove_prefix(1);
  while (!text.empty() && (text.back() == ' ' || text.back() == '\t')) text.remove_suffix(1);
  return text;
}

// Methods whose requests oxbow reads a body of; any other method with a body is refused.
bool TakesBody(std::string_view method) { return method == "POST" || method == "PUT" || method == "PATCH"; }

HeadParse Refuse(HeadParse parse, int status, std::string code, std::string message) {
  parse.kind = HeadParse::Kind::kRefused;
  parse.refused.refusal = Refusal{status, std::move(code), std::move(message)};
  return parse;
}

HeadParse RefuseFraming(HeadParse parse, std::string message) {
  return Refuse(std::move(parse), 400, "bad_request", "malformed HTTP request: " + std::move(message));
}

HeadParse RefuseHeadSize(HeadParse parse, std::string message) {
  return Refuse(std::move(parse), 431, "headers_too_large", std::move(message));
}

// Checks a complete request line and records its method and target; the refusal, if any.
std::optional<HeadParse> CheckRequestLine(std::string_view line, HeadParse* parse) {
  const size_t first = line.find(' ');
  const size_t second = first == std::string_view::npos ? first : line.find(' ', first + 1);
  if (second == std::string_view::npos || line.find(' ', second + 1) != std::string_view::npos) {
    return RefuseFraming(std::move(*parse), "the request line is not a method, a target and a version separated by single spaces");
  }
  const std::string_view method = line.substr(0, first);
  const std::string_view target = line.substr(first + 1, second - first - 1);
  const std::string_view version = line.substr(second + 1);
  if (!IsToken(method)) return RefuseFraming(std::move(*parse), "the method is not a token");
  parse->refused.method.assign(method);
  if (target.size() > kMaxTargetBytes) {
    return Refuse(std::move(*parse), 414, "uri_too_long", "request target over " + std::to_string(kMaxTargetBytes) + " bytes");
  }
  if (target.empty() || std::any_of(target.begin(), target.end(), [](char c) {
        const auto u = static_cast<unsigned char>(c);
        return u <= 0x20 || u == 0x7f;
      })) {
    return RefuseFraming(std::move(*parse), "the request target is empty or holds control bytes");
  }
  parse->refused.target.assign(target);
  if (version != "HTTP/1.1" && version != "HTTP/1.0") {
    if (version.size() == 8 && version.substr(0, 5) == "HTTP/") {
      // Worded without a version ("HTTP/1.1 ..."): the body must not hold what a client scanning the
      // bytes would read as a second status line.
      return Refuse(std::move(*parse), 505, "http_version_not_supported", "only versions 1.0 and 1.1 of HTTP are served");
    }
    return RefuseFraming(std::move(*parse), "the request line does not end in an HTTP version");
  }
  static constexpr std::string_view kServed[] = {"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"};
  if (std::find(std::begin(kServed), std::end(kServed), method) == std::end(kServed)) {
    return Refuse(std::move(*parse), 501, "not_implemented",
                  "the method is not one the server implements (GET, HEAD, POST, PUT, PATCH, DELETE, OPTIONS)");
  }
  return std::nullopt;
}

// Checks one header line; refuses names that are not tokens and values with control bytes (NUL, CR,
// LF, ...; a value is compared whole, so what follows such a byte must not be silently dropped).
std::optional<HeadParse> CheckHeaderLine(std::string_view line, HeadParse* parse) {
  if (line.front() == ' ' || line.front() == '\t') {
    return RefuseFraming(std::move(*parse), "obsolete header line folding");
  }
  const size_t colon = line.find(':');
  if (colon == std::string_view::npos || !IsToken(line.substr(0, colon))) {
    return RefuseFraming(std::move(*parse), "a header line is not 'Name: value' with a token name");
  }
  const std::string_view value = TrimSpace(line.substr(colon + 1));
  if (std::any_of(value.begin(), value.end(), [](char c) {
        const auto u = static_cast<unsigned char>(c);
        return (u < 0x20 && u != '\t') || u == 0x7f;
      })) {
    return RefuseFraming(std::move(*parse), "header '" + std::string(line.substr(0, colon)) + "' holds a control byte");
  }
  parse->head.headers.emplace_back(line.substr(0, colon), value);
  if (EqualsIgnoreCase(line.substr(0, colon), "X-Request-Id") && parse->refused.request_id.empty()) {
    parse->refused.request_id.assign(value);
  }
  return std::nullopt;
}

// The body framing of a complete head: Content-Length / Transfer-Encoding / Content-Encoding rules.
std::optional<HeadParse> CheckBodyFraming(HeadParse* parse, const RequestHeadLimits& limits, bool* add_zero_length) {
  // A plain flag and value, not std::optional: clang-tidy 16's unchecked-optional-access analysis of
  // this loop sometimes ran for over 10 minutes (CI's per-file limit) where it usually takes 2 s.
  bool has_length = false;
  uint64_t length = 0;
  std::string transfer_encoding;
  bool has_transfer_encoding = false;
  for (const auto& [name, value] : parse->head.headers) {
    if (EqualsIgnoreCase(name, "Content-Length")) {
      if (value.empty() || value.size() > 19 || !std::all_of(value.begin(), value.end(), [](char c) { return c >= '0' && c <= '9'; })) {
        return RefuseFraming(std::move(*parse), "Content-Length '" + value + "' is not a decimal byte count");
      }
      const uint64_t n = std::stoull(value);
      if (has_length && length != n) return RefuseFraming(std::move(*parse), "two different Content-Length headers");
      length = n;
      has_length = true;
    } else if (EqualsIgnoreCase(name, "Transfer-Encoding")) {
      transfer_encoding += (has_transfer_encoding ? "," : "") + value;
      has_transfer_encoding = true;
    } else if (EqualsIgnoreCase(name, "Content-Encoding") && !EqualsIgnoreCase(value, "identity")) {
      return Refuse(std::move(*parse), 415, "unsupported_encoding",
                    "Content-Encoding '" + value + "' is not accepted: send the body as it is (images are compressed already)");
    }
  }
  parse->declared_body_bytes = length;
  if (has_transfer_encoding) {
    if (has_length) return RefuseFraming(std::move(*parse), "both Content-Length and Transfer-Encoding");
    if (!EqualsIgnoreCase(TrimSpace(transfer_encoding), "chunked")) {
      return Refuse(std::move(*parse), 501, "not_implemented", "Transfer-Encoding '" + transfer_encoding + "' is not supported (only chunked)");
    }
    parse->head.chunked = true;
  }
  const bool has_body = parse->head.chunked || length > 0;
  if (has_body && !TakesBody(parse->refused.method)) {
    return RefuseFraming(std::move(*parse), parse->refused.method + " requests take no body");
  }
  if (length > limits.max_body_bytes) {
    return Refuse(std::move(*parse), 413, "payload_too_large",
                  "request body over the server's limit of " + std::to_string(limits.max_body_bytes) + " bytes (oxbow serve --max-upload-mb)");
  }
  *add_zero_length = !has_length && !parse->head.chunked;
  return std::nullopt;
}

// ---- Refusals written by the loop

const char* ReasonPhrase(int status) {
  switch (status) {
    case 400: return "Bad Request";
    case 408: return "Request Timeout";
    case 413: return "Payload Too Large";
    case 414: return "URI Too Long";
    case 415: return "Unsupported Media Type";
    case 431: return "Request Header Fields Too Large";
    case 501: return "Not Implemented";
    case 503: return "Service Unavailable";
    case 505: return "HTTP Version Not Supported";
    default: return "Error";
  }
}

void WriteRefusal(httplib::Stream& stream, const RefusedRequest& refused, const RefusalWriter& writer) {
  httplib::Response res;
  writer(refused, res);
  std::string out = "HTTP/1.1 " + std::to_string(res.status) + " " + ReasonPhrase(res.status) + "\r\n";
  for (const auto& [name, value] : res.headers) out.append(name).append(": ").append(value).append("\r\n");
  out += "Content-Length: " + std::to_string(res.body.size()) + "\r\nConnection: close\r\n\r\n" + res.body;
  for (size_t sent = 0; sent < out.size();) {
    const ssize_t n = stream.write(out.data() + sent, out.size() - sent);
    if (n <= 0) return;
    sent += static_cast<size_t>(n);
  }
}

}  // namespace

HeadParse ParseRequestHead(std::string_view bytes, const RequestHeadLimits& limits) {
  HeadParse parse;
  size_t pos = 0;
  for (int empty = 0; bytes.substr(pos, 2) == "\r\n"; ++empty, pos += 2) {
    if (empty == kMaxLeadingEmptyLines) return RefuseFraming(std::move(parse), "empty lines instead of a request line");
  }
  const size_t start = pos;
  bool request_line = true;
  bool add_zero_length = false;
  for (;;) {
    const size_t lf = bytes.find('\n', pos);
    const size_t line_end = lf == std::string_view::npos ? bytes.size() : lf;
    if (line_end - pos > (request_line ? kMaxTargetBytes + 64 : kMaxHeaderLineBytes)) {
      if (request_line) return Refuse(std::move(parse), 414, "uri_too_long", "request line over " + std::to_string(kMaxTargetBytes) + " bytes");
      return RefuseHeadSize(std::move(parse), "a header line over " + std::to_string(kMaxHeaderLineBytes) + " bytes");
    }
    if (line_end - start > limits.max_head_bytes) {
      return RefuseHeadSize(std::move(parse), "request headers over " + std::to_string(limits.max_head_bytes) + " bytes (oxbow serve --max-header-kb)");
    }
    if (lf == std::string_view::npos) {
      // A CR must be the last byte so far (its LF still to come).
      const size_t cr = bytes.find('\r', pos);
      if (cr != std::string_view::npos && cr + 1 < bytes.size()) return RefuseFraming(std::move(parse), "a CR without LF");
      return parse;  // kIncomplete
    }
    if (lf == pos || bytes[lf - 1] != '\r') return RefuseFraming(std::move(parse), "a line ends in LF without CR");
    const std::string_view line = bytes.substr(pos, lf - 1 - pos);
    if (line.find('\r') != std::string_view::npos) return RefuseFraming(std::move(parse), "a CR inside a line");
    pos = lf + 1;
    if (request_line) {
      if (auto refused = CheckRequestLine(line, &parse)) return std::move(*refused);
      request_line = false;
      continue;
    }
    if (line.empty()) break;
    if (parse.head.headers.size() == limits.max_header_count) {
      return RefuseHeadSize(std::move(parse), "more than " + std::to_string(limits.max_header_count) + " request headers (oxbow serve --max-header-count)");
    }
    if (auto refused = CheckHeaderLine(line, &parse)) return std::move(*refused);
  }
  if (auto refused = CheckBodyFraming(&parse, limits, &add_zero_length)) return std::move(*refused);
  parse.kind = HeadParse::Kind::kComplete;
  parse.head.method = parse.refused.method;
  parse.head.target = parse.refused.target;
  parse.head.consumed = pos;
  parse.head.replay.assign(bytes.substr(start, pos - start - 2));
  if (add_zero_length) parse.head.replay += "Content-Length: 0\r\n";
  parse.head.replay += "\r\n";
  return parse;
}

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

bool RequestDeadlineExpired() { return t_deadline_expired; }

bool RequestReadTimedOut() { return t_read_timed_out; }

bool ChunkedBodyOverLimit() { return t_chunked_over_limit; }

void CloseConnectionAfterResponse() { t_close_after_response = true; }

std::string FullHeaderValue(const httplib::Request& req, const char* name) {
  const auto it = req.headers.find(name);
  return it == req.headers.end() ? std::string() : it->second;
}
int CurrentConnectionSocket() { return t_socket; }

bool ReserveUploadForThisRequest(const httplib::Request& req, UploadBudget* budget, uint64_t max_body_bytes) {
  if (budget == nullptr) return true;
  uint64_t bytes = 0;
  if (req.has_header("Content-Length")) {
    // ParseRequestHead let only decimal lengths up to max_body_bytes through.
    bytes = std::min<uint64_t>(std::stoull(FullHeaderValue(req, "Content-Length")), max_body_bytes);
  } else if (req.has_header("Transfer-Encoding")) {
    bytes = max_body_bytes;
  }
  if (bytes == 0) return true;
  if (!budget->TryReserve(bytes)) return false;
  t_reserved_bytes += bytes;
  return true;
}

// ---- Connection scheduling

// httplib's accept loop wraps each accepted socket in an opaque job for TaskQueue::enqueue. This queue
// runs that job at once on the accept thread: it is GuardedHttpServer::process_and_close_socket, which
// files the socket here (Admit), where its client address and accept time are known. Workers then
// serve the queued connections; the ones over the queue or per-client limit go to the shedding thread.
class ConnectionScheduler : public httplib::TaskQueue {
 public:
  ConnectionScheduler(GuardedHttpServer* server, const GuardOptions& options)
      : server_(server),
        max_queued_(static_cast<size_t>(options.max_queued)),
        max_per_client_(static_cast<size_t>(options.max_connections_per_client)) {
    for (int i = 0; i < options.threads; ++i) workers_.emplace_back([this] { Work(&queued_, false); });
    shedder_ = std::thread([this] { Work(&shed_, true); });
  }
  ~ConnectionScheduler() override = default;
  ConnectionScheduler(const ConnectionScheduler&) = delete;
  ConnectionScheduler& operator=(const ConnectionScheduler&) = delete;

  void enqueue(std::function<void()> fn) override { fn(); }

  void Admit(socket_t sock) {
    std::string client;
    int port = 0;
    DeadlineStream(sock, 0, 0).Address(true, client, port);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      Connection connection{sock, client, Clock::now(), std::nullopt};
      size_t& open = open_per_client_[client];
      ++open;
      if (open > max_per_client_) {
        connection.shed = Refusal{503, "unavailable",
                                  "too many connections from " + client + ": at most " + std::to_string(max_per_client_) +
                                      " at once (oxbow serve --max-connections-per-client)"};
        shed_.push_back(std::move(connection));
      } else if (queued_.size() >= max_queued_) {
        connection.shed = Refusal{503, "unavailable",
                                  "server busy: " + std::to_string(max_queued_) +
                                      " connections already wait for a worker; retry later"};
        shed_.push_back(std::move(connection));
      } else {
        queued_.push_back(std::move(connection));
      }
    }
    cond_.notify_all();
  }

  // Whether connections wait for a thread of the caller's kind (workers, or the shedding thread).
  bool OthersWaiting() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return !(t_shedding_thread ? shed_ : queued_).empty();
  }

  void shutdown() override {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      shutdown_ = true;
    }
    cond_.notify_all();
    for (auto& t : workers_) t.join();
    shedder_.join();
  }

 private:
  struct Connection {
    socket_t sock;
    std::string client;
    Clock::time_point accepted;
    std::optional<Refusal> shed;  // set for the shedding thread
  };

  void Work(std::deque<Connection>* queue, bool shedding) {
    t_shedding_thread = shedding;
    for (;;) {
      Connection connection;
      {
        std::unique_lock<std::mutex> lock(mutex_);
        cond_.wait(lock, [&] { return !queue->empty() || shutdown_; });
        if (queue->empty()) return;  // shutdown_ and drained: queued connections are served first
        connection = std::move(queue->front());
        queue->pop_front();
      }
      server_->ServeConnection(connection.sock, connection.accepted, connection.shed ? &*connection.shed : nullptr);
      std::lock_guard<std::mutex> lock(mutex_);
      if (--open_per_client_[connection.client] == 0) open_per_client_.erase(connection.client);
    }
  }

  GuardedHttpServer* const server_;
  const size_t max_queued_;
  const size_t max_per_client_;
  mutable std::mutex mutex_;  // guards queued_, shed_, open_per_client_, shutdown_
  std::condition_variable cond_;
  std::deque<Connection> queued_;
  std::deque<Connection> shed_;
  std::map<std::string, size_t> open_per_client_;  // open connections by client address
  bool shutdown_ = false;
  std::vector<std::thread> workers_;
  std::thread shedder_;
};

GuardedHttpServer::GuardedHttpServer(GuardOptions options) : options_(std::move(options)) {
  new_task_queue = [this] {
    auto* scheduler = new ConnectionScheduler(this, options_);
    scheduler_ = scheduler;
    return scheduler;
  };
}

bool GuardedHttpServer::process_and_close_socket(socket_t sock) {
  scheduler_->Admit(sock);
  return true;
}

// The per-connection loop of httplib 0.11 (keep-alive: wait for the next request, serve it), with a
// stream that enforces the per-request read deadline, and the request head read and checked here first.
void GuardedHttpServer::ServeConnection(socket_t sock, Clock::time_point accepted, const Refusal* shed) {
  DeadlineStream stream(sock, static_cast<int>(read_timeout_sec_ * 1000 + read_timeout_usec_ / 1000),
                        static_cast<int>(write_timeout_sec_ * 1000 + write_timeout_usec_ / 1000));
  auto idle_since = accepted;
  uint64_t declared_body_bytes = 0;  // Content-Length of the last request
  bool body_unread = false;          // the last request was answered without reading its body
  t_socket = sock;
  for (size_t remaining = keep_alive_max_count_; remaining > 0; --remaining) {
    // Idle until the next request starts: at most keep_alive_timeout (kShedHeaderTimeout when shedding),
    // kBusyIdleTimeout while other connections wait (none when shedding), and not past stop().
    const auto idle_limit = shed != nullptr ? std::chrono::duration_cast<std::chrono::milliseconds>(kShedHeaderTimeout)
                                            : std::chrono::milliseconds(keep_alive_timeout_sec_ * 1000);
    const auto busy_limit = shed != nullptr ? std::chrono::milliseconds(0) : kBusyIdleTimeout;
    bool readable = stream.HasBufferedBytes();
    while (!readable && svr_sock_ != INVALID_SOCKET) {
      // A request already sent is served, however long its connection waited in the queue: only a
      // connection with nothing to read is dropped for idleness.
      readable = PollFor(sock, POLLIN, 0);
      if (readable) break;
      const auto idle = Clock::now() - idle_since;
      if (idle >= idle_limit || (idle >= busy_limit && scheduler_->OthersWaiting())) break;
      readable = PollFor(sock, POLLIN, 50);
    }
    if (!readable) {
      if (shed != nullptr) WriteRefusal(stream, RefusedRequest{{}, {}, {}, *shed}, options_.refusal_writer);
      break;
    }
    const auto timeout = shed != nullptr ? std::chrono::duration_cast<std::chrono::milliseconds>(kShedHeaderTimeout)
                                         : options_.request_timeout;
    stream.SetDeadline(Clock::now() + timeout);
    t_deadline_expired = false;
    t_read_timed_out = false;
    t_chunked_over_limit = false;
    t_close_after_response = false;
    HeadParse parse = ParseRequestHead(stream.Buffered(), options_.head);
    while (parse.kind == HeadParse::Kind::kIncomplete && (shed == nullptr || !scheduler_->OthersWaiting()) &&
           stream.ReadMore()) {
      parse = ParseRequestHead(stream.Buffered(), options_.head);
    }
    declared_body_bytes = parse.declared_body_bytes;
    body_unread = declared_body_bytes > 0 || parse.head.chunked;
    if (shed != nullptr) {
      // Busy: the head (when it came in time) only names the request in the answer and the log.
      RefusedRequest refused = parse.kind == HeadParse::Kind::kIncomplete ? RefusedRequest{} : parse.refused;
      refused.refusal = *shed;
      WriteRefusal(stream, refused, options_.refusal_writer);
      break;
    }
    if (parse.kind == HeadParse::Kind::kIncomplete) break;  // closed, failed or late: nothing to answer
    if (parse.kind == HeadParse::Kind::kRefused) {
      WriteRefusal(stream, parse.refused, options_.refusal_writer);
      break;
    }
    stream.Replay(parse.head.consumed, parse.head.replay,
                  parse.head.chunked ? std::optional<uint64_t>(options_.head.max_body_bytes) : std::nullopt);
    bool connection_closed = false;
    const bool close_connection = remaining == 1 || svr_sock_ == INVALID_SOCKET;
    const bool ok = process_request(stream, close_connection, connection_closed, nullptr);
    if (options_.budget != nullptr) options_.budget->Release(t_reserved_bytes);
    t_reserved_bytes = 0;
    body_unread = body_unread && t_close_after_response;
    if (!ok || connection_closed || close_connection || t_close_after_response) break;
    idle_since = Clock::now();
  }
  // A worker discards the declared body of the last request (at least 1 MiB) for up to 1 s, so that an
  // HTTP client still sending a refused body reads its 413/503 rather than a reset. The shedding thread
  // lingers briefly, and not at all while others wait for it: it must keep up with a flood.
  if (shed == nullptr) {
    LingeringClose(sock, std::chrono::milliseconds(1000), std::max<uint64_t>(1u << 20, declared_body_bytes), body_unread);
  } else {
    LingeringClose(sock, std::chrono::milliseconds(scheduler_->OthersWaiting() ? 0 : 200), 1u << 20, body_unread);
  }
  t_socket = -1;
}

}  // namespace oxbow::server
