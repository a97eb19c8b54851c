#include "index/postings/segment.h"

#include <algorithm>

#include "index/storage/huge_pages.h"
#include "sift/base/error.h"

namespace oxbow::index {

BagOfWords BagOfWords::FromWords(std::span<const uint32_t> words) {
  std::vector<uint32_t> sorted(words.begin(), words.end());
  std::sort(sorted.begin(), sorted.end());
  BagOfWords bag;
  for (size_t i = 0; i < sorted.size();) {
    size_t j = i;
    while (j < sorted.size() && sorted[j] == sorted[i]) ++j;
    bag.words.push_back(sorted[i]);
    bag.counts.push_back(static_cast<uint32_t>(j - i));
    i = j;
  }
  return bag;
}

uint64_t BagOfWords::total() const {
  uint64_t n = 0;
  for (uint32_t c : counts) n += c;
  return n;
}

}  // namespace oxbow::index

namespace oxbow::index::postings {

std::vector<uint32_t> Segment::Words() const {
  if (!dense) return words;
  std::vector<uint32_t> out;
  for (size_t w = 0; w + 1 < offsets.size(); ++w) {
    if (offsets[w + 1] > offsets[w]) out.push_back(static_cast<uint32_t>(w));
  }
  return out;
}

uint64_t Segment::MemoryBytes() const {
  return (owner ? mapped.size() : bytes.capacity()) + offsets.capacity() * sizeof(uint64_t) +
         words.capacity() * sizeof(uint32_t) + sizeof(*this);
}

void Segment::ChooseLayout(size_t vocabulary_size) {
  if (dense || words.size() * 8 < vocabulary_size) return;
  std::vector<uint64_t> table(vocabulary_size + 1, 0);
  size_t k = 0;
  for (size_t w = 0; w <= vocabulary_size; ++w) {
    while (k < words.size() && words[k] < w) ++k;
    table[w] = k < words.size() ? offsets[k] : size();
  }
  offsets = std::move(table);
  words.clear();
  words.shrink_to_fit();
  dense = true;
}

SegmentWriter::SegmentWriter(uint32_t first_image, uint32_t end_image, size_t vocabulary_size)
    : vocabulary_size_(vocabulary_size), offsets_(vocabulary_size + 1, 0), last_(vocabulary_size, first_image) {
  segment_->first_image = first_image;
  segment_->end_image = end_image;
}

void SegmentWriter::Allocate() {
  for (size_t w = 0; w < vocabulary_size_; ++w) {
    distinct_ += offsets_[w + 1] > 0 ? 1 : 0;
    offsets_[w + 1] += offsets_[w];
  }
  segment_->bytes.resize(offsets_[vocabulary_size_]);
  data_ = segment_->bytes.data();
  cursor_.assign(offsets_.begin(), offsets_.end() - 1);
  std::fill(last_.begin(), last_.end(), segment_->first_image);
}

bool SegmentWriter::Complete() const {
  for (size_t w = 0; w < vocabulary_size_; ++w) {
    if (cursor_[w] != offsets_[w + 1]) return false;
  }
  return true;
}

std::shared_ptr<Segment> SegmentWriter::Finish(uint64_t num_postings, bool dense) && {
  segment_->num_postings = num_postings;
  if (dense || distinct_ * 8 >= vocabulary_size_) {
    segment_->offsets = std::move(offsets_);
    segment_->dense = true;
    return std::move(segment_);
  }
  // The sparse layout, as ChooseLayout would leave it.
  segment_->words.reserve(distinct_);
  segment_->offsets.reserve(distinct_ + 1);
  for (size_t w = 0; w < vocabulary_size_; ++w) {
    if (offsets_[w + 1] == offsets_[w]) continue;
    segment_->words.push_back(static_cast<uint32_t>(w));
    segment_->offsets.push_back(offsets_[w]);
  }
  segment_->offsets.push_back(offsets_[vocabulary_size_]);
  return std::move(segment_);
}

namespace {

// BuildSegment for a large batch: one pass for the coded size of every word's list, one that writes the
// postings in place.
std::shared_ptr<Segment> WriteLargeBatch(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags,
                                         size_t vocabulary_size, uint64_t total) {
  SegmentWriter writer(images.front(), images.back() + 1, vocabulary_size);
  // Numbers closer together than the escape (a batch's are consecutive): no gap takes it, and the
  // sizes need no previous image per word (half the random accesses of this pass).
  const bool short_gaps = images.back() - images.front() < kGapEscape;
  for (size_t i = 0; i < images.size(); ++i) {
    for (size_t k = 0; k < bags[i]->words.size(); ++k) {
      if (short_gaps) {
        writer.CountShortGap(bags[i]->words[k], bags[i]->counts[k]);
      } else {
        writer.Count(bags[i]->words[k], images[i], bags[i]->counts[k]);
      }
    }
  }
  writer.Allocate();
  for (size_t i = 0; i < images.size(); ++i) {
    for (size_t k = 0; k < bags[i]->words.size(); ++k) writer.Put(bags[i]->words[k], images[i], bags[i]->counts[k]);
  }
  return std::move(writer).Finish(total, /*dense=*/false);
}

// BuildSegment for a few postings (single adds): sorted (word, image) triples.
std::shared_ptr<Segment> WriteSmallBatch(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags,
                                         size_t vocabulary_size, uint64_t total) {
  auto segment = std::make_shared<Segment>();
  segment->first_image = images.front();
  segment->end_image = images.back() + 1;
  segment->num_postings = total;
  struct Triple {
    uint32_t word, image, tf;
  };
  std::vector<Triple> triples;
  triples.reserve(total);
  for (size_t i = 0; i < images.size(); ++i) {
    for (size_t k = 0; k < bags[i]->words.size(); ++k) triples.push_back({bags[i]->words[k], images[i], bags[i]->counts[k]});
  }
  // The triples come in image order, so a stable sort by word gives (word, image) order.
  std::stable_sort(triples.begin(), triples.end(), [](const Triple& x, const Triple& y) { return x.word < y.word; });
  for (size_t i = 0; i < triples.size();) {
    segment->words.push_back(triples[i].word);
    segment->offsets.push_back(segment->bytes.size());
    uint32_t last = segment->first_image;
    size_t j = i;
    for (; j < triples.size() && triples[j].word == triples[i].word; ++j) {
      PutPosting(&segment->bytes, triples[j].image - last, triples[j].tf);
      last = triples[j].image;
    }
    i = j;
  }
  segment->offsets.push_back(segment->bytes.size());
  segment->ChooseLayout(vocabulary_size);
  return segment;
}

// Appends to `merged` the postings of `word` in `segment` of the images is_live keeps, decoding each.
void AppendLiveList(const Segment& segment, uint32_t word, const std::function<bool(uint32_t)>& is_live,
                    Segment* merged, uint32_t* last) {
  segment.ForEach(word, [&](uint32_t image, uint32_t tf) {
    if (!is_live(image)) return;
    PutPosting(&merged->bytes, image - *last, tf);
    *last = image;
    ++merged->num_postings;
  });
}

// Appends to `merged` the whole list of `word` in `segment`: only its first posting is coded again (its
// gap counts from its own segment's first image), the rest is copied as it is, its gaps decoded only to
// find its last image. The same bytes as decoding and coding every posting, without reading every
// image's state (a cache miss per posting at a million images).
void AppendWholeList(const Segment& segment, uint32_t word, Segment* merged, uint32_t* last) {
  auto [p, end] = segment.List(word);
  if (p == end) return;
  uint32_t gap = 0, tf = 1;
  GetPosting(p, &gap, &tf);
  uint32_t image = segment.first_image + gap;
  PutPosting(&merged->bytes, image - *last, tf);
  merged->bytes.insert(merged->bytes.end(), p, end);
  uint64_t count = 1;
  for (; p < end; ++count) {
    GetPosting(p, &gap, &tf);
    image += gap;
  }
  *last = image;
  merged->num_postings += count;
}

}  // namespace

std::shared_ptr<Segment> BuildSegment(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags,
                                      size_t vocabulary_size) {
  OXBOW_CHECK(!images.empty() && images.size() == bags.size());
  uint64_t total = 0;
  for (const BagOfWords* bag : bags) total += bag->words.size();
  if (total * 4 >= vocabulary_size) return WriteLargeBatch(images, bags, vocabulary_size, total);
  return WriteSmallBatch(images, bags, vocabulary_size, total);
}

std::shared_ptr<Segment> MergeSegments(std::span<const std::shared_ptr<const Segment>> segments,
                                       size_t vocabulary_size, const std::function<bool(uint32_t image)>& is_live) {
  OXBOW_CHECK(!segments.empty());
  // Word by word, in image order.
  std::vector<uint32_t> words;
  // An upper bound of the merged size: each list's first posting from a segment may take the 4-byte
  // escape of a longer gap; every other posting keeps its size or drops out.
  uint64_t bound = 0;
  for (const auto& segment : segments) {
    const auto w = segment->Words();
    words.insert(words.end(), w.begin(), w.end());
    bound += segment->size() + 4 * w.size();
  }
  std::sort(words.begin(), words.end());
  words.erase(std::unique(words.begin(), words.end()), words.end());
  auto merged = std::make_shared<Segment>();
  merged->first_image = segments.front()->first_image;
  merged->end_image = segments.back()->end_image;
  // Reserved at once, in huge pages where large: growing it posting by posting reallocated and copied
  // it about twice over, into fresh 4 KiB pages each taking a fault (dear in a VM).
  merged->bytes.reserve(bound);
  AdviseHugePages(merged->bytes.data(), bound);
  for (const uint32_t w : words) {
    const size_t begin = merged->bytes.size();
    uint32_t last = merged->first_image;
    for (const auto& segment : segments) {
      if (is_live) {
        AppendLiveList(*segment, w, is_live, merged.get(), &last);
      } else {
        AppendWholeList(*segment, w, merged.get(), &last);
      }
    }
    if (merged->bytes.size() > begin) {
      merged->words.push_back(w);
      merged->offsets.push_back(begin);
    }
  }
  merged->offsets.push_back(merged->bytes.size());
  // Pages of the reserve never written take no memory; shrink only when removed images left much.
  if (merged->bytes.capacity() - merged->bytes.size() > merged->bytes.size() / 8 + 4096) merged->bytes.shrink_to_fit();
  merged->ChooseLayout(vocabulary_size);
  return merged;
}

}  // namespace oxbow::index::postings
