// The inverted file: postings of visual words in log-structured segments, collection statistics and
// TF-IDF scoring (Sivic & Zisserman 2003; Philbin et al. 2007), independent of how words were made
// (vocab/) or stored (storage/catalogue.h). Its parts, in this folder: the posting codec (codec.h),
// segments and their building and merging (segment.h), the collection statistics (statistics.h),
// scoring (scoring.h) and the checkpoint form (serialisation.h).
//
// Images are numbered by the caller with dense uint32 "image numbers" that only grow (a removed number
// is never reused). For every visual word the postings (image number, tf) are kept sorted by image
// number, each coded in about 2 bytes (codec.h).
//
// Postings live in immutable segments (a log-structured merge): WithAdded() appends one segment for the
// new images, then merges the newest segments while `merge_factor` of them share a size level
// (level = floor(log_merge_factor(postings / 1024))), so there are O(merge_factor * log N) segments and
// each posting is rewritten O(log N) times over the index's life. Removed images are tombstoned (their
// postings are skipped when scoring and dropped at the next merge of their segment).
//
// Scoring (scoring.h): idf_w = log(N / n_w) over the N live images, n_w of which contain w; image
// vectors v_w(d) = t(tf) idf_w with t(x) = x or sqrt(x) (TfIdfOptions::sqrt_tf); the cosine of the
// query's and each image's vector, the best `max_results` kept (ties: smaller image number first).
//
// Collection statistics (statistics.h: N and every n_w, hence idf and the image norms) are those of the
// last *refresh*. An add or remove updates the live counts and computes only its own image's norm (with
// the refreshed statistics), so a write costs O(its words) at any collection size; a refresh recomputes
// every live image's norm from its postings in one parallel pass, O(total postings). Refreshes happen by
// themselves: after every write while the index holds at most `exact_statistics_postings` postings
// (small collections: scores always equal those of an index built from scratch on the live images),
// and otherwise once the images added and removed since the last refresh exceed
// `statistics_refresh_fraction` of the live images then (idf drifts by at most about log(1 + fraction)
// in between; amortised cost per added image features / fraction posting visits). Until a word's first
// refresh it is left out of query and image vectors (its n_w is 0 in the statistics). Build() and
// WithRefreshedStatistics() give exact statistics.
//
// Thread safety: an InvertedFile is an immutable value (its parts are shared_ptr<const> or copy-on-write
// arrays); any number of threads may call its const members. WithAdded/WithRemoved return a new value
// and leave this one alone. Copying an InvertedFile is O(vocabulary_size / 4096 + number of images / 4096).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "index/cow_array.h"
#include "index/postings/scoring.h"
#include "index/postings/segment.h"
#include "index/postings/statistics.h"
#include "sift/base/error.h"

namespace oxbow::index {

struct TfIdfOptions {
  // Use sqrt(tf) instead of tf in query and image vectors (burstiness; Jegou et al. 2009).
  bool sqrt_tf = true;
  // Query words contained in more than this fraction of the live images are left out of the query
  // vector (a stop list of the most frequent words). (0, 1].
  double max_document_frequency = 0.1;
  // ... but never a word contained in at most this many live images. [0, 2^32).
  // With the defaults the stop list adapts to the collection: it drops nothing while the index holds at
  // most 10,000 images (a word cannot be in more images than there are), so small collections keep
  // every word (a 5k-word vocabulary would lose most of its words to a bare 10% rule); from 100,000
  // images on it drops the words of more than 10% of them, whose postings are a large share of a query's
  // scan and whose idf (< log 10) adds little. The product defaults; IndexOptions takes them from here.
  uint32_t stop_list_min_images = 10'000;
  // Segments of one size level merged at once (see the file comment). [2, 64].
  int merge_factor = 8;
  // Statistics refresh (file comment): after every write while the index holds at most this many
  // postings (4M: about 4000 images of 1000 features; a refresh then costs a few ms), else when the
  // images added + removed since the last refresh exceed this fraction of the live images at that
  // refresh. [0, 2^64) and (0, 1]. Results never depend on the thread count. Growing from empty, every
  // posting is visited by about (1 + f) / f refreshes: 5 at 0.25, 11 at 0.1, where the refresh was a
  // sixth of bulk ingest at 1M images; idf drifts by at most about
  // log 1.25 = 0.22 in between, and not at all while the collection grows without changing its mix
  // (n_w and N grow alike).
  uint64_t exact_statistics_postings = 4'000'000;
  double statistics_refresh_fraction = 0.25;

  std::optional<std::string> Check() const;
};

struct InvertedFileStats {
  uint64_t num_images = 0;         // live
  uint64_t num_postings = 0;       // stored (live + not yet merged away)
  uint64_t num_features = 0;       // sum of tf over live images
  uint64_t postings_bytes = 0;     // coded postings + per-word offset tables
  uint64_t image_table_bytes = 0;  // per-image norms state
  uint64_t word_table_bytes = 0;   // per-word document frequencies
  uint64_t num_segments = 0;
};

class InvertedFile {
 public:
  // An empty inverted file over words [0, vocabulary_size). OXBOW_CHECKs options.Check().
  InvertedFile(size_t vocabulary_size, const TfIdfOptions& options);

  // Builds from scratch, as one segment, the images numbered [0, num_numbers) for which
  // `bag_of(image, bag)` returns true (false: no image with that number). `bag_of` is called twice
  // per number (two passes: sizes, then contents) and must give the same bag both times; it may be
  // called from several threads at once for different numbers when num_threads != 1. Words must be
  // < vocabulary_size (OXBOW_CHECK). O(total postings + vocabulary_size).
  static InvertedFile Build(size_t vocabulary_size, const TfIdfOptions& options, uint32_t num_numbers,
                            const std::function<bool(uint32_t image, BagOfWords* bag)>& bag_of,
                            int num_threads = 1);

  // A new version with `images` added (numbers ascending, each greater than every number used so far;
  // bags[i] for images[i]). Cost O(new postings + postings of the existing images that share a word
  // whose document frequency changed) + the amortised merge.
  InvertedFile WithAdded(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags) const;
  // A new version without `images` (live numbers; bags[i] must be the bag they were added with).
  // Cost O(postings of the live images sharing a word with them).
  InvertedFile WithRemoved(std::span<const uint32_t> images, std::span<const BagOfWords* const> bags) const;

  // --- Scoring (scoring.cc) ---
  // The L2-normalised tf-idf vector of a query bag, sorted by word. Words not in any live image (idf
  // undefined) and stop-listed words (n_w > max(max_document_frequency * N, stop_list_min_images)) are
  // left out, unless that would leave out every word (then the stop list is not applied); words in
  // every image have weight 0 and are left out too. Empty if nothing remains.
  std::vector<QueryTerm> QueryVector(const BagOfWords& bag) const;
  // The same for fractional term frequencies (soft / multiple assignment): words ascending and
  // distinct, tf[i] > 0 the (weighted) count of words[i]; t() applies to the real value.
  std::vector<QueryTerm> QueryVector(std::span<const uint32_t> words, std::span<const float> tf) const;

  // Scores every live image against `query` (terms sorted by word, weights of an L2-normalised vector;
  // any real weights are accepted) and returns the best `max_results` by cosine, best first.
  // `candidates` (optional) receives the number of live images with a non-zero dot product.
  // `allowed` (filtered search, optional): only images n with n < allowed->size() and (*allowed)[n]
  // != 0 are ranked and counted; the postings are still accumulated (a test per posting would cost
  // more than the one per touched image). Cost O(postings of the query words + number of images ever
  // added), on up to `num_threads` threads (0 = all cores) for long queries (kMaxScoreGroups); the
  // result does not depend on num_threads.
  // `max_postings` (0 = no limit): a query estimated to scan more postings than this is first cut to
  // WithinPostingBudget(query, max_postings); the scores stay cosines with the full image norms.
  std::vector<ScoredImage> Score(std::span<const QueryTerm> query, size_t max_results, ScoreScratch* scratch,
                                 uint64_t* candidates = nullptr, const std::vector<uint8_t>* allowed = nullptr,
                                 int num_threads = 1, uint64_t max_postings = 0) const;
  // The terms of `query` that Score() scans under a budget of `max_postings` postings (a term's cost:
  // its document frequency in the statistics). The whole query when it fits (0: no limit). Otherwise
  // the terms are taken in order of their per-posting contribution (weight x idf, which is q_w idf_w:
  // t(tf_q) idf_w^2 up to the query norm; ties: smaller word first), each kept when it still fits in
  // what is left of the budget, else skipped; the first is always kept. The rare words that dominate
  // the cosine are kept and the frequent words, whose long lists cost most for the least score, go
  // first: the "quit" strategy of Moffat & Zobel 1996 with a posting count instead of an accumulator
  // count. Sorted by word, as `query`. Depends on the query and the statistics only.
  std::vector<QueryTerm> WithinPostingBudget(std::span<const QueryTerm> query, uint64_t max_postings) const;
  // Postings Score() scans for `query` (terms it skips cost nothing), estimated by the statistics.
  uint64_t ScannedPostings(std::span<const QueryTerm> query) const;
  // Where Score() splits `query` into term groups (kMaxScoreGroups): the first term of each group, then
  // query.size().
  std::vector<size_t> ScoreGroups(std::span<const QueryTerm> query) const;
  // Score() restricted to a fixed set of images (scoring.h).
  using Subset = ScoringSubset;

  // --- Statistics (statistics.cc) ---
  // A new version whose statistics are those of the live images now (one pass over every posting,
  // on `num_threads` threads; 0 = all). Scores then equal those of Build() on the live images.
  InvertedFile WithRefreshedStatistics(int num_threads = 0) const;
  // A new version scoring with the given collection statistics instead of its own (a cluster partition
  // scoring with the whole cluster's N and n_w, api/partition.h): every live image's norm is recomputed
  // (one pass, as a refresh) and the statistics stay pinned: later writes compute their images' norms
  // with them and no refresh replaces them. document_frequency.size() == vocabulary_size (OXBOW_CHECK).
  InvertedFile WithPinnedStatistics(uint64_t num_images, std::span<const uint32_t> document_frequency,
                                    int num_threads = 0) const;
  // Images added + removed since the last refresh (0: the statistics are those of the live images).
  uint64_t changes_since_refresh() const { return changes_since_refresh_; }
  // The statistics scores are computed with (those of the last refresh, or pinned).
  const postings::CollectionStatistics& statistics() const { return statistics_; }

  double Idf(uint32_t word) const;                 // log(N / n_w) of the statistics; +inf when n_w == 0
  // Idf(w)^2 of every word, 0 where it is not finite (n_w == 0), as one table: computed at the first
  // call after a change of statistics (a refresh), then shared by every copy with these statistics,
  // so that scoring thousands of candidates' words (Hamming embedding) takes no logarithm. Thread-safe.
  std::shared_ptr<const std::vector<double>> IdfSquaredTable() const;
  uint32_t DocumentFrequency(uint32_t word) const; // live images containing the word now
  double Norm(uint32_t image) const { return image < norms_.size() ? norms_[image] : 0.0; }  // |v(d)|; 0 if not live
  bool IsLive(uint32_t image) const { return image < images_.size() && images_[image].live != 0; }
  float TermWeight(uint32_t tf) const { return statistics_.TermWeight(tf); }  // t(tf): tf or sqrt(tf)
  uint64_t num_images() const { return num_live_; }
  uint32_t num_numbers() const { return static_cast<uint32_t>(images_.size()); }  // one past the largest number used
  size_t vocabulary_size() const { return vocabulary_size_; }
  const TfIdfOptions& options() const { return options_; }
  InvertedFileStats Stats() const;

  // --- The checkpoint form (serialisation.h, serialisation.cc) ---
  using Writer = std::function<void(std::span<const uint8_t>)>;
  // The checkpoint form (storage/checkpoint.h) of the whole state: segments, document frequencies, the
  // statistics of the last refresh and every image's sums, so that a deserialised copy scores exactly
  // as this one. Little-endian; `write` receives the bytes in order.
  void Serialize(const Writer& write) const;
  // The same state in parts, so that a checkpoint writes only the segments new since the last one
  // (segments are immutable): each segment alone (SerializeSegment), and a head with everything else
  // that names the segments' files in order (SerializeHead, one name per segment, each < 4 KB).
  void SerializeHead(std::span<const std::string> segment_names, const Writer& write) const;
  void SerializeSegment(size_t i, const Writer& write) const;
  size_t num_segments() const { return segments_.size(); }
  // Identity of segment i: the same object in every version of this file that still has the segment
  // (hold a weak_ptr to recognise it later without keeping it alive).
  std::shared_ptr<const void> SegmentHandle(size_t i) const { return segments_[i]; }

  // What a head names: the bytes of a segment file and an owner that keeps them valid and unchanged
  // (the postings are used in place).
  using SegmentSource =
      std::function<Result<std::pair<std::span<const uint8_t>, std::shared_ptr<const void>>>(const std::string& name)>;
  // Reads what Serialize or SerializeHead wrote (a head's segment files through `segment_source`,
  // asked once per segment, in order). Checks the structure, not the content (the caller checksums
  // the files): kCorruptData for inconsistent bytes; kIncompatible when the vocabulary size or sqrt_tf
  // differ (image sums depend on sqrt_tf) or the format is newer than this build's. A file of an older
  // format (version 1: varint postings) is re-coded while loading (on all cores; the postings are
  // decoded with bounds checks); `recoded` (optional) then receives true, so that the caller can write
  // the current format once. With an `owner` (which must keep `bytes` valid and unchanged, e.g. a
  // read-only file mapping) the current format's postings are used in place, not copied: the file
  // keeps `owner` for as long as any version of it uses them.
  [[nodiscard]] static Result<InvertedFile> Deserialize(std::span<const uint8_t> bytes, size_t vocabulary_size,
                                                        const TfIdfOptions& options, bool* recoded = nullptr,
                                                        const std::shared_ptr<const void>& owner = nullptr,
                                                        const SegmentSource& segment_source = nullptr);

 private:
  void MergeTail(bool everything);
  void SerializeHead(uint32_t version, const Writer& write) const;  // up to the segment count
  void RefreshStatistics(int num_threads);
  void RecomputeSums(int num_threads);  // every live image's sums with the current statistics
  void RefreshIfDue();
  // norms_ of `images` (their sums or liveness changed), or of every image (the statistics changed).
  void SetNorms(std::span<const uint32_t> images);
  void RecomputeNorms();

  size_t vocabulary_size_ = 0;
  TfIdfOptions options_;
  std::vector<std::shared_ptr<const postings::Segment>> segments_;  // in image-number order
  CowArray<uint32_t> df_;                                            // n_w per word, live images now
  CowArray<postings::ImageState> images_;                            // per image number
  // Per image number, statistics_.Norm(images_[n]): Score() reads 8 bytes per image instead of the
  // state's 32 (a million images per query). Derived: kept by every change of images_ or of the statistics.
  CowArray<double> norms_;
  postings::CollectionStatistics statistics_;  // of the last refresh (or pinned)
  uint64_t changes_since_refresh_ = 0;
  bool pinned_statistics_ = false;  // WithPinnedStatistics: refreshes keep the given statistics
  uint64_t num_live_ = 0;
  uint64_t num_live_features_ = 0;
  uint64_t num_postings_ = 0;       // stored in segments, live or not
  uint64_t num_dead_postings_ = 0;  // of removed images, not yet merged away
};

}  // namespace oxbow::index
