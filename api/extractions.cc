#include "api/extractions.h"

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <condition_variable>
#include <deque>
#include <exception>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "api/pair_match.h"
#include "sift/base/log.h"

namespace oxbow::api {
namespace {

// Releases an extraction slot when the extraction ends, also on an early return or an exception.
class SlotGuard {
 public:
  SlotGuard(std::counting_semaphore<1024>* semaphore, std::atomic<int>* in_flight)
      : semaphore_(semaphore), in_flight_(in_flight) {
    in_flight_->fetch_add(1);
  }
  ~SlotGuard() {
    in_flight_->fetch_sub(1);
    semaphore_->release();
  }
  SlotGuard(const SlotGuard&) = delete;
  SlotGuard& operator=(const SlotGuard&) = delete;

 private:
  std::counting_semaphore<1024>* semaphore_;
  std::atomic<int>* in_flight_;
};

sift::SiftExtractor MustCreate(const sift::SiftOptions& options) {
  auto created = sift::SiftExtractor::Create(options);
  OXBOW_CHECK(created.has_value(), "settings derived from a valid extractor's are valid");
  return *created;
}

}  // namespace

// Threads that run jobs at a lower CPU priority (a higher nice value, set per thread on Linux). A nice
// value cannot be lowered again without privileges, hence dedicated threads rather than re-nicing the
// caller's. Run() blocks the caller until its job is done.
class Extractions::Threads {
 public:
  Threads(int threads, int nice) {
    for (int i = 0; i < threads; ++i) {
      threads_.emplace_back([this, nice] {
        if (nice > 0 && setpriority(PRIO_PROCESS, static_cast<id_t>(gettid()), nice) != 0) {
          OXBOW_LOG(kWarning) << "cannot lower the priority of an add thread; adds run at normal priority";
        }
        Work();
      });
    }
  }
  ~Threads() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    cond_.notify_all();
    for (auto& t : threads_) t.join();
  }
  void Run(const std::function<void()>& job) {
    std::mutex done_mutex;
    std::condition_variable done_cond;
    bool done = false;
    std::exception_ptr error;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      jobs_.emplace_back([&] {
        try {
          job();
        } catch (...) {
          error = std::current_exception();  // rethrown in the caller's thread
        }
        std::lock_guard<std::mutex> done_lock(done_mutex);
        done = true;
        done_cond.notify_one();
      });
    }
    cond_.notify_one();
    std::unique_lock<std::mutex> done_lock(done_mutex);
    done_cond.wait(done_lock, [&] { return done; });
    if (error) std::rethrow_exception(error);
  }

 private:
  void Work() {
    for (;;) {
      std::function<void()> job;
      {
        std::unique_lock<std::mutex> lock(mutex_);
        cond_.wait(lock, [&] { return stop_ || !jobs_.empty(); });
        if (jobs_.empty()) return;
        job = std::move(jobs_.front());
        jobs_.pop_front();
      }
      job();
    }
  }
  std::mutex mutex_;  // guards jobs_, stop_
  std::condition_variable cond_;
  std::deque<std::function<void()>> jobs_;
  bool stop_ = false;
  std::vector<std::thread> threads_;
};

Extractions::Extractions(const sift::SiftExtractor& extractor, const ExtractionOptions& options)
    : extractor_(extractor),
      options_(options),
      semaphore_(options.slots),
      pair_match_extractor_(MustCreate(PairMatchExtractorOptions(extractor.options()))) {
  if (options_.add_nice > 0) {
    add_threads_ = std::make_unique<Threads>(options_.slots, options_.add_nice);
    sift::SiftOptions one_thread = extractor.options();
    one_thread.num_threads = 1;
    auto created = sift::SiftExtractor::Create(one_thread);
    OXBOW_CHECK(created.has_value(), "a valid extractor's settings with one thread are valid");
    add_extractor_.emplace(*created);
  }
  normal_threads_ = std::make_unique<Threads>(options_.slots, 0);
}

Extractions::~Extractions() = default;

Extractions::Work Extractions::Start(const sift::StopRequested& client_gone) const {
  return Work{Clock::now() + std::chrono::milliseconds(options_.processing_timeout_ms), &client_gone};
}

void Extractions::Stop() {
  const auto at = (Clock::now() + std::chrono::milliseconds(options_.shutdown_grace_ms)).time_since_epoch().count();
  Clock::rep current = stop_at_.load();
  while (at < current && !stop_at_.compare_exchange_weak(current, at)) {
  }
}

std::optional<Error> Extractions::StopReason(const Work& work) const {
  const auto now = Clock::now();
  if (now.time_since_epoch().count() >= stop_at_.load()) {
    return Error{ErrorCode::kResourceExhausted, "the server is shutting down; retry on another instance"};
  }
  if (work.client_gone != nullptr && *work.client_gone && (*work.client_gone)()) {
    return Error{ErrorCode::kResourceExhausted, "the client closed its connection"};
  }
  if (now >= work.deadline) {
    return Error{ErrorCode::kResourceExhausted, "decoding and extracting the image took longer than the server's limit of " +
                                                    std::to_string(options_.processing_timeout_ms) +
                                                    " ms (oxbow serve --processing-timeout-s); send a smaller image"};
  }
  return std::nullopt;
}

Result<sift::FeatureSet> Extractions::Extract(std::span<const uint8_t> image, const Work& work, double* elapsed_ms,
                                              const std::function<void()>& also, Use use) const {
  // The wait for a slot is taken in short steps, so that a request abandoned meanwhile stops waiting.
  const auto wait_until = Clock::now() + std::chrono::milliseconds(options_.extraction_wait_ms);
  for (;;) {
    const auto step = std::clamp(std::chrono::duration_cast<std::chrono::milliseconds>(wait_until - Clock::now()),
                                 std::chrono::milliseconds(0), std::chrono::milliseconds(20));
    if (semaphore_.try_acquire_for(step)) break;
    if (auto reason = StopReason(work)) return std::unexpected(*reason);
    if (Clock::now() >= wait_until) {
      return Fail(ErrorCode::kResourceExhausted,
                  "all " + std::to_string(options_.slots) + " extraction slots stayed busy for " +
                      std::to_string(options_.extraction_wait_ms) + " ms; retry later");
    }
  }
  SlotGuard slot(&semaphore_, &in_flight_);
  // At most `slots` jobs hold a slot, and each pool has that many threads: no job waits here.
  Result<sift::FeatureSet> features = Fail(ErrorCode::kInternal, "extraction did not run");
  const sift::StopRequested stop = [this, &work] { return StopReason(work).has_value(); };
  Threads* threads = normal_threads_.get();
  const sift::SiftExtractor* extractor = &extractor_;
  if (use == Use::kAdd && add_threads_ && add_extractor_) {
    threads = add_threads_.get();
    extractor = &*add_extractor_;
  } else if (use == Use::kPairMatch) {
    extractor = &pair_match_extractor_;
  }
  threads->Run([&] {
    const auto start = Clock::now();
    features = extractor->ExtractFromBytes(image, options_.decode, stop);
    *elapsed_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
    if (features && also) also();
  });
  if (!features && features.error().code == ErrorCode::kResourceExhausted) {
    if (auto reason = StopReason(work)) {
      OXBOW_LOG(kInfo) << "extraction stopped after " << *elapsed_ms << " ms (" << features.error().message
                       << "): " << reason->message;
      return std::unexpected(*reason);
    }
  }
  return features;
}

}  // namespace oxbow::api
