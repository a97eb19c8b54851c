// The runs of equal words in a word-sorted list of features, with a lookup by word for a merge against
// another word-sorted list (a candidate image's features): most of the other list's words are absent,
// which one bit test tells; a present one costs a binary search from the previous hit.
//
// Thread safety: immutable after construction; Find may run concurrently (the cursor is the caller's).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

namespace oxbow::index {

class WordRuns {
 public:
  WordRuns() = default;
  // word_at(i) for i in [0, n), ascending.
  template <typename WordAt>
  WordRuns(size_t n, WordAt word_at) {
    for (size_t i = 0; i < n; ++i) {
      const uint32_t w = word_at(i);
      if (words_.empty() || words_.back() != w) {
        words_.push_back(w);
        begin_.push_back(static_cast<uint32_t>(i));
      }
    }
    begin_.push_back(static_cast<uint32_t>(n));
    if (!words_.empty()) {
      has_word_.assign(words_.back() / 64 + 1, 0);
      for (const uint32_t w : words_) has_word_[w / 64] |= uint64_t{1} << (w % 64);
    }
  }

  // Whether word w has a run (one bit test).
  bool Has(uint32_t w) const { return w / 64 < has_word_.size() && (has_word_[w / 64] >> (w % 64) & 1) != 0; }

  // The positions [first, second) of word w's run; empty (0, 0) when w is absent. Successive calls
  // must ask for ascending words with the same `cursor` (0 before the first call).
  std::pair<size_t, size_t> Find(uint32_t w, size_t& cursor) const {
    if (!Has(w)) return {0, 0};
    cursor = static_cast<size_t>(std::lower_bound(words_.begin() + static_cast<std::ptrdiff_t>(cursor), words_.end(), w) -
                                 words_.begin());
    return {begin_[cursor], begin_[cursor + 1]};
  }

 private:
  std::vector<uint32_t> words_;     // the distinct words, ascending
  std::vector<uint32_t> begin_;     // words_[r]'s run: [begin_[r], begin_[r + 1])
  std::vector<uint64_t> has_word_;  // bit w set when word w has a run
};

}  // namespace oxbow::index
