#include "api/duplicates.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cstring>
#include <cmath>
#include <map>
#include <set>
#include <mutex>
#include <numeric>
#include <sstream>
#include <unordered_map>

#include "index/search/overlay.h"
#include "index/search/pipeline.h"
#include "index/search/source.h"
#include "sift/base/log.h"
#include "sift/base/parallel.h"
#include "sift/base/system.h"
#include "sift/types.h"
#include "vocab/communicator.h"
#include "vocab/vocabulary.h"

namespace oxbow::api {
namespace {

using Clock = std::chrono::steady_clock;

index::search::OverlayRule OverlayRuleOf(const DuplicateOptions& options) {
  return {.min_coverage = options.min_coverage, .overlay_coverage = options.overlay_coverage,
          .overlay_density = options.overlay_density};
}

constexpr double kExactCoverage = 0.9;
constexpr double kExactTwins = 0.98;       // share of features with an identical twin in an exact copy

// Every rank's `part` (CBOR: doubles exact) on every rank: the ranks' encodings, each after its 8-byte size.
std::vector<uint8_t> GatherJson(vocab::Communicator& comm, const nlohmann::json& part) {
  const std::vector<uint8_t> encoded = nlohmann::json::to_cbor(part);
  std::vector<uint8_t> framed(8 + encoded.size());
  const uint64_t size = encoded.size();
  std::memcpy(framed.data(), &size, 8);
  std::memcpy(framed.data() + 8, encoded.data(), encoded.size());
  return comm.Allgather(framed);
}

// Calls `fn` with each rank's part of a GatherJson, in rank order.
void ForEachGathered(const std::vector<uint8_t>& all, const std::function<void(const nlohmann::json&)>& fn) {
  for (size_t at = 0; at + 8 <= all.size();) {
    uint64_t size = 0;
    std::memcpy(&size, all.data() + at, 8);
    at += 8;
    fn(nlohmann::json::from_cbor(all.begin() + static_cast<std::ptrdiff_t>(at),
                                 all.begin() + static_cast<std::ptrdiff_t>(at + size)));
    at += size;
  }
}

// The word of each word's mirrored centroid.
std::vector<uint32_t> MirrorWords(const vocab::Vocabulary& vocabulary, int threads) {
  const size_t k = vocabulary.size();
  const int d = vocabulary.dimension();
  std::vector<uint32_t> mirrored(k);
  if (d != sift::kDescriptorDim) {  // not a SIFT vocabulary: no mirror
    std::iota(mirrored.begin(), mirrored.end(), 0u);
    return mirrored;
  }
  std::vector<float> flipped(k * d);
  const std::span<const float> centroids = vocabulary.centroids();
  for (size_t w = 0; w < k; ++w) MirrorDescriptor(centroids.data() + w * d, flipped.data() + w * d);
  vocab::QuantizerOptions options;
  options.num_threads = threads;
  // Row w of the centroids is word w.
  vocabulary.Quantize(flipped, mirrored, options);
  return mirrored;
}

index::search::QueryFeatures Mirrored(const index::search::QueryFeatures& q, const std::vector<uint32_t>& word_map) {
  index::search::QueryFeatures m;
  m.width = q.width;
  m.height = q.height;
  m.keypoints = q.keypoints;
  m.words.resize(q.words.size());
  for (size_t i = 0; i < q.words.size(); ++i) {
    sift::Keypoint& kp = m.keypoints[i];
    kp.x = static_cast<float>(q.width) - 1.0f - kp.x;
    float o = static_cast<float>(M_PI) - kp.orientation;
    if (o < 0) o += static_cast<float>(2 * M_PI);
    kp.orientation = o;
    m.words[i] = word_map[q.words[i]];
  }
  return m;
}

struct Candidate {
  sift::Affine2D b_from_a;
  int verified_inliers = 0;
  bool mirrored = false;
  bool a_is_query = true;  // the map goes from the query (a) to the result (b); else reversed
};

// Verified pairs keyed by (a, b, mirrored), a < b.
using CandidateKey = std::tuple<std::string, std::string, bool>;
using CandidateMap = std::map<CandidateKey, Candidate>;

// A pair found by both images' searches: the search with more inliers gives the map; a tie goes to a's
// own search, so that the result depends neither on which worker nor on which rank searched first.
void Offer(CandidateMap& candidates, CandidateKey key, const Candidate& c) {
  const auto it = candidates.find(key);
  if (it == candidates.end() || it->second.verified_inliers < c.verified_inliers ||
      (it->second.verified_inliers == c.verified_inliers && c.a_is_query && !it->second.a_is_query)) {
    candidates[std::move(key)] = c;
  }
}

// --mpi: every rank's candidates, merged on every rank, and the first rank's failure (`failure`: this
// rank's, null when none), which every rank returns.
std::optional<Error> ExchangeCandidates(vocab::Communicator& comm, CandidateMap* candidates, const Error* failure) {
  nlohmann::json out = {{"failure", nullptr}, {"candidates", nlohmann::json::array()}};
  if (failure != nullptr) out["failure"] = {static_cast<int>(failure->code), failure->message};
  for (const auto& entry : *candidates) {
    const CandidateKey& key = entry.first;
    const Candidate& c = entry.second;
    out["candidates"].push_back({std::get<0>(key), std::get<1>(key), std::get<2>(key), c.b_from_a.m,
                                 c.verified_inliers, c.a_is_query});
  }
  const std::vector<uint8_t> all = GatherJson(comm, out);
  candidates->clear();
  nlohmann::json first_failure;  // null: none
  ForEachGathered(all, [&](const nlohmann::json& part) {
    if (first_failure.is_null()) first_failure = part["failure"];
    for (const auto& c : part["candidates"]) {
      Candidate candidate{{}, c[4].get<int>(), c[2].get<bool>(), c[5].get<bool>()};
      candidate.b_from_a.m = c[3].get<std::array<double, 6>>();
      Offer(*candidates, std::make_tuple(c[0].get<std::string>(), c[1].get<std::string>(), c[2].get<bool>()), candidate);
    }
  });
  if (first_failure.is_null()) return std::nullopt;
  return Error{static_cast<ErrorCode>(first_failure[0].get<int>()), first_failure[1].get<std::string>()};
}

// --mpi: the pairs each rank measured (`mine`: its positions in `measured`), on every rank.
void ExchangeMeasures(vocab::Communicator& comm, const std::vector<size_t>& mine,
                      std::vector<std::optional<DuplicatePair>>* measured) {
  nlohmann::json out = nlohmann::json::array();
  for (const size_t i : mine) {
    const std::optional<DuplicatePair>& one = (*measured)[i];
    if (!one.has_value()) continue;
    const DuplicatePair& p = one.value();
    out.push_back({i, p.a, p.b, static_cast<int>(p.kind), p.mirrored, p.inliers, p.coverage_a, p.coverage_b,
                   p.region_a, p.region_b, p.b_from_a.m});
  }
  const std::vector<uint8_t> all = GatherJson(comm, {{"pairs", std::move(out)}});
  ForEachGathered(all, [&](const nlohmann::json& part) {
    for (const auto& q : part["pairs"]) {
      DuplicatePair p;
      p.a = q[1].get<std::string>();
      p.b = q[2].get<std::string>();
      p.kind = static_cast<DuplicateKind>(q[3].get<int>());
      p.mirrored = q[4].get<bool>();
      p.inliers = q[5].get<int>();
      p.coverage_a = q[6].get<double>();
      p.coverage_b = q[7].get<double>();
      p.region_a = q[8].get<std::array<float, 4>>();
      p.region_b = q[9].get<std::array<float, 4>>();
      p.b_from_a.m = q[10].get<std::array<double, 6>>();
      measured->at(q[0].get<size_t>()) = std::move(p);
    }
  });
}

// Singular values of the linear part, larger first.
std::pair<double, double> SingularValues(const sift::Affine2D& t) {
  const double a = t.m[0], b = t.m[1], c = t.m[3], d = t.m[4];
  const double s1 = a * a + b * b + c * c + d * d;
  const double det = std::abs(a * d - b * c);
  const double root = std::sqrt(std::max(0.0, s1 * s1 - 4 * det * det));
  return {std::sqrt((s1 + root) / 2), std::sqrt(std::max(0.0, (s1 - root) / 2))};
}

// x -> width - 1 - x.
sift::Affine2D Flip(int width) { return sift::Affine2D{{-1, 0, static_cast<double>(width) - 1, 0, 1, 0}}; }

bool IsIdentity(const sift::Affine2D& t, int width, int height) {
  const double tolerance = 0.01 * std::max(width, height);
  return std::abs(t.m[0] - 1) < 0.01 && std::abs(t.m[4] - 1) < 0.01 && std::abs(t.m[1]) < 0.01 &&
         std::abs(t.m[3]) < 0.01 && std::abs(t.m[2]) < tolerance && std::abs(t.m[5]) < tolerance;
}

struct UnionFind {
  std::vector<size_t> parent;
  explicit UnionFind(size_t n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  size_t Find(size_t x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  }
  void Join(size_t x, size_t y) {
    x = Find(x), y = Find(y);
    if (x != y) parent[std::max(x, y)] = std::min(x, y);
  }
};

}  // namespace

void MirrorDescriptor(const float* descriptor, float* mirrored) {
  // Layout: [(row * 4 + column) * 8 + orientation bin]. Mirroring the image maps the keypoint's
  // orientation theta to pi - theta; in the patch frame that reverses the axis across the orientation
  // (rows) and negates every gradient direction relative to the orientation (bin k -> -k mod 8).
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) {
      for (int k = 0; k < 8; ++k) mirrored[(r * 4 + c) * 8 + k] = descriptor[((3 - r) * 4 + c) * 8 + ((8 - k) & 7)];
    }
  }
}

const char* DuplicateKindName(DuplicateKind kind) {
  switch (kind) {
    case DuplicateKind::kExact: return "exact";
    case DuplicateKind::kNearCopy: return "near_copy";
    case DuplicateKind::kSameScene: return "same_scene";
  }
  return "same_scene";
}

std::optional<std::string> DuplicateOptions::Check() const {
  if (candidates < 1 || candidates > 1000) return "candidates must be in [1, 1000]";
  if (!(min_coverage >= 0 && min_coverage <= 1)) return "min_coverage must be in [0, 1]";
  if (!(near_copy_coverage >= 0 && near_copy_coverage <= 1)) return "near_copy_coverage must be in [0, 1]";
  if (!(overlay_coverage >= 0 && overlay_coverage <= 1)) return "overlay_coverage must be in [0, 1]";
  if (!(overlay_density >= 0 && overlay_density <= 1)) return "overlay_density must be in [0, 1]";
  if (!(max_anisotropy >= 1 && max_anisotropy < 100)) return "max_anisotropy must be in [1, 100)";
  if (!(inlier_tolerance > 0 && inlier_tolerance <= 1)) return "inlier_tolerance must be in (0, 1]";
  if (threads < 0 || threads > 256) return "threads must be in [0, 256]";
  return std::nullopt;
}

Result<DuplicateReport> FindDuplicates(const index::ImageIndex& index, const DuplicateOptions& options,
                                       const DuplicateProgress& progress, const std::function<bool()>& stop,
                                       vocab::Communicator* comm) {
  vocab::SingleProcess single;
  if (comm == nullptr) comm = &single;
  const int rank = comm->rank();
  const int ranks = comm->size();
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, "duplicate options: " + *message);
  const auto t0 = Clock::now();
  std::vector<std::string> ids;
  for (uint64_t offset = 0;; offset += 10000) {
    auto page = index.List(offset, 10000);
    if (!page) return std::unexpected(page.error());
    for (auto& record : *page) ids.push_back(std::move(record.id));
    if (page->size() < 10000) break;
  }
  std::sort(ids.begin(), ids.end());
  DuplicateReport report;
  report.images = ids.size();
  const int threads = ResolveThreadCount(options.threads);
  const std::vector<uint32_t> word_map = options.mirrored ? MirrorWords(index.vocabulary(), threads) : std::vector<uint32_t>{};

  index::QueryOptions query;
  query.top_k = options.candidates;
  query.rerank_depth = options.candidates;
  query.query_expansion = false;
  query.transitive_depth = 0;
  index::QueryOptions mirror_query = query;
  mirror_query.hamming = false;

  // 1. Searches: every verified (a, b), keyed by the ordered pair and whether mirrored.
  CandidateMap candidates;
  std::mutex candidates_mutex;
  std::atomic<uint64_t> done{0};
  std::atomic<bool> cancelled{false};
  std::optional<Error> failure;
  // This rank's images: every ranks-th one.
  std::vector<size_t> mine;
  for (size_t i = static_cast<size_t>(rank); i < ids.size(); i += static_cast<size_t>(ranks)) mine.push_back(i);
  ParallelFor(mine.size(), threads, 1, [&](size_t begin, size_t end, int) {
    for (size_t k = begin; k < end; ++k) {
      if (cancelled.load() || (stop && stop())) {
        cancelled.store(true);
        return;
      }
      const std::string& id = ids[mine[k]];
      const std::unique_ptr<index::search::Source> source = index.OpenSearch();
      index::ImageRecord record;
      auto q = index::search::StoredQuery(*source, id, query, &record);
      if (!q) {
        if (q.error().code != ErrorCode::kNotFound) {  // deleted meanwhile: skipped
          std::lock_guard<std::mutex> lock(candidates_mutex);
          if (!failure) failure = q.error();
        }
        continue;
      }
      std::vector<std::pair<index::QueryResult, bool>> found;
      auto direct = index::search::Run(*source, *q, query, {});
      Result<index::QueryResponse> mirrored = index::QueryResponse{};
      if (direct && options.mirrored) mirrored = index::search::Run(*source, Mirrored(*q, word_map), mirror_query, {});
      {
        std::lock_guard<std::mutex> lock(candidates_mutex);
        if (!direct || !mirrored) {
          if (!failure) failure = !direct ? direct.error() : mirrored.error();
          continue;
        }
        for (auto& r : direct->results) found.emplace_back(std::move(r), false);
        for (auto& r : mirrored->results) found.emplace_back(std::move(r), true);
        for (const auto& [r, is_mirrored] : found) {
          if (!r.verified || r.id == id) continue;
          const bool a_first = id < r.id;
          Offer(candidates, std::make_tuple(a_first ? id : r.id, a_first ? r.id : id, is_mirrored),
                Candidate{r.db_from_query, r.inliers, is_mirrored, a_first});
        }
      }
      const uint64_t n = ++done;
      if (progress) progress(n, mine.size());
    }
  });
  if (cancelled.load()) failure = Error{ErrorCode::kResourceExhausted, "the duplicate search was cancelled"};
  // Every rank's candidates on every rank (and every rank's failure: all fail alike).
  if (ranks > 1) failure = ExchangeCandidates(*comm, &candidates, failure ? &*failure : nullptr);
  if (failure) return std::unexpected(*failure);
  report.search_s = SecondsSince(t0);

  // 2. Every candidate is measured; a pair found both directly and mirrored (a symmetric scene matches
  // itself mirrored in part) keeps the map that covers more.
  std::vector<std::pair<CandidateKey, Candidate>> work(candidates.begin(), candidates.end());

  // 3. The measure of every pair, on the stored features of both.
  const auto t1 = Clock::now();
  OXBOW_LOG(kInfo) << "duplicates: " << ids.size() << " images searched in " << report.search_s << " s; measuring "
                   << work.size() << " verified pairs";
  std::vector<std::optional<DuplicatePair>> measured(work.size());
  index::QueryOptions plain = mirror_query;  // features without signatures
  std::vector<size_t> my_work;  // this rank's pairs: every ranks-th one
  for (size_t i = static_cast<size_t>(rank); i < work.size(); i += static_cast<size_t>(ranks)) my_work.push_back(i);
  ParallelFor(my_work.size(), threads, 4, [&](size_t begin, size_t end, int) {
    for (size_t k = begin; k < end; ++k) {
      const size_t i = my_work[k];
      const auto& [key, c] = work[i];
      const auto& [a_id, b_id, is_mirrored] = key;
      const std::unique_ptr<index::search::Source> source = index.OpenSearch();
      index::ImageRecord record_a, record_b;  // the query's, the result's
      // The map goes from the query's pixels to the result's: measure in that direction.
      const std::string& from = c.a_is_query ? a_id : b_id;
      const std::string& to = c.a_is_query ? b_id : a_id;
      // A direct pair's features with their signatures: how alike the matched content is.
      const index::QueryOptions& loaded = is_mirrored ? plain : query;
      auto qa = index::search::StoredQuery(*source, from, loaded, &record_a);
      auto qb = index::search::StoredQuery(*source, to, loaded, &record_b);
      if (!qa || !qb) continue;  // deleted meanwhile
      const index::search::QueryFeatures query_side = is_mirrored ? Mirrored(*qa, word_map) : *qa;
      const index::search::MatchMeasure m = index::search::MeasureMatch(query_side, *qb, c.b_from_a, options.inlier_tolerance);
      if (index::search::OnlyAnOverlay(m, is_mirrored, OverlayRuleOf(options))) continue;
      DuplicatePair pair;
      pair.mirrored = is_mirrored;
      pair.inliers = m.inliers;
      const auto [s1, s2] = SingularValues(c.b_from_a);
      const bool similarity = s2 > 0 && s1 / s2 <= options.max_anisotropy;
      const double larger = std::max(m.coverage_a, m.coverage_b);
      // Identical pixels give identical stored features: every one has its twin.
      const size_t features = std::max(qa->words.size(), qb->words.size());
      if (!is_mirrored && record_a.width == record_b.width && record_a.height == record_b.height &&
          qa->words.size() == qb->words.size() && m.twins >= kExactTwins * static_cast<double>(features) &&
          IsIdentity(c.b_from_a, record_a.width, record_a.height) && std::min(m.coverage_a, m.coverage_b) >= kExactCoverage) {
        pair.kind = DuplicateKind::kExact;
      } else if (similarity && larger >= options.near_copy_coverage) {
        pair.kind = DuplicateKind::kNearCopy;
      } else {
        pair.kind = DuplicateKind::kSameScene;
      }
      // Reported with a < b and the map from a's pixels to b's (with the mirror: determinant < 0).
      pair.a = a_id, pair.b = b_id;
      const sift::Affine2D flip_from = Flip(record_a.width);  // record_a: the query's
      const sift::Affine2D to_from_from = is_mirrored ? index::search::Compose(c.b_from_a, flip_from) : c.b_from_a;
      if (c.a_is_query) {
        pair.coverage_a = m.coverage_a, pair.coverage_b = m.coverage_b;
        pair.region_a = m.region_a, pair.region_b = m.region_b;
        pair.b_from_a = to_from_from;
      } else {
        pair.coverage_a = m.coverage_b, pair.coverage_b = m.coverage_a;
        pair.region_a = m.region_b, pair.region_b = m.region_a;
        pair.b_from_a = to_from_from.Inverse().value_or(to_from_from);
      }
      if (is_mirrored) {  // the query side's region was measured on its mirrored features
        std::array<float, 4>& r = c.a_is_query ? pair.region_a : pair.region_b;
        const float w = static_cast<float>(record_a.width) - 1.0f;
        r = {w - r[2], r[1], w - r[0], r[3]};
      }
      measured[i] = std::move(pair);
    }
  });
  // Every rank's measures on every rank.
  if (ranks > 1) ExchangeMeasures(*comm, my_work, &measured);
  // Candidates are ordered by (a, b, mirrored): a direct and a mirrored measure of one pair are neighbours.
  for (size_t i = 0; i + 1 < work.size(); ++i) {
    if (std::get<0>(work[i].first) != std::get<0>(work[i + 1].first) ||
        std::get<1>(work[i].first) != std::get<1>(work[i + 1].first)) {
      continue;
    }
    auto& direct = measured[i];
    auto& mirrored = measured[i + 1];
    if (direct && mirrored) {
      const double d = std::max(direct->coverage_a, direct->coverage_b);
      const double m = std::max(mirrored->coverage_a, mirrored->coverage_b);
      (m > d ? direct : mirrored).reset();
    }
    ++i;
  }
  std::set<std::pair<std::string, std::string>> kept, verified;
  for (size_t i = 0; i < work.size(); ++i) {
    std::pair<std::string, std::string> ab(std::get<0>(work[i].first), std::get<1>(work[i].first));
    if (measured[i]) kept.insert(ab);
    verified.insert(std::move(ab));
  }
  report.candidate_pairs = verified.size();
  report.overlay_pairs = verified.size() - kept.size();
  report.measure_s = SecondsSince(t1);

  // 4. Groups: connected components, numbered by their first id.
  std::unordered_map<std::string, size_t> number;
  for (size_t i = 0; i < ids.size(); ++i) number[ids[i]] = i;
  UnionFind sets(ids.size());
  for (const auto& p : measured) {
    if (p) sets.Join(number[p->a], number[p->b]);
  }
  std::map<size_t, std::vector<std::string>> members;
  for (const auto& p : measured) {
    if (!p) continue;
    members[sets.Find(number[p->a])];
  }
  for (size_t i = 0; i < ids.size(); ++i) {
    auto it = members.find(sets.Find(i));
    if (it != members.end()) it->second.push_back(ids[i]);
  }
  std::unordered_map<size_t, int> group_of;
  for (auto& [root, list] : members) {
    group_of[root] = static_cast<int>(report.groups.size());
    report.groups.push_back(std::move(list));
  }
  for (auto& p : measured) {
    if (!p) continue;
    p->group = group_of[sets.Find(number[p->a])];
    report.pairs.push_back(std::move(*p));
  }
  std::sort(report.pairs.begin(), report.pairs.end(), [](const DuplicatePair& x, const DuplicatePair& y) {
    return std::tie(x.group, x.a, x.b, x.mirrored) < std::tie(y.group, y.a, y.b, y.mirrored);
  });
  return report;
}

nlohmann::json DuplicateReportToJson(const DuplicateReport& report, const DuplicateOptions& options) {
  using nlohmann::json;
  json pairs = json::array();
  for (const auto& p : report.pairs) {
    pairs.push_back({{"a", p.a}, {"b", p.b}, {"kind", DuplicateKindName(p.kind)}, {"mirrored", p.mirrored},
                     {"inliers", p.inliers}, {"coverage_a", std::round(p.coverage_a * 1000) / 1000},
                     {"coverage_b", std::round(p.coverage_b * 1000) / 1000}, {"region_a", p.region_a},
                     {"region_b", p.region_b}, {"transform", p.b_from_a.m}, {"group", p.group}});
  }
  json groups = json::array();
  for (size_t g = 0; g < report.groups.size(); ++g) groups.push_back({{"group", g}, {"images", report.groups[g]}});
  return {{"images", report.images},
          {"settings", {{"candidates", options.candidates}, {"mirrored", options.mirrored},
                        {"min_coverage", options.min_coverage}, {"near_copy_coverage", options.near_copy_coverage},
                        {"overlay_coverage", options.overlay_coverage}, {"overlay_density", options.overlay_density},
                        {"max_anisotropy", options.max_anisotropy}, {"inlier_tolerance", options.inlier_tolerance},
                        {"distinct_hamming", index::search::kIdenticalHamming},
                        {"distinct_central_share", index::search::kCentralShare},
                        {"distinct_central_share_other", index::search::kCentralShareOther},
                        {"distinct_coverage", std::min(options.min_coverage, index::search::kDistinctCoverage)},
                        {"mirrored_coverage", std::max(options.min_coverage, index::search::kMirroredCoverage)},
                        {"frame_twins", index::search::kFrameTwins},
                        {"framed_content", index::search::kFramedContent}}},
          {"pairs", pairs},
          {"groups", groups},
          {"candidate_pairs", report.candidate_pairs},
          {"overlay_pairs", report.overlay_pairs},
          {"timings_s", {{"search", report.search_s}, {"measure", report.measure_s}}}};
}

std::string DuplicateReportToCsv(const DuplicateReport& report) {
  std::ostringstream out;
  auto quoted = [](const std::string& text) {
    if (text.find_first_of(",\"\n\r") == std::string::npos) return text;
    std::string q = "\"";
    for (char c : text) q += c == '"' ? std::string("\"\"") : std::string(1, c);
    return q + "\"";
  };
  out << "a,b,kind,mirrored,inliers,coverage_a,coverage_b,group\n";
  char buf[64];
  for (const auto& p : report.pairs) {
    std::snprintf(buf, sizeof buf, "%.3f,%.3f", p.coverage_a, p.coverage_b);
    out << quoted(p.a) << "," << quoted(p.b) << "," << DuplicateKindName(p.kind) << "," << (p.mirrored ? "true" : "false")
        << "," << p.inliers << "," << buf << "," << p.group << "\n";
  }
  return out.str();
}

}  // namespace oxbow::api
