// `oxbow index build|add|remove|info|check|backup`: create and maintain an image index (index/image_index.h).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "api/duplicates.h"
#include "api/json.h"
#include "api/params.h"
#include "api/partition.h"
#include "api/service.h"
#include "index/storage/catalogue.h"
#include "index/image_index.h"
#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "server/cli/mpi_communicator.h"
#include "server/cluster/frequency_journal.h"
#include "sift/base/binary_io.h"
#include "sift/base/log.h"
#include "sift/base/parallel.h"
#include "sift/features_io.h"
#include "sift/sift.h"
#include "vocab/vocabulary.h"

namespace oxbow::cli {
namespace {

namespace fs = std::filesystem;

struct ImageJob {
  std::string id;
  std::string path;
  std::string taken_by;  // another input with the same id, listed first: this one is not indexed
};

// The extractor whose settings the index records.
sift::SiftExtractor ExtractorFor(const index::ImageIndex& idx, int threads_per_image) {
  sift::SiftOptions options = ValueOrExit(sift::SiftOptions::FromDescription(idx.extractor_settings()));
  options.num_threads = threads_per_image;
  return ValueOrExit(sift::SiftExtractor::Create(options));
}

// Settings for a new index: the vocabulary's, or this build's defaults for its descriptor kind.
std::string SettingsFor(const vocab::Vocabulary& vocabulary) {
  if (!vocabulary.extractor_settings().empty()) return vocabulary.extractor_settings();
  sift::SiftOptions options;
  options.descriptor = vocabulary.descriptor_kind();
  return options.Describe();
}

std::unique_ptr<index::ImageIndex> OpenOrCreate(const std::string& dir, const vocab::Vocabulary& vocabulary,
                                                const index::IndexOptions& options) {
  if (index::ImageIndex::Exists(dir)) {
    auto idx = ValueOrExit(index::ImageIndex::Open(dir, options));
    if (idx->vocabulary().fingerprint() != vocabulary.fingerprint()) {
      throw CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                         "the index at " + dir + " was built with another vocabulary; use that vocabulary or a new --out folder");
    }
    OXBOW_LOG(kInfo) << "resuming index " << dir << " (" << idx->Stats().num_images << " images)";
    return idx;
  }
  return ValueOrExit(index::ImageIndex::Create(dir, vocabulary, SettingsFor(vocabulary), options));
}

// One job per path, id = id_of(path); a path whose id an earlier one took is marked (taken_by), and
// counted among the failed images when the build reaches it.
std::vector<ImageJob> UniqueIdJobs(const std::vector<std::string>& paths,
                                   const std::function<std::string(const fs::path&)>& id_of) {
  std::vector<ImageJob> jobs;
  std::map<std::string, std::string> seen;
  for (const auto& p : paths) {
    const std::string id = id_of(p);
    auto [it, inserted] = seen.emplace(id, p);
    jobs.push_back({id, p, inserted ? std::string() : it->second});
  }
  return jobs;
}

std::vector<ImageJob> CollectImages(const std::string& images_dir, const std::string& list_file) {
  std::vector<std::string> paths;
  if (!images_dir.empty()) {
    paths = ValueOrExit(sift::ListImageFiles(images_dir));
  } else {
    std::error_code ec;
    if (fs::is_directory(list_file, ec)) {
      throw CommandError(2, "--list '" + list_file + "' is a folder: give a text file of image paths, one per line "
                            "(or --images FOLDER)");
    }
    std::ifstream in(list_file);
    if (!in) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "cannot read list " + list_file);
    const fs::path base = fs::path(list_file).parent_path();
    std::string line;
    while (std::getline(in, line)) {
      while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.pop_back();
      if (line.empty() || line[0] == '#') continue;
      if (line.find('\0') != std::string::npos) {
        throw CommandError(2, "--list '" + list_file + "' is not a text file of image paths (it holds NUL bytes: an "
                              "image? give it as a path in the list, or its folder as --images)");
      }
      fs::path p(line);
      if (p.is_relative() && !fs::exists(p, ec) && fs::exists(base / p, ec)) p = base / p;
      paths.push_back(p.string());
    }
  }
  return UniqueIdJobs(paths, [](const fs::path& p) { return p.stem().string(); });
}

// Every .oxfeat file under `folder` (recursively), id = the image name without its extension
// (`oxbow extract` writes <image file name>.oxfeat, so photo.jpg.oxfeat is the image "photo", the id
// `index build --images` would give photo.jpg).
std::vector<ImageJob> CollectFeatureFiles(const std::string& folder) {
  std::error_code ec;
  if (!fs::is_directory(folder, ec)) {
    throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "no folder " + folder);
  }
  std::vector<std::string> paths;
  for (fs::recursive_directory_iterator it(folder, ec), end; !ec && it != end; it.increment(ec)) {
    if (it->is_regular_file(ec) && it->path().extension() == ".oxfeat") paths.push_back(it->path().string());
  }
  if (ec) throw CommandError(ExitCodeFor(ErrorCode::kIoError), "cannot list " + folder + ": " + ec.message());
  if (paths.empty()) {
    throw CommandError(ExitCodeFor(ErrorCode::kNotFound),
                       "no .oxfeat files under " + folder + " (`oxbow extract IMAGES --out " + folder + "` writes them)");
  }
  std::sort(paths.begin(), paths.end());
  return UniqueIdJobs(paths, [](const fs::path& p) { return p.stem().stem().string(); });
}

void PrintJson(const nlohmann::json& j) { std::printf("%s\n", j.dump(2).c_str()); }

nlohmann::json StatsJson(const index::ImageIndex& idx) {
  const index::IndexStats s = idx.Stats();
  char fingerprint[32];
  std::snprintf(fingerprint, sizeof(fingerprint), "%016llx", static_cast<unsigned long long>(s.vocabulary_fingerprint));
  return {{"index", idx.directory()},
          {"images", s.num_images},
          {"features", s.num_features},
          {"bytes_per_feature", s.bytes_per_feature},
          {"memory_bytes", {{"postings", s.postings_bytes}, {"geometry", s.geometry_bytes}, {"other", s.other_bytes}}},
          {"segments", s.num_segments},
          {"vocabulary", {{"size", s.vocabulary_size}, {"fingerprint", fingerprint},
                          {"descriptor", sift::DescriptorKindName(idx.vocabulary().descriptor_kind())}}},
          {"extractor_settings", idx.extractor_settings()}};
}

struct BuildArgs {
  std::string vocab, images, list, features, out;
  int threads = 0;
  int probes = vocab::QuantizerOptions{}.num_probes;
  ImageFlags image;
  bool mpi = false;
  uint32_t partitions = 1;
};

index::IndexOptions IndexOptionsFor(const BuildArgs& build) {
  index::IndexOptions options;
  options.num_threads = build.threads;
  options.quantizer.num_threads = build.threads;
  options.quantizer.num_probes = build.probes;
  return options;
}

std::vector<ImageJob> CollectJobs(const BuildArgs& build) {
  return build.features.empty() ? CollectImages(build.images, build.list) : CollectFeatureFiles(build.features);
}

struct BuildCounts {
  size_t added = 0, failed = 0, skipped = 0;
  uint64_t features = 0;
  bool interrupted = false;  // stopped between batches by InterruptibleCommand
};

// Adds the jobs `idx` does not hold yet, in batches. With a journal, the words are assigned here (the
// index's own quantiser settings) and each batch's distinct words recorded in it before the commit.
BuildCounts IngestJobs(const BuildArgs& build, index::ImageIndex& idx, std::vector<ImageJob> all,
                       cluster::FrequencyJournal* journal) {
  const bool from_features = !build.features.empty();
  const sift::DecodeOptions decode = build.image.ToDecodeOptions();
  BuildCounts counts;
  std::vector<ImageJob> todo;
  for (auto& job : all) {
    if (!job.taken_by.empty()) {
      // Ids are file names without their extension: x/a.jpg and y/a.png are both 'a'.
      OXBOW_LOG(kWarning) << "not indexed: " << job.path << ": its id '" << job.id << "' is " << job.taken_by
                          << "'s (an id is the file name without its extension); rename it, or index it into "
                             "another --out";
      ++counts.failed;
    } else if (!idx.Contains(job.id)) {
      todo.push_back(std::move(job));
    } else {
      ++counts.skipped;
    }
  }
  if (counts.skipped) {
    OXBOW_LOG(kInfo) << counts.skipped << " images already indexed in " << idx.directory() << ", skipped";
  }
  const ThreadSplit split = SplitThreads(build.threads, todo.size());
  std::optional<sift::SiftExtractor> extractor;
  if (!from_features) extractor.emplace(ExtractorFor(idx, split.per_item));
  vocab::QuantizerOptions quantizer;
  quantizer.num_probes = build.probes;
  log::Progress progress("indexing", todo.size(), "images");
  // One committed transaction per batch (ImageIndex::AddBatch quantises it on every thread): a
  // crash loses at most the batch in flight, which the next run redoes.
  const size_t batch = from_features ? 256 : std::max<size_t>(32, static_cast<size_t>(split.workers) * 2);
  for (size_t begin = 0; begin < todo.size(); begin += batch) {
    if (InterruptibleCommand::Interrupted()) {
      counts.interrupted = true;
      break;
    }
    const size_t n = std::min(batch, todo.size() - begin);
    std::vector<Result<sift::FeatureFile>> loaded(n);  // every slot is assigned below
    std::vector<std::vector<uint32_t>> words(journal ? n : 0);
    // Extract (one image per worker) or read feature files in parallel, add in order.
    ParallelFor(n, from_features ? build.threads : split.workers, 1, [&](size_t lo, size_t hi, int) {
      for (size_t i = lo; i < hi; ++i) {
        const std::string& path = todo[begin + i].path;
        if (from_features) {
          loaded[i] = sift::ReadFeatureFile(path);
        } else if (auto f = extractor->ExtractFromFile(path, decode)) {
          loaded[i] = sift::FeatureFile{.features = std::move(*f), .extractor_description = idx.extractor_settings()};
        } else {
          loaded[i] = std::unexpected(f.error());
        }
        const Result<sift::FeatureFile>& f = loaded[i];
        if (journal && f && f->features.descriptors.size() == f->features.size() * idx.vocabulary().dimension()) {
          words[i].resize(f->features.size());
          idx.vocabulary().Quantize(f->features.descriptors, words[i], quantizer);
        }
      }
    });
    std::vector<index::BatchImage> items;
    std::vector<size_t> positions;
    std::vector<std::pair<std::string, std::vector<uint32_t>>> distinct;
    for (size_t i = 0; i < n; ++i) {
      const ImageJob& job = todo[begin + i];
      const Result<sift::FeatureFile>& f = loaded[i];
      if (!f) {
        OXBOW_LOG(kWarning) << "skipping " << job.path << ": " << f.error().ToString();
        ++counts.failed;
        progress.Advance();
        continue;
      }
      index::ImageInfo info;
      info.source_path = fs::absolute(job.path).string();
      info.extractor_settings = f->extractor_description;
      items.push_back({job.id, &f->features, std::move(info), {}, {}});
      positions.push_back(i);
      if (journal) {
        items.back().words = words[i];
        std::vector<uint32_t> d = words[i];
        std::sort(d.begin(), d.end());
        d.erase(std::unique(d.begin(), d.end()), d.end());
        distinct.emplace_back(job.id, std::move(d));
      }
    }
    if (journal) OkOrExit(journal->Prepare(std::move(distinct)));
    const auto results = idx.AddBatch(items);
    std::vector<bool> added(results.size(), false);
    for (size_t k = 0; k < results.size(); ++k) {
      const auto& record = results[k];
      if (!record) {
        if (record.error().code == ErrorCode::kIoError) throw CommandError(record.error());
        OXBOW_LOG(kWarning) << "skipping " << todo[begin + positions[k]].path << ": " << record.error().ToString();
        ++counts.failed;
      } else {
        added[k] = true;
        ++counts.added;
        counts.features += record->num_features;
      }
      progress.Advance();
    }
    if (journal) journal->Commit(added);
  }
  if (journal) OkOrExit(journal->Write());
  return counts;
}

nlohmann::json BuildSummary(const index::ImageIndex& idx, const BuildCounts& counts, double seconds) {
  nlohmann::json summary = StatsJson(idx);
  summary["added"] = counts.added;
  summary["already_indexed"] = counts.skipped;
  summary["failed"] = counts.failed;
  summary["added_features"] = counts.features;
  summary["seconds"] = seconds;
  summary["images_per_second"] = seconds > 0 ? static_cast<double>(counts.added) / seconds : 0.0;
  return summary;
}

// Why this rank cannot resume build.out with build.partitions, if it cannot: resuming with another
// number of partitions would route images to other partitions than the ones holding them. Rank 0 checks
// for a partition beyond the last; each rank checks the recorded count of its own partitions.
std::optional<CommandError> ResumeRefusal(const BuildArgs& build, int rank, std::span<const uint32_t> mine) {
  const uint32_t partitions = build.partitions;
  std::error_code ec;
  if (rank == 0 && fs::exists(api::PartitionFolder(build.out, partitions), ec)) {
    return CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                        build.out + " holds a cluster of more than " + std::to_string(partitions) +
                            " partitions; resume it with its own --partitions or build into a new --out");
  }
  for (uint32_t p : mine) {
    const std::string path = api::PartitionFolder(build.out, p) + "/" + std::string(api::kGlobalFrequenciesFile);
    if (!fs::exists(path, ec)) continue;
    const auto previous = api::ReadGlobalFrequencies(path);
    if (!previous) return CommandError(previous.error());
    if (previous->num_partitions != partitions) {
      return CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                          build.out + " is a cluster of " + std::to_string(previous->num_partitions) +
                              " partitions; resume it with --partitions " + std::to_string(previous->num_partitions) +
                              " or build into a new --out");
    }
  }
  return std::nullopt;
}

// `index build --mpi`: every rank builds the partitions p with p mod ranks == rank, then the ranks sum
// their partitions' document frequencies and each writes the totals beside its partitions.
void RunClusterBuild(const BuildArgs& build, vocab::Communicator& comm) {
  const auto t0 = std::chrono::steady_clock::now();
  const vocab::Vocabulary vocabulary = ValueOrExit(vocab::Vocabulary::Read(build.vocab));
  const uint32_t partitions = build.partitions;
  std::vector<std::vector<ImageJob>> jobs(partitions);
  for (ImageJob& job : CollectJobs(build)) jobs[api::PartitionOf(job.id, partitions)].push_back(std::move(job));
  std::vector<uint32_t> mine;
  for (uint32_t p = static_cast<uint32_t>(comm.rank()); p < partitions; p += static_cast<uint32_t>(comm.size()))
    mine.push_back(p);
  ThrowIfAnyRankRefuses(comm, ResumeRefusal(build, comm.rank(), mine));

  // [images, df per word], summed over this rank's partitions, then over all ranks.
  std::vector<int64_t> totals(1 + vocabulary.size(), 0);
  nlohmann::json summaries = nlohmann::json::array();
  std::vector<std::string> folders;
  for (uint32_t p : mine) {
    const std::string dir = api::PartitionFolder(build.out, p);
    auto idx = OpenOrCreate(dir, vocabulary, IndexOptionsFor(build));
    cluster::FrequencyJournal journal((fs::path(dir) / cluster::FrequencyJournal::kFile).string(),
                                      vocabulary.fingerprint(), vocabulary.size());
    OkOrExit(journal.Recover(*idx));
    const auto tp = std::chrono::steady_clock::now();
    const BuildCounts counts = IngestJobs(build, *idx, std::move(jobs[p]), &journal);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - tp).count();
    nlohmann::json summary = BuildSummary(*idx, counts, seconds);
    summary["partition"] = p;
    summary["rank"] = comm.rank();
    summaries.push_back(std::move(summary));
    totals[0] += static_cast<int64_t>(journal.images());
    const auto& df = journal.document_frequency();
    for (size_t w = 0; w < df.size(); ++w) totals[1 + w] += df[w];
    folders.push_back(dir);
  }
  comm.SumInPlace(totals);
  api::GlobalFrequencies global;
  global.num_partitions = partitions;
  global.vocabulary_fingerprint = vocabulary.fingerprint();
  global.num_images = static_cast<uint64_t>(totals[0]);
  global.document_frequency.resize(vocabulary.size());
  for (size_t w = 0; w < vocabulary.size(); ++w) global.document_frequency[w] = static_cast<uint32_t>(totals[1 + w]);
  for (size_t i = 0; i < mine.size(); ++i) {
    global.partition = mine[i];
    OkOrExit(api::WriteGlobalFrequencies((fs::path(folders[i]) / api::kGlobalFrequenciesFile).string(), global));
  }
  // Rank 0 prints one summary of all partitions.
  io::ByteWriter w;
  w.PutString(summaries.dump());
  const std::vector<uint8_t> gathered = comm.Allgather(w.bytes());
  if (comm.rank() != 0) return;
  io::ByteReader r(gathered, "partition summaries");
  nlohmann::json all = nlohmann::json::array();
  for (int rank = 0; rank < comm.size(); ++rank)
    for (auto& part : nlohmann::json::parse(ValueOrExit(r.GetString(1u << 30)))) all.push_back(std::move(part));
  std::sort(all.begin(), all.end(), [](const auto& a, const auto& b) { return a["partition"] < b["partition"]; });
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  PrintJson({{"cluster", build.out}, {"partitions", partitions}, {"ranks", comm.size()}, {"images", global.num_images},
             {"seconds", seconds}, {"partition_builds", all}});
}

// ---- duplicates (api/duplicates.h)
struct DuplicatesArgs {
  std::string index;
  std::string format = "json";
  std::string out;
  api::DuplicateOptions options;
  bool no_mirror = false;
  bool mpi = false;
};

// One process, or one rank of `--mpi` (comm): every rank finds the whole report; rank 0 writes it.
void RunDuplicates(const DuplicatesArgs& args, vocab::Communicator* comm) {
  const bool first = comm == nullptr || comm->rank() == 0;
  auto idx = ValueOrExit(comm ? index::ImageIndex::OpenReadOnly(args.index) : index::ImageIndex::Open(args.index));
  api::DuplicateReport report;
  {
    // Rank 0's share of the images (every ranks-th one).
    const uint64_t images = idx->Stats().num_images;
    const uint64_t ranks = comm ? static_cast<uint64_t>(comm->size()) : 1;
    std::optional<log::Progress> progress;
    if (first) progress.emplace(comm ? "duplicates (rank 0's share)" : "duplicates", (images + ranks - 1) / ranks, "images");
    uint64_t shown = 0;
    std::mutex mutex;
    report = ValueOrExit(api::FindDuplicates(
        *idx, args.options,
        [&](uint64_t done, uint64_t) {
          std::lock_guard<std::mutex> lock(mutex);
          if (progress && done > shown) {
            progress->Advance(done - shown);
            shown = done;
          }
        },
        {}, comm));
  }
  if (!first) return;
  const std::string text = args.format == "csv" ? api::DuplicateReportToCsv(report)
                                                 : api::DuplicateReportToJson(report, args.options).dump(1) + "\n";
  if (args.out.empty()) {
    std::fwrite(text.data(), 1, text.size(), stdout);
  } else {
    OkOrExit(io::WriteFileAtomically(args.out, {reinterpret_cast<const uint8_t*>(text.data()), text.size()}));
  }
  OXBOW_LOG(kInfo) << report.pairs.size() << " pairs in " << report.groups.size() << " groups over " << report.images
                   << " images (" << report.overlay_pairs << " dropped as overlays); search " << report.search_s
                   << " s, measure " << report.measure_s << " s" << (comm ? " (" + std::to_string(comm->size()) + " ranks)" : "");
}

void SetUpDuplicates(CLI::App& index_cmd) {
  auto args = std::make_shared<DuplicatesArgs>();
  CLI::App* d = index_cmd.add_subcommand("duplicates", "Find the images of an index that show the same thing: exact "
                                                       "copies, near copies, the same object or scene");
  d->footer(
      "Every image searches the index with its stored features, and again mirrored (a mirrored copy is found too); "
      "each verified pair is measured on both images' features: its inliers, the share of each image they cover, "
      "the map between them. Kept pairs are `exact` (same size, identity map, both covered), `near_copy` (one image "
      "covered at least --near-copy-coverage under a similarity: a resize, recompression, crop, rotation, mirror "
      "image, retouch or overlay of the other) or `same_scene` (another photo of the same object or place); a pair "
      "whose match covers little of both images, or only their borders, shares an overlay (a logo, a caption, a "
      "frame) and is dropped. Groups are the connected components of the pairs. Prints JSON {images, settings, "
      "pairs: [{a, b, kind, mirrored, inliers, coverage_a, coverage_b, region_a, region_b, transform (a pixels -> "
      "b pixels, 2x3 row-major), group}], groups: [{group, images}], timings_s}, or CSV (a,b,kind,mirrored,inliers,"
      "coverage_a,coverage_b,group). Reads the index while no server has it open; through a server: POST "
      "/v1/collections/{name}/duplicates (server/README.md, Duplicates).");
  d->add_option("--index", args->index, "index folder")->required();
  d->add_option("--format", args->format, "json or csv")->capture_default_str()->check(CLI::IsMember({"json", "csv"}));
  d->add_option("--out", args->out,
                "write the result to this file instead of stdout (an existing file only if a report: JSON or this CSV)")
      ->check(FileToWrite())
      ->check(ReplacesOnly("a duplicates report", [](std::string_view head) {
        return head.starts_with("{") || head.starts_with("a,b,kind,");
      }));
  d->add_option("--candidates", args->options.candidates,
                "best tf-idf candidates of each image that are verified (more: copies of much-copied images are "
                "found directly, slower)")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000));
  d->add_flag("--no-mirror", args->no_mirror, "do not look for mirrored copies (one search per image instead of two)");
  d->add_option("--min-coverage", args->options.min_coverage,
                "drop a pair whose match covers less than this share of both images (a shared logo or caption); "
                "a match of distinct content (another photo of one place or object) needs only 0.05 of one image (or this, when lower) "
                "(server/README.md, \"Duplicates\")")
      ->capture_default_str()
      ->check(NumberIn(0, 1));
  d->add_option("--near-copy-coverage", args->options.near_copy_coverage,
                "a near copy: one image covered at least this much by the match")
      ->capture_default_str()
      ->check(NumberIn(0, 1));
  d->add_option("--threads", args->options.threads, "threads; 0 = all cores (per rank with --mpi)")
      ->capture_default_str()
      ->check(CLI::Range(0, 256));
  d->add_flag("--mpi", args->mpi,
              "distributed under mpirun: every rank opens --index read-only (a folder every rank reaches, e.g. on a "
              "shared file system; no writer may open it meanwhile), searches every ranks-th image and measures "
              "every ranks-th pair; rank 0 writes the result, the same as one process's (one rank without mpirun)");
  d->callback([args] {
    args->options.mirrored = !args->no_mirror;
    if (args->mpi) {
      RunWithMpi([&](vocab::Communicator& comm) { RunDuplicates(*args, &comm); });
    } else {
      RunDuplicates(*args, nullptr);
    }
  });
}

void SetUpIndex(CLI::App& app) {
  CLI::App* cmd = app.add_subcommand("index", "Build and maintain an image index (build, add, remove, info, check, backup, duplicates)");
  cmd->require_subcommand(1);

  // ---- build
  auto build = std::make_shared<BuildArgs>();
  CLI::App* b = cmd->add_subcommand("build", "Index every image of a folder or list (resumable: indexed ids are skipped)");
  b->add_option("--vocab", build->vocab, "vocabulary file (oxbow vocab train)")->required();
  auto* images_opt = b->add_option("--images", build->images, "folder of images (searched recursively)");
  auto* list_opt = b->add_option("--list", build->list, "text file with one image path per line");
  auto* features_opt = b->add_option("--features", build->features,
                                     "folder of .oxfeat files from `oxbow extract` (searched recursively; id = image "
                                     "name without extension): no extraction here, only quantisation");
  images_opt->excludes(list_opt);
  features_opt->excludes(images_opt)->excludes(list_opt);
  b->add_option("--out", build->out, "index folder (created, or resumed when it holds an index)")->required();
  AddThreadsFlag(b, &build->threads);
  AddImageFlags(b, &build->image);
  b->add_option("--quantizer-probes", build->probes,
                "coarse quantiser lists probed per indexed descriptor (searches set their own, default 8)")
      ->capture_default_str()
      ->check(CLI::Range(1, 4096));
  b->add_flag("--mpi", build->mpi,
              "distributed build under mpirun (one rank without it): --out becomes a cluster folder of --partitions "
              "index folders partition-0 .. partition-(P-1); image id -> partition FNV-1a 64(id) mod P; partition p is "
              "written by rank p mod ranks; every partition also gets the cluster's document frequencies "
              "(global-frequencies.oxdf). Resumable like a single build")
      ->group("Distributed (MPI)");
  b->add_option("--partitions", build->partitions, "--mpi: number of partitions P of the cluster")
      ->capture_default_str()
      ->check(CLI::Range(1, 65536))
      ->group("Distributed (MPI)");
  b->callback([build] {
    if (build->images.empty() && build->list.empty() && build->features.empty()) {
      throw CommandError(2, "give --images DIR, --list FILE or --features DIR");
    }
    if (build->mpi) {
      RunWithMpi([&](vocab::Communicator& comm) { RunClusterBuild(*build, comm); });
      return;
    }
    if (build->partitions != 1) throw CommandError(2, "--partitions needs --mpi");
    const auto t0 = std::chrono::steady_clock::now();
    const vocab::Vocabulary vocabulary = ValueOrExit(vocab::Vocabulary::Read(build->vocab));
    // The inputs first: a mistyped --images or --list leaves no index behind.
    auto jobs = CollectJobs(*build);
    auto idx = OpenOrCreate(build->out, vocabulary, IndexOptionsFor(*build));
    const InterruptibleCommand interruptible;  // Ctrl-C: the batch in hand is committed, then the build stops
    const BuildCounts counts = IngestJobs(*build, *idx, std::move(jobs), nullptr);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    PrintJson(BuildSummary(*idx, counts, seconds));
    if (counts.interrupted) {
      throw CommandError(InterruptibleCommand::kExitCode,
                         "interrupted: the " + std::to_string(counts.added) + " images added are committed; run the "
                         "same command again to index the rest (indexed ids are skipped)");
    }
    if (counts.failed > 0 && counts.added == 0 && counts.skipped == 0) {
      // Failures among indexed images are reported and the build goes on; an index of none is an error.
      throw CommandError(ExitCodeFor(ErrorCode::kInvalidImage),
                         "none of the " + std::to_string(counts.failed) + " inputs could be indexed (see the "
                         "warnings above)");
    }
  });

  // ---- add
  struct AddArgs {
    std::string index, id, metadata;
    std::vector<std::string> images;
    ImageFlags image;
    int threads = 0;
  };
  auto add = std::make_shared<AddArgs>();
  CLI::App* a = cmd->add_subcommand("add", "Add images to an index (id = file name without extension)");
  a->add_option("--index", add->index, "index folder")->required();
  a->add_option("images", add->images, "image files")->required();
  a->add_option("--id", add->id, "id for the image (only with one image)")->check(CLI::Validator(
      [](std::string& id) { return id.empty() ? std::string("an id is not empty") : std::string(); }, "ID"));
  a->add_option("--metadata", add->metadata, "metadata JSON stored with the image(s)");
  AddImageFlags(a, &add->image);
  AddThreadsFlag(a, &add->threads);
  a->callback([add] {
    if (!add->id.empty() && add->images.size() != 1) throw CommandError(2, "--id needs exactly one image");
    if (!add->metadata.empty()) {
      auto metadata = api::ParseMetadata(add->metadata, "--metadata");
      if (!metadata) throw CommandError(2, metadata.error().message);
      add->metadata = std::move(*metadata);
    }
    auto idx = ValueOrExit(index::ImageIndex::Open(add->index));
    const sift::SiftExtractor extractor = ExtractorFor(*idx, add->threads);
    const sift::DecodeOptions decode = add->image.ToDecodeOptions();
    nlohmann::json out = nlohmann::json::array();
    int errors = 0;
    int exit_code = 0;  // the first failure's (exit codes: server/README.md, "Command line")
    for (const auto& path : add->images) {
      const std::string id = add->id.empty() ? fs::path(path).stem().string() : add->id;
      const auto add_one = [&]() -> Result<index::ImageRecord> {
        // The ids the HTTP API takes, so that every image added here is reachable through it.
        if (Status checked = api::CheckNewImageId(id); !checked) return std::unexpected(checked.error());
        auto f = extractor.ExtractFromFile(path, decode);
        if (!f) return std::unexpected(f.error());
        return idx->Add(id, *f, {fs::absolute(path).string(), add->metadata, idx->extractor_settings()});
      };
      const Result<index::ImageRecord> record = add_one();
      if (!record) {
        std::fprintf(stderr, "oxbow: %s: %s\n", path.c_str(), record.error().ToString().c_str());
        if (errors++ == 0) exit_code = ExitCodeFor(record.error().code);
        out.push_back({{"id", id}, {"error", record.error().ToString()}});
      } else {
        out.push_back({{"id", id}, {"features", record->num_features}});
      }
    }
    PrintJson(out);
    if (errors) throw CommandError(exit_code, std::to_string(errors) + " image(s) not added");
  });

  // ---- remove
  struct RemoveArgs {
    std::string index;
    std::vector<std::string> ids;
  };
  auto remove = std::make_shared<RemoveArgs>();
  CLI::App* r = cmd->add_subcommand("remove", "Remove images from an index by id");
  r->add_option("--index", remove->index, "index folder")->required();
  r->add_option("ids", remove->ids, "image ids")->required();
  r->callback([remove] {
    auto idx = ValueOrExit(index::ImageIndex::Open(remove->index));
    for (size_t k = 0; k < remove->ids.size(); ++k) {
      if (Status removed = idx->Remove(remove->ids[k]); !removed) {
        // Each remove is durable on its own: say which of the ids before this one are gone.
        throw CommandError(ExitCodeFor(removed.error().code),
                           removed.error().ToString() + (k == 0 ? "; nothing was removed"
                                                                : "; the " + std::to_string(k) +
                                                                      " id(s) before it were removed, the rest were not tried"));
      }
    }
    OXBOW_LOG(kInfo) << "removed " << remove->ids.size() << " image(s)";
  });

  // ---- info
  auto info_index = std::make_shared<std::string>();
  CLI::App* i = cmd->add_subcommand("info", "Print an index's statistics as JSON");
  i->add_option("--index", *info_index, "index folder")->required();
  i->callback([info_index] {
    auto idx = ValueOrExit(index::ImageIndex::Open(*info_index));
    PrintJson(StatsJson(*idx));
  });

  // ---- check
  struct CheckArgs {
    std::string index;
    bool drop_damaged = false;
  };
  auto check = std::make_shared<CheckArgs>();
  CLI::App* c = cmd->add_subcommand("check", "Check an index's catalogue: its records and every image's feature BLOB");
  c->footer(
      "Checks the vocabulary copy against the catalogue, runs SQLite's integrity check of the image records and "
      "checks every image's feature BLOB (CRC-32), also "
      "those an open does not read (the images a checkpoint covers), while no process has the index open (a "
      "running server's folder is refused). Prints {index, images, damaged: [{id, number, why}], dropped} as JSON; "
      "exits 6 (damaged) when a damaged image was found and not dropped. --drop-damaged deletes the damaged images from the "
      "catalogue (add them again from their source images).");
  c->add_option("--index", check->index, "index folder")->required();
  c->add_flag("--drop-damaged", check->drop_damaged, "delete the images whose feature BLOB is damaged");
  c->callback([check] {
    const index::IndexCheck result = ValueOrExit(index::CheckIndexFolder(check->index, check->drop_damaged));
    nlohmann::json damaged = nlohmann::json::array();
    for (const auto& image : result.damaged) {
      damaged.push_back({{"id", image.id}, {"number", image.number}, {"why", image.why}});
    }
    PrintJson({{"index", check->index}, {"images", result.images}, {"damaged", damaged}, {"dropped", result.dropped}});
    if (!result.damaged.empty() && !result.dropped) {
      throw CommandError(ExitCodeFor(ErrorCode::kCorruptData),
                         std::to_string(result.damaged.size()) + " damaged image(s) in " + check->index +
                             "; --drop-damaged deletes them");
    }
  });

  // ---- backup
  struct BackupArgs {
    std::string index;
    std::string out;
  };
  auto backup = std::make_shared<BackupArgs>();
  CLI::App* k = cmd->add_subcommand("backup", "Copy an index into a new folder, also while `oxbow serve` uses it");
  k->footer(
      "The copy is the index as committed at one instant: every write acknowledged before the command started, "
      "none started after it ended. It is verified (checksums, SQLite quick_check), fsync'ed and renamed into "
      "place only when complete; a damaged source file fails the backup and leaves nothing. Restore: oxbow serve "
      "--index OUT. Prints {out, images, generation, bytes, attempts} as JSON. Through a running server: POST "
      "/v1/admin/backup (server/README.md, Backup and restore).");
  k->add_option("--index", backup->index, "index folder to back up")->required();
  k->add_option("--out", backup->out,
                "new folder for the copy (absent or empty; written as OUT.tmp, then renamed; its parent must exist)")
      ->required();
  k->callback([backup] {
    PrintJson(api::BackupToJson(backup->out, ValueOrExit(api::Service::BackupFolder(backup->index, backup->out))));
  });

  SetUpDuplicates(*cmd);
}

const bool registered_index = RegisterCommand({"index", 30, &SetUpIndex});

}  // namespace
}  // namespace oxbow::cli
