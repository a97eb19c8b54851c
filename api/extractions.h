// Decoding and extracting uploaded images under a server's limits: what api::Service and the cluster
// front (server/cluster/front_http.h) both run an upload through.
//
//  - Slots: at most `slots` decodes + extractions run at once (each holds its image pyramid); a request
//    waits for one at most extraction_wait_ms, then fails with kResourceExhausted (503).
//  - Work: a request's processing deadline (processing_timeout_ms from Start) and its client. A decode or
//    extraction still running when the deadline passes, the client has gone, or Stop()'s grace has ended
//    is abandoned at the extractor's next check (its slot freed, nothing stored): kResourceExhausted with
//    the reason.
//  - Threads: extractions run on threads of this object, not the caller's. SIFT keeps its pyramid
//    buffers per thread that extracts (SiftOptions::thread_cache_mib), so extracting on HTTP workers
//    would let every worker keep ~200 MiB (32 workers: 7 GiB measured) whatever the slot count. Adds run
//    on threads at a lower CPU priority (add_nice), so that searches get the CPU first, and each on its
//    own thread only: the extractor's other threads (the process-wide pool) run at normal priority.
//
// Thread safety: every member may be called from any number of threads at once.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <semaphore>
#include <span>

#include "sift/base/error.h"
#include "sift/image.h"
#include "sift/sift.h"

namespace oxbow::api {

// No defaults of its own: filled from api::ServiceOptions (ServiceOptions::Extraction), where the
// product's defaults and their checked ranges live.
struct ExtractionOptions {
  int slots = 1;                   // decodes + extractions at once, [1, 1024]
  int extraction_wait_ms = 0;      // longest wait for a slot
  int processing_timeout_ms = 0;   // a request's deadline, from Start
  int shutdown_grace_ms = 0;       // after Stop(), how long running work may still finish
  int add_nice = 0;                // nice value of the add threads (0: adds run on the normal threads)
  sift::DecodeOptions decode;      // the upload's limits
};

class Extractions {
 public:
  using Clock = std::chrono::steady_clock;

  Extractions(const sift::SiftExtractor& extractor, const ExtractionOptions& options);
  ~Extractions();
  Extractions(const Extractions&) = delete;
  Extractions& operator=(const Extractions&) = delete;

  // A request's bounds. `client_gone` (not owned, may be null or empty) must outlive the work.
  struct Work {
    Clock::time_point deadline;
    const sift::StopRequested* client_gone;
  };
  [[nodiscard]] Work Start(const sift::StopRequested& client_gone) const;
  // Why `work` must stop now (Stop() and its grace ended, client gone, deadline passed), or nullopt.
  [[nodiscard]] std::optional<Error> StopReason(const Work& work) const;

  // What an extraction is for. kAdd runs on the low-priority add threads (add_nice > 0). kPairMatch
  // extracts with PairMatchExtractorOptions of the extractor's settings (api/pair_match.h), as `oxbow
  // match` does, so POST /v1/match and the CLI agree.
  enum class Use { kSearch, kAdd, kPairMatch };
  // Decode + extract `image` under a slot. After a successful extraction `also` (when given) runs under
  // the same slot (an add's thumbnail decode), so the slots bound its memory too. `elapsed_ms` receives
  // the decode + extraction time (the wait for a slot excluded).
  [[nodiscard]] Result<sift::FeatureSet> Extract(std::span<const uint8_t> image, const Work& work, double* elapsed_ms,
                                                 const std::function<void()>& also = {}, Use use = Use::kSearch) const;

  // For shutdown: work still running shutdown_grace_ms from now stops at its next check, as does later
  // work. Irreversible; a second call does not extend the grace.
  void Stop();

  int slots() const { return options_.slots; }
  int in_flight() const { return in_flight_.load(); }
  const sift::SiftExtractor& extractor() const { return extractor_; }
  const ExtractionOptions& options() const { return options_; }

 private:
  class Threads;

  sift::SiftExtractor extractor_;
  ExtractionOptions options_;
  mutable std::counting_semaphore<1024> semaphore_;
  mutable std::atomic<int> in_flight_{0};
  // When Stop()'s grace ends (Clock ticks since its epoch); the maximum until it is called.
  std::atomic<Clock::rep> stop_at_{Clock::time_point::max().time_since_epoch().count()};
  std::unique_ptr<Threads> add_threads_;      // low priority (add_nice > 0), else null
  std::optional<sift::SiftExtractor> add_extractor_;  // with add_threads_: extractor_ on one thread
  sift::SiftExtractor pair_match_extractor_;         // PairMatchExtractorOptions(extractor_.options())
  std::unique_ptr<Threads> normal_threads_;   // every other extraction
};

}  // namespace oxbow::api
