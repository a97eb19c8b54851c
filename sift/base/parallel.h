// Deterministic data parallelism shared by every module.
#pragma once

#include <algorithm>
#include <cstddef>
#include <functional>
#include <thread>

namespace oxbow {

// Number of threads to use for a request of `requested` (0 means all hardware threads).
inline int ResolveThreadCount(int requested) {
  if (requested > 0) return requested;
  return std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
}

// Calls fn(begin, end, worker) over [0, n) split into contiguous chunks of `grain` items, handed out in
// order to at most `num_threads` workers (worker in [0, num_threads)); the calling thread is worker 0
// and works until every chunk is taken. Which worker runs a chunk may vary between runs; results are
// deterministic as long as fn writes only to outputs indexed by item (or merges per-chunk outputs in
// chunk order). Exceptions from fn are rethrown in the caller after all workers finish.
//
// The other workers come from one process-wide pool of persistent threads, grown on demand to the
// largest num_threads - 1 ever requested and joined at exit: no thread is created per call, so
// thread_local scratch (the verifier's arenas, the scoring buffers) survives from call to call. Safe to
// call concurrently from many threads (callers share the pool; a caller whose helpers are busy
// elsewhere does its own chunks) and from inside fn (the nested caller works on its own loop, so
// nothing waits on a thread that waits on it). After fork() the child starts a fresh pool.
void ParallelFor(size_t n, int num_threads, size_t grain,
                 const std::function<void(size_t begin, size_t end, int worker)>& fn);

// While one is alive on a thread, that thread's ParallelFor calls are latency-sensitive: the helpers
// that ran one spin for up to 500 us afterwards (calling sched_yield between looks, so any other
// runnable thread gets the core) waiting for the next call, instead of going to sleep at once. A
// search makes dozens of calls a few hundred microseconds apart, and waking a sleeping helper cost
// each about 30 us on the 2-core VMs measured; throughput work (a batch ingest)
// ran 7-11% slower with every call spinning, so spinning is opt-in. Nests; not movable.
class LatencySensitiveScope {
 public:
  LatencySensitiveScope();
  ~LatencySensitiveScope();
  LatencySensitiveScope(const LatencySensitiveScope&) = delete;
  LatencySensitiveScope& operator=(const LatencySensitiveScope&) = delete;

 private:
  bool previous_;
};

}  // namespace oxbow
