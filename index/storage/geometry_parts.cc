#include "index/storage/geometry_parts.h"

#include <algorithm>
#include <filesystem>

#include "sift/base/log.h"

namespace oxbow::index {
namespace {

std::string JoinPath(const std::string& dir, const std::string& file) {
  return (std::filesystem::path(dir) / file).string();
}

}  // namespace

bool GeometryPart::Verified() const {
  const std::optional<bool> good = VerifiedUnless([] { return false; });  // never stops
  return good.has_value() && *good;
}

std::optional<bool> GeometryPart::VerifiedUnless(const std::function<bool()>& stop) const {
  const int state = state_.load(std::memory_order_acquire);
  if (state != kUnverified) return state == kGood;
  std::lock_guard<std::mutex> lock(verify_mutex_);
  if (!checked_) {
    const std::optional<Status> status = VerifyCheckpointFileUnless(dir_, file_, stop);
    if (!status.has_value()) return std::nullopt;
    checked_ = true;
    if (!*status) {
      MarkDamaged(status->error().message);
    } else {
      int expected = kUnverified;  // a damaged image found meanwhile wins
      state_.compare_exchange_strong(expected, kGood, std::memory_order_acq_rel);
    }
  }
  return state_.load(std::memory_order_acquire) == kGood;
}

bool GeometryPart::CopyChecked(uint32_t number, const PackedFeatures& stored, std::optional<uint64_t> checksum,
                               std::span<uint8_t> buffer, std::shared_ptr<const void> owner, PackedFeatures* out) const {
  if (Damaged()) return false;
  const std::span<const uint8_t> records = stored.bytes(), signatures = stored.signature_bytes();
  OXBOW_CHECK(buffer.size() == records.size() + signatures.size());
  const std::span<uint8_t> records_copy = buffer.first(records.size());
  const std::span<uint8_t> signatures_copy = buffer.subspan(records.size());
  if (!Copy(records, records_copy) || !Copy(signatures, signatures_copy)) {
    MarkDamaged("checkpoint file " + JoinPath(dir_, file_.name) + " no longer holds the bytes of image number " +
                std::to_string(number) + " (truncated, or a read error)");
    return false;
  }
  // View's message names the file (no string built per image).
  auto view = PackedFeatures::View(records_copy, signatures_copy, stored.width(), stored.height(), std::move(owner),
                                   file_.name);
  if (!view) {
    MarkDamaged(view.error().message);
    return false;
  }
  if (!checksum.has_value()) {
    if (!Verified()) return false;
  } else if (ImageChecksum(*view) != checksum.value()) {
    MarkDamaged("checkpoint file " + JoinPath(dir_, file_.name) + ": image number " + std::to_string(number) +
                " fails its checksum");
    return false;
  }
  *out = std::move(*view);
  return true;
}

std::optional<PackedFeatures> GeometryPart::Copied(uint32_t number, const PackedFeatures& stored,
                                                   std::optional<uint64_t> checksum) const {
  auto buffer = std::make_shared<std::vector<uint8_t>>(DataBytes(stored));
  PackedFeatures out;
  if (!CopyChecked(number, stored, checksum, *buffer, buffer, &out)) return std::nullopt;
  return out;
}

PackedFeatures GeometryPart::Checked(uint32_t number, const PackedFeatures& stored,
                                     std::optional<uint64_t> checksum) const {
  if (std::optional<PackedFeatures> copy = Copied(number, stored, checksum)) return std::move(*copy);
  std::lock_guard<std::mutex> lock(repair_mutex_);
  auto& slot = repaired_[number];
  if (!slot) slot = std::make_unique<const PackedFeatures>(FromCatalogue(number));
  return *slot;
}

bool GeometryPart::Copy(std::span<const uint8_t> from, std::span<uint8_t> to) const {
  if (mapped_) return mapped_->Copy(from, to);
  std::copy(from.begin(), from.end(), to.begin());
  return true;
}

void GeometryPart::MarkDamaged(const std::string& why) const {
  if (state_.exchange(kDamaged, std::memory_order_acq_rel) == kDamaged) return;
  OXBOW_LOG(kError) << "index " << dir_ << ": " << why
                    << "; its images are read from the catalogue instead, and the next checkpoint rewrites them";
}

PackedFeatures GeometryPart::FromCatalogue(uint32_t number) const {
  const std::string what = "image number " + std::to_string(number) + " of " + JoinPath(dir_, kCatalogueFile);
  if (!catalogue_) {
    auto opened = Catalogue::Open(JoinPath(dir_, kCatalogueFile));
    if (!opened) {
      OXBOW_LOG(kError) << "index " << dir_ << ": cannot read " << what << ": " << opened.error().message;
      return {};
    }
    catalogue_ = std::move(*opened);
  }
  auto blob = catalogue_->ReadFeatures(number);
  auto features = blob ? PackedFeatures::Deserialize(*blob, what) : Result<PackedFeatures>(std::unexpected(blob.error()));
  if (!features) {
    OXBOW_LOG(kError) << "index " << dir_ << ": cannot read " << what << ": " << features.error().message;
    return {};
  }
  return std::move(*features);
}

std::set<std::string> KeptGeometry(const CheckpointManifest& previous, const GeometryContents& contents,
                                   const std::set<std::string>& damaged, const std::function<bool(uint32_t)>& is_live) {
  std::set<std::string> kept;
  std::vector<std::string> small;
  for (const CheckpointFile& f : previous.files) {
    if (!f.name.starts_with("geometry-") || damaged.count(f.name)) continue;
    const auto it = contents.find(f.name);
    if (it == contents.end()) continue;
    const size_t live = static_cast<size_t>(std::count_if(it->second->begin(), it->second->end(), is_live));
    if (live == 0 || 2 * live < it->second->size()) continue;
    kept.insert(f.name);
    if (f.size_bytes < kSmallGeometryFileBytes) small.push_back(f.name);
  }
  if (small.size() > kMaxSmallGeometryFiles) {
    for (const std::string& name : small) kept.erase(name);
  }
  return kept;
}

}  // namespace oxbow::index
