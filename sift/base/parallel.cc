#include "sift/base/parallel.h"

#include <atomic>
#include <mutex>

namespace oxbow {

void ParallelFor(size_t n, int num_threads, size_t grain,
                 const std::function<void(size_t, size_t, int)>& fn) {
  if (n == 0) return;
  grain = std::max<size_t>(1, grain);
  const size_t chunks = (n + grain - 1) / grain;
  const int workers = static_cast<int>(std::min<size_t>(chunks, static_cast<size_t>(ResolveThreadCount(num_threads))));
  if (workers <= 1) {
    fn(0, n, 0);
    return;
  }
  std::atomic<size_t> next{0};
  std::exception_ptr failure;
  std::mutex failure_mutex;
  auto work = [&](int worker) {
    try {
      for (size_t c = next.fetch_add(1); c < chunks; c = next.fetch_add(1)) {
        const size_t begin = c * grain;
        fn(begin, std::min(n, begin + grain), worker);
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(failure_mutex);
      if (!failure) failure = std::current_exception();
      next.store(chunks);
    }
  };
  std::vector<std::thread> threads;
  threads.reserve(static_cast<size_t>(workers - 1));
  for (int w = 1; w < workers; ++w) threads.emplace_back(work, w);
  work(0);
  for (auto& t : threads) t.join();
  if (failure) std::rethrow_exception(failure);
}

}  // namespace oxbow
