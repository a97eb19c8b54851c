// Memory a search keeps for the next one.
#pragma once

#include <memory>
#include <mutex>
#include <vector>

namespace oxbow::index::search {

// Memory a search keeps for the next one (accumulators, the query's descriptors, transitive
// verification's tables), shared by every thread that searches: one value per search running at once,
// taken at the start and given back at the end. Kept per thread instead, it would be faulted in once by
// each of the server's many connection threads, so each of the first dozen or so searches after a start
// would pay for it again: at a million images the accumulators alone are 4 MB, about 1000 page faults, and a first
// touch costs about 18 us a page on the 2-core test VM (about 18 ms a search). At most kMaxKept values
// stay between searches. The pool is never destroyed (a search may still run while the process exits).
template <typename T>
class KeptForNextSearch {
 public:
  class Lease {
   public:
    Lease(KeptForNextSearch* pool, std::unique_ptr<T> value) : pool_(pool), value_(std::move(value)) {}
    Lease(const Lease&) = delete;
    Lease& operator=(const Lease&) = delete;
    Lease(Lease&& other) noexcept : pool_(other.pool_), value_(std::move(other.value_)) {}
    Lease& operator=(Lease&&) = delete;
    ~Lease() {
      if (value_) pool_->GiveBack(std::move(value_));
    }
    T& operator*() const { return *value_; }
    T* operator->() const { return value_.get(); }

   private:
    KeptForNextSearch* pool_;
    std::unique_ptr<T> value_;
  };

  static KeptForNextSearch& Shared() {
    static auto* pool = new KeptForNextSearch();  // NOLINT(cppcoreguidelines-owning-memory): never freed, see above
    return *pool;
  }

  Lease Take() {
    std::unique_ptr<T> value;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!free_.empty()) {
        value = std::move(free_.back());
        free_.pop_back();
      }
    }
    if (!value) value = std::make_unique<T>();
    return Lease(this, std::move(value));
  }

 private:
  static constexpr size_t kMaxKept = 8;

  void GiveBack(std::unique_ptr<T> value) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (free_.size() < kMaxKept) free_.push_back(std::move(value));
  }

  std::mutex mutex_;
  std::vector<std::unique_ptr<T>> free_;
};

}  // namespace oxbow::index::search
