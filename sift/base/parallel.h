// Deterministic data parallelism shared by every module.
#pragma once

#include <algorithm>
#include <cstddef>
#include <exception>
#include <functional>
#include <thread>
#include <vector>

namespace oxbow {

// Number of threads to use for a request of `requested` (0 means all hardware threads).
inline int ResolveThreadCount(int requested) {
  if (requested > 0) return requested;
  return std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
}

// Calls fn(begin, end, worker) over [0, n) split into contiguous chunks of `grain` items, handed out in
// order to `num_threads` workers (worker in [0, num_threads)); the calling thread is worker 0. Which
// worker runs a chunk may vary between runs; results are deterministic as long as fn writes only to
// outputs indexed by item (or merges per-chunk outputs in chunk order). Exceptions from fn are
// rethrown in the caller after all workers finish.
void ParallelFor(size_t n, int num_threads, size_t grain,
                 const std::function<void(size_t begin, size_t end, int worker)>& fn);

}  // namespace oxbow
