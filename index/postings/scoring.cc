#include "index/postings/scoring.h"

#include <algorithm>
#include <cmath>

#include "index/postings/inverted_file.h"
#include "index/storage/huge_pages.h"
#include "sift/base/error.h"
#include "sift/base/parallel.h"

namespace oxbow::index {
namespace {

using postings::CollectionStatistics;
using postings::ImageState;
using postings::PostingCursor;
using postings::Segment;

// Images per block of Score's accumulation: 64 Ki floats (256 KiB), well inside a core's L2 cache.
constexpr uint64_t kScoreBlock = 65536;

// Score()'s per-posting factor of a query term: its weight times idf, in float; 0 to skip the term.
float ScoringWeight(const CollectionStatistics& statistics, const QueryTerm& term) {
  if (term.word >= statistics.vocabulary_size() || term.weight == 0 || statistics.num_images() == 0) return 0;
  const uint32_t df = statistics.DocumentFrequency(term.word);
  if (df == 0) return 0;
  return static_cast<float>(static_cast<double>(term.weight) *
                            std::log(static_cast<double>(statistics.num_images()) / static_cast<double>(df)));
}

// Postings Score() scans for one term: its document frequency in the statistics, 0 if skipped.
uint64_t TermCost(const CollectionStatistics& statistics, const QueryTerm& term) {
  return ScoringWeight(statistics, term) != 0 ? statistics.DocumentFrequency(term.word) : 0;
}

// The L2-normalised tf-idf vector of (words, tf), with or without the stop list.
std::vector<QueryTerm> WeightedQueryVector(const CollectionStatistics& statistics, const TfIdfOptions& options,
                                           std::span<const uint32_t> words, std::span<const float> tf,
                                           bool use_stop_list) {
  std::vector<QueryTerm> out;
  const double n = static_cast<double>(statistics.num_images());
  double norm_sq = 0;
  std::vector<double> weights;
  for (size_t k = 0; k < words.size(); ++k) {
    const uint32_t w = words[k];
    if (w >= statistics.vocabulary_size() || !(tf[k] > 0)) continue;
    const uint32_t df = statistics.DocumentFrequency(w);
    if (df == 0) continue;
    if (use_stop_list && df > options.stop_list_min_images &&
        static_cast<double>(df) > options.max_document_frequency * n) {
      continue;
    }
    const double idf = std::log(n / static_cast<double>(df));
    if (!(idf > 0)) continue;
    const double t = options.sqrt_tf ? std::sqrt(static_cast<double>(tf[k])) : static_cast<double>(tf[k]);
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

// The accumulators of `num_groups` groups, each at least `num_numbers` zeros.
void PrepareAccumulators(ScoreScratch* scratch, size_t num_groups, size_t num_numbers) {
  for (size_t g = 0; g < num_groups; ++g) {
    std::vector<float>& acc = scratch->accumulators[g];
    if (acc.size() >= num_numbers) continue;
    if (acc.capacity() < num_numbers) {
      // Room for 1/16 more images, so that adds between searches do not move (and fault in again) 4 MB
      // at a million images on every search; in huge pages where the system gives them. The array is all
      // zeros between searches, so a fresh one replaces it.
      std::vector<float> grown;
      grown.reserve(num_numbers + num_numbers / 16);
      AdviseHugePages(reinterpret_cast<uint8_t*>(grown.data()), grown.capacity() * sizeof(float));
      acc.swap(grown);
    }
    acc.resize(num_numbers, 0.0f);
  }
}

// Adds the postings of the terms [begin, end) of `query` into `a`: segment by segment, and within a
// segment block of images by block (kScoreBlock images, every term's cursor advanced to the block's end
// before the next block), so that the accumulators written stay in the core's cache instead of
// spreading every list's writes over the whole array (4 MB at a million images). An image's postings
// all lie in one segment and are still added in the group's term order, so every sum is the same float
// as with the lists read whole.
void AccumulateGroup(std::span<const std::shared_ptr<const Segment>> segments, const CollectionStatistics& statistics,
                     std::span<const QueryTerm> query, size_t begin, size_t end, float* a) {
  struct Cursor : PostingCursor {
    float weight = 0;
  };
  std::vector<Cursor> cursors;
  cursors.reserve(end - begin);
  for (const auto& segment : segments) {
    cursors.clear();
    for (size_t q = begin; q < end; ++q) {
      const float weight = ScoringWeight(statistics, query[q]);
      if (weight == 0) continue;
      auto [p, list_end] = segment->List(query[q].word);
      if (p == list_end) continue;
      Cursor c{{p, list_end, segment->first_image}, weight};
      c.Advance();
      cursors.push_back(c);
    }
    for (uint64_t block = segment->first_image; block < segment->end_image && !cursors.empty(); block += kScoreBlock) {
      const auto limit = static_cast<uint32_t>(std::min<uint64_t>(block + kScoreBlock, segment->end_image));
      for (Cursor& c : cursors) {
        // Hot loop: one 16-bit unit per posting, one multiply-add.
        for (; c.image < limit; c.Advance()) a[c.image] += c.tf == 1 ? c.weight : c.weight * statistics.TermWeight(c.tf);
      }
    }
  }
}

// Total order of results: score, then image number.
bool Better(const ScoredImage& x, const ScoredImage& y) {
  return x.score != y.score ? x.score > y.score : x.image < y.image;
}

// The best `max_results` of a range of images, as a heap under Better whose front is the worst kept.
// An image's cosine is only computed when its dot product can beat the worst kept one: v^2 < worst^2
// |v(d)|^2 (1 - 1e-6)^2 means v / |v(d)| < worst (1 - 1e-6), below worst even after rounding to float
// (relative error 2^-24), so most of a million images cost no square root.
class BestImages {
 public:
  BestImages(size_t max_results, std::vector<ScoredImage>* heap) : max_results_(max_results), heap_(*heap) {
    heap_.clear();
  }

  // Offers image i with dot product v and norm |v(d)| > 0.
  void Offer(size_t i, double dv, double norm) {
    if (full_ && (dv <= 0 || dv * dv < bar_ * (norm * norm))) return;  // cannot enter (see above)
    const ScoredImage cand{static_cast<uint32_t>(i), static_cast<float>(dv / norm)};
    if (heap_.size() < max_results_) {
      heap_.push_back(cand);
      std::push_heap(heap_.begin(), heap_.end(), Better);
    } else if (Better(cand, heap_.front())) {
      std::pop_heap(heap_.begin(), heap_.end(), Better);
      heap_.back() = cand;
      std::push_heap(heap_.begin(), heap_.end(), Better);
    } else {
      return;
    }
    if (heap_.size() == max_results_ && heap_.front().score > 0) {
      full_ = true;
      bar_ = static_cast<double>(heap_.front().score) * static_cast<double>(heap_.front().score) * kMargin;
    }
  }

 private:
  static constexpr double kMargin = (1 - 1e-6) * (1 - 1e-6);
  size_t max_results_;
  std::vector<ScoredImage>& heap_;
  double bar_ = 0;  // worst kept score^2 x kMargin, once the heap is full and its worst is positive
  bool full_ = false;
};

// What SelectBest reads.
struct Accumulated {
  ScoreScratch* scratch;
  size_t num_groups;
  size_t num_numbers;
  const CowArray<double>* norms;
  const std::vector<uint8_t>* allowed;
};

constexpr size_t kChunk = CowArray<ImageState>::kChunk;
static_assert(CowArray<double>::kChunk == kChunk);

// Chunks [chunk0, chunk1) of the accumulators: their groups' dot products added in group order (and
// the accumulators re-zeroed), each image offered to `best`. Returns the images with a non-zero dot
// product that are live and allowed.
uint64_t SelectInChunks(const Accumulated& in, size_t chunk0, size_t chunk1, BestImages* best) {
  uint64_t touched = 0;
  std::array<float, kChunk> sum;  // this chunk's dot products: the groups added in group order
  for (size_t chunk = chunk0; chunk < chunk1; ++chunk) {
    const size_t chunk_begin = chunk * kChunk, chunk_end = std::min(in.num_numbers, chunk_begin + kChunk);
    const size_t len = chunk_end - chunk_begin;
    float* first = in.scratch->accumulators[0].data() + chunk_begin;
    std::copy(first, first + len, sum.begin());
    std::fill(first, first + len, 0.0f);
    for (size_t g = 1; g < in.num_groups; ++g) {
      float* a = in.scratch->accumulators[g].data() + chunk_begin;
      for (size_t k = 0; k < len; ++k) sum[k] += a[k];
      std::fill(a, a + len, 0.0f);
    }
    const double* norms = &(*in.norms)[chunk_begin];  // a chunk of the norms is contiguous
    for (size_t i = chunk_begin; i < chunk_end; ++i) {
      const float v = sum[i - chunk_begin];
      if (v == 0) continue;
      const double norm = norms[i - chunk_begin];  // 0: not live, or a zero vector
      if (!(norm > 0)) continue;
      if (in.allowed != nullptr && (i >= in.allowed->size() || (*in.allowed)[i] == 0)) continue;
      ++touched;
      best->Offer(i, static_cast<double>(v), norm);
    }
  }
  return touched;
}

// Normalises, selects the best max_results and re-zeroes the accumulators: on num_threads threads over
// ranges of image numbers, each keeping its own best; the ranges' lists are then merged. The order is
// total (score, then image number), so the result does not depend on the split.
std::vector<ScoredImage> SelectBest(const Accumulated& in, size_t max_results, int num_threads, uint64_t* candidates) {
  const size_t num_chunks = (in.num_numbers + kChunk - 1) / kChunk;
  const size_t num_parts = std::min<size_t>(num_chunks, 16);
  std::vector<std::vector<ScoredImage>> kept(num_parts);
  std::vector<uint64_t> touched_in(num_parts, 0);
  ParallelFor(num_parts, num_threads, 1, [&](size_t p0, size_t p1, int) {
    for (size_t part = p0; part < p1; ++part) {
      BestImages best(max_results, &kept[part]);
      touched_in[part] = SelectInChunks(in, num_chunks * part / num_parts, num_chunks * (part + 1) / num_parts, &best);
    }
  });
  uint64_t touched = 0;
  std::vector<ScoredImage> out;
  for (size_t part = 0; part < num_parts; ++part) {
    touched += touched_in[part];
    out.insert(out.end(), kept[part].begin(), kept[part].end());
  }
  const size_t n = std::min(out.size(), max_results);
  std::partial_sort(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(n), out.end(), Better);
  out.resize(n);
  if (candidates) *candidates = touched;
  return out;
}

}  // namespace

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

std::vector<QueryTerm> InvertedFile::QueryVector(const BagOfWords& bag) const {
  std::vector<float> tf(bag.counts.size());
  for (size_t k = 0; k < tf.size(); ++k) tf[k] = static_cast<float>(bag.counts[k]);
  return QueryVector(bag.words, tf);
}

std::vector<QueryTerm> InvertedFile::QueryVector(std::span<const uint32_t> words, std::span<const float> tf) const {
  OXBOW_CHECK(words.size() == tf.size());
  std::vector<QueryTerm> out;
  if (num_live_ == 0 || statistics_.num_images() == 0) return out;
  out = WeightedQueryVector(statistics_, options_, words, tf, /*use_stop_list=*/true);
  // A stop list must not make an image unfindable: when it would drop every word of the query (a small
  // vocabulary over many images), the query is scored with all its words.
  if (out.empty() && options_.max_document_frequency < 1) out = WeightedQueryVector(statistics_, options_, words, tf, false);
  return out;
}

std::vector<size_t> InvertedFile::ScoreGroups(std::span<const QueryTerm> query) const {
  uint64_t total = 0;  // postings the query scans, estimated by the document frequencies
  std::vector<uint64_t> cost(query.size(), 0);
  for (size_t i = 0; i < query.size(); ++i) {
    cost[i] = TermCost(statistics_, query[i]);
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

uint64_t InvertedFile::ScannedPostings(std::span<const QueryTerm> query) const {
  uint64_t total = 0;
  for (const QueryTerm& term : query) total += TermCost(statistics_, term);
  return total;
}

std::vector<QueryTerm> InvertedFile::WithinPostingBudget(std::span<const QueryTerm> query,
                                                         uint64_t max_postings) const {
  if (max_postings == 0 || ScannedPostings(query) <= max_postings) return {query.begin(), query.end()};
  std::vector<std::pair<float, size_t>> order;  // (per-posting contribution, position), scored terms only
  order.reserve(query.size());
  for (size_t i = 0; i < query.size(); ++i) {
    if (const float w = ScoringWeight(statistics_, query[i]); w != 0) order.emplace_back(std::abs(w), i);
  }
  std::sort(order.begin(), order.end(), [&](const auto& x, const auto& y) {
    return x.first != y.first ? x.first > y.first : query[x.second].word < query[y.second].word;
  });
  std::vector<uint8_t> keep(query.size(), 0);
  uint64_t used = 0;
  for (size_t k = 0; k < order.size(); ++k) {
    const uint64_t cost = TermCost(statistics_, query[order[k].second]);
    if (k > 0 && used + cost > max_postings) continue;
    used += cost;
    keep[order[k].second] = 1;
  }
  std::vector<QueryTerm> out;
  for (size_t i = 0; i < query.size(); ++i)
    if (keep[i]) out.push_back(query[i]);
  return out;
}

std::vector<ScoredImage> InvertedFile::Score(std::span<const QueryTerm> query, size_t max_results,
                                             ScoreScratch* scratch, uint64_t* candidates,
                                             const std::vector<uint8_t>* allowed, int num_threads,
                                             uint64_t max_postings) const {
  OXBOW_CHECK(scratch != nullptr);
  if (candidates) *candidates = 0;
  if (num_live_ == 0 || statistics_.num_images() == 0 || max_results == 0) return {};
  std::vector<QueryTerm> within_budget;
  if (max_postings != 0) {
    within_budget = WithinPostingBudget(query, max_postings);
    query = within_budget;
  }
  const std::vector<size_t> starts = ScoreGroups(query);
  const size_t num_groups = starts.size() - 1;
  PrepareAccumulators(scratch, num_groups, images_.size());
  ParallelFor(num_groups, num_threads, 1, [&](size_t g0, size_t g1, int) {
    for (size_t g = g0; g < g1; ++g) {
      AccumulateGroup(segments_, statistics_, query, starts[g], starts[g + 1], scratch->accumulators[g].data());
    }
  });
  return SelectBest({scratch, num_groups, images_.size(), &norms_, allowed}, max_results, num_threads, candidates);
}

ScoringSubset::ScoringSubset(const InvertedFile& file, std::span<const uint32_t> images,
                             std::span<const BagOfWords* const> bags, Buffers reuse)
    : file_(file), first_(std::move(reuse.first)), occurrences_(std::move(reuse.occurrences)), norms_(images.size()) {
  OXBOW_CHECK(images.size() == bags.size());
  const size_t num_words = file.vocabulary_size();
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

ScoringSubset::Buffers ScoringSubset::Release() && {
  Buffers out{std::move(first_), std::move(occurrences_)};
  first_.clear();
  occurrences_.clear();
  norms_.clear();
  return out;
}

std::vector<float> ScoringSubset::Score(std::span<const QueryTerm> query) const {
  // Score()'s float operations in its order: the same term groups, query terms in their order within a
  // group, one posting per word and image; the groups' dot products added in group order.
  const std::vector<size_t> starts = file_.ScoreGroups(query);
  std::vector<float> dot(norms_.size(), 0.0f), group(starts.size() > 2 ? norms_.size() : 0, 0.0f);
  for (size_t g = 0; g + 1 < starts.size(); ++g) {
    std::vector<float>& into = g == 0 ? dot : group;
    for (size_t q = starts[g]; q < starts[g + 1]; ++q) {
      const QueryTerm& term = query[q];
      if (term.word >= file_.vocabulary_size()) continue;
      const uint32_t begin = first_[term.word], end = first_[term.word + 1];
      if (begin == end) continue;
      const float weight = ScoringWeight(file_.statistics(), term);
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

}  // namespace oxbow::index
