// Posting storage: the bag of words an image is indexed with, and the immutable segments that hold the
// posting lists (codec.h) of a range of image numbers; how a segment is written from bags and how
// several are merged into one. The inverted file (inverted_file.h) keeps a list of segments and decides
// when to merge; scoring (scoring.h) and the statistics' refresh (statistics.h) scan them.
//
// Thread safety: a Segment is immutable once built and shared (shared_ptr<const Segment>); any number of
// threads may read it. A SegmentWriter is used by one thread.
#pragma once

#include <algorithm>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <utility>
#include <vector>

#include "index/postings/codec.h"

namespace oxbow::index {

// The words of one image: distinct word ids ascending, each with its count tf >= 1.
struct BagOfWords {
  std::vector<uint32_t> words;
  std::vector<uint32_t> counts;

  // From a list of word ids in any order (duplicates counted).
  static BagOfWords FromWords(std::span<const uint32_t> words);
  uint64_t total() const;  // sum of counts
};

}  // namespace oxbow::index

namespace oxbow::index::postings {

// One immutable run of postings for the images in [first_image, end_image): per word with postings
// here, its list sorted by image number. Two layouts of the list table: dense (offsets indexed by word,
// vocabulary_size + 1 entries) or sparse (the words with postings, binary-searched, and their offsets).
struct Segment {
  uint32_t first_image = 0;
  uint32_t end_image = 0;
  bool dense = false;             // offsets indexed by word (vocabulary_size + 1) instead of via `words`
  std::vector<uint32_t> words;    // sparse layout: distinct words, ascending
  std::vector<uint64_t> offsets;  // into the postings; dense: per word; sparse: per entry of `words` (+1)
  // The postings: built in this process (`bytes`), or read in place from a checkpoint file's mapping
  // (`mapped`, kept alive by `owner`; `bytes` empty), so that opening a large index copies nothing.
  std::vector<uint8_t> bytes;
  std::span<const uint8_t> mapped;
  std::shared_ptr<const void> owner;
  uint64_t num_postings = 0;

  const uint8_t* data() const { return owner ? mapped.data() : bytes.data(); }
  size_t size() const { return owner ? mapped.size() : bytes.size(); }

  // The coded list of `word`: [first, second), empty when the word has no postings here.
  std::pair<const uint8_t*, const uint8_t*> List(uint32_t word) const {
    if (dense) {
      if (word + 1 >= offsets.size()) return {nullptr, nullptr};
      return {data() + offsets[word], data() + offsets[word + 1]};
    }
    const auto it = std::lower_bound(words.begin(), words.end(), word);
    if (it == words.end() || *it != word) return {nullptr, nullptr};
    const size_t i = static_cast<size_t>(it - words.begin());
    return {data() + offsets[i], data() + offsets[i + 1]};
  }

  // Calls fn(image, tf) for every posting of `word`, in image order.
  template <typename Fn>
  void ForEach(uint32_t word, Fn&& fn) const {
    auto [p, end] = List(word);
    uint32_t image = first_image;
    while (p < end) {
      uint32_t gap = 0, tf = 1;
      GetPosting(p, &gap, &tf);
      image += gap;
      fn(image, tf);
    }
  }

  // Every word with postings here, ascending.
  std::vector<uint32_t> Words() const;
  // Heap bytes held (the postings, mapped or not, and the tables).
  uint64_t MemoryBytes() const;
  // Switches to the dense layout when at least 1/8 of the vocabulary has postings here (the dense table
  // then costs at most 2x the sparse one and saves the binary search).
  void ChooseLayout(size_t vocabulary_size);
};

// Writes a segment in two passes over its postings, for batches large next to the vocabulary: Count
// every posting (the coded size of every word's list), Allocate, then Put the same postings in the
// same order, each written in place; O(postings + vocabulary_size), no intermediate copy. Postings
// of one word must come in ascending image order.
class SegmentWriter {
 public:
  SegmentWriter(uint32_t first_image, uint32_t end_image, size_t vocabulary_size);

  void Count(uint32_t word, uint32_t image, uint32_t tf) {
    offsets_[word + 1] += PostingSize(image - last_[word], tf);
    last_[word] = image;
  }
  // Count() for a posting whose gap is known to be below kGapEscape (images closer together than it):
  // no previous image per word is needed.
  void CountShortGap(uint32_t word, uint32_t tf) { offsets_[word + 1] += PostingSize(0, tf); }
  void Allocate();
  void Put(uint32_t word, uint32_t image, uint32_t tf) {
    uint8_t* p = data_ + cursor_[word];
    cursor_[word] = static_cast<uint64_t>(PutPosting(p, image - last_[word], tf) - data_);
    last_[word] = image;
  }
  // Whether Put wrote exactly what Count counted.
  bool Complete() const;
  // The segment of `num_postings` postings; dense when `dense` or when at least 1/8 of the vocabulary
  // has postings, else sparse.
  std::shared_ptr<Segment> Finish(uint64_t num_postings, bool dense) &&;

 private:
  size_t vocabulary_size_;
  std::shared_ptr<Segment> segment_ = std::make_shared<Segment>();
  std::vector<uint64_t> offsets_;  // Count: list sizes (at w + 1); Allocate on: list starts, per word + end
  std::vector<uint32_t> last_;     // per word, the image of its last posting (the first image at the start)
  std::vector<uint64_t> cursor_;   // per word, where Put writes next
  uint8_t* data_ = nullptr;        // segment_->bytes.data() (Allocate)
  size_t distinct_ = 0;            // words with postings (Allocate)
};

// The segment of the images `images` (ascending), bags[i] that of images[i], every word <
// vocabulary_size. A batch of at least vocabulary_size / 4 postings is written by a SegmentWriter;
// a smaller one (single adds) from sorted (word, image) triples, so that no table has a vocabulary's
// size. May hold no posting (bags without words).
std::shared_ptr<Segment> BuildSegment(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags,
                                      size_t vocabulary_size);

// One segment holding the postings of `segments` (consecutive, ascending image ranges) of the images
// for which is_live(image) is true; an empty is_live keeps every posting, and the lists are then
// joined without decoding every posting's image state. num_postings counts the postings kept.
std::shared_ptr<Segment> MergeSegments(std::span<const std::shared_ptr<const Segment>> segments,
                                       size_t vocabulary_size, const std::function<bool(uint32_t image)>& is_live);

}  // namespace oxbow::index::postings
