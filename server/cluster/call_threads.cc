#include "server/cluster/call_threads.h"

#include <condition_variable>
#include <deque>
#include <latch>
#include <mutex>
#include <thread>
#include <vector>

namespace oxbow::cluster {
namespace {

class CallThreads {
 public:
  CallThreads() = default;
  CallThreads(const CallThreads&) = delete;
  CallThreads& operator=(const CallThreads&) = delete;

  ~CallThreads() {
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      stopping_ = true;
    }
    wake_.notify_all();
    for (std::thread& t : threads_) t.join();
  }

  // Queues `task`; starts a thread when none is idle to take it.
  void Post(std::function<void()> task) {
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      queue_.push_back(std::move(task));
      if (idle_ < queue_.size()) {
        threads_.emplace_back([this] { Work(); });
        return;
      }
    }
    wake_.notify_one();
  }

 private:
  void Work() {
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
      ++idle_;
      wake_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
      --idle_;
      if (queue_.empty()) return;  // stopping, nothing left
      std::function<void()> task = std::move(queue_.front());
      queue_.pop_front();
      lock.unlock();
      task();
      lock.lock();
    }
  }

  std::mutex mutex_;  // guards everything below; held only to queue, take a task or start a thread
  std::condition_variable wake_;
  std::deque<std::function<void()>> queue_;
  size_t idle_ = 0;  // threads waiting for a task
  bool stopping_ = false;
  std::vector<std::thread> threads_;
};

CallThreads& Threads() {
  static CallThreads threads;
  return threads;
}

}  // namespace

void PostOnCallThread(std::function<void()> task) { Threads().Post(std::move(task)); }

void RunOnCallThreads(size_t n, const std::function<void(size_t)>& fn) {
  if (n == 0) return;
  CallThreads& threads = Threads();
  std::latch done(static_cast<std::ptrdiff_t>(n - 1));
  for (size_t i = 1; i < n; ++i) {
    threads.Post([&fn, &done, i] {
      fn(i);
      done.count_down();
    });
  }
  fn(0);
  done.wait();
}

}  // namespace oxbow::cluster
