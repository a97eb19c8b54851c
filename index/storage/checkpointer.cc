#include "index/storage/checkpointer.h"

#include <pthread.h>
#include <sched.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>

#include "index/cow_array.h"
#include "sift/base/log.h"

namespace oxbow::index {
namespace {

using Clock = std::chrono::steady_clock;
double MsSince(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// Puts the calling thread in Linux's SCHED_IDLE class: it runs only on a core no other thread wants;
// and its disk reads in the idle I/O class, served when no other reads wait (where the I/O scheduler
// knows classes: mq-deadline and BFQ do), so that the first searches' page faults on a cold disk are
// not queued behind its large sequential reads. Best effort (a refusal leaves it as it was); allowed
// without privileges, and not undone: call it on a thread that ends with its work.
void RunOnlyWhenIdle() {
  sched_param param{};
  param.sched_priority = 0;
  (void)pthread_setschedparam(pthread_self(), SCHED_IDLE, &param);
  // ioprio_set(IOPRIO_WHO_PROCESS, 0 = this thread, IOPRIO_PRIO_VALUE(IOPRIO_CLASS_IDLE, 0)); glibc
  // has no wrapper, and the constants are those of <linux/ioprio.h>.
  constexpr int kWhoProcess = 1, kClassIdle = 3, kClassShift = 13;
  (void)::syscall(SYS_ioprio_set, kWhoProcess, 0, kClassIdle << kClassShift);
}

bool Names(const std::vector<CheckpointFile>& files, const CheckpointFile& file) {
  return std::find(files.begin(), files.end(), file) != files.end();
}

}  // namespace

Checkpointer::Checkpointer(std::string dir, const IndexOptions& options, std::mutex& writer_mutex,
                           Catalogue& catalogue, CurrentSnapshot& snapshot, const SearchActivity& searches, Start start)
    : dir_(std::move(dir)),
      sqrt_tf_(options.sqrt_tf),
      checkpoint_changes_(options.checkpoint_changes),
      writer_mutex_(writer_mutex),
      catalogue_(catalogue),
      snapshot_(snapshot),
      searches_(searches),
      manifest_(std::move(start.manifest)),
      contents_(std::move(start.contents)),
      changes_(start.changes),
      forced_(start.forced),
      loaded_parts_(std::move(start.parts)) {
  for (auto& [segment, file] : start.segment_files) segment_files_.push_back({segment, std::move(file)});
}

Checkpointer::~Checkpointer() {
  if (thread_.joinable()) Close();
}

void Checkpointer::Run() {
  thread_ = std::thread([this] { Loop(); });
}

void Checkpointer::Changed(uint64_t images) {
  changes_ += images;
  if (CheckpointDue()) due_.notify_one();
}

bool Checkpointer::CheckpointDue() const {
  const uint64_t live = snapshot_.Current()->inverted.num_images();
  return forced_ || changes_ >= std::max(checkpoint_changes_, live / 10) || !DamagedGeometry(manifest_).empty();
}

std::set<std::string> Checkpointer::DamagedGeometry(const CheckpointManifest& manifest) const {
  std::set<std::string> out;
  for (const auto* parts : {&loaded_parts_, &written_parts_}) {
    for (const auto& part : *parts) {
      if (part->Damaged() && Names(manifest.files, part->file())) out.insert(part->file().name);
    }
  }
  return out;
}

void Checkpointer::Loop() {
  // The loaded geometry files are checked on a thread of their own in SCHED_IDLE, pausing while a
  // search runs (VerifyParts): right after an open, reading and hashing every file (5-45 s at 1M
  // images) would otherwise take a core from the first searches, which then ran at half speed. A
  // search never waits for it (an image it uses first is checked alone, GeometryPart::CopyChecked), and
  // neither do checkpoints: under a load that keeps every core busy, or a search always running, the
  // check may not run for minutes. A checkpoint before it ends keeps the files
  // not checked yet (their images are still checked on use); one found damaged later is rewritten by
  // the next checkpoint, as DamagedGeometry names it in any manifest that still holds it.
  std::thread verifier([this] {
    RunOnlyWhenIdle();
    VerifyParts();
  });
  for (;;) {
    const std::optional<Job> next_job = NextJob();
    if (!next_job.has_value()) break;
    const Job& job = *next_job;
    GeometryContents next_contents;
    auto next = WriteFiles(*job.snapshot, job.previous, job.contents, &next_contents);  // writers go on
    const std::optional<Written> written = Commit(job, std::move(next), std::move(next_contents));
    if (written.has_value()) PublishViews(*job.snapshot, ReadBack(*job.snapshot, *written));
  }
  verifier.join();  // Close set stop_verifying_: it gives up before its next read
}

std::optional<Checkpointer::Job> Checkpointer::NextJob() {
  std::unique_lock<std::mutex> lock(writer_mutex_);
  due_.wait(lock, [&] { return closing_ || CheckpointDue(); });
  if (closing_) return std::nullopt;
  return Job{.snapshot = snapshot_.Current(), .previous = manifest_, .contents = contents_, .changes = changes_};
}

std::optional<Checkpointer::Written> Checkpointer::Commit(const Job& job, Result<CheckpointManifest> next,
                                                          GeometryContents next_contents) {
  std::lock_guard<std::mutex> lock(writer_mutex_);
  const Status status =
      next ? CommitManifest(std::move(*next), std::move(next_contents), job.changes) : Status(std::unexpected(next.error()));
  if (!status) {
    OXBOW_LOG(kWarning) << "index " << dir_ << ": cannot write a checkpoint (" << status.error().message
                        << "); trying again after as many changes, and at close";
    changes_ -= std::min(changes_, job.changes);
    forced_ = false;
    pending_after_failure_ += job.changes;
    return std::nullopt;
  }
  // Parts the committed manifest no longer names are forgotten here; their images move to the new
  // files (PublishViews), and each file's mapping (and descriptor) goes with the last snapshot that
  // views it.
  const auto dropped = [&](const auto& part) { return !Names(manifest_.files, part->file()); };
  std::erase_if(written_parts_, dropped);
  std::erase_if(loaded_parts_, dropped);
  Written written{.new_geometry = {}, .named = manifest_.files};
  for (const CheckpointFile& file : manifest_.files) {
    if (file.name.starts_with("geometry-") && !Names(job.previous.files, file)) written.new_geometry.push_back(file);
  }
  return written;
}

Status Checkpointer::CommitManifest(CheckpointManifest next, GeometryContents next_contents, uint64_t changes) {
  if (auto s = catalogue_.SetCheckpoint(next.Format()); !s) return s;
  CheckpointStage("manifest-committed");
  manifest_ = std::move(next);
  contents_ = std::move(next_contents);
  changes_ -= changes;
  forced_ = false;
  // Only now, with the new manifest durable (SetCheckpoint commits with synchronous=FULL), are the
  // files it no longer names deleted (a dropped geometry file, a merged-away segment, the previous
  // postings head): a crash before the commit leaves the previous manifest with every file it names
  // (the new files have new names), one after it leaves the new manifest, whose files are durable
  // (WriteCheckpointFile), and leftovers that Open deletes. A file still mapped by a snapshot in use
  // (a search, a backup) stays readable after the unlink: its disk space is freed once the last
  // mapping of it is gone (PublishViews moves the live images to the new files).
  RemoveUnreferencedCheckpointFiles(dir_, manifest_);
  CheckpointStage("cleaned");
  return Ok();
}

// After a checkpoint committed: the images its new geometry files hold that are still indexed view the
// files instead of the copies in memory that Add made, as after an open. Without it an index kept every
// image added since its open in memory (17 bytes per feature: 17 GB after ingesting 1M images of 1000
// features). Each image's data is checked on use, as in a file an open loaded. A file that cannot be
// mapped or read keeps its images in memory (logged).
std::vector<Checkpointer::Viewing> Checkpointer::ReadBack(const Snapshot& written, const Written& files) const {
  const auto named = [&](const GeometryPart& part) { return Names(files.named, part.file()); };
  std::vector<Viewing> viewing;
  for (const CheckpointFile& file : files.new_geometry) {
    const std::string path = (std::filesystem::path(dir_) / file.name).string();
    auto mapped = MappedFile::Open(path);
    auto images = mapped ? ReadGeometry(*mapped, "checkpoint file " + path)
                         : Result<std::vector<GeometryImage>>(std::unexpected(mapped.error()));
    if (!images) {
      OXBOW_LOG(kWarning) << "index " << dir_ << ": cannot read back " << path << " (" << images.error().message
                          << "); its images stay in memory until the next open";
      continue;
    }
    // Files without per-image checksums (formats 1 and 2, written only by tests) would be checked whole
    // at the first use of an image, with a search waiting: their images stay in memory.
    if (std::any_of(images->begin(), images->end(), [](const GeometryImage& image) { return !image.checksum; })) continue;
    Viewing& v = viewing.emplace_back();
    v.part = std::make_shared<const GeometryPart>(dir_, file, *mapped);
    for (GeometryImage& image : *images) {
      if (image.number >= written.entries.size()) continue;
      const Entry* entry = written.entries[image.number].get();
      // An image viewing a file still named stays there; one in memory, or viewing a file the manifest
      // dropped (compacted or damaged), views the new file.
      if (!entry || (entry->part && named(*entry->part)) || !RecordMatches(entry->record, image.features)) continue;
      v.entries.emplace_back(image.number, std::make_shared<const Entry>(Entry{
                                               entry->record, std::move(image.features), v.part, image.number, image.checksum}));
    }
  }
  return viewing;
}

void Checkpointer::PublishViews(const Snapshot& written, std::vector<Viewing> viewing) {
  std::lock_guard<std::mutex> lock(writer_mutex_);
  if (viewing.empty()) {
    CheckpointStage("geometry-viewed");
    return;
  }
  const auto current = snapshot_.Current();
  auto next = std::make_shared<Snapshot>(*current);
  size_t viewed = 0;
  {
    CowArray<std::shared_ptr<const Entry>>::Editor editor(&next->entries);
    for (Viewing& v : viewing) {
      size_t used = 0;
      for (auto& [number, entry] : v.entries) {
        // Removed since (or replaced: a new number): left as it is.
        if (number >= current->entries.size() || current->entries[number] != written.entries[number]) continue;
        next->geometry_bytes += entry->MemoryBytes();
        next->geometry_bytes -= current->entries[number]->MemoryBytes();
        editor.Mutable(number) = std::move(entry);
        ++used;
      }
      if (used > 0) written_parts_.push_back(std::move(v.part));
      viewed += used;
    }
  }
  if (viewed > 0) snapshot_.Publish(std::move(next));
  CheckpointStage("geometry-viewed");
}

void Checkpointer::VerifyParts() {
  // Weak: a part a checkpoint dropped meanwhile (Commit) is not kept open for its check.
  std::vector<std::weak_ptr<const GeometryPart>> parts;
  {
    std::lock_guard<std::mutex> lock(writer_mutex_);
    parts.assign(loaded_parts_.begin(), loaded_parts_.end());
  }
  if (parts.empty()) return;
  CheckpointStage("verifying-geometry");
  const auto t0 = Clock::now();
  size_t damaged = 0;
  // Between its 4 MiB reads the check waits while a search runs: SCHED_IDLE keeps it off a core a
  // search wants, but not off the disk, the memory bus or the page cache, and at 1M images (16 GB of
  // geometry, read for 5-45 s after an open) it would make the searches of that time 10-25% slower.
  // While a search ended less than kBusyWindow ago it also reads at most one
  // block per kBusyGap (80 MiB/s): read from disk at full speed (up to 1.2 GB/s right after a bulk
  // ingest, whose files the page cache no longer held) it took 22-36% of the CPU in the kernel between
  // the searches (vmstat), 6-8% so limited. Idle for kBusyWindow, it reads at full speed.
  static constexpr auto kBusyWindow = std::chrono::seconds(1);
  static constexpr auto kBusyGap = std::chrono::milliseconds(50);
  Clock::time_point last_read = Clock::now();
  const auto stop = [this, &last_read] {
    for (;;) {
      if (stop_verifying_.load()) return true;
      const auto now = Clock::now();
      const bool busy = now - searches_.last_end() < kBusyWindow;
      if (searches_.running() == 0 && (!busy || now - last_read >= kBusyGap)) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    last_read = Clock::now();
    CheckpointStage("geometry-read");
    return false;
  };
  for (const auto& weak : parts) {
    const std::shared_ptr<const GeometryPart> part = weak.lock();
    if (!part) continue;
    const std::optional<bool> good = part->VerifiedUnless(stop);
    if (!good.has_value()) return;  // closing
    if (!*good) ++damaged;
  }
  CheckpointStage("geometry-verified");
  OXBOW_LOG(kInfo) << "index " << dir_ << ": " << parts.size() << " geometry files of the checkpoint verified in "
                   << MsSince(t0) << " ms, " << damaged << " damaged";
  // A damaged file makes CheckpointDue() true: the checkpointer rewrites it once woken (under the lock,
  // so that the wake cannot fall between its test and its wait).
  if (damaged > 0) {
    std::lock_guard<std::mutex> lock(writer_mutex_);
    due_.notify_one();
  }
}

void Checkpointer::Close() {
  if (closed_) return;
  closed_ = true;
  {
    std::lock_guard<std::mutex> writer(writer_mutex_);
    closing_ = true;
  }
  stop_verifying_ = true;
  due_.notify_one();
  if (thread_.joinable()) thread_.join();
  std::lock_guard<std::mutex> writer(writer_mutex_);
  changes_ += pending_after_failure_;
  if (changes_ == 0 && !forced_ && DamagedGeometry(manifest_).empty()) return;
  GeometryContents next_contents;
  auto next = WriteFiles(*snapshot_.Current(), manifest_, contents_, &next_contents);
  const Status status =
      next ? CommitManifest(std::move(*next), std::move(next_contents), changes_) : Status(std::unexpected(next.error()));
  if (!status) {
    OXBOW_LOG(kWarning) << "index " << dir_ << ": cannot write a checkpoint at close (" << status.error().message
                        << "); the next open replays the changes from the catalogue";
  }
}

Result<CheckpointManifest> Checkpointer::WriteFiles(const Snapshot& snap, const CheckpointManifest& previous,
                                                    const GeometryContents& contents,
                                                    GeometryContents* next_contents) const {
  CheckpointManifest next;
  next.generation = previous.generation + 1;
  next.sqrt_tf = sqrt_tf_;
  const size_t num_numbers = snap.entries.size();
  next.high_water = num_numbers > 0 ? static_cast<int64_t>(num_numbers) - 1 : 0;
  // Geometry files are immutable: a previous one that KeptGeometry keeps is named again (its images
  // removed since are skipped at open), the others are dropped; new ones hold the images above the
  // previous high water and the live images of the dropped files. Each live image is in exactly one
  // file of the manifest (Open refuses overlaps).
  const auto is_live = [&](uint32_t n) { return n < num_numbers && snap.entries[n] != nullptr; };
  const std::set<std::string> kept = KeptGeometry(previous, contents, DamagedGeometry(previous), is_live);
  next_contents->clear();
  const size_t first = previous.files.empty() ? 0 : static_cast<size_t>(previous.high_water) + 1;
  std::vector<uint8_t> covered(first, 0);  // 1: in a file kept
  for (const CheckpointFile& f : previous.files) {
    if (!kept.count(f.name)) continue;
    next.files.push_back(f);
    const auto& numbers = contents.at(f.name);
    (*next_contents)[f.name] = numbers;
    for (const uint32_t n : *numbers) {
      if (n < first) covered[n] = 1;
    }
  }
  const std::string generation = std::to_string(next.generation);
  std::vector<GeometryImage> part;
  uint64_t part_bytes = 0;
  int parts = 0;
  const auto write_part = [&]() -> Status {
    auto file = WriteCheckpointFile(dir_, "geometry-" + generation + "-" + std::to_string(parts++) + ".oxck",
                                    [&](const ByteSink& sink) { WriteGeometry(part, sink); });
    if (!file) return std::unexpected(file.error());
    auto numbers = std::make_shared<std::vector<uint32_t>>();
    numbers->reserve(part.size());
    for (const GeometryImage& image : part) numbers->push_back(image.number);
    (*next_contents)[file->name] = std::move(numbers);
    next.files.push_back(std::move(*file));
    part.clear();
    part_bytes = 0;
    return Ok();
  };
  for (size_t n = 0; n < num_numbers; ++n) {
    const Entry* entry = snap.entries[n].get();
    if (!entry || (n < first && covered[n])) continue;
    const PackedFeatures& features = entry->features();
    part.push_back({static_cast<uint32_t>(n), features, std::nullopt});
    part_bytes += features.bytes().size() + features.signature_bytes().size();
    if (part_bytes >= kGeometryPartBytes) {
      if (auto s = write_part(); !s) return std::unexpected(s.error());
    }
  }
  if (!part.empty()) {
    if (auto s = write_part(); !s) return std::unexpected(s.error());
  }
  // Postings: a segment already in a file of the previous manifest is named again; each other one is
  // written to a new file (segments are immutable); the head names them in order.
  std::vector<std::string> segment_names;
  {
    std::lock_guard<std::mutex> lock(segment_files_mutex_);
    std::erase_if(segment_files_, [](const SegmentFile& f) { return f.segment.expired(); });
  }
  int segments_written = 0;
  for (size_t i = 0; i < snap.inverted.num_segments(); ++i) {
    auto file = FileOfSegment(snap, i, previous, generation, &segments_written);
    if (!file) return std::unexpected(file.error());
    segment_names.push_back(file->name);
    next.files.push_back(std::move(*file));
  }
  auto postings = WriteCheckpointFile(dir_, "postings-" + generation + ".oxck",
                                      [&](const ByteSink& sink) { snap.inverted.SerializeHead(segment_names, sink); });
  if (!postings) return std::unexpected(postings.error());
  next.files.push_back(std::move(*postings));
  CheckpointStage("files-written");
  return next;
}

Result<CheckpointFile> Checkpointer::FileOfSegment(const Snapshot& snap, size_t i, const CheckpointManifest& previous,
                                                   const std::string& generation, int* written) const {
  const std::shared_ptr<const void> handle = snap.inverted.SegmentHandle(i);
  {
    std::lock_guard<std::mutex> lock(segment_files_mutex_);
    for (const SegmentFile& f : segment_files_) {
      if (f.segment.lock() == handle && std::find(previous.files.begin(), previous.files.end(), f.file) != previous.files.end()) {
        return f.file;
      }
    }
  }
  auto file = WriteCheckpointFile(dir_, "segment-" + generation + "-" + std::to_string((*written)++) + ".oxck",
                                  [&](const ByteSink& sink) { snap.inverted.SerializeSegment(i, sink); });
  if (!file) return file;
  {
    std::lock_guard<std::mutex> lock(segment_files_mutex_);
    std::erase_if(segment_files_, [&](const SegmentFile& f) { return f.file.name == file->name; });
    segment_files_.push_back({handle, *file});
  }
  CheckpointStage("segment-written");
  return file;
}

}  // namespace oxbow::index
