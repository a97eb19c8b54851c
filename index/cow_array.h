// CowArray<T>: a growable array split into fixed-size chunks held by std::shared_ptr<const>, so that a
// new version of the array shares every chunk it did not change with the previous version
// (copy-on-write at chunk granularity). This is how index snapshots stay cheap to publish: a writer
// copies the chunk table (size / kChunk pointers), edits a few elements (each first touch of a chunk
// copies that chunk only), and publishes; readers of older versions are unaffected.
//
// Thread safety: a CowArray value is immutable once shared; const access from any number of threads.
// An Editor must be used by one thread and must not outlive its array.
// Complexity: operator[] O(1) (two loads); copy O(size / kChunk); first write to a chunk O(kChunk).
#pragma once

#include <cstddef>
#include <memory>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::index {

template <typename T, size_t kChunkLog2 = 12>
class CowArray {
 public:
  static constexpr size_t kChunk = size_t{1} << kChunkLog2;

  size_t size() const { return size_; }
  const T& operator[](size_t i) const { return (*chunks_[i >> kChunkLog2])[i & (kChunk - 1)]; }

  // Approximate heap bytes held (chunks + table), counting shared chunks fully.
  size_t MemoryBytes() const { return chunks_.size() * (sizeof(void*) * 2 + kChunk * sizeof(T)); }

  // Edits a copy of an array; the copy shares unchanged chunks with the original.
  class Editor {
   public:
    explicit Editor(CowArray* array) : array_(array), owned_(array->chunks_.size(), false) {}

    T& Mutable(size_t i) {
      OXBOW_CHECK(i < array_->size_);
      const size_t c = i >> kChunkLog2;
      if (!owned_[c]) {
        array_->chunks_[c] = std::make_shared<std::vector<T>>(*array_->chunks_[c]);
        owned_[c] = true;
      }
      return const_cast<std::vector<T>&>(*array_->chunks_[c])[i & (kChunk - 1)];
    }
    void Resize(size_t n, const T& value = T()) {
      OXBOW_CHECK(n >= array_->size_, "CowArray only grows");
      const size_t old_size = array_->size_;
      const size_t old_capacity = array_->chunks_.size() * kChunk;
      array_->size_ = n;
      while (array_->chunks_.size() * kChunk < n) {
        array_->chunks_.push_back(std::make_shared<std::vector<T>>(kChunk, value));
        owned_.push_back(true);
      }
      for (size_t i = old_size; i < n && i < old_capacity; ++i) Mutable(i) = value;
    }

   private:
    CowArray* array_;
    std::vector<bool> owned_;
  };

 private:
  std::vector<std::shared_ptr<const std::vector<T>>> chunks_;
  size_t size_ = 0;
};

}  // namespace oxbow::index
