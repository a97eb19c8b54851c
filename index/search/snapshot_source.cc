#include "index/search/snapshot_source.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <optional>
#include <utility>

#include "index/search/hamming.h"
#include "index/search/kept_memory.h"
#include "index/search/rerank.h"
#include "sift/base/parallel.h"

namespace oxbow::index::search {
namespace {

// The features of a search's Hamming shortlist as its re-scoring read them: copies made with pread
// (Entry::SignedFeatures), kept for the rest of the search, so that re-ranking, query expansion and
// transitive verification read the same images from here instead of through the geometry files'
// mapping, where the first touch of each page is a page fault (several microseconds each where page
// tables are paravirtualised; a search re-ranks and verifies a few hundred images, new ones for every
// new query). The same bytes, checked as through the mapping, so results do not change.
class CandidateCopies {
 public:
  // Room for n candidates (none copied yet).
  void Reserve(size_t n) {
    buffers_.resize(n);
    views_.resize(n);
    copied_.assign(n, 0);
    number_of_.assign(n, 0);
  }
  // Candidate c's features (image `number`), kept here (Entry::SignedFeatures: read from a geometry
  // file, a checked copy). Distinct candidates may be read on different threads at once.
  const PackedFeatures& Read(size_t c, uint32_t number, const Entry& entry) {
    const PackedFeatures& features = entry.SignedFeatures(&buffers_[c], &views_[c]);
    copied_[c] = &features == &views_[c] ? 1 : 0;
    number_of_[c] = number;
    return features;
  }
  // After the Reads, on one thread: makes Of() find them.
  void Index() {
    numbers_.clear();
    for (size_t c = 0; c < copied_.size(); ++c) {
      if (copied_[c]) numbers_.emplace_back(number_of_[c], c);
    }
    std::sort(numbers_.begin(), numbers_.end());
  }
  // Image `number`'s features: its copy when one was kept, else entry.features().
  PackedFeatures Of(uint32_t number, const Entry& entry) const {
    const auto it = std::lower_bound(numbers_.begin(), numbers_.end(), std::pair<uint32_t, size_t>{number, 0});
    if (it != numbers_.end() && it->first == number) return views_[it->second];
    return entry.features();
  }
  PackedFeatures Of(const Snapshot& snap, const std::string& id) const {
    uint32_t number = 0;
    const Entry* entry = snap.Find(id, &number);
    return Of(number, *entry);
  }

 private:
  std::vector<std::vector<uint8_t>> buffers_;
  std::vector<PackedFeatures> views_;  // views_[c] views buffers_[c] when copied_[c]
  std::vector<uint8_t> copied_;
  std::vector<uint32_t> number_of_;                   // by candidate
  std::vector<std::pair<uint32_t, size_t>> numbers_;  // (image number, candidate) of the copies, sorted
};


// One search over one snapshot (index/search/source.h): refs are image numbers (part 0). Keeps the
// Hamming shortlist's features (CandidateCopies) for the later stages, the allow-bitmap of the
// filter, and transitive verification's ranking.
class SnapshotSource final : public Source {
 public:
  SnapshotSource(std::shared_ptr<const Snapshot> snap, int num_threads)
      : snap_(std::move(snap)), num_threads_(num_threads) {}

  ~SnapshotSource() override {
    if (ranked_ && ranked_memory_) {
      // The ranking's tables go back to the memory kept for the next search (up to a bound).
      InvertedFile::Subset::Buffers buffers = std::move(*ranked_).Release();
      constexpr size_t kMaxKeptBytes = size_t{8} << 20;
      if (buffers.occurrences.capacity() * sizeof(InvertedFile::Subset::Occurrence) > kMaxKeptBytes) buffers = {};
      **ranked_memory_ = std::move(buffers);
    }
  }
  SnapshotSource(const SnapshotSource&) = delete;
  SnapshotSource& operator=(const SnapshotSource&) = delete;

  Result<std::optional<ImageRef>> Find(const std::string& id) override {
    uint32_t number = 0;
    if (snap_->Find(id, &number) == nullptr) return std::optional<ImageRef>();
    return std::optional<ImageRef>(ImageRef{.part = 0, .number = number});
  }

  Result<ScoreOutput> Score(const ScoreInput& input, size_t max_results,
                                    const QueryOptions& options) override {
    const InvertedFile& inverted = snap_->inverted;
    ScoreOutput out;
    if (input.words.empty()) {
      out.terms.assign(input.terms.begin(), input.terms.end());
    } else if (input.tf.empty()) {
      out.terms = inverted.QueryVector(BagOfWords::FromWords(input.words));
    } else {
      out.terms = inverted.QueryVector(input.words, input.tf);
    }
    if (options.filter && allowed_filter_ != options.filter.get()) {
      allowed_ = AllowedImages(*options.filter);
      allowed_filter_ = options.filter.get();
    }
    const auto kept_scratch = KeptForNextSearch<ScoreScratch>::Shared().Take();
    const std::vector<ScoredImage> scored =
        inverted.Score(out.terms, max_results, &*kept_scratch, &out.candidates, options.filter ? &allowed_ : nullptr,
                       num_threads_, static_cast<uint64_t>(options.max_scored_postings));
    out.best.resize(scored.size());
    for (size_t i = 0; i < scored.size(); ++i) {
      out.best[i] = {.ref = {.part = 0, .number = scored[i].image},
                     .id = snap_->entries[scored[i].image]->record.id,
                     .score = scored[i].score};
    }
    return out;
  }

  // Their reads start at once, on the index's threads (a madvise call each, several microseconds even
  // when the pages are in memory: ~2 ms for 300 candidates on one thread at 1M images).
  void Prefetch(std::span<const ScoredRef> refs) override {
    ParallelFor(refs.size(), num_threads_, 16, [&](size_t begin, size_t end, int) {
      for (size_t c = begin; c < end; ++c) snap_->entries[refs[c].ref.number]->stored.WillNeed();
    });
  }

  // With sqrt(tf) weighting (the default) a candidate's N_d is its tf-idf norm squared, which the
  // inverted file keeps: Score then skips the candidate's words the query lacks (hamming.h).
  Result<std::vector<double>> HammingScores(std::span<const uint32_t> words, std::span<const uint64_t> signatures,
                                            std::span<const ImageRef> refs, const QueryOptions& options) override {
    const QuerySignatures query(words, signatures, snap_->inverted.IdfSquaredTable(),
                                {.threshold = options.hamming_threshold,
                                 .sigma = options.hamming_sigma,
                                 .asmk_weight = static_cast<double>(options.asmk_weight),
                                 .norm_exponent = options.hamming_norm_exponent});
    const bool keep = !copied_;  // the first re-scoring's images are kept for the later stages
    if (keep) copies_.Reserve(refs.size());
    std::vector<double> out(refs.size());
    const bool norm_is_self = snap_->inverted.options().sqrt_tf;
    ParallelFor(refs.size(), num_threads_, 8, [&](size_t begin, size_t end, int) {
      thread_local std::vector<uint8_t> buffer;
      for (size_t c = begin; c < end; ++c) {
        const uint32_t n = refs[c].number;
        const Entry& entry = *snap_->entries[n];
        PackedFeatures copy;
        const PackedFeatures& features = keep ? copies_.Read(c, n, entry) : copies_.Of(n, entry);
        if (features.signature_bytes().empty() && features.size() > 0) {
          out[c] = std::nan("");
        } else if (norm_is_self) {
          const double norm = snap_->inverted.Norm(n);
          out[c] = query.Score(features, norm * norm);
        } else {
          out[c] = query.Score(features);
        }
      }
    });
    if (keep) {
      copies_.Index();
      copied_ = true;
    }
    return out;
  }

  Result<std::vector<Verified>> Verify(std::span<const GeometryQuery> geometries,
                                               std::span<const VerifyTask> tasks,
                                               const QueryOptions& options) override {
    // Only the geometries some task uses are prepared.
    std::vector<std::unique_ptr<const QueryGeometry>> prepared(geometries.size());
    for (const VerifyTask& task : tasks) {
      if (task.geometries.empty()) return Fail(ErrorCode::kInvalidArgument, "a verification of no geometry");
      for (const uint32_t g : task.geometries) {
        if (g >= prepared.size()) return Fail(ErrorCode::kInvalidArgument, "a verification of no geometry");
        if (!prepared[g]) {
          prepared[g] = std::make_unique<const QueryGeometry>(geometries[g].keypoints, geometries[g].words,
                                                              geometries[g].region, geometries[g].signatures,
                                                              options.hamming_threshold, options.max_tentative_matches);
        }
      }
    }
    std::vector<Verified> out(tasks.size());
    ParallelFor(tasks.size(), num_threads_, 1, [&](size_t begin, size_t end, int) {
      for (size_t c = begin; c < end; ++c) {
        const uint32_t n = tasks[c].ref.number;
        const PackedFeatures& features = copies_.Of(n, *snap_->entries[n]);
        for (const uint32_t g : tasks[c].geometries) {
          out[c].geometry = g;
          out[c].result = prepared[g]->Verify(features, options.max_pairs_per_word, options.verify, &out[c].overlay);
          if (out[c].result.verified) break;
        }
      }
    });
    return out;
  }

  Result<std::vector<RegionFeatures>> Features(std::span<const ImageRef> refs,
                                                       std::span<const std::array<float, 4>> regions,
                                                       const FeaturesRequest& request) override {
    std::vector<RegionFeatures> out(refs.size());
    for (size_t r = 0; r < refs.size(); ++r) {
      const uint32_t n = refs[r].number;
      const PackedFeatures& f = copies_.Of(n, *snap_->entries[n]);
      const auto& box = regions[r];
      std::vector<uint32_t> inside;
      for (size_t i = 0; i < f.size(); ++i) {
        const sift::Keypoint k = f.keypoint(i);
        if (k.x < box[0] || k.x > box[2] || k.y < box[1] || k.y > box[3]) continue;
        inside.push_back(static_cast<uint32_t>(i));
        if (request.all_words) out[r].all_words.push_back(f.word(i));
      }
      const size_t cap = request.max_features;
      if (cap > 0 && inside.size() > cap) {  // the rarest words' features (highest idf; ties by feature order)
        std::vector<double> idf(inside.size());
        for (size_t k = 0; k < inside.size(); ++k) idf[k] = snap_->inverted.Idf(f.word(inside[k]));
        std::vector<uint32_t> order(inside.size());
        std::iota(order.begin(), order.end(), 0u);
        std::nth_element(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(cap), order.end(),
                         [&](uint32_t x, uint32_t y) { return idf[x] != idf[y] ? idf[x] > idf[y] : x < y; });
        order.resize(cap);
        std::sort(order.begin(), order.end());
        for (size_t k = 0; k < cap; ++k) order[k] = inside[order[k]];
        inside = std::move(order);
      }
      const bool signed_features = request.signatures && f.has_signatures();
      for (const uint32_t i : inside) {
        out[r].keypoints.push_back(f.keypoint(i));
        out[r].words.push_back(f.word(i));
        if (signed_features) out[r].signatures.push_back(f.signature(i));
      }
    }
    return out;
  }

  Result<std::vector<std::vector<QueryTerm>>> RegionTerms(std::span<const ImageRef> refs,
                                                          std::span<const std::array<float, 4>> regions) override {
    std::vector<std::vector<QueryTerm>> out(refs.size());
    for (size_t r = 0; r < refs.size(); ++r) {
      const uint32_t n = refs[r].number;
      out[r] = snap_->inverted.QueryVector(copies_.Of(n, *snap_->entries[n]).BagInside(regions[r]));
    }
    return out;
  }

  // The ranking's tables are built in memory kept from a previous search (up to a bound): fresh, they
  // were several MB that every search faulted in page by page (blocks of 1 MiB and more are mapped and
  // unmapped each time, server/http/http_server.cc), about 10 ms of a search at 1M images.
  Status RankAmong(std::span<const ImageRef> refs) override {
    ranked_numbers_.resize(refs.size());
    ranked_bags_.assign(refs.size(), BagOfWords());
    std::vector<const BagOfWords*> bag_pointers(refs.size());
    ParallelFor(refs.size(), num_threads_, 16, [&](size_t begin, size_t end, int) {
      for (size_t c = begin; c < end; ++c) {
        ranked_numbers_[c] = refs[c].number;
        ranked_bags_[c] = copies_.Of(refs[c].number, *snap_->entries[refs[c].number]).Bag();
        bag_pointers[c] = &ranked_bags_[c];
      }
    });
    InvertedFile::Subset::Buffers buffers;
    if (ranked_) {
      buffers = std::move(*ranked_).Release();
    } else {
      ranked_memory_.emplace(KeptForNextSearch<InvertedFile::Subset::Buffers>::Shared().Take());
      buffers = std::move(**ranked_memory_);
    }
    ranked_.emplace(snap_->inverted, ranked_numbers_, bag_pointers, std::move(buffers));
    return Ok();
  }

  Result<std::vector<std::vector<float>>> ScoreAmong(std::span<const std::vector<uint32_t>> queries) override {
    if (!ranked_) return Fail(ErrorCode::kInvalidArgument, "ScoreAmong before RankAmong");
    std::vector<std::vector<float>> scores(queries.size());
    ParallelFor(queries.size(), num_threads_, 1, [&](size_t begin, size_t end, int) {
      for (size_t a = begin; a < end; ++a)
        scores[a] = ranked_->Score(snap_->inverted.QueryVector(BagOfWords::FromWords(queries[a])));
    });
    return scores;
  }

  Result<std::vector<ImageRecord>> Records(std::span<const ImageRef> refs) override {
    std::vector<ImageRecord> out(refs.size());
    for (size_t r = 0; r < refs.size(); ++r) out[r] = snap_->entries[refs[r].number]->record;
    return out;
  }

 private:
  // One Matches call per image number, in parallel: the filter parses each image's metadata (api/filter.h).
  std::vector<uint8_t> AllowedImages(const ImageFilter& filter) const {
    std::vector<uint8_t> allowed(snap_->entries.size(), 0);
    ParallelFor(allowed.size(), num_threads_, 4096, [&](size_t begin, size_t end, int) {
      for (size_t n = begin; n < end; ++n) {
        const Entry* entry = snap_->entries[n].get();
        allowed[n] = entry != nullptr && filter.Matches(entry->record) ? 1 : 0;
      }
    });
    return allowed;
  }

  const std::shared_ptr<const Snapshot> snap_;
  const int num_threads_;
  CandidateCopies copies_;
  bool copied_ = false;
  const ImageFilter* allowed_filter_ = nullptr;  // the filter allowed_ was made for
  std::vector<uint8_t> allowed_;
  std::vector<uint32_t> ranked_numbers_;
  std::vector<BagOfWords> ranked_bags_;
  std::optional<KeptForNextSearch<InvertedFile::Subset::Buffers>::Lease> ranked_memory_;
  std::optional<InvertedFile::Subset> ranked_;
};

}  // namespace

std::unique_ptr<Source> OpenSnapshotSearch(std::shared_ptr<const Snapshot> snapshot, int num_threads) {
  return std::make_unique<SnapshotSource>(std::move(snapshot), num_threads);
}

}  // namespace oxbow::index::search
