#include "index/storage/loader.h"

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <map>

#include "sift/base/log.h"
#include "sift/base/parallel.h"

namespace oxbow::index {
namespace {

using Clock = std::chrono::steady_clock;
double MsSince(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// What Open's validation of a BLOB also checks: the record agrees with its features.
Status CheckEntry(const ImageRecord& record, const PackedFeatures& features, size_t vocabulary_size,
                  const std::string& where) {
  if (!RecordMatches(record, features)) {
    return Fail(ErrorCode::kCorruptData, where + ": image '" + record.id + "' record disagrees with its features");
  }
  if (features.size() > 0 && features.word(features.size() - 1) >= vocabulary_size) {
    return Fail(ErrorCode::kCorruptData, where + ": image '" + record.id + "' has a word outside the vocabulary");
  }
  return Ok();
}

// The files of a checkpoint (LoadCheckpoint), each read and checked, in manifest order.
struct CheckpointFilesRead {
  std::vector<std::vector<GeometryImage>> geometry;                  // per geometry file
  std::vector<std::shared_ptr<const MappedFile>> geometry_files;     // geometry files, mapped
  std::vector<std::shared_ptr<const MappedFile>> postings_files;     // the head and segments, in memory
};

bool IsPostingsFile(const std::string& name) { return name.starts_with("postings-") || name.starts_with("segment-"); }

// Loads every file in parallel; the first failure in file order is returned. The postings files (the
// head and its segment files) are verified against their checksums here; a geometry file's size and
// image table are checked here, its checksum on first use (GeometryPart).
Result<CheckpointFilesRead> ReadCheckpointFiles(const std::string& dir, const std::vector<CheckpointFile>& files,
                                                int num_threads) {
  CheckpointFilesRead out;
  std::vector<Status> failures(files.size(), Ok());
  out.geometry.resize(files.size());
  out.geometry_files.resize(files.size());
  out.postings_files.resize(files.size());
  ParallelFor(files.size(), num_threads, 1, [&](size_t begin, size_t end, int) {
    for (size_t i = begin; i < end; ++i) {
      const std::string what = "checkpoint file " + (std::filesystem::path(dir) / files[i].name).string();
      const bool postings = IsPostingsFile(files[i].name);
      auto mapped = MappedFile::Open((std::filesystem::path(dir) / files[i].name).string(),
                                     postings ? MappedFile::Use::kResident : MappedFile::Use::kRandom);
      if (!mapped) {
        failures[i] = std::unexpected(mapped.error());
      } else if (!postings && (*mapped)->bytes().size() != files[i].size_bytes) {
        failures[i] = Fail(ErrorCode::kCorruptData, what + " has " + std::to_string((*mapped)->bytes().size()) +
                                                        " bytes, its manifest says " + std::to_string(files[i].size_bytes));
      } else if (postings) {
        // Checked whole before use, then used in place (no copy): the loaded file stays in memory for
        // as long as a version of the inverted file uses its postings.
        failures[i] = VerifyCheckpointBytes((*mapped)->bytes(), files[i], what);
        if (failures[i]) out.postings_files[i] = *mapped;
      } else {
        auto images = ReadGeometry(*mapped, what);
        if (images) {
          out.geometry[i] = std::move(*images);
          out.geometry_files[i] = *mapped;
        } else {
          failures[i] = std::unexpected(images.error());
        }
      }
    }
  });
  for (Status& failure : failures) {
    if (!failure) return std::unexpected(std::move(failure.error()));
  }
  return out;
}

// The inverted file of a checkpoint: its one postings head (`postings_files` from ReadCheckpointFiles)
// with the segment files it names, which the manifest must list. `segment_files` receives each
// segment's file, in order.
Result<InvertedFile> ReadPostings(const std::string& dir, const std::vector<CheckpointFile>& files,
                                  const std::vector<std::shared_ptr<const MappedFile>>& postings_files, size_t vocab_size,
                                  const IndexOptions& options, bool* recoded,
                                  std::vector<std::pair<std::weak_ptr<const void>, CheckpointFile>>* segment_files) {
  size_t head = files.size();
  for (size_t i = 0; i < files.size(); ++i) {
    if (!files[i].name.starts_with("postings-")) continue;
    if (head != files.size()) return Fail(ErrorCode::kCorruptData, "two postings files");
    head = i;
  }
  if (head == files.size()) return Fail(ErrorCode::kCorruptData, "no postings file");
  std::vector<size_t> used;  // files index of each segment, in order
  const InvertedFile::SegmentSource segment_source =
      [&](const std::string& name) -> Result<std::pair<std::span<const uint8_t>, std::shared_ptr<const void>>> {
    for (size_t i = 0; i < files.size(); ++i) {
      if (files[i].name == name && name.starts_with("segment-")) {
        used.push_back(i);
        return std::pair{postings_files[i]->bytes(), std::shared_ptr<const void>(postings_files[i])};
      }
    }
    return Fail(ErrorCode::kCorruptData, "not named by the manifest");
  };
  auto inverted = InvertedFile::Deserialize(postings_files[head]->bytes(), vocab_size, ToTfIdf(options), recoded,
                                            postings_files[head], segment_source);
  if (!inverted) {
    return Fail(inverted.error().code, "checkpoint file " + (std::filesystem::path(dir) / files[head].name).string() +
                                           ": " + inverted.error().message);
  }
  segment_files->clear();
  segment_files->reserve(used.size());
  for (size_t k = 0; k < used.size(); ++k) segment_files->emplace_back(inverted->SegmentHandle(k), files[used[k]]);
  return inverted;
}

}  // namespace

TfIdfOptions ToTfIdf(const IndexOptions& o) {
  return TfIdfOptions{.sqrt_tf = o.sqrt_tf, .max_document_frequency = o.max_document_frequency,
                      .stop_list_min_images = o.stop_list_min_images, .merge_factor = o.merge_factor};
}

// Open without a checkpoint: every row and BLOB read and validated, the inverted file built in one
// pass; an image whose BLOB fails its check is left out and added to *damaged.
Result<std::shared_ptr<Snapshot>> BuildFromCatalogue(const Catalogue& catalogue, size_t vocab_size, const IndexOptions& options,
                                       std::vector<DamagedBlob>* damaged) {
  std::vector<std::shared_ptr<const Entry>> by_number;
  const std::string& path = catalogue.path();
  auto status = catalogue.ForEach([&](CatalogueRow&& row) -> Status {
    if (row.number <= 0 || row.number >= (int64_t{1} << 31)) {
      return Fail(ErrorCode::kCorruptData, path + ": image number out of range");
    }
    auto features = PackedFeatures::Deserialize(row.features, "image '" + row.record.id + "' in " + path);
    Status valid = features ? CheckEntry(row.record, *features, vocab_size, path) : Status(std::unexpected(features.error()));
    if (!valid) {
      damaged->push_back({row.number, valid.error().message});
      return Ok();
    }
    const auto number = static_cast<size_t>(row.number);
    if (by_number.size() <= number) by_number.resize(number + 1);
    by_number[number] = std::make_shared<Entry>(Entry{std::move(row.record), std::move(*features), nullptr, 0, std::nullopt});
    return Ok();
  });
  if (!status) return std::unexpected(status.error());
  InvertedFile inverted = InvertedFile::Build(
      vocab_size, ToTfIdf(options), static_cast<uint32_t>(by_number.size()),
      [&](uint32_t number, BagOfWords* bag) {
        if (!by_number[number]) return false;
        *bag = by_number[number]->features().Bag();
        return true;
      },
      options.num_threads);
  return MakeSnapshot(std::move(inverted), by_number, options.num_threads);
}

// Open from the checkpoint the catalogue names, replaying the changes since. A damaged, missing or
// inconsistent checkpoint file gives a null snapshot (and a log line); an error is a catalogue failure.
Result<LoadedCheckpoint> LoadCheckpoint(const std::string& dir, const Catalogue& catalogue, size_t vocab_size,
                                        const IndexOptions& options) {
  const auto t0 = Clock::now();
  LoadedCheckpoint out;
  const auto unusable = [&](const std::string& why) {
    OXBOW_LOG(kWarning) << "index " << dir << ": checkpoint unusable (" << why
                        << "); rebuilding the index from the catalogue and writing a new checkpoint";
    out.snapshot = nullptr;
    return out;
  };
  auto manifest = CheckpointManifest::Parse(catalogue.meta().checkpoint);
  if (!manifest) return unusable(manifest.error().message);
  out.manifest = *manifest;
  if (manifest->sqrt_tf != options.sqrt_tf) return unusable("written with another sqrt_tf setting");

  const std::vector<CheckpointFile>& files = manifest->files;
  auto read = ReadCheckpointFiles(dir, files, options.num_threads);
  if (!read) return unusable(read.error().message);
  std::vector<std::vector<GeometryImage>>& geometry = read->geometry;
  const std::vector<std::shared_ptr<const MappedFile>>& geometry_files = read->geometry_files;
  auto postings = ReadPostings(dir, files, read->postings_files, vocab_size, options, &out.recoded, &out.segment_files);
  if (!postings) return unusable(postings.error().message);
  std::optional<InvertedFile> inverted(std::move(*postings));
  const int64_t high_water = manifest->high_water;
  if (static_cast<int64_t>(inverted->num_numbers()) > high_water + 1) return unusable("postings above the high water");

  std::vector<const GeometryImage*> stored(static_cast<size_t>(high_water) + 1, nullptr);
  std::vector<uint32_t> part_of(stored.size(), 0);  // index into out.parts
  for (size_t i = 0; i < files.size(); ++i) {
    if (IsPostingsFile(files[i].name)) continue;
    auto numbers = std::make_shared<std::vector<uint32_t>>();
    numbers->reserve(geometry[i].size());
    for (const GeometryImage& image : geometry[i]) numbers->push_back(image.number);
    out.contents[files[i].name] = std::move(numbers);
    if (geometry[i].empty()) continue;
    const auto part = static_cast<uint32_t>(out.parts.size());
    out.parts.push_back(std::make_shared<const GeometryPart>(dir, files[i], geometry_files[i]));
    for (const GeometryImage& image : geometry[i]) {
      if (image.number > high_water || stored[image.number]) return unusable("geometry files overlap");
      stored[image.number] = &image;
      part_of[image.number] = part;
    }
  }

  const double files_ms = MsSince(t0);
  // The catalogue's records (not its BLOBs): those up to the high water take their features from
  // the checkpoint; those above were added since.
  std::vector<std::shared_ptr<const Entry>> by_number(stored.size());
  std::map<int64_t, ImageRecord> added;
  std::string inconsistency;
  const std::string& path = catalogue.path();
  auto status = catalogue.ForEach(
      [&](CatalogueRow&& row) -> Status {
        if (row.number <= 0 || row.number >= (int64_t{1} << 31)) {
          return Fail(ErrorCode::kCorruptData, path + ": image number out of range");
        }
        if (row.number > high_water) {
          added.emplace(row.number, std::move(row.record));
          return Ok();
        }
        const auto n = static_cast<uint32_t>(row.number);
        // The words were checked when the image was added; reading them here would page in every
        // mapped geometry page.
        if (!stored[n] || !inverted->IsLive(n) || !RecordMatches(row.record, stored[n]->features)) {
          if (inconsistency.empty()) inconsistency = "image '" + row.record.id + "' differs from the catalogue";
          return Ok();
        }
        by_number[n] = std::make_shared<Entry>(Entry{std::move(row.record), stored[n]->features, out.parts[part_of[n]], n, stored[n]->checksum});
        return Ok();
      },
      /*with_features=*/false);
  if (!status) return std::unexpected(status.error());
  if (!inconsistency.empty()) return unusable(inconsistency);
  // Files mostly of removed images (what a checkpoint drops) are compacted by one right after open.
  const size_t num_geometry_files = out.contents.size();
  out.compact = KeptGeometry(*manifest, out.contents, {}, [&](uint32_t n) { return n < by_number.size() && by_number[n]; })
                    .size() < num_geometry_files;

  const double records_ms = MsSince(t0) - files_ms;
  // Removed since: live in the checkpoint, gone from the catalogue.
  std::vector<uint32_t> removed;
  std::vector<BagOfWords> removed_bags;
  for (uint32_t n = 0; n < inverted->num_numbers(); ++n) {
    if (!inverted->IsLive(n) || by_number[n]) continue;
    if (!stored[n]) return unusable("a live image without geometry");
    // Their words leave the postings: a copy checked now (the image, or the whole file without
    // per-image sums) is what is read.
    const GeometryPart& part = *out.parts[part_of[n]];
    const std::optional<PackedFeatures> copy = part.Copied(n, stored[n]->features, stored[n]->checksum);
    if (!copy) return unusable(part.file().name + ": the data of image number " + std::to_string(n) + " fails its check");
    removed.push_back(n);
    removed_bags.push_back(copy->Bag());
  }
  std::vector<const BagOfWords*> bag_pointers;
  bag_pointers.reserve(removed_bags.size());
  for (const BagOfWords& bag : removed_bags) bag_pointers.push_back(&bag);
  *inverted = inverted->WithRemoved(removed, bag_pointers);

  // Added since: their BLOBs, validated as a full open would.
  std::vector<uint32_t> added_numbers;
  std::vector<BagOfWords> added_bags;
  status = catalogue.ForEachFeaturesAfter(high_water, [&](int64_t number, std::span<const uint8_t> blob) -> Status {
    const auto it = added.find(number);
    if (it == added.end()) return Fail(ErrorCode::kCorruptData, path + " is damaged: features without a record");
    auto features = PackedFeatures::Deserialize(blob, "image '" + it->second.id + "' in " + path);
    Status valid = features ? CheckEntry(it->second, *features, vocab_size, path) : Status(std::unexpected(features.error()));
    if (!valid) {
      out.damaged.push_back({number, valid.error().message});
      added.erase(it);
      return Ok();
    }
    const auto n = static_cast<size_t>(number);
    if (by_number.size() <= n) by_number.resize(n + 1);
    added_numbers.push_back(static_cast<uint32_t>(n));
    added_bags.push_back(features->Bag());
    by_number[n] = std::make_shared<Entry>(Entry{std::move(it->second), std::move(*features), nullptr, 0, std::nullopt});
    added.erase(it);
    return Ok();
  });
  if (!status) return std::unexpected(status.error());
  if (!added.empty()) {
    return Fail(ErrorCode::kCorruptData, path + " is damaged: image '" + added.begin()->second.id + "' has no features");
  }
  bag_pointers.clear();
  bag_pointers.reserve(added_bags.size());
  for (const BagOfWords& bag : added_bags) bag_pointers.push_back(&bag);
  *inverted = inverted->WithAdded(added_numbers, bag_pointers);
  out.changes = removed.size() + added_numbers.size();
  const double replay_ms = MsSince(t0) - files_ms - records_ms;
  out.snapshot = MakeSnapshot(std::move(*inverted), by_number, options.num_threads);
  OXBOW_LOG(kInfo) << "index " << dir << ": opened from checkpoint generation " << manifest->generation << " in "
                   << MsSince(t0) << " ms (files loaded, postings verified " << files_ms << " ms, records " << records_ms
                   << " ms, replay of " << out.changes << " changes " << replay_ms << " ms, id maps "
                   << MsSince(t0) - files_ms - records_ms - replay_ms << " ms)";
  return out;
}

}  // namespace oxbow::index
