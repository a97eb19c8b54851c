#include "index/postings/statistics.h"

#include <algorithm>
#include <limits>

#include "index/postings/inverted_file.h"
#include "sift/base/error.h"
#include "sift/base/parallel.h"

namespace oxbow::index::postings {

CollectionStatistics::CollectionStatistics(bool sqrt_tf, CowArray<uint32_t> document_frequency, uint64_t num_images)
    : sqrt_tf_(sqrt_tf), document_frequency_(std::move(document_frequency)), num_images_(num_images) {
  for (uint32_t tf = 0; tf < term_weight_.size(); ++tf) {
    term_weight_[tf] = sqrt_tf ? static_cast<float>(std::sqrt(static_cast<double>(tf))) : static_cast<float>(tf);
  }
}

double CollectionStatistics::Idf(uint32_t word) const {
  const uint32_t df = document_frequency_[word];
  if (df == 0) return std::numeric_limits<double>::infinity();
  return std::log(static_cast<double>(num_images_) / static_cast<double>(df));
}

std::shared_ptr<const std::vector<double>> CollectionStatistics::IdfSquaredTable() const {
  Tables& tables = *tables_;
  std::call_once(tables.squared_once, [&] {
    auto squared = std::make_shared<std::vector<double>>(vocabulary_size(), 0.0);
    for (size_t w = 0; w < vocabulary_size(); ++w) {
      const double idf = Idf(static_cast<uint32_t>(w));
      if (std::isfinite(idf)) (*squared)[w] = idf * idf;
    }
    tables.squared = std::move(squared);
  });
  return tables.squared;
}

std::shared_ptr<const std::vector<double>> CollectionStatistics::LogDfTable() const {
  Tables& tables = *tables_;
  std::call_once(tables.log_df_once, [&] {
    auto log_df = std::make_shared<std::vector<double>>(vocabulary_size(), 0.0);
    for (size_t w = 0; w < vocabulary_size(); ++w) {
      if (document_frequency_[w] != 0) (*log_df)[w] = std::log(static_cast<double>(document_frequency_[w]));
    }
    tables.log_df = std::move(log_df);
  });
  return tables.log_df;
}

void CollectionStatistics::SetSums(const BagOfWords& bag, std::span<const double> log_df, ImageState* s) const {
  s->a = s->b = s->c = 0;
  for (size_t k = 0; k < bag.words.size(); ++k) {
    const uint32_t df = document_frequency_[bag.words[k]];
    if (df == 0) continue;  // unknown to the statistics until the next refresh
    const double l = log_df[bag.words[k]];
    const double t2 = TermWeightSquared(sqrt_tf_, bag.counts[k]);
    s->a += t2;
    s->b += t2 * l;
    s->c += t2 * l * l;
  }
}

double CollectionStatistics::Norm(const ImageState& s) const {
  if (s.live == 0) return 0;
  const double l = std::log(static_cast<double>(num_images_));
  const double sq = l * l * s.a - 2 * l * s.b + s.c;
  return sq > 0 ? std::sqrt(sq) : 0.0;
}

namespace {

constexpr size_t kWordsPerChunk = 4096;
constexpr size_t kSumGroups = 4;
constexpr size_t kImagesPerBlock = 16384;  // 16384 x 24 bytes of sums per group

struct Sums {
  double a = 0, b = 0, c = 0;
};

// The sums of group g: the postings of the words of chunks g, g + kSumGroups, ... (see
// RecomputeImageSums), into `sums` (one per image number).
void AddGroupSums(std::span<const std::shared_ptr<const Segment>> segments, const CollectionStatistics& statistics,
                  const std::vector<double>& log_df, const std::vector<uint8_t>& live, size_t g,
                  std::vector<Sums>* sums) {
  struct Cursor : PostingCursor {
    double log_df = 0;
  };
  const size_t vocabulary_size = statistics.vocabulary_size();
  const size_t num_chunks = (vocabulary_size + kWordsPerChunk - 1) / kWordsPerChunk;
  std::vector<Cursor> cursors;  // of one segment, in word order
  for (const auto& segment : segments) {
    cursors.clear();
    for (size_t chunk = g; chunk < num_chunks; chunk += kSumGroups) {
      const size_t w_end = std::min(vocabulary_size, (chunk + 1) * kWordsPerChunk);
      for (size_t w = chunk * kWordsPerChunk; w < w_end; ++w) {
        if (statistics.DocumentFrequency(static_cast<uint32_t>(w)) == 0) continue;
        const auto [p, list_end] = segment->List(static_cast<uint32_t>(w));
        if (p == list_end) continue;
        Cursor c{{p, list_end, segment->first_image}, log_df[w]};
        c.Advance();
        cursors.push_back(c);
      }
    }
    for (size_t block = segment->first_image; block < segment->end_image; block += kImagesPerBlock) {
      const auto limit = static_cast<uint32_t>(std::min<size_t>(block + kImagesPerBlock, segment->end_image));
      for (Cursor& c : cursors) {
        for (; c.image < limit; c.Advance()) {
          if (live[c.image] == 0) continue;
          const double t2 = TermWeightSquared(statistics.sqrt_tf(), c.tf);
          Sums& sum = (*sums)[c.image];
          sum.a += t2;
          sum.b += t2 * c.log_df;
          sum.c += t2 * c.log_df * c.log_df;
        }
      }
    }
  }
}

}  // namespace

// Words are dealt round-robin, in chunks, to a fixed number of groups with their own partial sums,
// added in group order at the end: the floating-point order, hence the result, is the same for any
// thread count. Segments hold disjoint, ascending image ranges and an image's postings all lie in one
// segment, so each group walks the segments in turn and, within a segment, its images in blocks small
// enough for the partial sums to stay in cache (one cursor per word of the segment carries on where the
// previous block stopped): a posting list's images are far apart, so unblocked updates would miss the
// cache at almost every posting. Only the cursors of the segment that holds a block are visited for it,
// and an image gets its terms in word order.
void RecomputeImageSums(std::span<const std::shared_ptr<const Segment>> segments,
                        const CollectionStatistics& statistics, CowArray<ImageState>* images, int num_threads) {
  const size_t num_images = images->size();
  std::vector<uint8_t> live(num_images);
  for (size_t i = 0; i < num_images; ++i) live[i] = (*images)[i].live != 0 ? 1 : 0;
  // The statistics' log n_w, kept in their table for the batches added after this refresh.
  const std::shared_ptr<const std::vector<double>> log_df = statistics.LogDfTable();
  std::vector<std::vector<Sums>> partial(kSumGroups);
  ParallelFor(kSumGroups, num_threads, 1, [&](size_t g0, size_t g1, int) {
    for (size_t g = g0; g < g1; ++g) {
      partial[g].assign(num_images, Sums{});
      AddGroupSums(segments, statistics, *log_df, live, g, &partial[g]);
    }
  });
  CowArray<ImageState>::Editor editor(images);
  for (size_t i = 0; i < num_images; ++i) {
    if (live[i] == 0) continue;
    ImageState& s = editor.Mutable(i);
    s.a = s.b = s.c = 0;
    for (const std::vector<Sums>& sums : partial) {
      s.a += sums[i].a;
      s.b += sums[i].b;
      s.c += sums[i].c;
    }
  }
}

}  // namespace oxbow::index::postings

namespace oxbow::index {

using postings::CollectionStatistics;

InvertedFile InvertedFile::WithRefreshedStatistics(int num_threads) const {
  InvertedFile next = *this;
  next.RefreshStatistics(num_threads);
  return next;
}

InvertedFile InvertedFile::WithPinnedStatistics(uint64_t num_images, std::span<const uint32_t> document_frequency,
                                                int num_threads) const {
  OXBOW_CHECK(document_frequency.size() == vocabulary_size_, "one document frequency per word");
  CowArray<uint32_t> pinned;
  {
    CowArray<uint32_t>::Editor editor(&pinned);
    editor.Resize(vocabulary_size_, 0);
    for (size_t w = 0; w < vocabulary_size_; ++w) editor.Mutable(w) = document_frequency[w];
  }
  InvertedFile next = *this;
  next.statistics_ = CollectionStatistics(options_.sqrt_tf, std::move(pinned), num_images);
  next.changes_since_refresh_ = 0;
  next.pinned_statistics_ = true;
  next.RecomputeSums(num_threads);
  return next;
}

void InvertedFile::RefreshIfDue() {
  if (changes_since_refresh_ == 0 || pinned_statistics_) return;
  if (num_postings_ <= options_.exact_statistics_postings ||
      static_cast<double>(changes_since_refresh_) >
          options_.statistics_refresh_fraction * static_cast<double>(statistics_.num_images())) {
    RefreshStatistics(0);
  }
}

void InvertedFile::RefreshStatistics(int num_threads) {
  statistics_ = CollectionStatistics(options_.sqrt_tf, df_, num_live_);
  changes_since_refresh_ = 0;
  pinned_statistics_ = false;
  RecomputeSums(num_threads);
}

void InvertedFile::RecomputeSums(int num_threads) {
  postings::RecomputeImageSums(segments_, statistics_, &images_, num_threads);
  RecomputeNorms();
}

void InvertedFile::SetNorms(std::span<const uint32_t> images) {
  CowArray<double>::Editor editor(&norms_);
  if (norms_.size() < images_.size()) editor.Resize(images_.size(), 0.0);
  for (const uint32_t n : images) editor.Mutable(n) = statistics_.Norm(images_[n]);
}

void InvertedFile::RecomputeNorms() {
  CowArray<double> fresh;
  CowArray<double>::Editor editor(&fresh);
  editor.Resize(images_.size(), 0.0);
  for (size_t n = 0; n < images_.size(); ++n) editor.Mutable(n) = statistics_.Norm(images_[n]);
  norms_ = std::move(fresh);
}

double InvertedFile::Idf(uint32_t word) const {
  OXBOW_CHECK(word < vocabulary_size_);
  return statistics_.Idf(word);
}

std::shared_ptr<const std::vector<double>> InvertedFile::IdfSquaredTable() const {
  return statistics_.IdfSquaredTable();
}

uint32_t InvertedFile::DocumentFrequency(uint32_t word) const {
  OXBOW_CHECK(word < vocabulary_size_);
  return df_[word];
}

}  // namespace oxbow::index
