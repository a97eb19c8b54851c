#include "index/postings/inverted_file.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <type_traits>
#include <limits>

#include "index/huge_pages.h"
#include "sift/base/error.h"
#include "sift/base/parallel.h"

namespace oxbow::index {
namespace {

constexpr uint64_t kLevelBasePostings = 1024;

inline size_t VarintSize(uint64_t v) {
  size_t n = 1;
  while (v >= 128) {
    v >>= 7;
    ++n;
  }
  return n;
}

inline uint8_t* PutVarint(uint8_t* p, uint64_t v) {
  while (v >= 128) {
    *p++ = static_cast<uint8_t>(v | 128);
    v >>= 7;
  }
  *p++ = static_cast<uint8_t>(v);
  return p;
}

inline uint64_t GetVarint(const uint8_t*& p) {
  uint64_t v = *p++;
  if (v < 128) return v;
  v &= 127;
  int shift = 7;
  while (true) {
    const uint64_t b = *p++;
    v |= (b & 127) << shift;
    if (b < 128) return v;
    shift += 7;
  }
}

// A posting (postings format 2): a 16-bit little-endian unit (g << 1) | (tf > 1), where g is the gap
// when it is below kGapEscape and kGapEscape otherwise, then followed by the gap in 4 little-endian
// bytes; then, when tf > 1, varint(tf - 2). Gaps of images in a list are below 2^15 unless the word is
// in fewer than about 1 of 32768 images, so the scan reads one fixed-size unit per posting, whose
// length does not depend on its value: no data-dependent branch per posting, unlike the varint gaps of
// format 1 (1-3 bytes each), which cost 2-3x the scan time.
constexpr uint32_t kGapEscape = 0x7FFF;

inline uint32_t Load16(const uint8_t* p) { return uint32_t{p[0]} | (uint32_t{p[1]} << 8); }
inline uint32_t Load32(const uint8_t* p) {
  return uint32_t{p[0]} | (uint32_t{p[1]} << 8) | (uint32_t{p[2]} << 16) | (uint32_t{p[3]} << 24);
}

inline size_t PostingSize(uint32_t gap, uint32_t tf) {
  return 2 + (gap >= kGapEscape ? 4 : 0) + (tf > 1 ? VarintSize(tf - 2) : 0);
}

inline uint8_t* PutPosting(uint8_t* p, uint32_t gap, uint32_t tf) {
  const uint32_t g = std::min(gap, kGapEscape);
  const uint32_t unit = (g << 1) | (tf > 1 ? 1 : 0);
  *p++ = static_cast<uint8_t>(unit);
  *p++ = static_cast<uint8_t>(unit >> 8);
  if (g == kGapEscape) {
    for (int k = 0; k < 4; ++k) *p++ = static_cast<uint8_t>(gap >> (8 * k));
  }
  if (tf > 1) p = PutVarint(p, tf - 2);
  return p;
}

inline void PutPosting(std::vector<uint8_t>* out, uint32_t gap, uint32_t tf) {
  const size_t at = out->size();
  out->resize(at + PostingSize(gap, tf));
  PutPosting(out->data() + at, gap, tf);
}

// Decodes the posting at p (trusted bytes: a checksummed file or this process's own) and moves past it.
inline void GetPosting(const uint8_t*& p, uint32_t* gap, uint32_t* tf) {
  const uint32_t unit = Load16(p);
  p += 2;
  *gap = unit >> 1;
  if (*gap == kGapEscape) [[unlikely]] {
    *gap = Load32(p);
    p += 4;
  }
  *tf = 1;
  if ((unit & 1) != 0) [[unlikely]] *tf = static_cast<uint32_t>(GetVarint(p)) + 2;
}

// One word's list in one segment, read a posting at a time, for the scans that go through a segment a
// block of image numbers at a time with a cursor per list (RecomputeSums, Score). Start it at the
// segment's first image, then Advance() decodes the first posting: `image` and `tf` are those of the
// posting decoded last, and `image` is UINT32_MAX once the list is done.
struct PostingCursor {
  const uint8_t* p = nullptr;
  const uint8_t* end = nullptr;
  uint32_t image = 0;
  uint32_t tf = 1;

  void Advance() {
    if (p >= end) {
      image = std::numeric_limits<uint32_t>::max();
      return;
    }
    uint32_t gap = 0;
    GetPosting(p, &gap, &tf);
    image += gap;
  }
};

// t(tf)^2 without rounding through sqrt: tf for sqrt-tf, tf^2 otherwise.
inline double TermWeightSquared(bool sqrt_tf, uint32_t tf) {
  return sqrt_tf ? static_cast<double>(tf) : static_cast<double>(tf) * static_cast<double>(tf);
}

}  // namespace

// One immutable run of postings for the images in [first_image, end_image).
struct InvertedFile::Segment {
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
  std::vector<uint32_t> Words() const {
    if (!dense) return words;
    std::vector<uint32_t> out;
    for (size_t w = 0; w + 1 < offsets.size(); ++w) {
      if (offsets[w + 1] > offsets[w]) out.push_back(static_cast<uint32_t>(w));
    }
    return out;
  }

  uint64_t MemoryBytes() const {
    return (owner ? mapped.size() : bytes.capacity()) + offsets.capacity() * sizeof(uint64_t) + words.capacity() * sizeof(uint32_t) +
           sizeof(*this);
  }

  // Switches to the dense layout when at least 1/8 of the vocabulary has postings here (the dense table
  // then costs at most 2x the sparse one and saves the binary search).
  void ChooseLayout(size_t vocabulary_size) {
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
};

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
    : vocabulary_size_(vocabulary_size), options_(options) {
  const auto error = options.Check();
  OXBOW_CHECK(!error, "invalid TfIdfOptions");
  OXBOW_CHECK(vocabulary_size > 0 && vocabulary_size < (uint64_t{1} << 32));
  CowArray<uint32_t>::Editor(&df_).Resize(vocabulary_size, 0);
  stats_df_ = df_;
  for (uint32_t tf = 0; tf < term_weight_.size(); ++tf) {
    term_weight_[tf] = options.sqrt_tf ? static_cast<float>(std::sqrt(static_cast<double>(tf)))
                                       : static_cast<float>(tf);
  }
}

float InvertedFile::TermWeight(uint32_t tf) const {
  if (tf < term_weight_.size()) return term_weight_[tf];
  return options_.sqrt_tf ? static_cast<float>(std::sqrt(static_cast<double>(tf))) : static_cast<float>(tf);
}

uint32_t InvertedFile::num_numbers() const { return static_cast<uint32_t>(images_.size()); }

uint32_t InvertedFile::DocumentFrequency(uint32_t word) const {
  OXBOW_CHECK(word < vocabulary_size_);
  return df_[word];
}

double InvertedFile::Idf(uint32_t word) const {
  OXBOW_CHECK(word < vocabulary_size_);
  const uint32_t df = stats_df_[word];
  if (df == 0) return std::numeric_limits<double>::infinity();
  return std::log(static_cast<double>(stats_num_live_) / static_cast<double>(df));
}

std::shared_ptr<const std::vector<double>> InvertedFile::IdfSquaredTable() const {
  IdfTable& table = *idf_table_;
  std::call_once(table.once, [&] {
    auto squared = std::make_shared<std::vector<double>>(vocabulary_size_, 0.0);
    for (size_t w = 0; w < vocabulary_size_; ++w) {
      const double idf = Idf(static_cast<uint32_t>(w));
      if (std::isfinite(idf)) (*squared)[w] = idf * idf;
    }
    table.squared = std::move(squared);
  });
  return table.squared;
}

std::shared_ptr<const std::vector<double>> InvertedFile::LogDfTable() const {
  IdfTable& table = *idf_table_;
  std::call_once(table.log_df_once, [&] {
    auto log_df = std::make_shared<std::vector<double>>(vocabulary_size_, 0.0);
    for (size_t w = 0; w < vocabulary_size_; ++w) {
      if (stats_df_[w] != 0) (*log_df)[w] = std::log(static_cast<double>(stats_df_[w]));
    }
    table.log_df = std::move(log_df);
  });
  return table.log_df;
}

bool InvertedFile::IsLive(uint32_t image) const { return image < images_.size() && images_[image].live != 0; }

double InvertedFile::Norm(uint32_t image) const { return image < norms_.size() ? norms_[image] : 0.0; }

double InvertedFile::ComputeNorm(const ImageState& s) const {
  if (s.live == 0) return 0;
  const double l = std::log(static_cast<double>(stats_num_live_));
  const double sq = l * l * s.a - 2 * l * s.b + s.c;
  return sq > 0 ? std::sqrt(sq) : 0.0;
}

void InvertedFile::SetNorms(std::span<const uint32_t> images) {
  CowArray<double>::Editor editor(&norms_);
  if (norms_.size() < images_.size()) editor.Resize(images_.size(), 0.0);
  for (const uint32_t n : images) editor.Mutable(n) = ComputeNorm(images_[n]);
}

void InvertedFile::RecomputeNorms() {
  CowArray<double> fresh;
  CowArray<double>::Editor editor(&fresh);
  editor.Resize(images_.size(), 0.0);
  for (size_t n = 0; n < images_.size(); ++n) editor.Mutable(n) = ComputeNorm(images_[n]);
  norms_ = std::move(fresh);
}

InvertedFile InvertedFile::Build(size_t vocabulary_size, const TfIdfOptions& options, uint32_t num_numbers,
                                 const std::function<bool(uint32_t, BagOfWords*)>& bag_of, int num_threads) {
  InvertedFile out(vocabulary_size, options);
  const int threads = ResolveThreadCount(num_threads);
  constexpr uint32_t kBatch = 4096;
  std::vector<BagOfWords> bags(kBatch);
  std::vector<uint8_t> present(kBatch);

  // Runs fn(image, bag) for every image in order, producing bags in parallel batches.
  auto for_each_bag = [&](const std::function<void(uint32_t, const BagOfWords&)>& fn) {
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
  };

  // Pass 1: document frequencies and the coded size of every word's list.
  std::vector<uint32_t> last(vocabulary_size, 0);
  std::vector<uint64_t> offsets(vocabulary_size + 1, 0);
  std::vector<uint32_t> df(vocabulary_size, 0);
  uint64_t live = 0;
  for_each_bag([&](uint32_t image, const BagOfWords& bag) {
    OXBOW_CHECK(bag.words.size() == bag.counts.size());
    for (size_t k = 0; k < bag.words.size(); ++k) {
      const uint32_t w = bag.words[k];
      OXBOW_CHECK(w < vocabulary_size, "word id outside the vocabulary");
      OXBOW_CHECK(bag.counts[k] >= 1 && (k == 0 || bag.words[k - 1] < w), "bag not sorted/distinct");
      offsets[w + 1] += PostingSize(image - last[w], bag.counts[k]);
      last[w] = image;
      ++df[w];
    }
    ++live;
  });
  for (size_t w = 0; w < vocabulary_size; ++w) offsets[w + 1] += offsets[w];

  auto segment = std::make_shared<Segment>();
  segment->first_image = 0;
  segment->end_image = num_numbers;
  segment->bytes.resize(offsets[vocabulary_size]);
  std::vector<double> log_df(vocabulary_size, 0);
  for (size_t w = 0; w < vocabulary_size; ++w) log_df[w] = df[w] ? std::log(static_cast<double>(df[w])) : 0;

  // Pass 2: postings and per-image norm sums.
  std::vector<uint64_t> cursor(offsets.begin(), offsets.end() - 1);
  std::fill(last.begin(), last.end(), 0);
  CowArray<ImageState>::Editor images(&out.images_);
  images.Resize(num_numbers);
  uint64_t postings = 0, features = 0;
  for_each_bag([&](uint32_t image, const BagOfWords& bag) {
    ImageState& s = images.Mutable(image);
    for (size_t k = 0; k < bag.words.size(); ++k) {
      const uint32_t w = bag.words[k], tf = bag.counts[k];
      uint8_t* p = segment->bytes.data() + cursor[w];
      cursor[w] = static_cast<uint64_t>(PutPosting(p, image - last[w], tf) - segment->bytes.data());
      last[w] = image;
      const double t2 = TermWeightSquared(options.sqrt_tf, tf);
      s.a += t2;
      s.b += t2 * log_df[w];
      s.c += t2 * log_df[w] * log_df[w];
      s.features += tf;
    }
    s.live = 1;
    postings += bag.words.size();
    features += s.features;
  });
  for (size_t w = 0; w < vocabulary_size; ++w) OXBOW_CHECK(cursor[w] == offsets[w + 1], "bag_of changed between passes");

  segment->dense = true;
  segment->offsets = std::move(offsets);
  segment->num_postings = postings;
  {
    CowArray<uint32_t>::Editor dfe(&out.df_);
    for (size_t w = 0; w < vocabulary_size; ++w) {
      if (df[w]) dfe.Mutable(w) = df[w];
    }
  }
  if (postings > 0) out.segments_.push_back(std::move(segment));
  out.stats_df_ = out.df_;
  out.stats_num_live_ = live;
  out.num_live_ = live;
  out.num_live_features_ = features;
  out.num_postings_ = postings;
  out.RecomputeNorms();
  return out;
}

void InvertedFile::SetSums(const BagOfWords& bag, std::span<const double> log_df, ImageState* s) const {
  s->a = s->b = s->c = 0;
  for (size_t k = 0; k < bag.words.size(); ++k) {
    const uint32_t df = stats_df_[bag.words[k]];
    if (df == 0) continue;  // unknown to the statistics until the next refresh
    const double l = log_df[bag.words[k]];
    const double t2 = TermWeightSquared(options_.sqrt_tf, bag.counts[k]);
    s->a += t2;
    s->b += t2 * l;
    s->c += t2 * l * l;
  }
}

InvertedFile InvertedFile::WithRefreshedStatistics(int num_threads) const {
  InvertedFile next = *this;
  next.RefreshStatistics(num_threads);
  return next;
}

InvertedFile InvertedFile::WithPinnedStatistics(uint64_t num_images, std::span<const uint32_t> document_frequency,
                                                int num_threads) const {
  OXBOW_CHECK(document_frequency.size() == vocabulary_size_, "one document frequency per word");
  InvertedFile next = *this;
  {
    CowArray<uint32_t>::Editor editor(&next.stats_df_);
    for (size_t w = 0; w < vocabulary_size_; ++w) editor.Mutable(w) = document_frequency[w];
  }
  next.stats_num_live_ = num_images;
  next.changes_since_refresh_ = 0;
  next.pinned_statistics_ = true;
  next.RecomputeSums(num_threads);
  return next;
}

void InvertedFile::RefreshIfDue() {
  if (changes_since_refresh_ == 0 || pinned_statistics_) return;
  if (num_postings_ <= options_.exact_statistics_postings ||
      static_cast<double>(changes_since_refresh_) >
          options_.statistics_refresh_fraction * static_cast<double>(stats_num_live_)) {
    RefreshStatistics(0);
  }
}

// Every live image's sums from the postings. Words are dealt round-robin, in chunks, to a fixed number
// of groups with their own partial sums, added in group order at the end: the floating-point order,
// hence the result, is the same for any thread count. Segments hold disjoint, ascending image ranges and
// an image's postings all lie in one segment, so each group walks the segments in turn and, within a
// segment, its images in blocks small enough for the partial sums to stay in cache (one cursor per word
// of the segment carries on where the previous block stopped): a posting list's images are far apart, so
// unblocked updates would miss the cache at almost every posting. Only the cursors of the segment that
// holds a block are visited for it, and an image gets its terms in word order.
void InvertedFile::RefreshStatistics(int num_threads) {
  stats_df_ = df_;
  stats_num_live_ = num_live_;
  changes_since_refresh_ = 0;
  pinned_statistics_ = false;
  RecomputeSums(num_threads);
}

void InvertedFile::RecomputeSums(int num_threads) {
  idf_table_ = std::make_shared<IdfTable>();  // called when the statistics changed: a new idf^2 table
  const size_t num_images = images_.size();
  std::vector<uint8_t> live(num_images);
  for (size_t i = 0; i < num_images; ++i) live[i] = images_[i].live != 0 ? 1 : 0;
  // The new statistics' log n_w, kept in the new table for the batches added after this refresh.
  const std::shared_ptr<const std::vector<double>> log_df_table = LogDfTable();
  const std::vector<double>& log_df = *log_df_table;
  constexpr size_t kWordsPerChunk = 4096;
  const size_t num_chunks = (vocabulary_size_ + kWordsPerChunk - 1) / kWordsPerChunk;
  constexpr size_t kGroups = 4;
  constexpr size_t kImagesPerBlock = 16384;  // 16384 x 24 bytes of sums per group
  struct Sum {
    double a = 0, b = 0, c = 0;
  };
  struct Cursor : PostingCursor {
    double log_df = 0;
  };
  std::vector<std::vector<Sum>> partial(kGroups);
  ParallelFor(kGroups, num_threads, 1, [&](size_t g0, size_t g1, int) {
    for (size_t g = g0; g < g1; ++g) {
      std::vector<Sum>& sums = partial[g];
      sums.assign(num_images, Sum{});
      std::vector<Cursor> cursors;  // of one segment, in word order
      for (const auto& segment : segments_) {
        cursors.clear();
        for (size_t chunk = g; chunk < num_chunks; chunk += kGroups) {
          const size_t w_end = std::min(vocabulary_size_, (chunk + 1) * kWordsPerChunk);
          for (size_t w = chunk * kWordsPerChunk; w < w_end; ++w) {
            if (stats_df_[w] == 0) continue;
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
              const double t2 = TermWeightSquared(options_.sqrt_tf, c.tf);
              Sum& sum = sums[c.image];
              sum.a += t2;
              sum.b += t2 * c.log_df;
              sum.c += t2 * c.log_df * c.log_df;
            }
          }
        }
      }
    }
  });
  CowArray<ImageState>::Editor editor(&images_);
  for (size_t i = 0; i < num_images; ++i) {
    if (live[i] == 0) continue;
    ImageState& s = editor.Mutable(i);
    s.a = s.b = s.c = 0;
    for (const std::vector<Sum>& sums : partial) {
      s.a += sums[i].a;
      s.b += sums[i].b;
      s.c += sums[i].c;
    }
  }
  RecomputeNorms();
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

  // The new images' own sums (with the statistics of the last refresh) and their segment.
  CowArray<ImageState>::Editor editor(&next.images_);
  editor.Resize(images.back() + size_t{1});
  uint64_t total = 0;
  const std::shared_ptr<const std::vector<double>> log_df = next.LogDfTable();
  for (size_t i = 0; i < images.size(); ++i) {
    ImageState& s = editor.Mutable(images[i]);
    s = ImageState{};
    next.SetSums(*bags[i], *log_df, &s);
    for (const uint32_t tf : bags[i]->counts) s.features += tf;
    s.live = 1;
    ++next.num_live_;
    next.num_live_features_ += s.features;
    total += bags[i]->words.size();
  }
  next.SetNorms(images);
  next.changes_since_refresh_ += images.size();
  auto segment = std::make_shared<Segment>();
  segment->first_image = images.front();
  segment->end_image = images.back() + 1;
  segment->num_postings = total;
  if (total * 4 >= vocabulary_size_) {
    // A large batch next to the vocabulary (bulk ingest): as Build, one pass for the coded size of every
    // word's list, one that writes the postings in place; O(postings + words), no intermediate copy.
    std::vector<uint64_t> offsets(vocabulary_size_ + 1, 0);
    std::vector<uint32_t> last(vocabulary_size_, segment->first_image);
    // Numbers closer together than the escape (a batch's are consecutive): no gap takes it, and the
    // sizes need no previous image per word (half the random accesses of this pass).
    const bool short_gaps = images.back() - images.front() < kGapEscape;
    for (size_t i = 0; i < images.size(); ++i) {
      for (size_t k = 0; k < bags[i]->words.size(); ++k) {
        const uint32_t w = bags[i]->words[k];
        if (short_gaps) {
          offsets[w + 1] += PostingSize(0, bags[i]->counts[k]);
        } else {
          offsets[w + 1] += PostingSize(images[i] - last[w], bags[i]->counts[k]);
          last[w] = images[i];
        }
      }
    }
    size_t distinct = 0;
    for (size_t w = 0; w < vocabulary_size_; ++w) {
      distinct += offsets[w + 1] > 0 ? 1 : 0;
      offsets[w + 1] += offsets[w];
    }
    segment->bytes.resize(offsets[vocabulary_size_]);
    std::vector<uint64_t> cursor(offsets.begin(), offsets.end() - 1);
    std::fill(last.begin(), last.end(), segment->first_image);
    for (size_t i = 0; i < images.size(); ++i) {
      for (size_t k = 0; k < bags[i]->words.size(); ++k) {
        const uint32_t w = bags[i]->words[k];
        uint8_t* p = segment->bytes.data() + cursor[w];
        cursor[w] = static_cast<uint64_t>(PutPosting(p, images[i] - last[w], bags[i]->counts[k]) - segment->bytes.data());
        last[w] = images[i];
      }
    }
    if (distinct * 8 >= vocabulary_size_) {
      segment->offsets = std::move(offsets);
      segment->dense = true;
    } else {  // the sparse layout, as ChooseLayout would leave it
      segment->words.reserve(distinct);
      segment->offsets.reserve(distinct + 1);
      for (size_t w = 0; w < vocabulary_size_; ++w) {
        if (offsets[w + 1] == offsets[w]) continue;
        segment->words.push_back(static_cast<uint32_t>(w));
        segment->offsets.push_back(offsets[w]);
      }
      segment->offsets.push_back(offsets[vocabulary_size_]);
    }
  } else {
    // Few postings (single adds): sorted (word, image) triples, so that no table has a vocabulary's size.
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
    segment->ChooseLayout(vocabulary_size_);
  }
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
    // Merge segments [first, end): word by word, in image order, dropping removed images.
    std::vector<uint32_t> words;
    // An upper bound of the merged size: each list's first posting from a segment may take the 4-byte
    // escape of a longer gap; every other posting keeps its size or drops out.
    uint64_t bound = 0;
    for (size_t i = first; i < segments_.size(); ++i) {
      const auto w = segments_[i]->Words();
      words.insert(words.end(), w.begin(), w.end());
      bound += segments_[i]->size() + 4 * w.size();
    }
    std::sort(words.begin(), words.end());
    words.erase(std::unique(words.begin(), words.end()), words.end());
    auto merged = std::make_shared<Segment>();
    merged->first_image = segments_[first]->first_image;
    merged->end_image = segments_.back()->end_image;
    uint64_t old_postings = 0;
    for (size_t i = first; i < segments_.size(); ++i) old_postings += segments_[i]->num_postings;
    // Reserved at once, in huge pages where large: growing it posting by posting reallocated and copied
    // it about twice over, into fresh 4 KiB pages each taking a fault (dear in a VM).
    merged->bytes.reserve(bound);
    AdviseHugePages(merged->bytes.data(), bound);
    // With no removed image's postings anywhere, a word's merged list is its lists in these segments one
    // after another: only each list's first posting is coded again (its gap counts from its own
    // segment's first image), the rest is copied as it is, its gaps decoded only to find its last
    // image. The same bytes as decoding and coding every posting, without reading every image's state
    // (a cache miss per posting at a million images).
    const bool all_live = num_dead_postings_ == 0;
    for (const uint32_t w : words) {
      const size_t begin = merged->bytes.size();
      uint32_t last = merged->first_image;
      for (size_t i = first; i < segments_.size(); ++i) {
        if (!all_live) {
          segments_[i]->ForEach(w, [&](uint32_t image, uint32_t tf) {
            if (images_[image].live == 0) return;
            PutPosting(&merged->bytes, image - last, tf);
            last = image;
            ++merged->num_postings;
          });
          continue;
        }
        auto [p, end] = segments_[i]->List(w);
        if (p == end) continue;
        uint32_t gap = 0, tf = 1;
        GetPosting(p, &gap, &tf);
        uint32_t image = segments_[i]->first_image + gap;
        PutPosting(&merged->bytes, image - last, tf);
        merged->bytes.insert(merged->bytes.end(), p, end);
        uint64_t count = 1;
        for (; p < end; ++count) {
          GetPosting(p, &gap, &tf);
          image += gap;
        }
        last = image;
        merged->num_postings += count;
      }
      if (merged->bytes.size() > begin) {
        merged->words.push_back(w);
        merged->offsets.push_back(begin);
      }
    }
    merged->offsets.push_back(merged->bytes.size());
    // Pages of the reserve never written take no memory; shrink only when removed images left much.
    if (merged->bytes.capacity() - merged->bytes.size() > merged->bytes.size() / 8 + 4096) merged->bytes.shrink_to_fit();
    merged->ChooseLayout(vocabulary_size_);
    const uint64_t dropped = old_postings - merged->num_postings;
    num_postings_ -= dropped;
    num_dead_postings_ -= std::min(num_dead_postings_, dropped);
    segments_.resize(first);
    if (merged->num_postings > 0) segments_.push_back(std::move(merged));
    if (everything) return;
  }
}

std::vector<QueryTerm> InvertedFile::QueryVector(const BagOfWords& bag) const {
  std::vector<float> tf(bag.counts.size());
  for (size_t k = 0; k < tf.size(); ++k) tf[k] = static_cast<float>(bag.counts[k]);
  return QueryVector(bag.words, tf);
}

std::vector<QueryTerm> InvertedFile::QueryVector(std::span<const uint32_t> words, std::span<const float> tf) const {
  OXBOW_CHECK(words.size() == tf.size());
  std::vector<QueryTerm> out;
  if (num_live_ == 0 || stats_num_live_ == 0) return out;
  out = WeightedQueryVector(words, tf, /*use_stop_list=*/true);
  // A stop list must not make an image unfindable: when it would drop every word of the query (a small
  // vocabulary over many images), the query is scored with all its words.
  if (out.empty() && options_.max_document_frequency < 1) out = WeightedQueryVector(words, tf, false);
  return out;
}

std::vector<QueryTerm> InvertedFile::WeightedQueryVector(std::span<const uint32_t> words, std::span<const float> tf,
                                                         bool use_stop_list) const {
  std::vector<QueryTerm> out;
  const double n = static_cast<double>(stats_num_live_);
  double norm_sq = 0;
  std::vector<double> weights;
  for (size_t k = 0; k < words.size(); ++k) {
    const uint32_t w = words[k];
    if (w >= vocabulary_size_ || !(tf[k] > 0)) continue;
    const uint32_t df = stats_df_[w];
    if (df == 0) continue;
    if (use_stop_list && df > options_.stop_list_min_images &&
        static_cast<double>(df) > options_.max_document_frequency * n) {
      continue;
    }
    const double idf = std::log(n / static_cast<double>(df));
    if (!(idf > 0)) continue;
    const double t = options_.sqrt_tf ? std::sqrt(static_cast<double>(tf[k])) : static_cast<double>(tf[k]);
    const double v = t * idf;
    out.push_back({w, 0});
    weights.push_back(v);
    norm_sq += v * v;
  }
  if (norm_sq <= 0) return {};
  const double inv = 1.0 / std::sqrt(norm_sq);
  for (size_t i = 0; i < out.size(); ++i) out[i].weight = static_cast<float>(weights[i] * inv);
  return out;
}

std::vector<QueryTerm> StrongestTerms(std::vector<QueryTerm> terms, size_t n) {
  if (terms.size() <= n) return terms;
  std::nth_element(terms.begin(), terms.begin() + static_cast<std::ptrdiff_t>(n), terms.end(),
                   [](const QueryTerm& x, const QueryTerm& y) {
                     return x.weight != y.weight ? x.weight > y.weight : x.word < y.word;
                   });
  terms.resize(n);
  std::sort(terms.begin(), terms.end(), [](const QueryTerm& x, const QueryTerm& y) { return x.word < y.word; });
  return terms;
}

float InvertedFile::ScoringWeight(const QueryTerm& term) const {
  if (term.word >= vocabulary_size_ || term.weight == 0 || stats_num_live_ == 0) return 0;
  const uint32_t df = stats_df_[term.word];
  if (df == 0) return 0;
  return static_cast<float>(static_cast<double>(term.weight) *
                            std::log(static_cast<double>(stats_num_live_) / static_cast<double>(df)));
}

std::vector<size_t> InvertedFile::ScoreGroups(std::span<const QueryTerm> query) const {
  uint64_t total = 0;  // postings the query scans, estimated by the document frequencies
  std::vector<uint64_t> cost(query.size(), 0);
  for (size_t i = 0; i < query.size(); ++i) {
    cost[i] = TermCost(query[i]);
    total += cost[i];
  }
  // Rounded up: a query within the default posting budget (4M) scans up to 4M postings, and rounded
  // down it stayed in one group, so on one core, however many the search had.
  const uint64_t wanted = (total + kPostingsPerScoreGroup - 1) / kPostingsPerScoreGroup;
  const size_t groups = static_cast<size_t>(std::clamp<uint64_t>(wanted, 1, kMaxScoreGroups));
  std::vector<size_t> starts = {0};
  uint64_t sum = 0;
  for (size_t i = 0; i < query.size() && starts.size() < groups; ++i) {
    sum += cost[i];
    if (sum * groups >= total * starts.size()) starts.push_back(i + 1);
  }
  starts.push_back(query.size());
  return starts;
}

uint64_t InvertedFile::TermCost(const QueryTerm& term) const {
  return ScoringWeight(term) != 0 ? stats_df_[term.word] : 0;
}

uint64_t InvertedFile::ScannedPostings(std::span<const QueryTerm> query) const {
  uint64_t total = 0;
  for (const QueryTerm& term : query) total += TermCost(term);
  return total;
}

std::vector<QueryTerm> InvertedFile::WithinPostingBudget(std::span<const QueryTerm> query,
                                                         uint64_t max_postings) const {
  if (max_postings == 0 || ScannedPostings(query) <= max_postings) return {query.begin(), query.end()};
  std::vector<std::pair<float, size_t>> order;  // (per-posting contribution, position), scored terms only
  order.reserve(query.size());
  for (size_t i = 0; i < query.size(); ++i) {
    if (const float w = ScoringWeight(query[i]); w != 0) order.emplace_back(std::abs(w), i);
  }
  std::sort(order.begin(), order.end(), [&](const auto& x, const auto& y) {
    return x.first != y.first ? x.first > y.first : query[x.second].word < query[y.second].word;
  });
  std::vector<uint8_t> keep(query.size(), 0);
  uint64_t used = 0;
  for (size_t k = 0; k < order.size(); ++k) {
    const uint64_t cost = TermCost(query[order[k].second]);
    if (k > 0 && used + cost > max_postings) continue;
    used += cost;
    keep[order[k].second] = 1;
  }
  std::vector<QueryTerm> out;
  for (size_t i = 0; i < query.size(); ++i)
    if (keep[i]) out.push_back(query[i]);
  return out;
}

namespace {
// Images per block of Score's accumulation: 64 Ki floats (256 KiB), well inside a core's L2 cache.
constexpr uint64_t kScoreBlock = 65536;
}  // namespace

std::vector<ScoredImage> InvertedFile::Score(std::span<const QueryTerm> query, size_t max_results,
                                             ScoreScratch* scratch, uint64_t* candidates,
                                             const std::vector<uint8_t>* allowed, int num_threads,
                                             uint64_t max_postings) const {
  OXBOW_CHECK(scratch != nullptr);
  if (candidates) *candidates = 0;
  if (num_live_ == 0 || stats_num_live_ == 0 || max_results == 0) return {};
  std::vector<QueryTerm> within_budget;
  if (max_postings != 0) {
    within_budget = WithinPostingBudget(query, max_postings);
    query = within_budget;
  }

  const std::vector<size_t> starts = ScoreGroups(query);
  const size_t num_groups = starts.size() - 1;
  for (size_t g = 0; g < num_groups; ++g) {
    std::vector<float>& acc = scratch->accumulators[g];
    if (acc.size() >= images_.size()) continue;
    if (acc.capacity() < images_.size()) {
      // Room for 1/16 more images, so that adds between searches do not move (and fault in again) 4 MB
      // at a million images on every search; in huge pages where the system gives them. The array is all
      // zeros between searches, so a fresh one replaces it.
      std::vector<float> grown;
      grown.reserve(images_.size() + images_.size() / 16);
      AdviseHugePages(reinterpret_cast<uint8_t*>(grown.data()), grown.capacity() * sizeof(float));
      acc.swap(grown);
    }
    acc.resize(images_.size(), 0.0f);
  }
  // Each group adds its terms' postings segment by segment, and within a segment block of images by
  // block (kScoreBlock images, every term's cursor advanced to the block's end before the next block),
  // so that the accumulators written stay in the core's cache instead of spreading every list's writes
  // over the whole array (4 MB at a million images). An image's postings all lie in one segment and are
  // still added in the group's term order, so every sum is the same float as with the lists read whole.
  ParallelFor(num_groups, num_threads, 1, [&](size_t g0, size_t g1, int) {
    struct Cursor : PostingCursor {
      float weight = 0;
    };
    std::vector<Cursor> cursors;
    for (size_t g = g0; g < g1; ++g) {
      float* a = scratch->accumulators[g].data();
      cursors.reserve(starts[g + 1] - starts[g]);
      for (const auto& segment : segments_) {
        cursors.clear();
        for (size_t q = starts[g]; q < starts[g + 1]; ++q) {
          const float weight = ScoringWeight(query[q]);
          if (weight == 0) continue;
          auto [p, end] = segment->List(query[q].word);
          if (p == end) continue;
          Cursor c{{p, end, segment->first_image}, weight};
          c.Advance();
          cursors.push_back(c);
        }
        for (uint64_t block = segment->first_image; block < segment->end_image && !cursors.empty();
             block += kScoreBlock) {
          const auto limit = static_cast<uint32_t>(std::min<uint64_t>(block + kScoreBlock, segment->end_image));
          for (Cursor& c : cursors) {
            // Hot loop: one 16-bit unit per posting, one multiply-add.
            for (; c.image < limit; c.Advance()) a[c.image] += c.tf == 1 ? c.weight : c.weight * TermWeight(c.tf);
          }
        }
      }
    }
  });

  // Normalise, select the best max_results, and re-zero the accumulators: on num_threads threads over
  // ranges of image numbers, each keeping its own best (a min-heap on (score, -image)); the ranges' lists
  // are then merged. The order is total (score, then image number), so the result does not depend on
  // the split. An image's cosine is only computed when its dot product can beat the range's worst kept
  // one: v^2 < worst^2 |v(d)|^2 (1 - 1e-6)^2 means v / |v(d)| < worst (1 - 1e-6), below worst even after
  // rounding to float (relative error 2^-24), so most of a million images cost no square root.
  auto better = [](const ScoredImage& x, const ScoredImage& y) {
    return x.score != y.score ? x.score > y.score : x.image < y.image;
  };
  const size_t end = images_.size();
  constexpr size_t kChunk = CowArray<ImageState>::kChunk;
  static_assert(CowArray<double>::kChunk == kChunk);
  const size_t num_chunks = (end + kChunk - 1) / kChunk;
  const size_t num_parts = std::min<size_t>(num_chunks, 16);
  std::vector<std::vector<ScoredImage>> kept(num_parts);
  std::vector<uint64_t> touched_in(num_parts, 0);
  constexpr double kMargin = (1 - 1e-6) * (1 - 1e-6);
  ParallelFor(num_parts, num_threads, 1, [&](size_t p0, size_t p1, int) {
    for (size_t part = p0; part < p1; ++part) {
      std::vector<ScoredImage>& heap = kept[part];  // a heap under `better`: front = worst kept
      heap.clear();
      uint64_t touched = 0;
      double bar = 0;  // worst kept score^2 x kMargin, once the heap is full and its worst is positive
      bool full = false;
      std::array<float, kChunk> sum;  // this chunk's dot products: the groups added in group order
      for (size_t chunk = num_chunks * part / num_parts; chunk < num_chunks * (part + 1) / num_parts; ++chunk) {
        const size_t chunk_begin = chunk * kChunk, chunk_end = std::min(end, chunk_begin + kChunk);
        const size_t len = chunk_end - chunk_begin;
        float* first = scratch->accumulators[0].data() + chunk_begin;
        std::copy(first, first + len, sum.begin());
        std::fill(first, first + len, 0.0f);
        for (size_t g = 1; g < num_groups; ++g) {
          float* a = scratch->accumulators[g].data() + chunk_begin;
          for (size_t k = 0; k < len; ++k) sum[k] += a[k];
          std::fill(a, a + len, 0.0f);
        }
        const double* norms = &norms_[chunk_begin];  // a chunk of norms_ is contiguous
        for (size_t i = chunk_begin; i < chunk_end; ++i) {
          const float v = sum[i - chunk_begin];
          if (v == 0) continue;
          const double norm = norms[i - chunk_begin];  // 0: not live, or a zero vector
          if (!(norm > 0)) continue;
          if (allowed != nullptr && (i >= allowed->size() || (*allowed)[i] == 0)) continue;
          ++touched;
          const double dv = static_cast<double>(v);
          if (full && (dv <= 0 || dv * dv < bar * (norm * norm))) continue;  // cannot enter (see above)
          const ScoredImage cand{static_cast<uint32_t>(i), static_cast<float>(dv / norm)};
          if (heap.size() < max_results) {
            heap.push_back(cand);
            std::push_heap(heap.begin(), heap.end(), better);
          } else if (better(cand, heap.front())) {
            std::pop_heap(heap.begin(), heap.end(), better);
            heap.back() = cand;
            std::push_heap(heap.begin(), heap.end(), better);
          } else {
            continue;
          }
          if (heap.size() == max_results && heap.front().score > 0) {
            full = true;
            bar = static_cast<double>(heap.front().score) * static_cast<double>(heap.front().score) * kMargin;
          }
        }
      }
      touched_in[part] = touched;
    }
  });
  uint64_t touched = 0;
  std::vector<ScoredImage> out;
  for (size_t part = 0; part < num_parts; ++part) {
    touched += touched_in[part];
    out.insert(out.end(), kept[part].begin(), kept[part].end());
  }
  const size_t n = std::min(out.size(), max_results);
  std::partial_sort(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(n), out.end(), better);
  out.resize(n);
  if (candidates) *candidates = touched;
  return out;
}

namespace {

constexpr char kFileMagic[4] = {'O', 'X', 'I', 'F'};
// 1: postings coded as varints (gap << 1 | tf > 1); read and re-coded at load (RecodeFormat1).
// 2: postings in 16-bit units (PutPosting), every segment in the file (Serialize).
// 3: a head (SerializeHead) naming a file per segment, each the segment alone after its own header
//    (SerializeSegment: magic "OXIS", the same version, byte-order mark and vocabulary size).
constexpr uint32_t kFileVersion = 2;
constexpr uint32_t kHeadVersion = 3;
constexpr uint32_t kOldestReadableVersion = 1;
constexpr char kSegmentMagic[4] = {'O', 'X', 'I', 'S'};
constexpr uint32_t kByteOrderMark = 0x01020304;

template <typename T>
std::span<const uint8_t> AsBytes(const T& value) {
  return {reinterpret_cast<const uint8_t*>(&value), sizeof(T)};
}

template <typename T>
std::span<const uint8_t> AsBytes(std::span<const T> values) {
  return {reinterpret_cast<const uint8_t*>(values.data()), values.size_bytes()};
}

// Bounds-checked reads of the serialised form; a short read sets `ok` to false and yields zeros.
struct FileReader {
  std::span<const uint8_t> bytes;
  size_t at = 0;
  bool ok = true;

  template <typename T>
  T Get() {
    T value{};
    Copy(&value, sizeof(T));
    return value;
  }
  template <typename T>
  std::vector<T> GetVector(uint64_t max_count) {
    const auto count = Get<uint64_t>();
    if (!ok || count > max_count || count > (bytes.size() - at) / sizeof(T)) {
      ok = false;
      return {};
    }
    std::vector<T> out(count);
    Copy(out.data(), count * sizeof(T));
    return out;
  }
  // The next `count` bytes in place (a view of `bytes`), after their u64 count.
  std::span<const uint8_t> View(uint64_t max_count) {
    const auto count = Get<uint64_t>();
    if (!ok || count > max_count || count > bytes.size() - at) {
      ok = false;
      return {};
    }
    const std::span<const uint8_t> out = bytes.subspan(at, count);
    at += count;
    return out;
  }
  void Copy(void* out, size_t n) {
    if (!ok || bytes.size() - at < n) {
      ok = false;
      return;
    }
    if (n == 0) return;  // an empty vector's data() may be null, which memcpy must not get
    std::memcpy(out, bytes.data() + at, n);
    at += n;
  }
};

}  // namespace

// A segment read from a version-1 file, its postings re-coded from varints into 16-bit units (same
// words, layout and postings). Bounds-checked, and the posting count must match the segment's; lists in
// parallel (two passes: sizes, then contents), so that loading a large version-1 file stays fast.
Result<std::shared_ptr<InvertedFile::Segment>> InvertedFile::RecodeFormat1(const Segment& old) {
  const size_t lists = old.offsets.size() - 1;
  // Decodes list k of `old`, calling fn(gap, tf) per posting; false on a malformed list.
  const auto decode = [&old](size_t k, auto&& fn) {
    const uint8_t* p = old.data() + old.offsets[k];
    const uint8_t* end = old.data() + old.offsets[k + 1];
    const auto varint = [&](uint64_t* v) {
      *v = 0;
      for (int shift = 0; shift < 64 && p < end; shift += 7) {
        const uint8_t b = *p++;
        *v |= uint64_t{b & 127u} << shift;
        if (b < 128) return true;
      }
      return false;
    };
    while (p < end) {
      uint64_t v = 0, extra = 0;
      if (!varint(&v) || (v >> 1) > std::numeric_limits<uint32_t>::max()) return false;
      if ((v & 1) != 0 && (!varint(&extra) || extra > std::numeric_limits<uint32_t>::max() - 2)) return false;
      fn(static_cast<uint32_t>(v >> 1), (v & 1) != 0 ? static_cast<uint32_t>(extra) + 2 : 1u);
    }
    return true;
  };
  std::vector<uint64_t> offsets(lists + 1, 0);
  std::vector<uint64_t> counts(lists, 0);
  std::atomic<bool> ok{true};
  ParallelFor(lists, 0, 256, [&](size_t begin, size_t end, int) {
    for (size_t k = begin; k < end; ++k) {
      uint64_t size = 0, n = 0;
      if (!decode(k, [&](uint32_t gap, uint32_t tf) {
            size += PostingSize(gap, tf);
            ++n;
          })) {
        ok = false;
      }
      offsets[k + 1] = size;
      counts[k] = n;
    }
  });
  uint64_t postings = 0;
  for (size_t k = 0; k < lists; ++k) {
    offsets[k + 1] += offsets[k];
    postings += counts[k];
  }
  if (!ok || postings != old.num_postings) return Fail(ErrorCode::kCorruptData, "malformed version-1 postings");
  auto out = std::make_shared<Segment>();
  out->first_image = old.first_image;
  out->end_image = old.end_image;
  out->dense = old.dense;
  out->words = old.words;
  out->num_postings = old.num_postings;
  out->bytes.resize(offsets.back());
  ParallelFor(lists, 0, 256, [&](size_t begin, size_t end, int) {
    for (size_t k = begin; k < end; ++k) {
      uint8_t* q = out->bytes.data() + offsets[k];
      decode(k, [&](uint32_t gap, uint32_t tf) { q = PutPosting(q, gap, tf); });
    }
  });
  out->offsets = std::move(offsets);
  return out;
}

void InvertedFile::SerializeHead(uint32_t version, const Writer& write) const {
  write(AsBytes(kFileMagic));
  write(AsBytes(version));
  write(AsBytes(kByteOrderMark));
  write(AsBytes(uint64_t{vocabulary_size_}));
  write(AsBytes(uint8_t{options_.sqrt_tf ? uint8_t{1} : uint8_t{0}}));
  for (const uint64_t v : {stats_num_live_, changes_since_refresh_, num_live_, num_live_features_, num_postings_,
                           num_dead_postings_}) {
    write(AsBytes(v));
  }
  // Arrays as a count then the elements; CowArrays chunk by chunk.
  auto put_cow = [&](const auto& array) {
    write(AsBytes(uint64_t{array.size()}));
    for (size_t i = 0; i < array.size(); i += std::remove_reference_t<decltype(array)>::kChunk) {
      const size_t n = std::min(array.size() - i, std::remove_reference_t<decltype(array)>::kChunk);
      write(AsBytes(std::span(&array[i], n)));
    }
  };
  put_cow(df_);
  put_cow(stats_df_);
  put_cow(images_);
  write(AsBytes(uint64_t{segments_.size()}));
}

void InvertedFile::SerializeSegmentRecord(const Segment& segment, const Writer& write) {
  write(AsBytes(segment.first_image));
  write(AsBytes(segment.end_image));
  write(AsBytes(uint8_t{segment.dense ? uint8_t{1} : uint8_t{0}}));
  write(AsBytes(segment.num_postings));
  write(AsBytes(uint64_t{segment.words.size()}));
  write(AsBytes(std::span<const uint32_t>(segment.words)));
  write(AsBytes(uint64_t{segment.offsets.size()}));
  write(AsBytes(std::span<const uint64_t>(segment.offsets)));
  write(AsBytes(uint64_t{segment.size()}));
  write(std::span<const uint8_t>(segment.data(), segment.size()));
}

void InvertedFile::Serialize(const Writer& write) const {
  SerializeHead(kFileVersion, write);
  for (const auto& segment : segments_) SerializeSegmentRecord(*segment, write);
}

void InvertedFile::SerializeHead(std::span<const std::string> segment_names, const Writer& write) const {
  OXBOW_CHECK(segment_names.size() == segments_.size(), "one name per segment");
  SerializeHead(kHeadVersion, write);
  for (const std::string& name : segment_names) {
    write(AsBytes(uint64_t{name.size()}));
    write(std::span(reinterpret_cast<const uint8_t*>(name.data()), name.size()));
  }
}

void InvertedFile::SerializeSegment(size_t i, const Writer& write) const {
  write(AsBytes(kSegmentMagic));
  write(AsBytes(kHeadVersion));
  write(AsBytes(kByteOrderMark));
  write(AsBytes(uint64_t{vocabulary_size_}));
  SerializeSegmentRecord(*segments_[i], write);
}

// One segment record of the serialised form (SerializeSegmentRecord), its structure checked; `owner`
// non-null: its postings viewed in place.
namespace {

Result<std::shared_ptr<InvertedFile::Segment>> ParseSegment(FileReader& in, size_t vocabulary_size, uint64_t num_numbers,
                                                            const std::shared_ptr<const void>& owner) {
  using Segment = InvertedFile::Segment;
  auto segment = std::make_shared<Segment>();
  segment->first_image = in.Get<uint32_t>();
  segment->end_image = in.Get<uint32_t>();
  segment->dense = in.Get<uint8_t>() != 0;
  segment->num_postings = in.Get<uint64_t>();
  segment->words = in.GetVector<uint32_t>(vocabulary_size);
  segment->offsets = in.GetVector<uint64_t>(vocabulary_size + 1);
  if (owner) {
    segment->mapped = in.View(std::numeric_limits<uint64_t>::max());
    segment->owner = owner;
  } else {
    segment->bytes = in.GetVector<uint8_t>(std::numeric_limits<uint64_t>::max());
  }
  if (!in.ok) return Fail(ErrorCode::kCorruptData, "truncated");
  const size_t expected_offsets = segment->dense ? vocabulary_size + 1 : segment->words.size() + 1;
  if (segment->first_image > segment->end_image || segment->end_image > num_numbers ||
      segment->offsets.size() != expected_offsets || segment->offsets.back() != segment->size() ||
      (segment->dense && !segment->words.empty()) || !std::is_sorted(segment->offsets.begin(), segment->offsets.end()) ||
      std::adjacent_find(segment->words.begin(), segment->words.end(), std::greater_equal<>()) != segment->words.end() ||
      (!segment->words.empty() && segment->words.back() >= vocabulary_size)) {
    return Fail(ErrorCode::kCorruptData, "inconsistent");
  }
  return segment;
}

}  // namespace

Result<InvertedFile> InvertedFile::Deserialize(std::span<const uint8_t> bytes, size_t vocabulary_size,
                                               const TfIdfOptions& options, bool* recoded,
                                               const std::shared_ptr<const void>& owner,
                                               const SegmentSource& segment_source) {
  const auto corrupt = [](const std::string& why) {
    return Fail(ErrorCode::kCorruptData, "inconsistent inverted file: " + why);
  };
  FileReader in{bytes};
  char magic[4] = {};
  in.Copy(magic, sizeof(magic));
  if (!in.ok || !std::equal(magic, magic + 4, kFileMagic)) return corrupt("bad magic");
  const auto version = in.Get<uint32_t>();
  if (version < kOldestReadableVersion || version > kHeadVersion || in.Get<uint32_t>() != kByteOrderMark) {
    return Fail(ErrorCode::kIncompatible, "inverted file format version " + std::to_string(version) +
                                              " or byte order not readable by this build");
  }
  if (version == kHeadVersion && !segment_source) {
    return Fail(ErrorCode::kInvalidArgument, "an inverted file's head read without its segment files");
  }
  const auto stored_vocabulary_size = in.Get<uint64_t>();
  const bool sqrt_tf = in.Get<uint8_t>() != 0;
  if (stored_vocabulary_size != vocabulary_size || sqrt_tf != options.sqrt_tf) {
    return Fail(ErrorCode::kIncompatible, "inverted file made for another vocabulary size or sqrt_tf setting");
  }
  InvertedFile out(vocabulary_size, options);
  out.stats_num_live_ = in.Get<uint64_t>();
  out.changes_since_refresh_ = in.Get<uint64_t>();
  out.num_live_ = in.Get<uint64_t>();
  out.num_live_features_ = in.Get<uint64_t>();
  out.num_postings_ = in.Get<uint64_t>();
  out.num_dead_postings_ = in.Get<uint64_t>();
  // expected_size: the only size accepted (any when max).
  auto get_cow = [&](auto& array, uint64_t expected_size) {
    using Array = std::remove_reference_t<decltype(array)>;
    using T = std::remove_cvref_t<decltype(array[0])>;
    const auto size = in.Get<uint64_t>();
    if (!in.ok || (size != expected_size && expected_size != std::numeric_limits<uint64_t>::max()) ||
        size >= (uint64_t{1} << 32) || size > (bytes.size() - in.at) / sizeof(T)) {
      in.ok = false;
      return;
    }
    Array fresh;
    typename Array::Editor editor(&fresh);
    editor.Resize(size);
    for (size_t i = 0; i < size; ++i) in.Copy(&editor.Mutable(i), sizeof(T));
    array = std::move(fresh);
  };
  get_cow(out.df_, vocabulary_size);
  get_cow(out.stats_df_, vocabulary_size);
  get_cow(out.images_, std::numeric_limits<uint64_t>::max());
  const uint64_t num_numbers = out.images_.size();
  const auto num_segments = in.Get<uint64_t>();
  if (!in.ok || num_segments > num_numbers + 1) return corrupt("truncated or bad segment count");
  uint64_t postings = 0;
  uint32_t previous_end = 0;
  for (uint64_t i = 0; i < num_segments; ++i) {
    Result<std::shared_ptr<Segment>> segment = nullptr;
    if (version == kHeadVersion) {
      // The segment's own file, named here; its header must match this head's.
      const auto length = in.Get<uint64_t>();
      if (!in.ok || length > 4096 || length > bytes.size() - in.at) return corrupt("truncated segment name");
      const std::string name(reinterpret_cast<const char*>(bytes.data() + in.at), length);
      in.at += length;
      auto source = segment_source(name);
      if (!source) return Fail(source.error().code, "segment file " + name + ": " + source.error().message);
      FileReader file{source->first};
      char segment_magic[4] = {};
      file.Copy(segment_magic, sizeof(segment_magic));
      const auto segment_version = file.Get<uint32_t>();
      const auto bom = file.Get<uint32_t>();
      const auto segment_vocabulary = file.Get<uint64_t>();
      if (!file.ok || !std::equal(segment_magic, segment_magic + 4, kSegmentMagic) || segment_version != kHeadVersion ||
          bom != kByteOrderMark || segment_vocabulary != vocabulary_size) {
        return corrupt("segment file " + name + " has a bad header");
      }
      segment = ParseSegment(file, vocabulary_size, num_numbers, source->second);
      if (segment && file.at != file.bytes.size()) segment = Fail(ErrorCode::kCorruptData, "trailing bytes");
      if (!segment) return corrupt("segment file " + name + ": " + segment.error().message);
    } else {
      segment = ParseSegment(in, vocabulary_size, num_numbers, owner);
      if (!segment) return corrupt("segment " + std::to_string(i) + " is " + segment.error().message);
    }
    if ((*segment)->first_image < previous_end) return corrupt("segment " + std::to_string(i) + " overlaps");
    previous_end = (*segment)->end_image;
    postings += (*segment)->num_postings;
    out.segments_.push_back(std::move(*segment));
  }
  if (version == 1) {
    for (size_t i = 0; i < out.segments_.size(); ++i) {
      auto segment = RecodeFormat1(*out.segments_[i]);
      if (!segment) return corrupt("segment " + std::to_string(i) + ": " + segment.error().message);
      out.segments_[i] = std::move(*segment);
    }
  }
  if (recoded != nullptr) *recoded = version == 1;
  if (in.at != bytes.size()) return corrupt("trailing bytes");
  if (postings != out.num_postings_ || out.num_live_ > num_numbers || out.stats_num_live_ > num_numbers) {
    return corrupt("counts disagree");
  }
  out.RecomputeNorms();
  return out;
}

InvertedFile::Subset::Subset(const InvertedFile& file, std::span<const uint32_t> images,
                             std::span<const BagOfWords* const> bags, Buffers reuse)
    : file_(file), first_(std::move(reuse.first)), occurrences_(std::move(reuse.occurrences)), norms_(images.size()) {
  OXBOW_CHECK(images.size() == bags.size());
  const size_t num_words = file.vocabulary_size_;
  first_.assign(num_words + 1, 0);
  // Counting sort by word: images in order within each word, as in a posting list. first_[w] counts
  // word w, then (inclusive prefix sums) the end of its occurrences; the images are then placed from the
  // last one back, each word's at its end minus one, which leaves first_[w] at the word's start without
  // a second table of cursors.
  for (const BagOfWords* bag : bags) {
    for (const uint32_t w : bag->words) {
      OXBOW_CHECK(w < num_words);
      ++first_[w];
    }
  }
  for (size_t w = 1; w < num_words; ++w) first_[w] += first_[w - 1];
  if (num_words > 0) first_[num_words] = first_[num_words - 1];
  occurrences_.resize(first_[num_words]);
  for (size_t i = bags.size(); i-- > 0;) {
    for (size_t k = 0; k < bags[i]->words.size(); ++k) {
      const uint32_t tf = bags[i]->counts[k];
      occurrences_[--first_[bags[i]->words[k]]] = {static_cast<uint32_t>(i), tf == 1 ? 1.0f : file.TermWeight(tf)};
    }
    norms_[i] = file.Norm(images[i]);
  }
}

InvertedFile::Subset::Buffers InvertedFile::Subset::Release() && {
  Buffers out{std::move(first_), std::move(occurrences_)};
  first_.clear();
  occurrences_.clear();
  norms_.clear();
  return out;
}

std::vector<float> InvertedFile::Subset::Score(std::span<const QueryTerm> query) const {
  // Score()'s float operations in its order: the same term groups, query terms in their order within a
  // group, one posting per word and image; the groups' dot products added in group order.
  const std::vector<size_t> starts = file_.ScoreGroups(query);
  std::vector<float> dot(norms_.size(), 0.0f), group(starts.size() > 2 ? norms_.size() : 0, 0.0f);
  for (size_t g = 0; g + 1 < starts.size(); ++g) {
    std::vector<float>& into = g == 0 ? dot : group;
    for (size_t q = starts[g]; q < starts[g + 1]; ++q) {
      const QueryTerm& term = query[q];
      if (term.word >= file_.vocabulary_size_) continue;
      const uint32_t begin = first_[term.word], end = first_[term.word + 1];
      if (begin == end) continue;
      const float weight = file_.ScoringWeight(term);
      if (weight == 0) continue;
      for (uint32_t o = begin; o < end; ++o) into[occurrences_[o].image] += weight * occurrences_[o].t;
    }
    if (g > 0) {
      for (size_t i = 0; i < dot.size(); ++i) {
        dot[i] += group[i];
        group[i] = 0;
      }
    }
  }
  std::vector<float> out(norms_.size(), 0.0f);
  for (size_t i = 0; i < out.size(); ++i) {
    if (dot[i] != 0 && norms_[i] > 0) out[i] = static_cast<float>(static_cast<double>(dot[i]) / norms_[i]);
  }
  return out;
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
