// The inverted file's writes: building from scratch, adding and removing images, and the
// log-structured merge of its segments. Scoring is in scoring.cc, statistics in statistics.cc, the
// checkpoint form in serialisation.cc.
#include "index/postings/inverted_file.h"

#include <algorithm>
#include <cmath>

#include "sift/base/error.h"
#include "sift/base/parallel.h"

namespace oxbow::index {
namespace {

using postings::CollectionStatistics;
using postings::ImageState;
using postings::Segment;
using postings::SegmentWriter;

constexpr uint64_t kLevelBasePostings = 1024;

// n_w = 0 for every word, after the constructor's checks of its arguments.
CowArray<uint32_t> NoDocuments(size_t vocabulary_size, const TfIdfOptions& options) {
  const auto error = options.Check();
  OXBOW_CHECK(!error, "invalid TfIdfOptions");
  OXBOW_CHECK(vocabulary_size > 0 && vocabulary_size < (uint64_t{1} << 32));
  CowArray<uint32_t> df;
  CowArray<uint32_t>::Editor(&df).Resize(vocabulary_size, 0);
  return df;
}

// Build's images: the bags of [0, num_numbers) that bag_of gives, produced in parallel batches and
// handed over in image order.
struct BagSource {
  uint32_t num_numbers;
  int threads;
  const std::function<bool(uint32_t, BagOfWords*)>& bag_of;

  void ForEach(const std::function<void(uint32_t, const BagOfWords&)>& fn) const {
    constexpr uint32_t kBatch = 4096;
    std::vector<BagOfWords> bags(kBatch);
    std::vector<uint8_t> present(kBatch);
    for (uint32_t begin = 0; begin < num_numbers; begin += kBatch) {
      const uint32_t n = std::min(kBatch, num_numbers - begin);
      ParallelFor(n, threads, 64, [&](size_t b, size_t e, int) {
        for (size_t i = b; i < e; ++i) {
          bags[i].words.clear();
          bags[i].counts.clear();
          present[i] = bag_of(begin + static_cast<uint32_t>(i), &bags[i]) ? 1 : 0;
        }
      });
      for (uint32_t i = 0; i < n; ++i) {
        if (present[i]) fn(begin + i, bags[i]);
      }
    }
  }
};

// Build's first pass: every bag checked, its postings counted into `writer` and its words into `df`.
// Returns the number of images.
uint64_t CountPostings(const BagSource& source, size_t vocabulary_size, SegmentWriter* writer,
                       std::vector<uint32_t>* df) {
  uint64_t live = 0;
  source.ForEach([&](uint32_t image, const BagOfWords& bag) {
    OXBOW_CHECK(bag.words.size() == bag.counts.size());
    for (size_t k = 0; k < bag.words.size(); ++k) {
      const uint32_t w = bag.words[k];
      OXBOW_CHECK(w < vocabulary_size, "word id outside the vocabulary");
      OXBOW_CHECK(bag.counts[k] >= 1 && (k == 0 || bag.words[k - 1] < w), "bag not sorted/distinct");
      writer->Count(w, image, bag.counts[k]);
      ++(*df)[w];
    }
    ++live;
  });
  return live;
}

// Build's second pass: the postings put into `writer` and every image's state (its norm sums with
// log n_w = log_df[w]). Adds to *postings and *features.
void WritePostings(const BagSource& source, std::span<const double> log_df, bool sqrt_tf, SegmentWriter* writer,
                   CowArray<ImageState>* images, uint64_t* postings, uint64_t* features) {
  CowArray<ImageState>::Editor editor(images);
  editor.Resize(source.num_numbers);
  source.ForEach([&](uint32_t image, const BagOfWords& bag) {
    ImageState& s = editor.Mutable(image);
    for (size_t k = 0; k < bag.words.size(); ++k) {
      const uint32_t w = bag.words[k], tf = bag.counts[k];
      writer->Put(w, image, tf);
      const double t2 = postings::TermWeightSquared(sqrt_tf, tf);
      s.a += t2;
      s.b += t2 * log_df[w];
      s.c += t2 * log_df[w] * log_df[w];
      s.features += tf;
    }
    s.live = 1;
    *postings += bag.words.size();
    *features += s.features;
  });
}

}  // namespace

std::optional<std::string> TfIdfOptions::Check() const {
  if (!(max_document_frequency > 0 && max_document_frequency <= 1)) {
    return "max_document_frequency must be in (0, 1], got " + std::to_string(max_document_frequency);
  }
  if (merge_factor < 2 || merge_factor > 64) {
    return "merge_factor must be in [2, 64], got " + std::to_string(merge_factor);
  }
  if (!(statistics_refresh_fraction > 0 && statistics_refresh_fraction <= 1)) {
    return "statistics_refresh_fraction must be in (0, 1], got " + std::to_string(statistics_refresh_fraction);
  }
  return std::nullopt;
}

InvertedFile::InvertedFile(size_t vocabulary_size, const TfIdfOptions& options)
    : vocabulary_size_(vocabulary_size),
      options_(options),
      df_(NoDocuments(vocabulary_size, options)),
      statistics_(options.sqrt_tf, df_, 0) {}

InvertedFile InvertedFile::Build(size_t vocabulary_size, const TfIdfOptions& options, uint32_t num_numbers,
                                 const std::function<bool(uint32_t, BagOfWords*)>& bag_of, int num_threads) {
  InvertedFile out(vocabulary_size, options);
  const BagSource source{num_numbers, ResolveThreadCount(num_threads), bag_of};
  SegmentWriter writer(0, num_numbers, vocabulary_size);
  std::vector<uint32_t> df(vocabulary_size, 0);
  const uint64_t live = CountPostings(source, vocabulary_size, &writer, &df);
  writer.Allocate();
  std::vector<double> log_df(vocabulary_size, 0);
  for (size_t w = 0; w < vocabulary_size; ++w) log_df[w] = df[w] ? std::log(static_cast<double>(df[w])) : 0;
  uint64_t postings = 0, features = 0;
  WritePostings(source, log_df, options.sqrt_tf, &writer, &out.images_, &postings, &features);
  OXBOW_CHECK(writer.Complete(), "bag_of changed between passes");
  std::shared_ptr<Segment> segment = std::move(writer).Finish(postings, /*dense=*/true);
  {
    CowArray<uint32_t>::Editor dfe(&out.df_);
    for (size_t w = 0; w < vocabulary_size; ++w) {
      if (df[w]) dfe.Mutable(w) = df[w];
    }
  }
  if (postings > 0) out.segments_.push_back(std::move(segment));
  out.statistics_ = CollectionStatistics(options.sqrt_tf, out.df_, live);
  out.num_live_ = live;
  out.num_live_features_ = features;
  out.num_postings_ = postings;
  out.RecomputeNorms();
  return out;
}

InvertedFile InvertedFile::WithAdded(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags) const {
  OXBOW_CHECK(images.size() == bags.size());
  InvertedFile next = *this;
  if (images.empty()) return next;
  for (size_t i = 0; i < images.size(); ++i) {
    OXBOW_CHECK(images[i] >= images_.size() && (i == 0 || images[i] > images[i - 1]),
                "image numbers must be new and ascending");
  }
  {
    CowArray<uint32_t>::Editor dfe(&next.df_);
    for (const BagOfWords* bag : bags) {
      OXBOW_CHECK(bag->words.size() == bag->counts.size());
      for (size_t k = 0; k < bag->words.size(); ++k) {
        const uint32_t w = bag->words[k];
        OXBOW_CHECK(w < vocabulary_size_, "word id outside the vocabulary");
        OXBOW_CHECK(bag->counts[k] >= 1 && (k == 0 || bag->words[k - 1] < w), "bag not sorted/distinct");
        ++dfe.Mutable(w);
      }
    }
  }
  // The new images' own sums, with the statistics of the last refresh.
  {
    CowArray<ImageState>::Editor editor(&next.images_);
    editor.Resize(images.back() + size_t{1});
    const std::shared_ptr<const std::vector<double>> log_df = next.statistics_.LogDfTable();
    for (size_t i = 0; i < images.size(); ++i) {
      ImageState& s = editor.Mutable(images[i]);
      s = ImageState{};
      next.statistics_.SetSums(*bags[i], *log_df, &s);
      for (const uint32_t tf : bags[i]->counts) s.features += tf;
      s.live = 1;
      ++next.num_live_;
      next.num_live_features_ += s.features;
    }
  }
  next.SetNorms(images);
  next.changes_since_refresh_ += images.size();
  std::shared_ptr<Segment> segment = postings::BuildSegment(images, bags, vocabulary_size_);
  if (segment->num_postings > 0) {
    next.num_postings_ += segment->num_postings;
    next.segments_.push_back(std::move(segment));
  }
  next.MergeTail(false);
  next.RefreshIfDue();
  return next;
}

InvertedFile InvertedFile::WithRemoved(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags) const {
  OXBOW_CHECK(images.size() == bags.size());
  InvertedFile next = *this;
  if (images.empty()) return next;
  {
    CowArray<ImageState>::Editor editor(&next.images_);
    CowArray<uint32_t>::Editor dfe(&next.df_);
    for (size_t i = 0; i < images.size(); ++i) {
      OXBOW_CHECK(next.IsLive(images[i]), "removing an image that is not live");
      ImageState& s = editor.Mutable(images[i]);
      s.live = 0;
      --next.num_live_;
      next.num_live_features_ -= s.features;
      next.num_dead_postings_ += bags[i]->words.size();
      for (const uint32_t w : bags[i]->words) {
        OXBOW_CHECK(w < vocabulary_size_ && df_[w] > 0, "bag does not match the indexed image");
        --dfe.Mutable(w);
      }
    }
  }
  next.SetNorms(images);
  next.changes_since_refresh_ += images.size();
  if (next.num_dead_postings_ * 2 > next.num_postings_) next.MergeTail(true);
  next.RefreshIfDue();
  return next;
}

// Merges the newest segments while merge_factor of them share a size level (everything: all of them,
// once), dropping the postings of removed images.
void InvertedFile::MergeTail(bool everything) {
  auto level = [&](const Segment& s) {
    int l = 0;
    for (uint64_t n = s.num_postings / kLevelBasePostings; n > 0; n /= static_cast<uint64_t>(options_.merge_factor)) ++l;
    return l;
  };
  while (segments_.size() >= (everything ? 1u : 2u)) {
    size_t first = segments_.size() - 1;
    if (everything) {
      first = 0;
    } else {
      const int last_level = level(*segments_.back());
      while (first > 0 && level(*segments_[first - 1]) <= last_level) --first;
      if (segments_.size() - first < static_cast<size_t>(options_.merge_factor)) return;
    }
    const std::span<const std::shared_ptr<const Segment>> merging(segments_.begin() + static_cast<std::ptrdiff_t>(first),
                                                                  segments_.end());
    uint64_t old_postings = 0;
    for (const auto& segment : merging) old_postings += segment->num_postings;
    // With no removed image's postings anywhere, the lists are joined without reading image states.
    std::function<bool(uint32_t)> is_live;
    if (num_dead_postings_ != 0) is_live = [this](uint32_t image) { return images_[image].live != 0; };
    std::shared_ptr<Segment> merged = postings::MergeSegments(merging, vocabulary_size_, is_live);
    const uint64_t dropped = old_postings - merged->num_postings;
    num_postings_ -= dropped;
    num_dead_postings_ -= std::min(num_dead_postings_, dropped);
    segments_.resize(first);
    if (merged->num_postings > 0) segments_.push_back(std::move(merged));
    if (everything) return;
  }
}

InvertedFileStats InvertedFile::Stats() const {
  InvertedFileStats s;
  s.num_images = num_live_;
  s.num_postings = num_postings_;
  s.num_features = num_live_features_;
  for (const auto& segment : segments_) s.postings_bytes += segment->MemoryBytes();
  s.image_table_bytes = images_.MemoryBytes() + norms_.MemoryBytes();
  s.word_table_bytes = df_.MemoryBytes();
  s.num_segments = segments_.size();
  return s;
}

}  // namespace oxbow::index
