#include "eval/synthetic_collection.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <thread>

#include "sift/base/parallel.h"
#include "sift/features_io.h"

namespace oxbow::eval {
namespace {

using Clock = std::chrono::steady_clock;
double Seconds(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double>(b - a).count(); }
double Ms(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double, std::milli>(b - a).count(); }

}  // namespace

SyntheticCollection::SyntheticCollection(std::span<const sift::FeatureSet> photos, const vocab::Vocabulary& vocabulary,
                                         const vocab::QuantizerOptions& quantizer, const SyntheticOptions& options)
    : photos_(photos), options_(options), signatures_(vocabulary.has_hamming()) {
  for (size_t p = 0; p < photos.size(); ++p) {
    const sift::FeatureSet& f = photos[p];
    std::vector<uint32_t> words(f.size());
    vocabulary.Quantize(f.descriptors, words, quantizer);
    std::vector<uint64_t> signatures(signatures_ ? f.size() : 0);
    if (signatures_) vocabulary.Signatures(f.descriptors, words, signatures);
    for (size_t i = 0; i < f.size(); ++i) {
      const sift::Keypoint& k = f.keypoints[i];
      pool_.push_back({words[i], k.x / static_cast<float>(f.image_width), k.y / static_cast<float>(f.image_height),
                       k.scale, k.orientation, static_cast<uint32_t>(p), static_cast<uint32_t>(i),
                       signatures_ ? signatures[i] : 0});
    }
  }
}

// Appended: GCC 12 reports a false -Wrestrict overlap on `"s" + std::to_string(number)` once inlined.
std::string SyntheticCollection::Id(uint64_t number) { return std::string("s").append(std::to_string(number)); }

SyntheticImage SyntheticCollection::Make(uint64_t number) const {
  OXBOW_CHECK(!pool_.empty());
  SyntheticImage s;
  s.features.image_width = options_.image_width;
  s.features.image_height = options_.image_height;
  s.features.kind = sift::DescriptorKind::kRootSift;
  const auto max_x = static_cast<float>(options_.image_width - 1), max_y = static_cast<float>(options_.image_height - 1);
  // Seeded by a hash of the number: SplitMix sequences from consecutive raw seeds are shifts of one
  // another (image k would be image 0's draws shifted by k).
  SplitMix rng{SplitMix{number}.Next()};
  for (int i = 0; i < options_.features_per_image; ++i) {
    const PoolFeature& p = pool_[rng.Next() % pool_.size()];
    s.features.keypoints.push_back(
        sift::Keypoint{.x = p.rx * max_x, .y = p.ry * max_y, .scale = p.scale, .orientation = p.orientation});
    s.words.push_back(p.word);
    if (signatures_) s.signatures.push_back(p.signature);
    if (options_.descriptors) {
      const float* d = photos_[p.photo].descriptors.data() + static_cast<size_t>(p.feature) * sift::kDescriptorDim;
      s.features.descriptors.insert(s.features.descriptors.end(), d, d + sift::kDescriptorDim);
    }
  }
  return s;
}

Result<IngestReport> IngestSynthetic(index::ImageIndex& index, const SyntheticCollection& collection,
                                     const IngestOptions& options) {
  namespace fs = std::filesystem;
  OXBOW_CHECK(options.batch > 0);
  OXBOW_CHECK(options.export_dir.empty() || collection.options().descriptors);
  if (!options.export_dir.empty()) {
    std::error_code ec;
    fs::create_directories(options.export_dir, ec);
    if (ec) return Fail(ErrorCode::kIoError, "cannot create " + options.export_dir.string() + ": " + ec.message());
  }
  IngestReport report;
  const auto t0 = Clock::now();
  std::vector<SyntheticImage> images;
  for (uint64_t done = 0; done < options.count; done += options.batch) {
    const uint64_t n = std::min(options.batch, options.count - done);
    const uint64_t begin = options.first + done;
    images.resize(n);
    ParallelFor(n, options.num_threads, 16, [&](size_t b, size_t e, int) {
      for (size_t i = b; i < e; ++i) images[i] = collection.Make(begin + i);
    });
    std::vector<index::BatchImage> items;
    items.reserve(n);
    for (uint64_t i = 0; i < n; ++i) {
      items.push_back({SyntheticCollection::Id(begin + i), &images[i].features, {}, images[i].words, images[i].signatures});
    }
    const auto a0 = Clock::now();
    const std::vector<Result<index::ImageRecord>> added = index.AddBatch(items);
    report.add_seconds += Seconds(a0, Clock::now());
    for (const auto& r : added) {
      if (!r) return std::unexpected(r.error());
    }
    if (!options.export_dir.empty()) {
      for (const index::BatchImage& item : items) {
        const sift::FeatureFile file{.features = *item.features,
                                     .extractor_fingerprint = options.extractor.Fingerprint(),
                                     .extractor_description = options.extractor.Describe()};
        if (Status st = sift::WriteFeatureFile((options.export_dir / (item.id + ".oxfeat")).string(), file); !st) {
          return std::unexpected(st.error());
        }
      }
    }
    if (options.progress) options.progress(done + n);
  }
  report.total_seconds = Seconds(t0, Clock::now());
  return report;
}

Result<WriteLatencies> AddAndRemoveWhileSearching(index::ImageIndex& index, const SyntheticCollection& collection,
                                                  uint64_t first, int count,
                                                  std::span<const sift::FeatureSet* const> queries) {
  WriteLatencies out;
  std::atomic<bool> stop{false};
  std::atomic<uint64_t> searched{0};
  std::thread searcher([&] {
    for (size_t i = 0; !stop.load() && !queries.empty(); i = (i + 1) % queries.size()) {
      if (index.Query(*queries[i], index::QueryOptions{})) ++searched;
    }
  });
  Status status = Ok();
  int added = 0;
  for (; added < count && status; ++added) {
    const SyntheticImage s = collection.Make(first + static_cast<uint64_t>(added));
    const std::vector<index::BatchImage> one = {
        {"added" + std::to_string(added), &s.features, {}, s.words, s.signatures}};
    const auto a0 = Clock::now();
    if (auto r = index.AddBatch(one); !r[0]) {
      status = std::unexpected(r[0].error());
      break;
    }
    out.add_ms.push_back(Ms(a0, Clock::now()));
  }
  for (int i = 0; i < added; ++i) {
    const auto r0 = Clock::now();
    if (Status st = index.Remove("added" + std::to_string(i)); !st && status) status = st;
    out.remove_ms.push_back(Ms(r0, Clock::now()));
  }
  stop = true;
  searcher.join();
  out.searches = searched.load();
  if (!status) return std::unexpected(status.error());
  return out;
}

}  // namespace oxbow::eval
