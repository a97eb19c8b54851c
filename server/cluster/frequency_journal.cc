#include "server/cluster/frequency_journal.h"

#include <filesystem>
#include <span>

#include "sift/base/binary_io.h"

namespace oxbow::cluster {
namespace {

constexpr std::string_view kMagic = "OXBWPDFJ";
constexpr uint32_t kVersion = 1;

}  // namespace

FrequencyJournal::FrequencyJournal(std::string path, uint64_t vocabulary_fingerprint, size_t vocabulary_size)
    : path_(std::move(path)), fingerprint_(vocabulary_fingerprint), df_(vocabulary_size, 0) {}

Status FrequencyJournal::Load(const std::function<bool(const std::string& id)>& committed) {
  std::error_code ec;
  if (!std::filesystem::exists(path_, ec)) return Ok();
  const auto c = io::ReadContainerFile(path_, kMagic, kVersion, kVersion);
  if (!c) return std::unexpected(c.error());
  io::ByteReader r(c->payload, "partition frequencies " + path_);
  const auto fingerprint = r.Get<uint64_t>();
  if (!fingerprint) return std::unexpected(fingerprint.error());
  if (*fingerprint != fingerprint_) return Fail(ErrorCode::kIncompatible, path_ + " counts another vocabulary's words");
  const auto images = r.Get<uint64_t>();
  if (!images) return std::unexpected(images.error());
  const auto words = r.Get<uint64_t>();
  if (!words) return std::unexpected(words.error());
  if (*words != df_.size()) return Fail(ErrorCode::kCorruptData, path_ + ": wrong number of words");
  std::vector<uint32_t> df(df_.size());
  if (Status st = r.GetArray(std::span<uint32_t>(df)); !st) return st;
  const auto pending = r.Get<uint64_t>();
  if (!pending) return std::unexpected(pending.error());
  std::vector<std::vector<uint32_t>> settled;
  for (uint64_t i = 0; i < *pending; ++i) {
    const auto id = r.GetString();
    if (!id) return std::unexpected(id.error());
    const auto count = r.Get<uint64_t>();
    if (!count) return std::unexpected(count.error());
    if (*count > df_.size()) return Fail(ErrorCode::kCorruptData, path_ + ": more distinct words than the vocabulary has");
    std::vector<uint32_t> image_words(*count);
    if (Status st = r.GetArray(std::span<uint32_t>(image_words)); !st) return st;
    for (const uint32_t w : image_words) {
      if (w >= df_.size()) return Fail(ErrorCode::kCorruptData, path_ + ": a word beyond the vocabulary");
    }
    if (committed(*id)) settled.push_back(std::move(image_words));
  }
  // Only a journal read whole replaces the counts.
  images_ = *images;
  df_ = std::move(df);
  pending_.clear();
  for (const auto& image_words : settled) Count(image_words);
  return Ok();
}

Status FrequencyJournal::Recover(const index::ImageIndex& idx) {
  if (Status st = Load([&](const std::string& id) { return idx.Contains(id); }); !st) return st;
  const uint64_t indexed = idx.Stats().num_images;
  if (indexed != images_) {
    return Fail(ErrorCode::kIncompatible,
                idx.directory() + " holds " + std::to_string(indexed) + " images but the words of " +
                    std::to_string(images_) + " were recorded (" + path_ +
                    "): it was changed outside `index build --mpi`; build the cluster into a new --out");
  }
  return Ok();
}

Status FrequencyJournal::Prepare(std::vector<std::pair<std::string, std::vector<uint32_t>>> batch) {
  pending_ = std::move(batch);
  return Write();
}

void FrequencyJournal::Commit(const std::vector<bool>& added) {
  for (size_t i = 0; i < pending_.size(); ++i) {
    if (added[i]) Count(pending_[i].second);
  }
  pending_.clear();
}

Status FrequencyJournal::Write() const {
  io::ByteWriter w;
  w.Put(fingerprint_);
  w.Put(images_);
  w.Put(uint64_t{df_.size()});
  w.PutArray(std::span<const uint32_t>(df_));
  w.Put(uint64_t{pending_.size()});
  for (const auto& [id, words] : pending_) {
    w.PutString(id);
    w.Put(uint64_t{words.size()});
    w.PutArray(std::span<const uint32_t>(words));
  }
  return io::WriteContainerFile(path_, kMagic, kVersion, 0, w.bytes());
}

void FrequencyJournal::Count(const std::vector<uint32_t>& distinct_words) {
  ++images_;
  for (const uint32_t w : distinct_words) ++df_.at(w);
}

}  // namespace oxbow::cluster
