// Slow, stalled and greedy clients against the real `oxbow serve` (server/request_guard.h): more
// trickling clients than worker threads, idle connections and a header trickle must not keep a normal
// request from being answered; the stalled ones are cut by the server (408 or a close) rather than
// holding their worker for as long as they like; uploads beyond --max-inflight-upload-mb get 503 with
// Retry-After, unread, and the budget comes back once a request ends. No wall-clock assertions: the
// tests check who ended each connection, with generous give-up times.
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <latch>
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
using oxbow::testing::kContinue;
using oxbow::testing::SendAll;

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

// A stalled client: sends `head`, then one byte every `interval` until the server answers or closes
// the connection, `give_up` passes or `*stop` is set. `*ready` is counted down once the head is sent
// and, for a head with "Expect: 100-continue", once the server's 100 Continue shows that a worker (not
// the queue) holds the connection; or on any failure before that, so that waiters never hang.
struct Trickle {
  std::string head;
  std::chrono::milliseconds interval{200};
  std::chrono::seconds give_up{25};
  std::latch* ready = nullptr;
  const std::atomic<bool>* stop = nullptr;

  Outcome Run(int port) const {
    Outcome outcome;
    const int fd = ConnectTo(port);
    bool started = fd >= 0 && SendAll(fd, head);
    if (started && head.find("Expect: 100-continue") != std::string::npos) {
      started = oxbow::testing::ReadUntil(fd, kContinue, &outcome.response);
      if (started) outcome.response.erase(0, outcome.response.find(kContinue) + std::string(kContinue).size());
    }
    if (ready != nullptr) ready->count_down();
    if (fd < 0) return outcome;
    outcome.ended_by_server = !started;
    const auto until = Clock::now() + give_up;
    while (!outcome.ended_by_server && Clock::now() < until && (stop == nullptr || !stop->load())) {
      std::this_thread::sleep_for(interval);
      outcome.ended_by_server = ServerSpoke(fd, &outcome) || !SendAll(fd, "x");
    }
    // Collect the rest of a response that was being written.
    pollfd p{fd, POLLIN, 0};
    while (outcome.ended_by_server && poll(&p, 1, 200) > 0 && !ServerSpoke(fd, &outcome)) {
    }
    close(fd);
    return outcome;
  }
};

// Connects and sends nothing (then counts down `connected`); reports whether the server closed the
// connection before `give_up`.
bool IdleConnectionClosedByServer(int port, std::chrono::seconds give_up, std::latch* connected) {
  const int fd = ConnectTo(port);
  connected->count_down();
  if (fd < 0) return false;
  pollfd p{fd, POLLIN, 0};
  const bool closed = poll(&p, 1, static_cast<int>(give_up.count() * 1000)) > 0;
  close(fd);
  return closed;
}

// A POST head whose body will trickle; with Expect: 100-continue (see Trickle).
std::string PostHead(const std::string& path, size_t content_length) {
  return "POST " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\nContent-Length: " +
         std::to_string(content_length) + "\r\nExpect: 100-continue\r\n\r\n";
}

class SlowClientsTest : public oxbow::testing::ServerSuite {
 protected:
  static void SetUpTestSuite() { SetUpServerSuite("oxbow-slow-clients-test"); }
  static std::unique_ptr<oxbow::testing::ServerProcess> Start(const std::vector<std::string>& extra) { return StartServer(extra); }
};

TEST_F(SlowClientsTest, TricklingAndIdleClientsDoNotStarveANormalRequest) {
  // Two workers; three tricklers (two bodies, one header) and two idle connections: more than the workers.
  // Without the request deadline they would hold both workers until they give up (25 s); each sends a
  // byte every 200 ms, far inside the 30 s per-read timeout.
  const char* timeout = std::getenv("OXBOW_SLOW_CLIENTS_REQUEST_TIMEOUT_S");  // 3600 shows the unguarded server
  auto server = Start({"--http-workers", "2", "--queue", "16", "--read-timeout-s", "30", "--request-timeout-s",
                       timeout != nullptr ? timeout : "2"});
  const int port = server->port();
  std::vector<Outcome> bodies(2);
  Outcome header;
  std::array<bool, 2> idle_closed{};  // not vector<bool>: its bits share a word, written by two threads
  // The trickled bodies are held by the two workers (100 Continue) before the others connect; the
  // others have connected (so queue ahead of it) before the normal request does.
  std::latch workers_taken(static_cast<ptrdiff_t>(bodies.size()));
  std::latch queued(static_cast<ptrdiff_t>(1 + idle_closed.size()));
  std::vector<std::thread> stalled;
  stalled.reserve(bodies.size() + 1 + idle_closed.size());
  for (auto& outcome : bodies) {
    stalled.emplace_back([&, port] {
      outcome = Trickle{.head = PostHead("/v1/search", 100000), .ready = &workers_taken}.Run(port);
    });
  }
  workers_taken.wait();
  stalled.emplace_back([&, port] {
    header = Trickle{.head = "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ", .ready = &queued}.Run(port);
  });
  for (size_t i = 0; i < idle_closed.size(); ++i) {
    stalled.emplace_back([&, i, port] { idle_closed[i] = IdleConnectionClosedByServer(port, std::chrono::seconds(25), &queued); });
  }
  queued.wait();

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

// A body that stops arriving: once no byte came for a whole --read-timeout-s, the server answers 408
// naming that timeout (not a 400 that calls the request malformed), on a route that streams its body and
// on one that reads it whole.
TEST_F(SlowClientsTest, ABodyThatStopsArrivingGets408AfterTheReadTimeout) {
  auto server = Start({"--read-timeout-s", "1", "--request-timeout-s", "60"});
  for (const char* head : {"POST /v1/search HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n",
                           "POST /v1/match HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; "
                           "boundary=B\r\n"}) {
    const int fd = oxbow::testing::ConnectTo(server->port());
    ASSERT_GE(fd, 0);
    ASSERT_TRUE(SendAll(fd, std::string(head) + "Content-Length: 100000\r\n\r\n" + std::string(1000, 'x')));
    std::string answer;
    const auto sent = Clock::now();
    oxbow::testing::ReadUntil(fd, "}", &answer, std::chrono::seconds(30));
    close(fd);
    EXPECT_LT(Clock::now() - sent, std::chrono::seconds(20)) << head;
    EXPECT_EQ(answer.rfind("HTTP/1.1 408", 0), 0u) << head << answer;
    EXPECT_NE(answer.find("request_timeout"), std::string::npos) << answer;
    EXPECT_NE(answer.find("--read-timeout-s"), std::string::npos) << answer;
  }
  auto health = server->Client().Get("/healthz");
  ASSERT_TRUE(health);
  EXPECT_EQ(health->status, 200);
}

TEST_F(SlowClientsTest, AStalledClientCannotBlockTheBusyAnswer) {
  // One worker, a queue of one: the first trickler (a body) holds the worker, the second (headers) waits
  // in the queue, the third is handed to the shedding thread and trickles its headers there. Each
  // connects once the previous one is in place. A normal request after them must get its 503 while
  // the first trickler still holds the worker (the shedder's header deadline).
  auto server = Start({"--http-workers", "1", "--queue", "1", "--request-timeout-s", "30"});
  const int port = server->port();
  const std::string slow_headers = "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ";
  std::vector<Outcome> outcomes(3);
  std::atomic<bool> first_still_connected{true}, release{false};
  std::latch held(1), queued(1), shed(1);
  std::vector<std::thread> stalled;
  stalled.emplace_back([&, port] {
    outcomes[0] = Trickle{.head = PostHead("/v1/search", 100000), .ready = &held, .stop = &release}.Run(port);
    first_still_connected = false;
  });
  held.wait();
  stalled.emplace_back([&, port] { outcomes[1] = Trickle{.head = slow_headers, .ready = &queued, .stop = &release}.Run(port); });
  queued.wait();
  stalled.emplace_back([&, port] { outcomes[2] = Trickle{.head = slow_headers, .ready = &shed}.Run(port); });
  shed.wait();
  auto busy = server->Client().Get("/healthz");
  const bool answered_while_held = first_still_connected.load();
  release = true;
  for (auto& t : stalled) t.join();
  ASSERT_TRUE(busy) << httplib::to_string(busy.error());
  EXPECT_EQ(busy->status, 503) << busy->body;
  EXPECT_EQ(json::parse(busy->body)["error"]["code"], "unavailable");
  EXPECT_TRUE(answered_while_held) << "the busy answer waited for the stalled clients";
  EXPECT_TRUE(outcomes[2].ended_by_server) << "the shedding thread waited for trickled headers";
  EXPECT_FALSE(outcomes[0].ended_by_server) << "inside --request-timeout-s the worker's client is not cut";
}

TEST_F(SlowClientsTest, UploadsBeyondTheInFlightBudgetGet503Unread) {
  auto server = Start({"--max-upload-mb", "1", "--max-inflight-upload-mb", "1", "--request-timeout-s", "3"});
  const int port = server->port();
  // A slow upload declaring 900 000 bytes holds most of the 1 MiB budget while it trickles.
  Outcome slow;
  std::latch started(1);
  std::thread holder([&] { slow = Trickle{.head = PostHead("/v1/images?id=slow", 900000), .ready = &started}.Run(port); });
  started.wait();
  auto client = server->Client();
  const std::string body(300000, 'x');  // not an image: once admitted it gets 400, never 503
  // The worker reserves the slow upload's budget just after its 100 Continue: until then a request
  // may still be admitted (400), after that it must be refused, for as long as the upload trickles.
  const auto deadline = Clock::now() + std::chrono::seconds(20);
  int status = 0;
  std::string refused_body, retry_after;
  do {
    auto res = client.Post("/v1/search", body, "image/png");
    ASSERT_TRUE(res) << httplib::to_string(res.error());
    status = res->status;
    refused_body = res->body;
    retry_after = res->get_header_value("Retry-After");
  } while (status == 400 && Clock::now() < deadline);
  EXPECT_EQ(status, 503) << refused_body;
  EXPECT_EQ(json::parse(refused_body)["error"]["code"], "resource_exhausted");
  EXPECT_EQ(retry_after, "1");
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
  for (int upload_status : statuses) EXPECT_TRUE(upload_status == 400 || upload_status == 503) << upload_status;
  auto found = client.Post("/v1/search", image_, "image/png");
  ASSERT_TRUE(found);
  EXPECT_EQ(found->status, 200) << found->body;
}

}  // namespace
}  // namespace oxbow
