// Slow, stalled and greedy clients against the real `oxbow serve` (server/request_guard.h): more
// trickling clients than worker threads, idle connections and a header trickle must not keep a normal
// request from being answered; the stalled ones are cut by the server (408 or a close) rather than
// holding their worker for as long as they like; uploads beyond --max-inflight-upload-mb get 503 with
// Retry-After, unread, and the budget comes back once a request ends. No wall-clock assertions: the
// tests check who ended each connection, with generous give-up times.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "api/testing.h"
#include "sift/sift.h"
#include "tests/e2e_testing.h"

namespace oxbow {
namespace {

using Clock = std::chrono::steady_clock;
using nlohmann::json;

int Connect(int port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    close(fd);
    return -1;
  }
  return fd;
}

bool SendAll(int fd, const std::string& text) {
  for (size_t sent = 0; sent < text.size();) {
    const ssize_t n = send(fd, text.data() + sent, text.size() - sent, MSG_NOSIGNAL);
    if (n <= 0) return false;
    sent += static_cast<size_t>(n);
  }
  return true;
}

// How a stalled client's connection ended.
struct Outcome {
  bool ended_by_server = false;  // the server answered, closed or reset it (not our give-up)
  std::string response;          // what the server sent, if anything
};

// Reads what the server has sent so far without blocking; true when the server answered or closed.
bool ServerSpoke(int fd, Outcome* outcome) {
  char buf[4096];
  for (;;) {
    const ssize_t n = recv(fd, buf, sizeof buf, MSG_DONTWAIT);
    if (n > 0) {
      outcome->response.append(buf, static_cast<size_t>(n));
      continue;
    }
    if (n == 0) return true;                                     // closed
    if (errno == EAGAIN || errno == EWOULDBLOCK) return !outcome->response.empty();
    return true;                                                 // reset
  }
}

// Sends `head`, then one byte of `filler` every `interval` until the server answers or closes the
// connection, or `give_up` passes.
Outcome Trickle(int port, const std::string& head, std::chrono::milliseconds interval, std::chrono::seconds give_up) {
  Outcome outcome;
  const int fd = Connect(port);
  if (fd < 0) return outcome;
  const auto until = Clock::now() + give_up;
  if (SendAll(fd, head)) {
    while (Clock::now() < until) {
      std::this_thread::sleep_for(interval);
      if (ServerSpoke(fd, &outcome) || !SendAll(fd, "x")) {
        outcome.ended_by_server = true;
        break;
      }
    }
  } else {
    outcome.ended_by_server = true;
  }
  // Collect the rest of a response that was being written.
  pollfd p{fd, POLLIN, 0};
  while (outcome.ended_by_server && poll(&p, 1, 200) > 0 && !ServerSpoke(fd, &outcome)) {
  }
  close(fd);
  return outcome;
}

// Connects and sends nothing; reports whether the server closed the connection before `give_up`.
bool IdleConnectionClosedByServer(int port, std::chrono::seconds give_up) {
  const int fd = Connect(port);
  if (fd < 0) return false;
  pollfd p{fd, POLLIN, 0};
  const bool closed = poll(&p, 1, static_cast<int>(give_up.count() * 1000)) > 0;
  close(fd);
  return closed;
}

std::string PostHead(const std::string& path, size_t content_length) {
  return "POST " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\nContent-Length: " +
         std::to_string(content_length) + "\r\n\r\n";
}

class SlowClientsTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new api::testing::TempDir("oxbow-slow-clients-test");
    vocab_ = dir_->path() + "/vocab.oxvoc";
    ASSERT_TRUE(oxbow::testing::RandomVocabulary(api::testing::TestSiftOptions().Describe())->Write(vocab_));
    std::vector<uchar> png;
    ASSERT_TRUE(cv::imencode(".png", oxbow::testing::Texture(400, 300), png));
    image_.assign(png.begin(), png.end());
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  std::unique_ptr<oxbow::testing::ServerProcess> Start(const std::vector<std::string>& extra) {
    const std::string n = std::to_string(counter_++);
    std::vector<std::string> args = {"serve", "--index", dir_->path() + "/index-" + n, "--vocab", vocab_, "--port", "0"};
    args.insert(args.end(), extra.begin(), extra.end());
    auto server = std::make_unique<oxbow::testing::ServerProcess>(args, dir_->path() + "/server-" + n + ".log");
    EXPECT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
    return server;
  }

  static inline api::testing::TempDir* dir_ = nullptr;
  static inline std::string vocab_;
  static inline std::string image_;
  static inline int counter_ = 0;
};

TEST_F(SlowClientsTest, TricklingAndIdleClientsDoNotStarveANormalRequest) {
  // Two workers; three tricklers (two bodies, one header) and two idle connections: more than the workers.
  // Without the request deadline they would hold both workers until they give up (25 s); each sends a
  // byte every 200 ms, far inside the 30 s per-read timeout.
  const char* timeout = std::getenv("OXBOW_SLOW_CLIENTS_REQUEST_TIMEOUT_S");  // 3600 shows the unguarded server
  auto server = Start({"--http-workers", "2", "--queue", "16", "--read-timeout-s", "30", "--request-timeout-s",
                       timeout != nullptr ? timeout : "2"});
  const int port = server->port();
  const auto interval = std::chrono::milliseconds(200);
  const auto give_up = std::chrono::seconds(25);
  std::vector<Outcome> bodies(2);
  Outcome header;
  std::array<bool, 2> idle_closed{};  // not vector<bool>: its bits share a word, written by two threads
  std::vector<std::thread> stalled;
  stalled.reserve(bodies.size() + 1 + idle_closed.size());
  for (auto& outcome : bodies) {
    stalled.emplace_back([&, port] { outcome = Trickle(port, PostHead("/v1/search", 100000), interval, give_up); });
  }
  stalled.emplace_back([&, port] {
    header = Trickle(port, "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ", interval, give_up);
  });
  for (size_t i = 0; i < idle_closed.size(); ++i) {
    stalled.emplace_back([&, i, port] { idle_closed[i] = IdleConnectionClosedByServer(port, give_up); });
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));  // let them take the workers

  auto client = server->Client();
  auto found = client.Post("/v1/search", image_, "image/png");
  ASSERT_TRUE(found) << httplib::to_string(found.error());
  EXPECT_EQ(found->status, 200) << found->body;
  for (auto& t : stalled) t.join();

  for (const Outcome& outcome : bodies) {
    EXPECT_TRUE(outcome.ended_by_server) << "a trickled body held its worker until the client gave up";
    EXPECT_EQ(outcome.response.rfind("HTTP/1.1 408", 0), 0u) << outcome.response;
    EXPECT_NE(outcome.response.find("request_timeout"), std::string::npos) << outcome.response;
  }
  EXPECT_TRUE(header.ended_by_server) << "trickled headers held their worker until the client gave up";
  for (bool closed : idle_closed) EXPECT_TRUE(closed) << "an idle connection was never closed";
  auto health = client.Get("/healthz");
  ASSERT_TRUE(health);
  EXPECT_EQ(health->status, 200);
  EXPECT_NE(server->Log().find("status=408"), std::string::npos);
}

TEST_F(SlowClientsTest, AStalledClientCannotBlockTheBusyAnswer) {
  // One worker, a queue of one: the first trickler holds the worker, the second waits in the queue, the
  // third is handed to the shedding thread and trickles its headers there. A normal request after them
  // must get its 503 while the first trickler still holds the worker (the shedder's header deadline).
  auto server = Start({"--http-workers", "1", "--queue", "1", "--request-timeout-s", "30"});
  const int port = server->port();
  std::vector<Outcome> outcomes(3);
  std::atomic<bool> first_still_connected{true};
  std::vector<std::thread> stalled;
  for (size_t i = 0; i < outcomes.size(); ++i) {
    stalled.emplace_back([&, i, port] {
      outcomes[i] = Trickle(port, "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ", std::chrono::milliseconds(200),
                            std::chrono::seconds(6));
      if (i == 0) first_still_connected = false;
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // connect in this order
  }
  auto busy = server->Client().Get("/healthz");
  const bool answered_while_held = first_still_connected.load();
  ASSERT_TRUE(busy) << httplib::to_string(busy.error());
  EXPECT_EQ(busy->status, 503) << busy->body;
  EXPECT_EQ(json::parse(busy->body)["error"]["code"], "unavailable");
  EXPECT_TRUE(answered_while_held) << "the busy answer waited for the stalled clients";
  for (auto& t : stalled) t.join();
  EXPECT_TRUE(outcomes[2].ended_by_server) << "the shedding thread waited for trickled headers";
  EXPECT_FALSE(outcomes[0].ended_by_server) << "inside --request-timeout-s the worker's client is not cut";
}

TEST_F(SlowClientsTest, UploadsBeyondTheInFlightBudgetGet503Unread) {
  auto server = Start({"--max-upload-mb", "1", "--max-inflight-upload-mb", "1", "--request-timeout-s", "3"});
  const int port = server->port();
  // A slow upload declaring 900 000 bytes holds most of the 1 MiB budget while it trickles.
  Outcome slow;
  std::thread holder([&] { slow = Trickle(port, PostHead("/v1/images?id=slow", 900000), std::chrono::milliseconds(200),
                                          std::chrono::seconds(25)); });
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  auto client = server->Client();
  const std::string body(300000, 'x');  // not an image: once admitted it gets 400, never 503
  auto refused = client.Post("/v1/search", body, "image/png");
  ASSERT_TRUE(refused) << httplib::to_string(refused.error());
  EXPECT_EQ(refused->status, 503) << refused->body;
  EXPECT_EQ(json::parse(refused->body)["error"]["code"], "resource_exhausted");
  EXPECT_EQ(refused->get_header_value("Retry-After"), "1");
  // Requests without a body are not affected.
  auto stats = client.Get("/v1/stats");
  ASSERT_TRUE(stats);
  EXPECT_EQ(stats->status, 200);
  holder.join();
  EXPECT_TRUE(slow.ended_by_server);
  EXPECT_EQ(slow.response.rfind("HTTP/1.1 408", 0), 0u) << slow.response;
  // The cut upload gave its reservation back; nothing was added.
  auto admitted = server->Client().Post("/v1/search", body, "image/png");
  ASSERT_TRUE(admitted);
  EXPECT_EQ(admitted->status, 400) << admitted->body;
  auto record = client.Get("/v1/images/slow");
  ASSERT_TRUE(record);
  EXPECT_EQ(record->status, 404);
  // Many uploads at once: each is admitted (then 400: not an image) or refused 503, none goes unanswered.
  std::vector<int> statuses(12, 0);
  std::vector<std::thread> uploaders;
  for (size_t i = 0; i < statuses.size(); ++i) {
    uploaders.emplace_back([&, i] {
      auto res = server->Client().Post("/v1/search", body, "image/png");
      statuses[i] = res ? res->status : -1;
    });
  }
  for (auto& t : uploaders) t.join();
  for (int status : statuses) EXPECT_TRUE(status == 400 || status == 503) << status;
  auto found = client.Post("/v1/search", image_, "image/png");
  ASSERT_TRUE(found);
  EXPECT_EQ(found->status, 200) << found->body;
}

}  // namespace
}  // namespace oxbow
