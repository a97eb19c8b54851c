// TF-IDF scoring with cosine similarity (Sivic & Zisserman 2003; Philbin et al. 2007): the query vector,
// the query's terms, scored images, the scratch memory of a scoring pass, and scoring restricted to a
// few known images. The passes over the postings are InvertedFile members (inverted_file.h: QueryVector,
// Score, WithinPostingBudget, ScoreGroups), implemented in scoring.cc beside ScoringSubset.
//
// Scoring: idf_w = log(N / n_w) with the statistics of the last refresh (statistics.h); image vectors
// v_w(d) = t(tf) idf_w; Score() accumulates q_w idf_w t(tf_d) over the postings of the query's words
// into a dense float array over image numbers, segment by segment and 65,536 images at a time, then
// divides by |v(d)| and keeps the best (ties: smaller image number first).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "index/postings/segment.h"

namespace oxbow::index {

class InvertedFile;

// One component of a query vector: the word and its weight in the L2-normalised query tf-idf vector.
struct QueryTerm {
  uint32_t word = 0;
  float weight = 0;
};

// The `n` terms of largest weight (ties: smaller word first), sorted by word; all of them when there
// are at most n.
std::vector<QueryTerm> StrongestTerms(std::vector<QueryTerm> terms, size_t n);

struct ScoredImage {
  uint32_t image = 0;  // image number
  float score = 0;     // cosine similarity in [0, 1]
};

// Score() splits a long query into at most this many groups of consecutive terms, about one per
// kPostingsPerScoreGroup postings it scans; each group accumulates on its own (on its own thread when
// Score() is given several) and the groups' dot products are added in group order. The split depends
// on the query and the statistics only, never on the thread count, so neither do the scores. Queries
// over small collections stay in one group: splitting pays once a scan costs more than the extra pass
// over the accumulators (about 2M postings, ~8 ms on one core).
inline constexpr size_t kMaxScoreGroups = 4;
inline constexpr uint64_t kPostingsPerScoreGroup = 2'000'000;

// Per-thread scratch memory of Score() (dense accumulators over image numbers, one per term group).
// Reuse it across queries on one thread; never share one between threads at the same time.
struct ScoreScratch {
  std::array<std::vector<float>, kMaxScoreGroups> accumulators;
};

// InvertedFile::Subset: Score() restricted to a fixed set of images and computed from their bags instead
// of the postings, for scoring several queries against a few known images (transitive verification
// ranks anchors' neighbours with it): the bags are inverted once, O(their words + vocabulary_size),
// then each query costs O(its terms + their occurrences in the bags), whatever the collection size. The
// scores are those of Score() (0 for an image it would not list) up to float rounding (the same
// operations in the same order; the compiler may fuse a multiply-add in one loop and not the other).
// Keeps a reference to the InvertedFile. Immutable after construction: Score may run concurrently.
class ScoringSubset {
 public:
  struct Occurrence {
    uint32_t image;  // index into `images`
    float t;         // t(tf)
  };
  // The memory of a subset's tables, handed from one subset to the next (Release): a search builds one
  // per query, and its tables (the word index is vocabulary_size + 1 entries, the occurrences several
  // MB) would otherwise be fresh memory that each search faults in page by page.
  struct Buffers {
    std::vector<uint32_t> first;
    std::vector<Occurrence> occurrences;
  };
  // bags[i]: the bag images[i] was added with. `reuse`: memory to build the tables in (its contents do
  // not matter).
  ScoringSubset(const InvertedFile& file, std::span<const uint32_t> images, std::span<const BagOfWords* const> bags,
                Buffers reuse = {});
  std::vector<float> Score(std::span<const QueryTerm> query) const;  // one score per image, in order
  // The tables' memory, for the next subset; this subset is left empty (Score must not be called).
  Buffers Release() &&;

 private:
  const InvertedFile& file_;
  std::vector<uint32_t> first_;          // per word: its occurrences are [first_[w], first_[w + 1])
  std::vector<Occurrence> occurrences_;  // by word, then image
  std::vector<double> norms_;            // per image
};

}  // namespace oxbow::index
