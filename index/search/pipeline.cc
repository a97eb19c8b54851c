// The search pipeline over a Source (see pipeline.h).
#include "index/search/pipeline.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>

#include "index/search/hamming.h"
#include "index/search/kept_memory.h"
#include "sift/base/parallel.h"

namespace oxbow::index::search {
namespace {

using Clock = std::chrono::steady_clock;

double MsSince(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

// A match with the query rejected as only an overlay on at least this many inliers keeps its image out
// of transitive verification: a pasted logo or caption matches itself with dozens of inliers (60 and
// more on the duplicate benchmark), while a rejection on a few (a facade's repeated pattern with alike
// signatures: 16 on a Paris photo) may be wrong, and a chain may still verify the image.
constexpr int kCertainOverlayInliers = 30;

// A result while the stages rank it: the image as the source names it, and what it became.
struct Hit {
  ImageRef ref;
  QueryResult result;  // without its record until the end
  bool firm = false;   // verified, and firmly (sift::VerificationResult::firm): may anchor a chain
  bool overlay = false;  // the query's own verification rejected it as sharing only an overlay, on at
                         // least kCertainOverlayInliers inliers: no chain may verify it
};

std::vector<ImageRef> RefsOf(std::span<const Hit> hits) {
  std::vector<ImageRef> refs(hits.size());
  for (size_t i = 0; i < hits.size(); ++i) refs[i] = hits[i].ref;
  return refs;
}

std::vector<std::array<float, 4>> RegionsOf(std::span<const Hit> hits) {
  std::vector<std::array<float, 4>> regions(hits.size());
  for (size_t i = 0; i < hits.size(); ++i) regions[i] = hits[i].result.db_region;
  return regions;
}

// Re-ranking's order: verified first by inliers (then score), the unverified after them in the order
// given (stable).
void SortVerifiedFirst(std::span<Hit> hits) {
  std::stable_sort(hits.begin(), hits.end(), [](const Hit& x, const Hit& y) {
    const QueryResult& a = x.result;
    const QueryResult& b = y.result;
    if (a.verified != b.verified) return a.verified;
    if (a.verified && a.inliers != b.inliers) return a.inliers > b.inliers;
    return a.score > b.score;
  });
}

// Indices 0..n-1 ordered by descending score, NaN (no signatures) last, ties and NaNs in index order.
std::vector<size_t> ByScore(const std::vector<double>& scores) {
  std::vector<size_t> order(scores.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    if (std::isnan(scores[a]) || std::isnan(scores[b])) return !std::isnan(scores[a]) && std::isnan(scores[b]);
    return scores[a] > scores[b];
  });
  return order;
}

// hits[0, n) re-ordered by `scores` (ByScore), each taking its score unless NaN.
void ReorderByScore(std::span<Hit> hits, const std::vector<double>& scores) {
  const std::vector<Hit> before(hits.begin(), hits.end());
  const std::vector<size_t> order = ByScore(scores);
  for (size_t c = 0; c < order.size(); ++c) {
    hits[c] = before[order[c]];
    if (!std::isnan(scores[order[c]])) hits[c].result.score = scores[order[c]];
  }
}

// 1b. The Hamming-embedding re-scoring of the first hamming_shortlist hits (tf-idf order); hits
// without signatures follow the re-scored ones in their tf-idf order.
Status RescoreHamming(Source& source, const QueryFeatures& query, const QueryOptions& options, std::vector<Hit>& hits) {
  const size_t shortlist = std::min(hits.size(), static_cast<size_t>(options.hamming_shortlist));
  const std::vector<ImageRef> refs = RefsOf(std::span(hits).first(shortlist));
  auto scores = source.HammingScores(query.words, query.signatures, refs, options);
  if (!scores) return std::unexpected(scores.error());
  ReorderByScore(std::span(hits).first(shortlist), *scores);
  // Scores are floats as tf-idf's (a single index's re-scoring wrote them back into its float scores).
  for (size_t c = 0; c < shortlist; ++c) hits[c].result.score = static_cast<float>(hits[c].result.score);
  return Ok();
}

// 2. Spatial re-ranking of the first rerank_depth hits; returns how many it verified (first).
Result<size_t> Rerank(Source& source, const QueryFeatures& query, const QueryOptions& options, std::vector<Hit>& hits) {
  const size_t rerank = std::min(hits.size(), static_cast<size_t>(options.rerank_depth));
  if (rerank == 0) return size_t{0};
  GeometryQuery geometry{.keypoints = query.keypoints, .words = query.words, .signatures = query.signatures};
  geometry.region = options.region ? *options.region
                                   : std::array<float, 4>{0, 0, static_cast<float>(query.width),
                                                          static_cast<float>(query.height)};
  std::vector<VerifyTask> tasks(rerank);
  for (size_t c = 0; c < rerank; ++c) tasks[c] = {.ref = hits[c].ref, .geometries = {0}};
  auto verified = source.Verify(std::span(&geometry, 1), tasks, options);
  if (!verified) return std::unexpected(verified.error());
  for (size_t c = 0; c < rerank; ++c) {
    const sift::VerificationResult& v = (*verified)[c].result;
    QueryResult& r = hits[c].result;
    r.inliers = v.num_inliers;
    hits[c].firm = v.firm;
    hits[c].overlay = (*verified)[c].overlay && v.num_inliers >= kCertainOverlayInliers;
    if (v.verified) {
      r.verified = true;
      r.db_from_query = v.db_from_query;
      r.db_region = v.db_region;
    }
  }
  SortVerifiedFirst(std::span(hits).first(rerank));
  size_t num_verified = 0;
  for (size_t c = 0; c < rerank; ++c) num_verified += hits[c].result.verified ? 1 : 0;
  return num_verified;
}

// 3. Average query expansion (tf-idf): the query's vector averaged with the matched regions' of the
// first qe_images verified hits, scored again; the verified hits stay first, the rest follows the
// expanded query's scores.
Status ExpandQuery(Source& source, std::span<const QueryTerm> terms, const QueryOptions& options, size_t num_verified,
                   std::vector<Hit>& hits) {
  const size_t used = std::min(num_verified, static_cast<size_t>(options.qe_images));
  const std::span<const Hit> anchors = std::span(hits).first(used);
  auto regions = source.RegionTerms(RefsOf(anchors), RegionsOf(anchors));
  if (!regions) return std::unexpected(regions.error());
  const std::vector<QueryTerm> expanded = search::ExpandedQuery(terms, *regions);
  // Deep enough for transitive verification's window as well as for top_k.
  const size_t expanded_depth =
      static_cast<size_t>(std::max(options.top_k, options.transitive_depth > 0 ? options.transitive_depth : 0));
  auto rescored = source.Score(ScoreInput{.terms = expanded}, expanded_depth + num_verified, options);
  if (!rescored) return std::unexpected(rescored.error());
  std::vector<Hit> merged(hits.begin(), hits.begin() + static_cast<std::ptrdiff_t>(num_verified));
  std::map<ImageRef, const Hit*> first_stage;
  for (const Hit& h : hits) first_stage[h.ref] = &h;
  for (const ScoredRef& s : rescored->best) {
    const auto it = first_stage.find(s.ref);
    if (it != first_stage.end() && it->second->result.verified) continue;
    Hit h;
    if (it != first_stage.end()) h = *it->second;
    h.ref = s.ref;
    h.result.id = s.id;
    h.result.score = s.score;
    merged.push_back(std::move(h));
  }
  hits = std::move(merged);
  return Ok();
}

// 3. Query expansion with Hamming embedding: the unverified hits re-ordered by their Hamming score
// against the query's features plus those inside the matched regions of its first qe_images verified
// hits (with their signatures), with qe_asmk_weight times their aggregated score added.
Status ExpandQueryHamming(Source& source, const QueryFeatures& query, const QueryOptions& options, size_t num_verified,
                          std::vector<Hit>& hits) {
  std::vector<uint32_t> words = query.words;
  std::vector<uint64_t> signatures = query.signatures;
  const size_t used = std::min(num_verified, static_cast<size_t>(options.qe_images));
  const std::span<const Hit> anchors = std::span(hits).first(used);
  auto features = source.Features(RefsOf(anchors), RegionsOf(anchors), FeaturesRequest{.signatures = true});
  if (!features) return std::unexpected(features.error());
  for (const RegionFeatures& f : *features) {
    if (f.signatures.size() != f.words.size()) continue;  // an image without signatures adds nothing
    words.insert(words.end(), f.words.begin(), f.words.end());
    signatures.insert(signatures.end(), f.signatures.begin(), f.signatures.end());
  }
  const std::span<Hit> unverified = std::span(hits).subspan(num_verified);
  QueryOptions expanded = options;
  expanded.asmk_weight = options.qe_asmk_weight;
  auto scores = source.HammingScores(words, signatures, RefsOf(unverified), expanded);
  if (!scores) return std::unexpected(scores.error());
  ReorderByScore(unverified, *scores);
  return Ok();
}

// Transitive verification's plan. scores[a][c]: anchor a's matched region (its features inside
// db_region, as a tf-idf query) scored against hits[c], c < last = tie.size(); tie[c] orders equal
// scores (smaller first). Each anchor keeps its transitive_neighbours + 1 best-scoring hits (one for
// itself); each hit of [first, last) not verified yet, and not rejected as an overlay by the query's
// own verification, is tried against at most transitive_attempts of the anchors keeping it, those
// that score it highest, listed in anchor order.
struct Attempt {
  float score = 0;      // the candidate's tf-idf score against the anchor's region
  uint32_t anchor = 0;  // index into the round's anchors
};

// Each anchor only verifies its own nearest tf-idf neighbours (its region's bag scored as a tf-idf
// query): most candidates share little with most anchors, and the verifier is the expensive part.
// Neighbours are ranked among the ranking so far, hits[0, last) (the anchors themselves, the other
// verified hits and the window), scored from their bags: the cost does not grow with the collection,
// and on a small collection, where the ranking holds an anchor's nearest images, the neighbours are
// those of a whole index pass. A candidate is tried against at most transitive_attempts anchors, those
// whose regions score it highest, in anchor order: a view of the object verifies against one of its
// closest anchors or rarely at all, while a negative would otherwise pay one verification per anchor
// listing it.
std::vector<std::vector<Attempt>> PlanAttempts(std::span<const std::vector<float>> scores, std::span<const uint32_t> tie,
                                               std::span<const Hit> hits, size_t first, const QueryOptions& options) {
  struct Neighbour {
    float score;
    uint32_t tie;
    size_t position;  // in `hits`
  };
  const size_t last = tie.size();
  std::vector<std::vector<Attempt>> attempts(last - first);
  for (size_t a = 0; a < scores.size(); ++a) {
    std::vector<Neighbour> list;
    for (size_t c = 0; c < scores[a].size(); ++c) {
      if (scores[a][c] > 0) list.push_back({scores[a][c], tie[c], c});
    }
    // Best first, ties by `tie`; one more for the anchor itself.
    const size_t keep = std::min(list.size(), static_cast<size_t>(options.transitive_neighbours) + 1);
    std::partial_sort(list.begin(), list.begin() + static_cast<std::ptrdiff_t>(keep), list.end(),
                      [](const Neighbour& x, const Neighbour& y) {
                        return x.score != y.score ? x.score > y.score : x.tie < y.tie;
                      });
    list.resize(keep);
    for (const Neighbour& n : list) {
      if (n.position >= first && !hits[n.position].result.verified && !hits[n.position].overlay) {
        attempts[n.position - first].push_back({n.score, static_cast<uint32_t>(a)});
      }
    }
  }
  const auto max_attempts = static_cast<size_t>(options.transitive_attempts);
  for (auto& list : attempts) {
    std::sort(list.begin(), list.end(), [](const Attempt& x, const Attempt& y) {
      return x.score != y.score ? x.score > y.score : x.anchor < y.anchor;
    });
    if (list.size() > max_attempts) list.resize(max_attempts);
    // Among those, the better anchor first (anchors are ordered best first).
    std::sort(list.begin(), list.end(), [](const Attempt& x, const Attempt& y) { return x.anchor < y.anchor; });
  }
  return attempts;
}

// 4. Unverified candidates against the matched regions of verified hits (anchors), in rounds; a
// candidate verified in one round is an anchor of the next, up to transitive_anchors anchors in all. A
// candidate stops at its first anchor that verifies it (attempts in anchor order).
Status VerifyTransitively(Source& source, const QueryOptions& options, bool hamming, size_t num_verified,
                          std::vector<Hit>& hits) {
  const size_t first = num_verified;
  const size_t last = std::min(hits.size(), first + static_cast<size_t>(options.transitive_depth));
  if (auto s = source.RankAmong(RefsOf(std::span(hits).first(last))); !s) return s;
  // Equal neighbour scores are ordered by id: the same order on one index and over partitions.
  std::vector<uint32_t> tie(last);
  {
    std::vector<size_t> by_id(last);
    std::iota(by_id.begin(), by_id.end(), size_t{0});
    std::sort(by_id.begin(), by_id.end(), [&](size_t x, size_t y) { return hits[x].result.id < hits[y].result.id; });
    for (size_t k = 0; k < last; ++k) tie[by_id[k]] = static_cast<uint32_t>(k);
  }
  // Anchor candidates: positions in `hits`, in anchor order. Only firm results anchor: a line of matched
  // text plus one stray point verifies a caption against another, and would pass that on to every copy
  // of the other's photo.
  std::vector<size_t> pool;
  for (size_t c = 0; c < num_verified; ++c) {
    if (hits[c].firm) pool.push_back(c);
  }
  const auto max_anchors = static_cast<size_t>(options.transitive_anchors);
  // With Hamming embedding an anchor's region is verified against as a query is: with at most
  // max_query_features features, those of its rarest words (stored features keep no DoG response).
  // An anchor may be a whole 37000-feature image.
  const FeaturesRequest request{.max_features = hamming ? static_cast<size_t>(options.max_query_features) : 0,
                                .signatures = hamming,
                                .all_words = true};
  size_t used = 0;
  while (used < std::min(pool.size(), max_anchors)) {
    const size_t round_end = std::min(pool.size(), max_anchors);
    std::vector<ImageRef> anchor_refs;
    std::vector<std::array<float, 4>> anchor_regions;
    for (size_t a = used; a < round_end; ++a) {
      anchor_refs.push_back(hits[pool[a]].ref);
      anchor_regions.push_back(hits[pool[a]].result.db_region);
    }
    auto anchors = source.Features(anchor_refs, anchor_regions, request);
    if (!anchors) return std::unexpected(anchors.error());
    std::vector<GeometryQuery> geometries(anchors->size());
    std::vector<std::vector<uint32_t>> anchor_words(anchors->size());
    for (size_t a = 0; a < anchors->size(); ++a) {
      RegionFeatures& f = (*anchors)[a];
      geometries[a] = {.keypoints = f.keypoints, .words = f.words, .signatures = f.signatures,
                       .region = anchor_regions[a]};
      anchor_words[a] = std::move(f.all_words);
    }
    auto scores = source.ScoreAmong(anchor_words);
    if (!scores) return std::unexpected(scores.error());
    const std::vector<std::vector<Attempt>> attempts = PlanAttempts(*scores, tie, hits, first, options);
    // Each candidate against its anchors in anchor order, up to the first that verifies it.
    std::vector<uint8_t> found(last - first, 0);
    std::vector<VerifyTask> tasks;
    std::vector<size_t> positions;
    for (size_t c = first; c < last; ++c) {
      const auto& list = attempts[c - first];
      if (hits[c].result.verified || list.empty()) continue;
      VerifyTask& task = tasks.emplace_back();
      task.ref = hits[c].ref;
      for (const Attempt& attempt : list) task.geometries.push_back(attempt.anchor);
      positions.push_back(c);
    }
    if (!tasks.empty()) {
      auto verified = source.Verify(geometries, tasks, options);
      if (!verified) return std::unexpected(verified.error());
      for (size_t i = 0; i < tasks.size(); ++i) {
        const Verified& v = (*verified)[i];
        if (!v.result.verified) continue;
        hits[positions[i]].firm = v.result.firm;
        QueryResult& r = hits[positions[i]].result;
        r.verified = true;
        r.inliers = v.result.num_inliers;
        const QueryResult& anchor = hits[pool[used + v.geometry]].result;
        r.via = anchor.id;
        r.db_from_query = Compose(v.result.db_from_query, anchor.db_from_query);
        r.db_region = v.result.db_region;
        found[positions[i] - first] = 1;
      }
    }
    used = round_end;
    // The candidates this round verified join the pool, the anchors of later rounds, most inliers first.
    std::vector<size_t> fresh;
    for (size_t c = first; c < last; ++c) {
      if (found[c - first] && hits[c].firm) fresh.push_back(c);
    }
    std::stable_sort(fresh.begin(), fresh.end(),
                     [&](size_t x, size_t y) { return hits[x].result.inliers > hits[y].result.inliers; });
    pool.insert(pool.end(), fresh.begin(), fresh.end());
  }
  // The window once done: verified first by inliers, the rest in the order given (stable).
  std::stable_sort(hits.begin() + static_cast<std::ptrdiff_t>(first), hits.begin() + static_cast<std::ptrdiff_t>(last),
                   [](const Hit& x, const Hit& y) {
                     if (x.result.verified != y.result.verified) return x.result.verified;
                     return x.result.verified && x.result.inliers > y.result.inliers;
                   });
  return Ok();
}

}  // namespace

void SelectInRegion(const sift::FeatureSet& features, const std::optional<std::array<float, 4>>& region,
                    size_t max_features, std::vector<sift::Keypoint>* keypoints, std::vector<float>* descriptors) {
  std::vector<uint32_t> selected;
  for (size_t i = 0; i < features.size(); ++i) {
    const sift::Keypoint& k = features.keypoints[i];
    if (region) {
      const auto& r = *region;
      if (k.x < r[0] || k.x > r[2] || k.y < r[1] || k.y > r[3]) continue;
    }
    selected.push_back(static_cast<uint32_t>(i));
  }
  if (max_features > 0 && selected.size() > max_features) {
    const auto stronger = [&](uint32_t a, uint32_t b) {
      const float ra = std::abs(features.keypoints[a].response), rb = std::abs(features.keypoints[b].response);
      return ra != rb ? ra > rb : a < b;
    };
    std::nth_element(selected.begin(), selected.begin() + static_cast<std::ptrdiff_t>(max_features), selected.end(),
                     stronger);
    selected.resize(max_features);
    std::sort(selected.begin(), selected.end());
  }
  keypoints->reserve(keypoints->size() + selected.size());
  if (!selected.empty()) {
    descriptors->reserve(descriptors->size() + selected.size() * features.Descriptor(selected[0]).size());
  }
  for (const uint32_t i : selected) {
    keypoints->push_back(features.keypoints[i]);
    const auto d = features.Descriptor(i);
    descriptors->insert(descriptors->end(), d.begin(), d.end());
  }
}

QueryFeatures PrepareQuery(const sift::FeatureSet& query, const vocab::Vocabulary& vocabulary,
                           const QueryOptions& options, vocab::QuantizerOptions quantizer) {
  QueryFeatures q;
  q.width = query.image_width;
  q.height = query.image_height;
  // The selected descriptors, in a buffer kept between searches (up to a bound): 1.5 MB at 3000
  // features, which a fresh vector faulted in page by page on every search.
  const auto kept_descriptors = KeptForNextSearch<std::vector<float>>::Shared().Take();
  std::vector<float>& descriptors = *kept_descriptors;
  descriptors.clear();
  SelectInRegion(query, options.region, static_cast<size_t>(options.max_query_features), &q.keypoints, &descriptors);
  q.words.resize(q.keypoints.size());
  quantizer.num_probes = options.quantizer_probes;
  if (options.query_assignments == 1) {
    vocabulary.Quantize(descriptors, q.words, quantizer);
  } else {
    const auto k = static_cast<size_t>(options.query_assignments);
    std::vector<uint32_t> words(q.keypoints.size() * k);
    std::vector<float> sq_distances(words.size());
    vocabulary.QuantizeMulti(descriptors, options.query_assignments, words, sq_distances, quantizer);
    std::map<uint32_t, float> tf;
    const size_t vocabulary_size = vocabulary.size();
    for (size_t i = 0; i < q.keypoints.size(); ++i) {
      q.words[i] = words[i * k];
      for (size_t j = 0; j < k; ++j) {
        const uint32_t w = words[i * k + j];
        if (w >= vocabulary_size || !std::isfinite(sq_distances[i * k + j])) break;
        const double excess = static_cast<double>(sq_distances[i * k + j]) - sq_distances[i * k];
        tf[w] += static_cast<float>(std::exp(-excess / (2 * options.assignment_sigma_sq)));
      }
    }
    for (const auto& [w, c] : tf) {
      q.soft_words.push_back(w);
      q.soft_tf.push_back(c);
    }
  }
  if (options.hamming && vocabulary.has_hamming()) {
    // On the quantiser's threads too: a 64 x 128 projection per descriptor, ~1.4 ms for 2500 on one.
    q.signatures.resize(q.words.size());
    const auto dim = static_cast<size_t>(vocabulary.dimension());
    ParallelFor(q.words.size(), quantizer.num_threads, 512, [&](size_t begin, size_t end, int) {
      vocabulary.Signatures(std::span<const float>(descriptors).subspan(begin * dim, (end - begin) * dim),
                            std::span<const uint32_t>(q.words).subspan(begin, end - begin),
                            std::span<uint64_t>(q.signatures).subspan(begin, end - begin));
    });
  }
  constexpr size_t kMaxKeptFloats = size_t{2} << 20;  // 8 MiB
  if (descriptors.capacity() > kMaxKeptFloats) descriptors = std::vector<float>();
  return q;
}

Result<QueryFeatures> StoredQuery(Source& source, const std::string& id, const QueryOptions& options,
                                  ImageRecord* record) {
  auto found = source.Find(id);
  if (!found) return std::unexpected(found.error());
  const std::optional<ImageRef>& maybe = *found;
  if (!maybe) return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
  const ImageRef ref = *maybe;
  constexpr float kAll = std::numeric_limits<float>::infinity();
  const std::array<float, 4> region = options.region.value_or(std::array<float, 4>{-kAll, -kAll, kAll, kAll});
  auto features = source.Features(std::span(&ref, 1), std::span(&region, 1),
                                  FeaturesRequest{.signatures = options.hamming});
  if (!features) return std::unexpected(features.error());
  auto records = source.Records(std::span(&ref, 1));
  if (!records) return std::unexpected(records.error());
  *record = std::move(records->front());
  RegionFeatures& f = features->front();
  QueryFeatures q;
  q.keypoints = std::move(f.keypoints);
  q.words = std::move(f.words);
  if (f.signatures.size() == q.words.size() && !q.words.empty()) q.signatures = std::move(f.signatures);
  q.width = record->width;
  q.height = record->height;
  return q;
}

Result<QueryResponse> Run(Source& source, const QueryFeatures& query, const QueryOptions& options,
                          QueryTimings timings) {
  QueryResponse response;
  response.query_features = static_cast<uint32_t>(query.words.size());

  // 1. TF-IDF scoring.
  auto t = Clock::now();
  const bool hamming = !query.signatures.empty();
  const size_t depth = std::max({static_cast<size_t>(options.top_k), static_cast<size_t>(options.rerank_depth),
                                 hamming ? static_cast<size_t>(options.hamming_shortlist) : size_t{0}});
  const ScoreInput input = query.soft_words.empty() ? ScoreInput{.words = query.words}
                                                    : ScoreInput{.words = query.soft_words, .tf = query.soft_tf};
  auto scored = source.Score(input, depth, options);
  if (!scored) return std::unexpected(scored.error());
  response.candidates = scored->candidates;
  // The features read next (Hamming scores, verification) are asked for at once.
  const size_t to_read = std::min(scored->best.size(), hamming ? depth : static_cast<size_t>(options.rerank_depth));
  source.Prefetch(std::span(scored->best).first(to_read));
  std::vector<Hit> hits(scored->best.size());
  for (size_t i = 0; i < hits.size(); ++i) {
    hits[i].ref = scored->best[i].ref;
    hits[i].result.id = std::move(scored->best[i].id);
    hits[i].result.score = scored->best[i].score;
  }
  // 1b. Hamming-embedding re-scoring of the shortlist.
  if (hamming) {
    if (auto s = RescoreHamming(source, query, options, hits); !s) return std::unexpected(s.error());
  }
  timings.score_ms = MsSince(t);

  // 2. Spatial re-ranking of the top R.
  t = Clock::now();
  auto num_verified = Rerank(source, query, options, hits);
  if (!num_verified) return std::unexpected(num_verified.error());
  timings.verify_ms = MsSince(t);

  // 3. Average query expansion over the verified results.
  if (options.query_expansion && *num_verified > 0) {
    t = Clock::now();
    const Status s = hamming ? ExpandQueryHamming(source, query, options, *num_verified, hits)
                             : ExpandQuery(source, scored->terms, options, *num_verified, hits);
    if (!s) return std::unexpected(s.error());
    timings.qe_ms = MsSince(t);
  }

  // 4. Transitive verification.
  if (options.transitive_depth > 0 && *num_verified > 0) {
    t = Clock::now();
    if (auto s = VerifyTransitively(source, options, hamming, *num_verified, hits); !s) return std::unexpected(s.error());
    timings.verify_ms += MsSince(t);
  }

  std::erase_if(hits, [&](const Hit& h) { return !source.Answered(h.ref); });
  if (hits.size() > static_cast<size_t>(options.top_k)) hits.resize(static_cast<size_t>(options.top_k));
  auto records = source.Records(RefsOf(hits));
  if (!records) return std::unexpected(records.error());
  response.results.reserve(hits.size());
  for (size_t i = 0; i < hits.size(); ++i) {
    response.results.push_back(std::move(hits[i].result));
    response.results.back().record = std::move((*records)[i]);
  }
  response.timings = timings;
  return response;
}

std::vector<QueryTerm> ExpandedQuery(std::span<const QueryTerm> terms, std::span<const std::vector<QueryTerm>> regions) {
  std::map<uint32_t, double> average;
  for (const QueryTerm& term : terms) average[term.word] += term.weight;
  for (const std::vector<QueryTerm>& region : regions)
    for (const QueryTerm& term : region) average[term.word] += term.weight;
  std::vector<QueryTerm> expanded;
  expanded.reserve(average.size());
  double norm_sq = 0;
  for (const auto& [word, weight] : average) norm_sq += weight * weight;
  const double inv = norm_sq > 0 ? 1.0 / std::sqrt(norm_sq) : 0.0;
  for (const auto& [word, weight] : average) expanded.push_back({word, static_cast<float>(weight * inv)});
  // Only the strongest words, twice as many as the query's: the average of the query and 5 regions has
  // about 3x the query's words, most from one region only with small weights, and its pass over every
  // posting of those words was the costliest stage at 1M images. Measured: that pass about 35% cheaper
  // (100k images), mAP Paris subset 0.896 -> 0.900, groups_dev 0.985 -> 0.986 (eval/results/accuracy.md).
  return StrongestTerms(std::move(expanded), 2 * terms.size());
}

sift::Affine2D Compose(const sift::Affine2D& outer, const sift::Affine2D& inner) {
  const auto& b = outer.m;
  const auto& a = inner.m;
  return sift::Affine2D{{b[0] * a[0] + b[1] * a[3], b[0] * a[1] + b[1] * a[4], b[0] * a[2] + b[1] * a[5] + b[2],
                         b[3] * a[0] + b[4] * a[3], b[3] * a[1] + b[4] * a[4], b[3] * a[2] + b[4] * a[5] + b[5]}};
}

}  // namespace oxbow::index::search
