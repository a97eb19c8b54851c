// Threads that wait on calls to shards, kept between calls.
//
// A front asks every partition at once: each call blocks its thread on gRPC for the shard's answer. A
// search makes about ten such rounds, and creating a thread per call was about an eighth of a front's
// CPU time per search (perf on the Paris subset, 3 local shards, 2-core VM). The process-wide pool
// below keeps the threads: it grows to the most calls ever in flight at
// once and never shrinks (an idle thread holds its stack's touched pages, a few tens of KiB, and
// nothing else). Unlike ParallelFor's pool (sift/base/parallel.h), which is sized for computation and
// whose callers do the work themselves when its helpers are busy, a call here always gets a thread of
// its own: calls that wait on the network are never serialised behind one another.
#pragma once

#include <cstddef>
#include <functional>

namespace oxbow::cluster {

// fn(i) for every i in [0, n) at once: i = 0 on the calling thread, the others on kept threads; returns
// when every call has returned. fn must not throw. Safe to call from many threads concurrently.
void RunOnCallThreads(size_t n, const std::function<void(size_t)>& fn);

// task() on a kept thread, without waiting for it (the caller waits for its effects itself, if at all).
// task must not throw.
void PostOnCallThread(std::function<void()> task);

}  // namespace oxbow::cluster
