#include "sift/base/parallel.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <mutex>
#include <numeric>
#include <set>
#include <stdexcept>
#include <thread>
#include <vector>

#include <sys/wait.h>
#include <unistd.h>

namespace oxbow {
namespace {

// A number that identifies the calling thread for its whole life and is never reused by a later thread
// (std::thread::id values, unlike this, are reused once a thread has been joined).
uint64_t ThreadSerial() {
  static std::atomic<uint64_t> counter{0};
  thread_local const uint64_t serial = ++counter;
  return serial;
}

// Runs `workers` chunks of one item, each of which waits until all `workers` chunks are running, so every
// worker takes exactly one chunk; returns each worker's ThreadSerial() (index = worker number).
// The wait gives up after a minute (a pool that never lends its helpers), leaving 0 for absent workers.
std::vector<uint64_t> SerialsOfAllWorkers(int workers) {
  std::vector<uint64_t> serials(static_cast<size_t>(workers), 0);
  std::atomic<int> arrived{0};
  ParallelFor(static_cast<size_t>(workers), workers, 1, [&](size_t begin, size_t, int worker) {
    serials[static_cast<size_t>(worker)] = ThreadSerial();
    arrived.fetch_add(1);
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::minutes(1);
    while (arrived.load() < workers && std::chrono::steady_clock::now() < give_up) std::this_thread::yield();
    EXPECT_EQ(arrived.load(), workers) << "chunk " << begin << " never saw all workers";
  });
  return serials;
}

// No test here asks for more threads, so the process-wide pool has exactly kMaxThreads - 1 threads
// once a test has asked for kMaxThreads.
constexpr int kMaxThreads = 8;

TEST(ParallelFor, CoversEveryItemOnceWithWorkersInRange) {
  for (const int threads : {1, 2, 3, kMaxThreads}) {
    for (const size_t n : {size_t{0}, size_t{1}, size_t{7}, size_t{1000}}) {
      for (const size_t grain : {size_t{0}, size_t{1}, size_t{3}, size_t{64}}) {
        std::vector<std::atomic<int>> hits(n);
        ParallelFor(n, threads, grain, [&](size_t begin, size_t end, int worker) {
          ASSERT_GE(worker, 0);
          ASSERT_LT(worker, threads);
          for (size_t i = begin; i < end; ++i) hits[i].fetch_add(1);
        });
        for (size_t i = 0; i < n; ++i) ASSERT_EQ(hits[i].load(), 1) << threads << " threads, n " << n << ", item " << i;
      }
    }
  }
}

TEST(ParallelFor, ReusesTheSameThreadsFromCallToCall) {
  // Every call needs all kMaxThreads - 1 helpers at once, i.e. every thread of the pool: the same
  // threads each time (in any order), where a thread per call would bring new ones.
  const std::vector<uint64_t> first = SerialsOfAllWorkers(kMaxThreads);
  EXPECT_EQ(first[0], ThreadSerial()) << "the caller is worker 0";
  const std::set<uint64_t> helpers(first.begin() + 1, first.end());
  ASSERT_EQ(helpers.size(), static_cast<size_t>(kMaxThreads - 1));
  ASSERT_EQ(helpers.count(0), 0u);
  for (int call = 0; call < 20; ++call) {
    const std::vector<uint64_t> again = SerialsOfAllWorkers(kMaxThreads);
    EXPECT_EQ(again[0], first[0]);
    EXPECT_EQ(std::set<uint64_t>(again.begin() + 1, again.end()), helpers) << "call " << call;
  }
  // A smaller request is served by threads of the same pool.
  const std::vector<uint64_t> two = SerialsOfAllWorkers(2);
  EXPECT_EQ(helpers.count(two[1]), 1u);
}

TEST(ParallelFor, RethrowsTheExceptionInTheCallerAndStaysUsable) {
  for (const size_t bad : {size_t{0}, size_t{42}, size_t{999}}) {
    std::atomic<int> done{0};
    EXPECT_THROW(ParallelFor(1000, 4, 1,
                             [&](size_t begin, size_t, int) {
                               if (begin == bad) throw std::runtime_error("item");
                               done.fetch_add(1);
                             }),
                 std::runtime_error);
    EXPECT_LT(done.load(), 1000);
  }
  std::vector<std::atomic<int>> hits(500);
  ParallelFor(hits.size(), 4, 7, [&](size_t begin, size_t end, int) {
    for (size_t i = begin; i < end; ++i) hits[i].fetch_add(1);
  });
  for (const auto& h : hits) ASSERT_EQ(h.load(), 1);
}

TEST(ParallelFor, NestedCallsFromEveryWorkerComplete) {
  // Every worker of the outer loop (pool threads included) runs an inner loop that asks for the whole
  // pool: the inner callers must do their own chunks rather than wait for busy helpers.
  constexpr size_t kOuter = 16, kInner = 300;
  std::vector<std::atomic<int>> hits(kOuter * kInner);
  ParallelFor(kOuter, 4, 1, [&](size_t ob, size_t oe, int) {
    for (size_t o = ob; o < oe; ++o) {
      ParallelFor(kInner, 4, 5, [&](size_t ib, size_t ie, int) {
        for (size_t i = ib; i < ie; ++i) {
          ParallelFor(1, 4, 1, [&](size_t, size_t, int) { hits[o * kInner + i].fetch_add(1); });
        }
      });
    }
  });
  for (size_t i = 0; i < hits.size(); ++i) ASSERT_EQ(hits[i].load(), 1) << i;
}

TEST(ParallelFor, ConcurrentCallersNeverShareAWorkerNumber) {
  // Callers index per-worker scratch by the worker number: two chunks of one call running at the same
  // time must have different numbers, also while other threads' calls compete for the pool.
  constexpr int kCallers = 4, kThreads = 3, kCalls = 50;
  std::atomic<int> failures{0};
  std::vector<std::thread> callers;
  callers.reserve(kCallers);
  for (int c = 0; c < kCallers; ++c) {
    callers.emplace_back([&] {
      for (int call = 0; call < kCalls; ++call) {
        std::vector<std::atomic<int>> busy(kThreads);
        std::vector<std::atomic<int>> hits(200);
        ParallelFor(hits.size(), kThreads, 2, [&](size_t begin, size_t end, int worker) {
          if (busy[static_cast<size_t>(worker)].fetch_add(1) != 0) failures.fetch_add(1);
          for (size_t i = begin; i < end; ++i) hits[i].fetch_add(1);
          busy[static_cast<size_t>(worker)].fetch_sub(1);
        });
        for (const auto& h : hits) {
          if (h.load() != 1) failures.fetch_add(1);
        }
      }
    });
  }
  for (std::thread& t : callers) t.join();
  EXPECT_EQ(failures.load(), 0);
}

// Latency-sensitive callers leave the helpers spinning for their next call; a call must still get
// every helper whether it comes while they spin (no gap), after their spin ended in sleep (2 ms), or
// from a caller that is not latency-sensitive, and scopes nest.
TEST(ParallelFor, LatencySensitiveCallsGetEveryHelperWhetherItSpinsOrSleeps) {
  constexpr int kThreads = 3;
  for (const auto gap : {std::chrono::microseconds(0), std::chrono::microseconds(100), std::chrono::microseconds(2000)}) {
    for (int call = 0; call < 20; ++call) {
      std::this_thread::sleep_for(gap);
      std::vector<uint64_t> serials;
      if (call % 3 == 2) {
        serials = SerialsOfAllWorkers(kThreads);  // not latency-sensitive
      } else {
        const LatencySensitiveScope outer;
        const LatencySensitiveScope inner;
        serials = SerialsOfAllWorkers(kThreads);
      }
      const std::set<uint64_t> distinct(serials.begin(), serials.end());
      EXPECT_EQ(distinct.size(), static_cast<size_t>(kThreads)) << "gap " << gap.count() << " us, call " << call;
      EXPECT_EQ(distinct.count(0), 0u) << "a helper never joined (gap " << gap.count() << " us, call " << call << ")";
    }
  }
}

TEST(ParallelFor, AForkedChildGetsWorkingHelpers) {
#if defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "ThreadSanitizer cannot start threads in the child of a multi-threaded fork";
#endif
  SerialsOfAllWorkers(3);  // the parent's pool has threads, which the child does not inherit
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    const std::vector<uint64_t> serials = SerialsOfAllWorkers(3);
    const bool ok = std::set<uint64_t>(serials.begin(), serials.end()).size() == 3 &&
                    std::count(serials.begin(), serials.end(), 0) == 0;
    _exit(ok ? 0 : 1);
  }
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
}

}  // namespace
}  // namespace oxbow
