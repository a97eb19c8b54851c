// Collection statistics of TF-IDF scoring (Sivic & Zisserman 2003): the number of images N and every
// word's document frequency n_w as of the last refresh, hence idf_w = log(N / n_w); the term weight t(tf)
// (tf, or sqrt(tf): burstiness, Jegou et al. 2009); and per image the three sums that give its norm
// |v(d)| under any N without a pass over its words:
//   A = sum t(tf)^2, B = sum t(tf)^2 log n_w, C = sum t(tf)^2 (log n_w)^2,
//   |v(d)|^2 = sum (t(tf) (log N - log n_w))^2 = L^2 A - 2 L B + C with L = log N,
// over the image's words known to the statistics (n_w > 0).
//
// The inverted file (inverted_file.h) keeps a CollectionStatistics and decides when to refresh it; a
// refresh makes a new one and recomputes every image's sums from the postings (RecomputeImageSums).
//
// Thread safety: a CollectionStatistics is immutable (copies share its tables); any number of threads
// may call its const members, including the tables made at their first use.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <mutex>
#include <span>
#include <vector>

#include "index/cow_array.h"
#include "index/postings/segment.h"

namespace oxbow::index::postings {

// Per image number: the sums of the file comment with the statistics they were computed with, and
// what the image is now.
struct ImageState {
  double a = 0;           // sum over the image's words of t(tf)^2
  double b = 0;           // sum of t(tf)^2 log n_w
  double c = 0;           // sum of t(tf)^2 (log n_w)^2
  uint32_t live = 0;      // 1 while the image is in the index
  uint32_t features = 0;  // sum of tf
};

// t(tf)^2 without rounding through sqrt: tf for sqrt-tf, tf^2 otherwise.
inline double TermWeightSquared(bool sqrt_tf, uint32_t tf) {
  return sqrt_tf ? static_cast<double>(tf) : static_cast<double>(tf) * static_cast<double>(tf);
}

class CollectionStatistics {
 public:
  // N = num_images, n_w = document_frequency[w] for the words [0, document_frequency.size()); t(tf) is
  // sqrt(tf) when sqrt_tf, else tf.
  CollectionStatistics(bool sqrt_tf, CowArray<uint32_t> document_frequency, uint64_t num_images);

  uint64_t num_images() const { return num_images_; }
  size_t vocabulary_size() const { return document_frequency_.size(); }
  bool sqrt_tf() const { return sqrt_tf_; }
  uint32_t DocumentFrequency(uint32_t word) const { return document_frequency_[word]; }  // word < vocabulary_size
  const CowArray<uint32_t>& document_frequencies() const { return document_frequency_; }

  // t(tf): tf or sqrt(tf), from a table for tf < 256.
  float TermWeight(uint32_t tf) const {
    if (tf < term_weight_.size()) return term_weight_[tf];
    return sqrt_tf_ ? static_cast<float>(std::sqrt(static_cast<double>(tf))) : static_cast<float>(tf);
  }
  // log(N / n_w); +inf when n_w == 0. word < vocabulary_size.
  double Idf(uint32_t word) const;
  // Idf(w)^2 of every word, 0 where it is not finite (n_w == 0), as one table made at the first call and
  // shared by every copy of these statistics, so that scoring thousands of candidates' words (Hamming
  // embedding) takes no logarithm.
  std::shared_ptr<const std::vector<double>> IdfSquaredTable() const;
  // log n_w per word (0 where n_w = 0), made at its first use as IdfSquaredTable(): a batch of new images
  // takes its sums' logarithms from it instead of one std::log per posting.
  std::shared_ptr<const std::vector<double>> LogDfTable() const;

  // The sums a, b, c of one image's bag (words unknown to the statistics left out); log_df is
  // LogDfTable(). Leaves s->live and s->features alone.
  void SetSums(const BagOfWords& bag, std::span<const double> log_df, ImageState* s) const;
  // |v(d)| of an image state: 0 when not live or not positive.
  double Norm(const ImageState& s) const;

 private:
  // The tables made at their first use. Each once_flag guards the one-time making of the table after
  // it; the makers take no other lock, so there is no lock order.
  struct Tables {
    std::once_flag squared_once;
    std::shared_ptr<const std::vector<double>> squared;  // IdfSquaredTable()
    std::once_flag log_df_once;
    std::shared_ptr<const std::vector<double>> log_df;  // LogDfTable()
  };

  bool sqrt_tf_ = true;
  CowArray<uint32_t> document_frequency_;  // n_w
  uint64_t num_images_ = 0;                // N
  std::array<float, 256> term_weight_{};   // t(tf) for tf < 256
  std::shared_ptr<Tables> tables_ = std::make_shared<Tables>();
};

// Every live image's sums a, b, c (`images`, live images only) recomputed from the postings of
// `segments` with `statistics`, on `num_threads` threads (0 = all cores); the result does not depend on
// the thread count. O(total postings).
void RecomputeImageSums(std::span<const std::shared_ptr<const Segment>> segments,
                        const CollectionStatistics& statistics, CowArray<ImageState>* images, int num_threads);

}  // namespace oxbow::index::postings
