// ImageIndex: the retrieval index facade. Images go in as FeatureSets (keypoints + descriptors, see
// sift/types.h; extraction happens in the caller), a query FeatureSet comes back as a ranked list of
// indexed images with the region they matched.
//
// ==== Method ========================================================================================
//
// 1. Visual words (Sivic & Zisserman 2003, "Video Google"). Every descriptor is quantised to its nearest
//    word of the index's vocab::Vocabulary. An image becomes a bag of words: tf_w(d) = how often word w
//    occurs in image d.
// 2. TF-IDF with cosine similarity (Sivic & Zisserman 2003; Philbin et al. 2007). With N live images and
//    n_w of them containing w, idf_w = log(N / n_w). An image's vector has components
//    v_w(d) = t(tf_w(d)) * idf_w, where t(x) = x, or sqrt(x) with IndexOptions::sqrt_tf (burstiness
//    down-weighting; Jegou et al. 2009 "On the burstiness of visual elements"). The score of image d for
//    query q is the cosine  s(q, d) = <v(q), v(d)> / (|v(q)| |v(d)|), in [0, 1]; an image whose vector
//    is zero (every word in every image, e.g. N = 1) scores 0.
//    N and n_w (hence idf and every norm) are the collection statistics of the last refresh
//    (postings/inverted_file.h): while the index holds at most TfIdfOptions::exact_statistics_postings postings
//    (about 4000 images) every write refreshes them, so scores equal those of an index built from
//    scratch on the live images; above that, an add or remove costs O(its own words) and the
//    statistics are refreshed (one parallel pass over the postings) once the images changed since the
//    last refresh exceed 25% of the live images (TfIdfOptions::statistics_refresh_fraction). Norms use three per-image sums:
//    |v(d)|^2 = L^2 A_d - 2 L B_d + C_d with L = log N, A_d = sum t^2, B_d = sum t^2 log n_w,
//    C_d = sum t^2 (log n_w)^2.
// 3. Inverted file: per visual word, the postings (image, tf) sorted by image, each a 16-bit unit
//    (gap << 1 | tf > 1, long gaps escaped; postings/codec.h),
//    kept in immutable segments (a log-structured merge: each add makes a small segment, segments of
//    similar size are merged, removed images are dropped at merge time). Scoring accumulates into a
//    dense float array over images (one pass over the postings of the query's words).
// 4. Spatial re-ranking (Philbin et al. 2007): the top `rerank_depth` images by tf-idf are matched to the
//    query through shared visual words (one-to-one; sift::EnforceOneToOne) and verified with Lowe's
//    Hough/affine verifier (sift::VerifyHoughAffine). Verified images come first, by inlier count, the
//    tf-idf score breaking ties; unverified ones keep their tf-idf order after them.
//    Geometry is stored per indexed feature in 9 bytes: word (24 bits), x and y quantised to 1/65535 of
//    the image size (16 bits each), log2 scale in 1/16 octave steps (8 bits), orientation in 1/256 turns
//    (8 bits).
//    With QueryOptions::hamming (and an index whose vocabulary has Hamming-embedding parameters, so
//    every feature carries a 64-bit signature: vocab/vocabulary.h), the best hamming_shortlist tf-idf
//    candidates are first re-ordered by their Hamming-embedding score (index/hamming.h), tentative
//    matches must have close signatures (index/search/rerank.h; at most max_tentative_matches of them, the
//    closest, per candidate), and query expansion re-orders the unverified results by the Hamming
//    score of the query plus the verified regions' features instead of the averaged tf-idf vector
//    below; transitive verification (6.) filters its tentative matches by signature the same way.
// 5. Average query expansion (Chum et al. 2007, "Total recall"), optional: the query's tf-idf vector
//    and those of the first `qe_images` verified results (each restricted to the features inside the
//    region it matched, all L2-normalised) are averaged and the index is queried again; the verified
//    results stay first, the rest of the list follows the expanded query's scores.
// 6. Transitive verification (same paper, its transitive closure), optional: the first
//    `transitive_depth` unverified results are verified against the matched regions of up to
//    `transitive_anchors` verified results (directly verified first, then the transitively verified
//    ones of earlier rounds; only firm ones, sift::VerificationResult::firm: not a line of matched
//    text), and those that pass are ranked right after the directly verified ones (by inliers); a
//    result whose match with the query was rejected as only an overlay on at least 30 inliers (a logo
//    both carry; with Hamming embedding, index/search/rerank.h) is not tried. Their
//    db_from_query is the composition through the result they matched. Each anchor
//    only checks its own `transitive_neighbours` best tf-idf matches among the results so far, and
//    each candidate is verified against at most `transitive_attempts` of a round's anchors (those that
//    score it highest).
//
// ==== Storage and durability ========================================================================
//
// An index is a folder:
//   catalogue.sqlite   SQLite (WAL, synchronous=FULL): table `meta` (schema version, vocabulary
//                      fingerprint, extractor settings, checkpoint manifest), table `images` (internal
//                      number, id, source path, width, height, feature count, metadata JSON, added
//                      time) and table `features` (the image's words + geometry as a checksummed BLOB;
//                      storage/catalogue.h). Add/Remove commit one transaction before they return, so an
//                      acknowledged change survives a crash or kill -9 at any moment and a half-done
//                      one is rolled back by SQLite.
//   *.oxck             checkpoint files (storage/checkpoint.h): the inverted file and the packed geometry as
//                      of the manifest in `meta`, written by a background thread and at close.
//   vocabulary.oxvoc   a copy of the vocabulary (vocab::Vocabulary file format, CRC-checked); its
//                      fingerprint must equal the one in `meta`.
// Open loads the checkpoint (the postings file verified by checksum; geometry memory-mapped, its size
// and image table checked at open and its data on use: at every use, that the file still holds the
// image's bytes and the image's checksum; each file whole by the checkpointer right after open; damaged
// or truncated geometry is read from the catalogue's BLOBs and rewritten by the next checkpoint) and
// replays the catalogue's changes since; without a usable checkpoint (none yet, or a file missing,
// damaged or inconsistent: logged) it rebuilds from the BLOBs (one pass, O(total features)) and
// checkpoints again in the background. A BLOB that Open reads (a rebuild reads all, a replay those
// added since the checkpoint) and finds damaged (checksum) costs that image only: it is dropped from
// the index and its catalogue row deleted, with an error logged naming it. The BLOBs a checkpoint
// covers are not read by an open: `oxbow index check` checks them all (CheckIndexFolder, storage/catalogue.h).
// A checkpoint names the geometry files its images are in; it drops those mostly of removed images
// and merges small ones (KeptGeometry, storage/geometry_parts.h), so files, disk and descriptors stay bounded.
// Open refuses: a folder without a catalogue, an unknown schema version, a vocabulary copy whose
// fingerprint differs from the catalogue's, a damaged SQLite file (its image records are checked
// with SQLite's integrity check at every open: Catalogue::CheckRecords); and,
// with kIoError, a folder it cannot write (read-only permissions or file system): the index is always
// open for writing. Open validates through a read-only connection and writes nothing to a catalogue it
// refuses (a stray or foreign catalogue.sqlite-wal is not checkpointed into it).
//
// ==== Thread safety =================================================================================
//
// All const members (Query, QuerySimilar, OpenSearch, Get, List, Stats, CountLive, vocabulary,
// extractor_settings) may run concurrently with each other and with the writers, from any number of
// threads, and never wait for a writer: each call takes the current immutable snapshot
// (storage/snapshot.h; a shared_ptr copied under a mutex held only for the copy) and works on it.
// Add, AddBatch, Replace, Remove and PinCollectionStatistics serialise on the writer mutex; each writes
// SQLite, builds the next snapshot (sharing every unchanged part with the previous one) and publishes
// it. A query sees an image either fully added or not at all.
//
// Threads besides the callers': the checkpointer's (storage/checkpointer.h: background checkpoints)
// and, after an open, its verifier (the background check of the geometry files); the catalogue's log
// copier (storage/catalogue.h); the shared pool of ParallelFor.
//
// Locks (in the order they are taken; each is documented where it is declared):
//   ImageIndex::Impl::writer_mutex      (image_index.cc) one writer at a time: the catalogue's write
//                                       connection, the next snapshot from Current() to Publish(), and
//                                       the checkpointer's state; the checkpointer takes it to start,
//                                       commit and publish a checkpoint, never while writing files.
//   Checkpointer::segment_files_mutex_  (storage/checkpointer.h) the segment files already written.
//   CurrentSnapshot's mutex             (storage/snapshot.h) only the snapshot pointer.
//   GeometryPart's two mutexes          (storage/geometry_parts.h) a file's whole check, and its images
//                                       read back from the catalogue.
// The last three are leaves. No function is handed a held lock; the checkpointer's steps each take
// the writer mutex with a scoped guard.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "index/postings/inverted_file.h"  // TfIdfOptions: the defaults IndexOptions shares
#include "sift/base/error.h"
#include "sift/types.h"
#include "sift/verify.h"
#include "vocab/vocabulary.h"

namespace oxbow::index {

inline constexpr int kSchemaVersion = 2;  // version of catalogue.sqlite's schema (1 is migrated at open)

// Options fixed for the life of an open index (scoring behaviour and performance).
struct IndexOptions {
  // --- Behaviour (change scores)
  // Burstiness down-weighting: use sqrt(tf) instead of tf in both query and image vectors (Jegou et al.
  // 2009). Measured on Paris: see README (index section).
  bool sqrt_tf = true;
  // Stop list: query words contained in more than this fraction of the live images are ignored when
  // scoring (their idf is below log(1 / fraction)). Image norms still count every word. (0, 1];
  // 1 keeps every word (except those in every image, whose idf is 0 anyway). A query all of whose words
  // would be dropped is scored with all of them.
  double max_document_frequency = TfIdfOptions{}.max_document_frequency;
  // The stop list never drops a word contained in at most this many live images (a floor that keeps
  // small collections whole: the fraction alone would drop most words of a 20-image index, or of a
  // 5k-word vocabulary on Paris, see README). [0, 2^32). With the defaults (0.1, 10,000) the stop list
  // is a no-op up to 10,000 images and drops the words of more than 10% of the images from 100,000 on
  // (TfIdfOptions): fast at a million images without changing small collections' results.
  uint32_t stop_list_min_images = TfIdfOptions{}.stop_list_min_images;
  // --- Performance
  // Merge policy of the segment log: at most this many segments of about the same size before they are
  // merged into one. [2, 64].
  int merge_factor = 8;
  // Threads used by Open to rebuild the index, by AddBatch (one image per thread), and by a single
  // Add or Query to quantise its descriptors and re-rank; 0 = all hardware threads. [0, 256]. Results
  // do not depend on it.
  int num_threads = 0;
  // Checkpoints (index/storage/checkpoint.h): a background thread writes one once the images added + removed
  // since the last exceed max(checkpoint_changes, 10% of the live images); Open replays at most that
  // many images from their BLOBs. Close writes one when anything changed. [1, 2^32).
  uint64_t checkpoint_changes = 10000;
  // Search parameters of the vocabulary quantiser: Add uses them as they are (num_threads aside, see
  // num_threads), Query with QueryOptions::quantizer_probes instead of num_probes. Deliberately more probes when adding (16,
  // vocab::QuantizerOptions) than when querying (8): adding is paid once per image, and 8 probes at
  // index time measured 0.006-0.008 lower mAP (Paris subset, 20k words, three vocabulary seeds) and
  // 0.003 lower on groups_dev for 5-15% less indexing CPU (eval/results/vocabulary.md).
  vocab::QuantizerOptions quantizer;

  std::optional<std::string> Check() const;  // message for an invalid field, nullopt when valid
};

struct ImageRecord;
namespace search {
class Source;  // index/search/source.h
}  // namespace search

// Filtered search: which indexed images a query may return (api/filter.h builds one from the `filter`
// search parameter). A query asks it about every live image once, from several threads at once, and
// keeps the answers in an allow-bitmap over image numbers that tf-idf scoring (first pass and query
// expansion) consults, so re-ranking, expansion and transitive verification only ever see allowed
// images and the top-k are the best allowed ones, not a post-filtered top-k.
class ImageFilter {
 public:
  virtual ~ImageFilter() = default;
  [[nodiscard]] virtual bool Matches(const ImageRecord& record) const = 0;  // thread-safe
  // The filter as text that api::ParseFilter parses back into an equal filter: what a cluster's front
  // sends its partitions, which filter while they score. Empty for a filter that has no such text (a
  // front refuses it).
  [[nodiscard]] virtual std::string Text() const { return {}; }
};

// Per-query options. CLI flags and HTTP parameters map 1:1 onto these fields.
struct QueryOptions {
  // Number of results returned. [1, 10000].
  int top_k = 20;
  // Spatial re-ranking depth R: the top R tf-idf candidates are verified; 0 disables re-ranking.
  // [0, 10000]. 200 verifies the views that tf-idf ranks past 100 (eval/results/accuracy.md, "Re-ranking
  // depth").
  int rerank_depth = 200;
  // Query region x1,y1,x2,y2 in query-image pixels (x1 < x2, y1 < y2): only features whose keypoint lies
  // inside (x1 <= x <= x2, y1 <= y <= y2) are used, as in the Oxford/Paris queries. Unset: the whole image.
  std::optional<std::array<float, 4>> region;
  // An image query (Query; not QuerySimilar, whose stored features keep no DoG response) uses at most
  // this many of its features inside the region: the strongest by |DoG response|, ties by extraction
  // order. With Hamming embedding, transitive verification verifies against an anchor's region with
  // at most this many of its features too, those of its rarest words (highest idf; ties by feature
  // order). Every stage after
  // extraction grows with these counts: a 1600-pixel photo of a textured object gives 7000-37000
  // features. Measured with 3000 (eval/results/accuracy.md, "Query cost settings"): mAP equal or better
  // on the three dev sets than without a limit, p95 after extraction about a third lower.
  // 0 = all. [0, 1000000].
  int max_query_features = 3000;
  // Postings each tf-idf pass (the first one and query expansion's) may scan, at most, estimated from
  // the document frequencies: a longer query keeps its words of largest per-posting contribution
  // (InvertedFile::WithinPostingBudget: the rare words) and drops the most frequent ones, whose long
  // lists are most of a search's time at 1M images. With Hamming embedding (the default) the tf-idf
  // pass only picks the hamming_shortlist candidates that the signatures re-score, and there a 4M budget
  // costs the Paris subset planted among 1M synthetic images 0.141 -> 0.134 mAP, for a search 1.3-1.5x
  // faster (eval/results/index-scale.md, "Posting budget"); without Hamming embedding it costs a quarter
  // of that mAP (0.473 -> 0.342). A query scans at most (images) x (its distinct words) postings, so
  // below 666 images
  // (6000 words: an expanded query of 3000 features) it provably changes nothing, and a collection of
  // a few thousand images does not reach millions. 0 = no limit. [0, 2000000000].
  int max_scored_postings = 4'000'000;
  // Average query expansion (Chum et al. 2007): the query is re-issued as the average of itself and its
  // best `qe_images` verified results (its words of largest weight, twice as many as the query's,
  // which makes that pass cheaper and measured no worse on Paris and groups_dev). On by default (every command and the server): it raises mAP at
  // every vocabulary size on the Paris subset (README) for a few ms. Averages verified results, so it
  // does nothing when rerank_depth is 0.
  bool query_expansion = true;
  // Multiple assignment of the query's descriptors when scoring (Philbin et al. 2008, "Lost in
  // quantization"; Jegou et al. 2010): each descriptor counts for its `query_assignments` nearest
  // words, word j with weight exp(-(d_j^2 - d_1^2) / (2 assignment_sigma_sq)), d_j its distance to
  // centroid j (d_1 the nearest, weight 1). Re-ranking still uses the nearest word. [1, 8]; 1 = hard
  // assignment. Ignored by QuerySimilar (stored images keep one word per feature).
  int query_assignments = 1;
  // Coarse lists of the vocabulary's quantiser probed per query descriptor (vocab::QuantizerOptions::
  // num_probes for the query; images are added with IndexOptions::quantizer). Fewer probes: faster,
  // more descriptors miss their exact nearest word. [1, 4096]. Default chosen by measurement on Paris
  // (8 probes: 0.916 recall@1 at 10k words, 1.6x the speed of 16; eval/results/vocabulary.md).
  int quantizer_probes = 8;
  // Kernel width of the assignment weights, in squared descriptor distance (RootSIFT descriptors have
  // unit L2 norm, so squared distances lie in [0, 4]). (0, 4].
  double assignment_sigma_sq = 0.02;
  // Hamming-embedding re-scoring (index/hamming.h; Jegou et al. 2008, with burstiness normalisation,
  // Jegou et al. 2009): the `hamming_shortlist` best tf-idf candidates are re-scored by matching the
  // query's features to theirs word by word, each match weighted by the similarity of their 64-bit
  // signatures, and re-ordered by that score before spatial re-ranking. Needs a vocabulary with
  // Hamming-embedding parameters (`oxbow vocab train --hamming`) and images added with it; ignored
  // otherwise, and for images without signatures (they keep their tf-idf order after the re-scored ones).
  // On by default: it measures better on groups_hard and groups_dev and equal on Paris
  // (eval/results/accuracy.md).
  bool hamming = true;
  // Candidates re-scored. [1, 10000]. 300 gives the dev sets the mAP of 1000 (groups_hard + distractors,
  // the only one above 300 images: 0.6148 both), and at 1M images a search reads a third of the features
  // 1000 would (cold p50 over HTTP 129 against 287 ms; eval/results/index-scale.md).
  int hamming_shortlist = 300;
  // Largest Hamming distance between two signatures that still matches. [0, 64]. 32 measured best
  // over the three dev sets together (README: 24 is better on groups_hard alone, worse on Paris).
  int hamming_threshold = 32;
  // With Hamming embedding, a candidate's tentative matches given to the verifier, at most: the
  // closest signatures first. An unrelated image shares thousands of words with a large query or
  // anchor, about half of their pairs pass the threshold, and the verifier's votes for those were most
  // of transitive verification's time. Measured with 500 (eval/results/accuracy.md): mAP up on the three
  // dev sets and transitive verification about a third cheaper per candidate. 0 = no limit.
  // [0, 1000000].
  int max_tentative_matches = 500;
  // Width of the match weight exp(-h^2 / sigma^2), in bits. (0, 64].
  double hamming_sigma = 16;
  // The candidate's share of the Hamming-embedding score's normalisation: the score is divided by
  // N_q^(1 - e) N_d^e, N the query's and the candidate's self-scores (index/search/hamming.h); 0.5 is
  // the symmetric form. Larger values weigh a candidate's size more, so a large image that shares many
  // words with the query by chance ranks below a smaller one whose features match. [0, 1]. Measured
  // (eval/results/accuracy.md, "Score normalisation"): 0.9 against 0.5 raises the Paris subset from
  // 0.937 to 0.949, groups_dev from 0.993 to 0.997 and groups_hard + distractors from 0.711 / 0.897
  // to 0.768 / 0.913 (mAP / recall@1).
  double hamming_norm_exponent = 0.9;
  // Aggregated matching (ASMK*, index/search/hamming.h): the Hamming-embedding re-scoring adds this
  // many times an aggregated score, where each image is one majority signature per word. asmk_weight
  // for the re-scoring of the tf-idf shortlist, qe_asmk_weight for query expansion's re-scoring of the
  // unverified results (its expanded query holds the query's features and those of its verified
  // results: a word's consensus over several views votes once). 0 = Hamming embedding alone. [0, 1000].
  // Measured (eval/results/accuracy.md, "Aggregated matching"): in the expansion, 20 raises
  // groups_hard + distractors from 0.654 / 0.873 to 0.711 / 0.897 (mAP / recall@1) and groups_dev
  // from 0.991 to 0.993, for 0.004 on Paris; in the first re-scoring it buys nothing.
  int asmk_weight = 0;
  int qe_asmk_weight = 20;
  // Verified results whose features join the expanded query. [1, 100]. Measured over three vocabulary
  // seeds (eval/results/accuracy.md, "Query settings over three vocabularies"): 10 against 5 raises the
  // Paris subset with every seed (mean 0.932 to 0.944; 8 and 20 the same as 10), while groups_dev and
  // groups_hard + distractors, whose queries rarely have more than 5 verified results, are unchanged.
  int qe_images = 10;
  // Transitive verification, the transitive closure of Chum et al. 2007 ("Total recall"): the first
  // `transitive_depth` unverified results of the ranking (the expanded one with query_expansion) are
  // verified against the regions matched in verified results ("anchors": the directly verified ones
  // best first, then those verified transitively, round after round; only firm verifications anchor,
  // sift::VerificationResult::firm); those that pass join the
  // verified results, after the directly verified ones, by inliers. A result whose own match with the
  // query was rejected as an overlay (a logo both carry) on at least 30 inliers is not tried. Finds views too different from the
  // query to match it directly. 0 disables. [0, 10000]. Does nothing without re-ranking
  // (rerank_depth 0: nothing is verified). Default chosen by measurement on Paris (see README).
  int transitive_depth = 200;
  // At most this many anchors in all. [1, 1000].
  int transitive_anchors = 20;
  // An anchor is only verified against candidates among its own `transitive_neighbours` best tf-idf
  // matches (its matched region's words as a tf-idf query), ranked among the results so far (the
  // verified ones and the transitive_depth candidates, scored from their bags: no pass over the index,
  // so the cost does not grow with the collection; on a small collection these are its nearest images
  // in the whole index). Cost: at most transitive_anchors * min(transitive_depth,
  // transitive_neighbours) verifications (a candidate stops at its first verifying anchor). [1, 10000].
  int transitive_neighbours = 30;
  // A candidate is verified against at most this many anchors: those among whose neighbours it scores
  // highest (ties: earlier anchor first). Bounds the cost of candidates that verify against none
  // (negatives) to transitive_attempts verifications each. [1, 1000].
  int transitive_attempts = 2;
  // A shared word contributes all its query x image feature pairs as tentative matches when both sides
  // have at most this many features with that word; burstier words are skipped (not with Hamming
  // embedding, whose signatures filter the pairs instead). [1, 100].
  int max_pairs_per_word = 4;
  // Verifier settings (sift/verify.h); min_inliers decides what counts as verified.
  sift::HoughVerifyOptions verify;
  // When non-empty, must equal the index's extractor settings (refuses features from another extractor).
  std::string extractor_settings;
  // Only images this allows are scored and returned (null: every image). Cost: one Matches call per
  // live image per query (server/README.md); QuerySimilar's own image too must match to be
  // returned.
  std::shared_ptr<const ImageFilter> filter;

  std::optional<std::string> Check() const;
};

// What the caller knows about an image besides its features.
struct ImageInfo {
  std::string source_path;     // where it came from (informational), may be empty
  std::string metadata_json;   // user metadata, a JSON document (validated as JSON by api/, stored as is)
  // When non-empty, must equal the index's extractor settings (sift::SiftOptions::Describe()).
  std::string extractor_settings;
};

// One indexed image, as stored in the catalogue.
struct ImageRecord {
  std::string id;              // external key, unique, 1..256 bytes, no control characters
  std::string source_path;
  int width = 0;               // pixels
  int height = 0;
  uint32_t num_features = 0;   // indexed features (keypoints)
  std::string metadata_json;
  int64_t added_unix_ms = 0;   // wall-clock time of the Add, milliseconds since 1970 UTC

  bool operator==(const ImageRecord&) const = default;
};

// One image of ImageIndex::AddBatch (`features` must stay valid during the call).
struct BatchImage {
  std::string id;
  const sift::FeatureSet* features = nullptr;
  ImageInfo info;
  // Visual words already assigned with this index's vocabulary, one per keypoint (ingest of
  // pre-quantised features, e.g. the storage benchmark): quantisation is skipped and the
  // descriptors may be empty. Each word must be < the vocabulary size.
  std::span<const uint32_t> words;
  // With `words`: their Hamming-embedding signatures, one per keypoint, as vocab::Vocabulary::Signatures
  // gives them (e.g. computed once per real descriptor by the storage benchmark). Only for a vocabulary
  // with Hamming-embedding parameters. Empty: computed from the descriptors when they are given, else
  // the image is stored without signatures (it then has no Hamming score).
  std::span<const uint64_t> signatures;
};

struct QueryResult {
  std::string id;
  double score = 0;            // tf-idf cosine in [0, 1] (of the expanded query for QE-only results;
                               // the Hamming-embedding score with QueryOptions::hamming)
  bool verified = false;       // passed spatial verification
  int inliers = 0;             // inlier correspondences (0 when not re-ranked); with `via`, those
                               // with the anchor's matched region, not with the query
  std::string via;             // verified transitively: the id of the verified result (the anchor)
                               // whose matched region verified this one; empty when verified against
                               // the query itself (or not verified)
  sift::Affine2D db_from_query;  // query-image pixels -> db-image pixels (identity when not verified)
  std::array<float, 4> db_region = {0, 0, 0, 0};  // x1,y1,x2,y2 in the db image (zeros when not verified)
  ImageRecord record;          // catalogue entry (id, size, metadata, ...)
};

// Wall time of each stage of a query, milliseconds.
struct QueryTimings {
  double quantize_ms = 0;      // descriptors -> words (and Hamming-embedding signatures)
  double score_ms = 0;         // tf-idf over the inverted file (+ top-R selection), and with
                               // QueryOptions::hamming the re-scoring of the shortlist
  double verify_ms = 0;        // spatial re-ranking
  double qe_ms = 0;            // query expansion (second scoring)
  double total_ms = 0;
};

struct QueryResponse {
  std::vector<QueryResult> results;  // best first, at most top_k
  uint32_t query_features = 0;       // features used (inside the region)
  uint64_t candidates = 0;           // images with a non-zero tf-idf score (allowed ones, with a filter)
  QueryTimings timings;
};

struct IndexStats {
  uint64_t num_images = 0;           // live images
  uint64_t num_features = 0;         // indexed features of the live images
  uint64_t postings_bytes = 0;       // inverted file (postings + per-word offsets), bytes in memory
  uint64_t geometry_bytes = 0;       // per-feature words + geometry, bytes in memory
  uint64_t other_bytes = 0;          // per-image tables (norms, records, id map), bytes in memory, approx.
  double bytes_per_feature = 0;      // (postings + geometry + other) / num_features
  uint64_t num_segments = 0;         // inverted-file segments
  uint64_t vocabulary_size = 0;
  uint64_t vocabulary_fingerprint = 0;
};

class ImageIndex {
 public:

  // Creates a new, empty index in `dir` (created if missing; must not already hold an index).
  // `extractor_settings` (sift::SiftOptions::Describe()) must equal vocabulary.extractor_settings()
  // when the latter is non-empty. Errors: kAlreadyExists, kIncompatible, kIoError, kInvalidArgument.
  [[nodiscard]] static Result<std::unique_ptr<ImageIndex>> Create(const std::string& dir,
                                                                  const vocab::Vocabulary& vocabulary,
                                                                  std::string extractor_settings,
                                                                  const IndexOptions& options = {});
  // Opens an existing index (see "Storage" above for what is refused). O(images + changes since the
  // checkpoint + checkpoint file bytes verified); O(total features) when it must rebuild.
  [[nodiscard]] static Result<std::unique_ptr<ImageIndex>> Open(const std::string& dir,
                                                                const IndexOptions& options = {});
  // Opens an existing index to read it only, as Open checks it, writing nothing to the folder (but
  // SQLite's shared-memory index and an empty WAL beside the catalogue, catalogue.h): several
  // read-only opens (other processes, e.g. the ranks of `index duplicates --mpi`) may hold it at once,
  // and no writer opens it meanwhile (a shared folder lock). A checkpoint that must be rebuilt is rebuilt
  // in memory; images with damaged features are left out; no checkpointer runs. Every write (Add,
  // Replace, AddBatch, Remove, PinCollectionStatistics) answers kIncompatible. kIncompatible too for a
  // catalogue an earlier build wrote (open it for writing once to migrate it).
  [[nodiscard]] static Result<std::unique_ptr<ImageIndex>> OpenReadOnly(const std::string& dir,
                                                                        const IndexOptions& options = {});
  // True when `dir` holds an index catalogue (cheap check, no validation).
  static bool Exists(const std::string& dir);

  ~ImageIndex();
  ImageIndex(const ImageIndex&) = delete;
  ImageIndex& operator=(const ImageIndex&) = delete;

  // Quantises and adds one image, durably (committed before returning). `features.kind` must be the
  // vocabulary's descriptor kind. Errors: kInvalidArgument (bad id, size mismatch, non-positive image
  // size), kAlreadyExists (id taken), kIncompatible (descriptor kind / extractor settings), kIoError.
  // Cost: quantisation + O(features + sum of n_w over the image's distinct words) + the amortised merge.
  [[nodiscard]] Result<ImageRecord> Add(const std::string& id, const sift::FeatureSet& features,
                                        const ImageInfo& info);
  // Adds several images in one durable SQLite transaction and one published snapshot, quantising them
  // on IndexOptions::num_threads threads: one result per image, in order. An image that fails
  // validation (id, features, settings, an id already indexed or repeated earlier in the batch) gets
  // its own error and the others are added; a catalogue failure (kIoError) fails every image and
  // changes nothing. Bulk ingest: the per-commit costs (fsync, snapshot) are paid once per batch.
  [[nodiscard]] std::vector<Result<ImageRecord>> AddBatch(std::span<const BatchImage> images);
  // Adds one image as Add does, or, when `id` is indexed, replaces it: the removal of the old image and
  // the addition of the new one are one durable SQLite transaction and one published snapshot, so a
  // crash or a failure at any moment leaves the old image or the new one, never neither, and a query
  // sees one of them. Errors as Add (except kAlreadyExists); nothing changed on an error.
  [[nodiscard]] Result<ImageRecord> Replace(const std::string& id, const sift::FeatureSet& features,
                                            const ImageInfo& info);
  // Removes an image durably. kNotFound for an unknown id. Cost O(sum of n_w over its distinct words).
  [[nodiscard]] Status Remove(const std::string& id);

  [[nodiscard]] Result<ImageRecord> Get(const std::string& id) const;        // kNotFound if unknown
  [[nodiscard]] bool Contains(const std::string& id) const;
  // Live images ordered by id, [offset, offset + limit). O(N log N) per call.
  [[nodiscard]] Result<std::vector<ImageRecord>> List(uint64_t offset, uint64_t limit) const;

  // Ranks the indexed images for the query features (see "Method"). Errors: kInvalidArgument (options,
  // sizes), kIncompatible (descriptor kind / extractor settings). A query with no usable feature returns
  // an empty result list, not an error.
  [[nodiscard]] Result<QueryResponse> Query(const sift::FeatureSet& query, const QueryOptions& options) const;
  // Queries with an indexed image's own stored words and geometry (the image itself ranks first).
  // kNotFound for an unknown id. `options.region` applies to that image's coordinates.
  [[nodiscard]] Result<QueryResponse> QuerySimilar(const std::string& id, const QueryOptions& options) const;

  // --- A partition of a cluster (api/partition.h, server/cluster/): the front runs the search pipeline
  // over the partitions (OpenSearch below), which score with the cluster's statistics.
  // Scores with the whole cluster's statistics from now on (InvertedFile::WithPinnedStatistics; not
  // stored: the caller pins again after Open). kInvalidArgument unless one frequency per word.
  [[nodiscard]] Status PinCollectionStatistics(uint64_t num_images, std::span<const uint32_t> document_frequency);
  // This index's own live counts: its images, and per word the images containing it now (a cluster's
  // statistics are their sums over the partitions). O(vocabulary size).
  struct LiveCounts {
    uint64_t num_images = 0;
    std::vector<uint32_t> document_frequency;
  };
  LiveCounts CountLive() const;
  // A search over the current snapshot (index/search/source.h): what Query and QuerySimilar run the
  // search pipeline over, and what a cluster partition answers its front's calls with. It keeps that
  // snapshot (and so the images it holds) alive until it is destroyed.
  std::unique_ptr<search::Source> OpenSearch() const;

  IndexStats Stats() const;
  // Catalogue::WriteSequence as of the last committed write: images inserted + removed over the index's
  // life (a replacement counts 2). Replicas of a cluster partition that applied the same writes agree.
  uint64_t write_sequence() const;
  const vocab::Vocabulary& vocabulary() const;
  const std::string& extractor_settings() const;
  const std::string& directory() const;

  struct Impl;

 private:
  explicit ImageIndex(std::unique_ptr<Impl> impl);
  static Result<std::unique_ptr<ImageIndex>> OpenFolder(const std::string& dir, const IndexOptions& options,
                                                        bool read_only);
  std::unique_ptr<Impl> impl_;
};

}  // namespace oxbow::index
