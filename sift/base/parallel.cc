#include "sift/base/parallel.h"

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <exception>
#include <mutex>
#include <vector>

#include <pthread.h>
#include <sched.h>

namespace oxbow {
namespace {

// One ParallelFor call. Lives on the caller's stack; the pool's queue points at it while it takes helpers.
struct Job {
  size_t n = 0, grain = 1, chunks = 0;
  const std::function<void(size_t, size_t, int)>* fn = nullptr;
  std::atomic<size_t> next{0};
  int max_helpers = 0;
  bool spin_after = false;  // the caller is latency-sensitive: helpers spin for its next call
  // Guarded by the pool's mutex:
  int joined = 0;  // helpers that took a worker number (numbers 1..joined)
  int active = 0;  // helpers still inside Work(); the caller waits for 0 before the Job goes away
  std::exception_ptr failure;
  std::condition_variable left;  // notified (under the mutex) when active drops to 0
};

class Pool {
 public:
  explicit Pool(Pool* abandoned = nullptr) : abandoned_(abandoned) {}

  void Run(Job& job, int workers) {
    int to_wake = 0;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!stop_) {  // (exiting: no helper is asked, the caller does everything)
        job.max_helpers = workers - 1;
        while (threads_.size() < static_cast<size_t>(job.max_helpers)) threads_.emplace_back([this] { WorkerLoop(); });
        queue_.push_back(&job);
        queued_.fetch_add(1, std::memory_order_release);
        // Workers still spinning (WorkerLoop) see the job without a wake-up.
        to_wake = std::min(workers - 1, sleeping_);
      }
    }
    for (int h = 0; h < to_wake; ++h) wake_.notify_one();
    Work(job, 0, /*helper=*/false);
    std::exception_ptr failure;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      Unqueue(&job);
      job.left.wait(lock, [&] { return job.active == 0; });
      failure = job.failure;
    }
    if (failure) std::rethrow_exception(failure);
  }

  // Stops and joins the workers (at exit). Helpers leave their loop between chunks; callers finish alone.
  void Shutdown() {
    std::vector<std::thread> threads;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
      threads.swap(threads_);
    }
    stopping_.store(true);
    wake_.notify_all();
    for (std::thread& t : threads) {
      if (t.get_id() == std::this_thread::get_id()) {
        t.detach();  // exit() called from inside a worker
      } else {
        t.join();
      }
    }
  }

 private:
  void Work(Job& job, int worker, bool helper) {
    try {
      for (size_t c = job.next.fetch_add(1); c < job.chunks; c = job.next.fetch_add(1)) {
        const size_t begin = c * job.grain;
        (*job.fn)(begin, std::min(job.n, begin + job.grain), worker);
        if (helper && stopping_.load(std::memory_order_relaxed)) return;
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!job.failure) job.failure = std::current_exception();
      job.next.store(job.chunks);
    }
  }

  void Unqueue(const Job* job) {
    for (auto it = queue_.begin(); it != queue_.end(); ++it) {
      if (*it == job) {
        queue_.erase(it);
        return;
      }
    }
  }

  // Whether there is something to do (finished jobs still queued are dropped); mutex_ held.
  bool WorkOrStop() {
    while (!queue_.empty() && queue_.front()->next.load() >= queue_.front()->chunks) queue_.erase(queue_.begin());
    return stop_ || !queue_.empty();
  }

  void WorkerLoop() {
    std::unique_lock<std::mutex> lock(mutex_);
    bool spin = false;  // the last job taken was from a latency-sensitive caller
    for (;;) {
      while (!WorkOrStop()) {
        if (!spin) {
          ++sleeping_;
          wake_.wait(lock, [&] { return WorkOrStop(); });
          --sleeping_;
          continue;
        }
        // After a latency-sensitive job, a worker spins for up to kSpin before sleeping (yielding its
        // core to any other thread that wants it), watching for a new job (LatencySensitiveScope). A
        // job seen while spinning (maybe already done by its caller) starts a new spin; only a spin
        // that saw none ends in sleep.
        const uint64_t seen = queued_.load(std::memory_order_acquire);
        lock.unlock();
        const auto deadline = std::chrono::steady_clock::now() + kSpin;
        bool saw_job = false;
        while (!stopping_.load(std::memory_order_relaxed)) {
          if (queued_.load(std::memory_order_acquire) != seen) {
            saw_job = true;
            break;
          }
          if (std::chrono::steady_clock::now() >= deadline) break;
          sched_yield();
        }
        lock.lock();
        if (!saw_job) spin = false;  // sleeps at the next look, unless work came meanwhile
      }
      if (stop_) return;
      Job& job = *queue_.front();
      spin = job.spin_after;
      const int worker = ++job.joined;
      if (job.joined == job.max_helpers) queue_.erase(queue_.begin());
      ++job.active;
      lock.unlock();
      Work(job, worker, /*helper=*/true);
      lock.lock();
      // Notified under the mutex: the caller cannot see active == 0, return and destroy `job` before
      // this thread is done with it.
      if (--job.active == 0) job.left.notify_one();
    }
  }

  static constexpr std::chrono::microseconds kSpin{500};
  std::mutex mutex_;
  std::condition_variable wake_;
  std::atomic<uint64_t> queued_{0};  // jobs ever queued: what a spinning worker watches
  int sleeping_ = 0;                 // workers waiting on wake_; guarded by mutex_
  std::vector<Job*> queue_;  // jobs that still take helpers, oldest first (a vector: no allocation once grown)
  std::vector<std::thread> threads_;
  bool stop_ = false;
  std::atomic<bool> stopping_{false};
  [[maybe_unused]] Pool* abandoned_;  // the parent's pool in a forked child: kept reachable, never used
};

thread_local bool t_latency_sensitive = false;

Pool*& CurrentPool() {
  static Pool* pool = [] {
    // Never destroyed (a caller may still be running when static destructors do); its threads are
    // joined at exit instead.
    std::atexit([] { CurrentPool()->Shutdown(); });
    // A forked child has only the forking thread: the parent's workers (and maybe a locked mutex)
    // did not come along, so the child starts from an empty pool.
    pthread_atfork(nullptr, nullptr, [] { CurrentPool() = new Pool(CurrentPool()); });
    return new Pool();
  }();
  return pool;
}

}  // namespace

void ParallelFor(size_t n, int num_threads, size_t grain, const std::function<void(size_t, size_t, int)>& fn) {
  if (n == 0) return;
  grain = std::max<size_t>(1, grain);
  const size_t chunks = (n + grain - 1) / grain;
  const int workers = static_cast<int>(std::min<size_t>(chunks, static_cast<size_t>(ResolveThreadCount(num_threads))));
  if (workers <= 1) {
    fn(0, n, 0);
    return;
  }
  Job job;
  job.n = n;
  job.grain = grain;
  job.chunks = chunks;
  job.fn = &fn;
  job.spin_after = t_latency_sensitive;
  CurrentPool()->Run(job, workers);
}

LatencySensitiveScope::LatencySensitiveScope() : previous_(t_latency_sensitive) { t_latency_sensitive = true; }
LatencySensitiveScope::~LatencySensitiveScope() { t_latency_sensitive = previous_; }

}  // namespace oxbow
