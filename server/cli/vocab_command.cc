// `oxbow vocab train` (k-means visual vocabulary from images, an image list or feature files) and
// `oxbow vocab info` (print a vocabulary file's header). See vocab/vocabulary.h.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <span>
#include <optional>
#include <string>
#include <vector>

#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "server/cli/mpi_communicator.h"
#include "sift/base/binary_io.h"
#include "sift/features_io.h"
#include "sift/base/log.h"
#include "sift/sift.h"
#include "vocab/distributed.h"
#include "vocab/vocabulary.h"

namespace oxbow::cli {
namespace {

namespace fs = std::filesystem;

struct VocabTrainArgs {
  std::optional<std::string> images_dir, list_file, features_dir;
  std::string out;
  size_t words = 0;
  sift::DescriptorKind descriptor = sift::SiftOptions{}.descriptor;
  size_t sample = vocab::SampleOptions{}.max_total;
  size_t per_image = vocab::SampleOptions{}.max_per_image;
  int iterations = vocab::TrainOptions{}.max_iterations;
  uint64_t seed = 1;
  int threads = 0;
  std::string assignment = "auto";
  int probes = vocab::TrainOptions{}.ivf_probes;
  ImageFlags image;
  // Extractor of --images and --list (descriptor and threads come from the fields above): `vocab train
  // --upright` sets it, `vocab hamming` takes the vocabulary's recorded settings.
  sift::SiftOptions extractor;
  bool mpi = false;
  std::string checkpoint;  // --mpi: k-means checkpoint file ("" = <out>.checkpoint)
  int stop_after = 0;      // --mpi: iterations this run (0 = to the end)
  bool hamming = true;     // also learn Hamming-embedding parameters from the sample
  std::string vocab_in;    // `vocab hamming`: the vocabulary to extend
};

// Files under `dir` (recursively, sorted by path: the sample depends on this order) that `keep` accepts.
std::vector<std::string> ListFolder(const std::string& dir, const std::function<bool(const std::string&)>& keep) {
  return ValueOrExit(sift::ListFiles(dir, keep));
}

// The images (or feature files) to train on, in path order, each with a name that identifies it on
// every machine (its path relative to the folder, or the list's line) for the --mpi sampling.
struct TrainingInputs {
  std::vector<std::string> paths;
  std::vector<std::string> names;
};

TrainingInputs CollectInputs(const VocabTrainArgs& args) {
  const int sources = args.images_dir.has_value() + args.list_file.has_value() + args.features_dir.has_value();
  if (sources != 1)
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), "give exactly one of --images, --list, --features");
  TrainingInputs in;
  if (args.features_dir) {
    in.paths = ListFolder(*args.features_dir, [](const std::string& p) { return fs::path(p).extension() == ".oxfeat"; });
    if (in.paths.empty()) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "no .oxfeat files in '" + *args.features_dir + "'");
    for (const auto& p : in.paths) in.names.push_back(fs::path(p).lexically_relative(*args.features_dir).string());
    return in;
  }
  if (args.images_dir) {
    in.paths = ListFolder(*args.images_dir, sift::IsImageFile);
    for (const auto& p : in.paths) in.names.push_back(fs::path(p).lexically_relative(*args.images_dir).string());
  } else {
    std::ifstream list(*args.list_file);
    if (!list) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "cannot read the list '" + *args.list_file + "'");
    for (std::string line; std::getline(list, line);) {
      while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.pop_back();
      if (!line.empty() && line[0] != '#') in.paths.push_back(line);
    }
    in.names = in.paths;
  }
  if (in.paths.empty()) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "no images to train on");
  return in;
}

// The descriptors of inputs first, first + stride, ... (converted to `args.descriptor`), each handed to
// `take(name, descriptors)`. Returns the extractor settings they were made with ("" when this share
// is empty); `failures` counts unreadable images (skipped with a warning).
std::string ReadDescriptors(const VocabTrainArgs& args, const TrainingInputs& inputs, size_t first, size_t stride,
                            const std::function<void(const std::string&, std::span<const float>)>& take,
                            size_t& failures) {
  const sift::DescriptorKind kind = args.descriptor;
  const size_t share = first < inputs.paths.size() ? (inputs.paths.size() - first + stride - 1) / stride : 0;
  std::string settings;
  if (args.features_dir) {
    log::Progress progress("sampling feature files", share, "files");
    std::string first_file;
    for (size_t i = first; i < inputs.paths.size(); i += stride) {
      const std::string& path = inputs.paths[i];
      auto read = sift::ReadFeatureFile(path);
      if (!read) {  // a damaged or unreadable file is skipped, as an unreadable image is
        ++failures;
        OXBOW_LOG(kWarning) << "skipping " << path << ": " << read.error().ToString();
        progress.Advance();
        continue;
      }
      sift::FeatureFile file = std::move(*read);
      if (first_file.empty()) {
        settings = file.extractor_description;
        first_file = path;
      } else if (file.extractor_description != settings) {
        std::string message = "'" + path + "' was extracted with other settings (";
        message.append(file.extractor_description).append(") than '").append(first_file).append("' (");
        message.append(settings).append("); a vocabulary needs one extractor");
        throw CommandError(ExitCodeFor(ErrorCode::kIncompatible), message);
      }
      if (file.features.kind != kind) {
        if (file.features.kind == sift::DescriptorKind::kRootSift)
          throw CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                             "'" + path + "' holds RootSIFT descriptors; raw SIFT cannot be recovered from them: "
                             "train with --descriptor rootsift");
        for (size_t r = 0; r < file.features.size(); ++r)  // SIFT files, RootSIFT asked: convert
          sift::ToRootSift({file.features.descriptors.data() + r * sift::kDescriptorDim, size_t{sift::kDescriptorDim}});
      }
      take(inputs.names[i], file.features.descriptors);
      progress.Advance();
    }
    if (settings.empty()) return settings;
    // The vocabulary records the extractor whose output it was trained on, so that `index build` and
    // `serve` extract the same way. SIFT files converted to RootSIFT: the files' extractor with the
    // RootSIFT descriptor, which extracts exactly what the conversion produced.
    sift::SiftOptions extractor = ValueOrExit(sift::SiftOptions::FromDescription(settings));
    extractor.descriptor = kind;
    return extractor.Describe();
  }
  sift::SiftOptions options = args.extractor;
  options.descriptor = kind;
  options.num_threads = args.threads;
  const sift::SiftExtractor extractor = ValueOrExit(sift::SiftExtractor::Create(options));
  settings = options.Describe();
  const sift::DecodeOptions decode = args.image.ToDecodeOptions();
  log::Progress progress("extracting and sampling", share, "images");
  for (size_t i = first; i < inputs.paths.size(); i += stride) {
    const std::string& path = inputs.paths[i];
    auto features = extractor.ExtractFromFile(path, decode);
    progress.Advance();
    if (!features) {
      ++failures;
      OXBOW_LOG(kWarning) << "skipping " << path << ": " << features.error().ToString();
      continue;
    }
    take(inputs.names[i], features->descriptors);
  }
  return settings;
}

vocab::TrainOptions TrainOptionsFrom(const VocabTrainArgs& args) {
  vocab::TrainOptions train;
  train.num_words = args.words;
  train.max_iterations = args.iterations;
  train.seed = args.seed;
  train.num_threads = args.threads;
  train.quantizer.num_threads = args.threads;
  train.quantizer.seed = args.seed;
  if (args.assignment == "exact") train.assignment = vocab::AssignmentMethod::kExact;
  if (args.assignment == "kdforest") train.assignment = vocab::AssignmentMethod::kKdForest;
  if (args.assignment == "ivf") train.assignment = vocab::AssignmentMethod::kInvertedFile;
  train.ivf_probes = args.probes;
  if (auto problem = train.Check()) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), *problem);
  return train;
}

vocab::SampleOptions SampleOptionsFrom(const VocabTrainArgs& args) {
  vocab::SampleOptions sample;
  sample.max_total = args.sample;
  sample.max_per_image = args.per_image;
  sample.seed = args.seed;
  if (auto problem = sample.Check()) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), *problem);
  if (args.sample < args.words)
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument),
                       "--sample (" + std::to_string(args.sample) + ") must be at least --words (" +
                           std::to_string(args.words) + ")");
  return sample;
}

// `read` inputs were read, `unreadable` could not be (each warned about as it was met).
void CheckEnoughDescriptors(uint64_t sampled, uint64_t read, uint64_t unreadable, const VocabTrainArgs& args) {
  if (read == 0 && unreadable > 0) {
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidImage),
                       "none of the inputs could be read (" + std::to_string(unreadable) +
                           " unreadable, see the warnings above): no descriptors to train on");
  }
  if (sampled < args.words)
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument),
                       "only " + std::to_string(sampled) + " descriptors for " + std::to_string(args.words) +
                           " words: add images, raise --per-image or lower --words");
}

void PrintTrainSummary(const VocabTrainArgs& args, const vocab::Vocabulary& vocabulary, const vocab::TrainReport& report) {
  std::printf("%s: %zu words, %s, %zu iterations%s, objective %.6g, %.1f s (seeding %.1f s), fingerprint %016llx\n",
              args.out.c_str(), vocabulary.size(), sift::DescriptorKindName(args.descriptor), report.iterations.size(),
              report.converged ? " (converged)" : "", report.iterations.empty() ? 0.0 : report.iterations.back().objective,
              report.total_seconds, report.seeding_seconds, static_cast<unsigned long long>(vocabulary.fingerprint()));
}

vocab::Vocabulary WithHamming(const vocab::Vocabulary& vocabulary, std::span<const float> sample,
                              const VocabTrainArgs& args) {
  vocab::QuantizerOptions quantizer;
  quantizer.num_threads = args.threads;
  OXBOW_LOG(kInfo) << "learning Hamming-embedding medians from " << sample.size() / sift::kDescriptorDim
                   << " descriptors";
  return ValueOrExit(vocabulary.WithHamming(sample, args.seed, quantizer));
}

// The seeded sample of the inputs' descriptors (at least args.words of them), and the extractor
// settings they were made with.
struct Sample {
  std::vector<float> descriptors;
  std::string settings;
};
Sample SampleDescriptors(const VocabTrainArgs& args) {
  const vocab::SampleOptions options = SampleOptionsFrom(args);
  const TrainingInputs inputs = CollectInputs(args);
  vocab::DescriptorSampler sampler(options, sift::kDescriptorDim);
  size_t failures = 0;
  Sample out;
  out.settings = ReadDescriptors(
      args, inputs, 0, 1, [&](const std::string&, std::span<const float> d) { sampler.AddImage(d); }, failures);
  OXBOW_LOG(kInfo) << "sampled " << sampler.size() << " of " << sampler.rows_seen() << " descriptors from "
                   << sampler.images_seen() << " images" << (failures ? " (" + std::to_string(failures) + " unreadable)" : "");
  CheckEnoughDescriptors(sampler.size(), sampler.images_seen(), failures, args);
  out.descriptors = sampler.TakeDescriptors();
  return out;
}

void RunVocabTrain(const VocabTrainArgs& args) {
  const vocab::TrainOptions train = TrainOptionsFrom(args);
  const auto [descriptors, settings] = SampleDescriptors(args);
  vocab::TrainReport report;
  vocab::Vocabulary vocabulary =
      ValueOrExit(vocab::Train(descriptors, sift::kDescriptorDim, args.descriptor, settings, train, &report));
  if (args.hamming) vocabulary = WithHamming(vocabulary, descriptors, args);
  OkOrExit(vocabulary.Write(args.out));
  PrintTrainSummary(args, vocabulary, report);
}

// `vocab hamming`: an existing vocabulary with Hamming-embedding parameters learnt from a new sample.
void RunVocabHamming(VocabTrainArgs args) {
  std::error_code ec;
  if (fs::equivalent(args.vocab_in, args.out, ec)) {
    throw CommandError(2, "--out is the --vocab file itself, which 'vocab hamming' leaves as it is: give another file");
  }
  const vocab::Vocabulary vocabulary = ValueOrExit(vocab::Vocabulary::Read(args.vocab_in));
  args.descriptor = vocabulary.descriptor_kind();
  args.words = 1;  // any sample size will do: no k-means
  // Images are extracted as the vocabulary's own were (its recorded settings; the descriptor kind is
  // set above), so that a sample of images matches it whatever extractor setting it was trained with.
  if (!vocabulary.extractor_settings().empty())
    args.extractor = ValueOrExit(sift::SiftOptions::FromDescription(vocabulary.extractor_settings()));
  const auto [descriptors, settings] = SampleDescriptors(args);
  if (!vocabulary.extractor_settings().empty() && settings != vocabulary.extractor_settings()) {
    throw CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                       "the sample was extracted with '" + settings + "', the vocabulary with '" +
                           vocabulary.extractor_settings() + "': give feature files of the vocabulary's extractor");
  }
  const vocab::Vocabulary out = WithHamming(vocabulary, descriptors, args);
  OkOrExit(out.Write(args.out));
  std::printf("%s: %zu words with Hamming embedding, fingerprint %016llx\n", args.out.c_str(), out.size(),
              static_cast<unsigned long long>(out.fingerprint()));
}

// The one extractor setting string of all ranks' shares (ranks without inputs have none).
std::string AgreeOnSettings(vocab::Communicator& comm, const std::string& mine) {
  io::ByteWriter w;
  w.PutString(mine);
  const std::vector<uint8_t> all = comm.Allgather(w.bytes());
  io::ByteReader r(all, "extractor settings of the ranks");
  std::string agreed;
  for (int rank = 0; rank < comm.size(); ++rank) {
    const std::string s = ValueOrExit(r.GetString());
    if (s.empty()) continue;
    if (!agreed.empty() && s != agreed) {
      std::string message = "the feature files were extracted with different settings (" + agreed;
      message.append(" and ").append(s).append("); a vocabulary needs one extractor");
      throw CommandError(ExitCodeFor(ErrorCode::kIncompatible), message);
    }
    agreed = s;
  }
  return agreed;
}

void RunVocabTrainMpi(const VocabTrainArgs& args, vocab::Communicator& comm) {
  if (args.assignment == "kdforest")
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument),
                       "--mpi needs a reproducible assignment: --assignment auto, exact or ivf (FLANN's kd-forest "
                       "differs from run to run)");
  const vocab::SampleOptions sample_options = SampleOptionsFrom(args);
  vocab::DistributedTrainOptions options;
  options.train = TrainOptionsFrom(args);
  options.checkpoint_path = args.checkpoint.empty() ? args.out + ".checkpoint" : args.checkpoint;
  options.stop_after_iterations = args.stop_after;
  options.hamming = args.hamming;
  const TrainingInputs inputs = CollectInputs(args);

  // Images are dealt out round-robin in path order; the sample does not depend on who reads what.
  vocab::NamedSampler sampler(sample_options, sift::kDescriptorDim);
  size_t failures = 0;
  const std::string mine = ReadDescriptors(
      args, inputs, static_cast<size_t>(comm.rank()), static_cast<size_t>(comm.size()),
      [&](const std::string& name, std::span<const float> d) { sampler.AddImage(name, d); }, failures);
  const std::string settings = AgreeOnSettings(comm, mine);
  std::vector<int64_t> unreadable = {static_cast<int64_t>(failures)};
  comm.SumInPlace(unreadable);
  const vocab::DistributedSample sample = sampler.Finish(comm);
  OXBOW_LOG(kInfo) << "sampled " << sample.total_rows << " of " << sample.rows_seen << " descriptors from "
                   << sample.images_seen << " images on " << comm.size() << " ranks"
                   << (unreadable[0] ? " (" + std::to_string(unreadable[0]) + " unreadable)" : "");
  CheckEnoughDescriptors(sample.total_rows, sample.images_seen, static_cast<uint64_t>(unreadable[0]), args);
  vocab::TrainReport report;
  const vocab::DistributedTrainResult result =
      ValueOrExit(vocab::TrainDistributed(sample, comm, args.descriptor, settings, options, &report));
  if (comm.rank() != 0) return;
  if (!result.finished) {
    std::printf("%s: stopped after iteration %d (--stop-after-iterations); run the same command again to continue\n",
                options.checkpoint_path.c_str(), result.resumed_after_iteration + static_cast<int>(report.iterations.size()));
    return;
  }
  OXBOW_CHECK(result.vocabulary.has_value(), "rank 0 of a finished training holds the vocabulary");
  const vocab::Vocabulary& vocabulary = *result.vocabulary;
  OkOrExit(vocabulary.Write(args.out));
  std::error_code ec;
  fs::remove(options.checkpoint_path, ec);  // the vocabulary is durable: the checkpoint has served
  PrintTrainSummary(args, vocabulary, report);
}

void SetUpVocab(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "vocab",
      "Visual vocabularies: k-means centroids of SIFT/RootSIFT descriptors ('visual words', Sivic & Zisserman 2003;\n"
      "large vocabularies as in Philbin et al. 2007) and the quantiser that maps a descriptor to its word.");
  cmd->require_subcommand(1);

  auto args = std::make_shared<VocabTrainArgs>();
  auto* train = cmd->add_subcommand(
      "train",
      "Train a vocabulary with k-means.\n"
      "Descriptors come from images (extracted with oxbow's SIFT), an image list, or feature files written by\n"
      "'oxbow extract'. At most --per-image descriptors are kept per image (uniform random subset) and at most\n"
      "--sample in total (reservoir sampling over images in name order), both seeded by --seed.\n"
      "Seeding is k-means++ up to 4096 words, random distinct descriptors above. Each Lloyd iteration assigns\n"
      "every descriptor to its nearest centroid: exactly up to 4096 words, above that with the two-level\n"
      "inverted-file quantiser rebuilt on the current centroids (--assignment kdforest: FLANN kd-forest as in\n"
      "Philbin et al. 2007); a descriptor never moves to a farther word, so the objective never increases.\n"
      "Stops after --iterations or when the objective improves by less than 0.01%. Same seed and input give\n"
      "the same vocabulary for any --threads (not with --assignment kdforest: FLANN seeds its trees itself).\n"
      "Use about 10-50 descriptors per word.\n"
      "Examples:\n"
      "  oxbow vocab train --images photos/ --words 20000 --out paris20k.oxvoc\n"
      "  oxbow vocab train --features feats/ --words 100000 --sample 5000000 --per-image 2000 --out 100k.vocab");
  auto* source = train->add_option_group("source", "where the training descriptors come from (exactly one)");
  source->add_option("--images", args->images_dir, "folder of images (JPEG, PNG, PPM/PGM, BMP, TIFF, WebP), searched recursively");
  source->add_option("--list", args->list_file, "text file with one image path per line (a line starting with '#' is a comment)");
  source->add_option("--features", args->features_dir, "folder of .oxfeat feature files from 'oxbow extract', searched recursively");
  source->require_option(1);
  train->add_option("--words", args->words, "vocabulary size k (number of visual words)")->required()->check(Positive());
  train->add_option("--out", args->out, "vocabulary file to write (atomically; an existing file only if a vocabulary)")
      ->required()
      ->check(FileToWrite())
      ->check(VocabularyToWrite());
  AddDescriptorFlag(train, &args->descriptor);  // with --features, SIFT files are converted to RootSIFT
  train->add_flag("--upright", args->extractor.upright,
                  "extract upright features (every orientation along the image's x axis; for photos taken upright, such "
                  "as buildings: see 'oxbow extract --help'); index build and serve then extract them too")
      ->excludes("--features");
  for (CLI::Option* flag : AddDescriptorWindowFlags(train, &args->extractor)) flag->excludes("--features");
  train->add_flag_callback("--root-sift", [args] { args->descriptor = sift::DescriptorKind::kRootSift; },
                           "same as --descriptor rootsift (the default)")
      ->excludes("--descriptor");
  train->add_option("--sample", args->sample, "maximum training descriptors in total")->capture_default_str()->check(Positive());
  train->add_option("--per-image", args->per_image, "maximum descriptors kept per image")->capture_default_str()->check(Positive());
  train->add_option("--iterations", args->iterations, "maximum Lloyd iterations")->capture_default_str()->check(CLI::Range(1, 1000));
  train->add_option("--seed", args->seed, "seed of the sampling, the seeding and the search structures")
      ->check(NonNegative())
      ->capture_default_str();
  AddThreadsFlag(train, &args->threads);
  train->add_option("--assignment", args->assignment, "nearest-centroid search in the iterations: auto, exact, ivf, kdforest")
      ->capture_default_str()
      ->check(CLI::IsMember({"auto", "exact", "ivf", "kdforest"}));
  train->add_option("--quantizer-probes", args->probes,
                    "ivf assignment: coarse lists probed per descriptor in the iterations")
      ->capture_default_str()
      ->check(CLI::Range(1, 1 << 20));
  AddImageFlags(train, &args->image);
  train->add_flag("--mpi", args->mpi,
                  "distributed training under mpirun (one rank without it): each rank extracts and samples its "
                  "share of the images, the k-means sums and the Hamming-embedding medians are combined exactly, so any "
                  "number of ranks gives the same vocabulary file "
                  "(not the one training without --mpi gives: the sample is drawn by image name)")
      ->group("Distributed (MPI)");
  train->add_option("--checkpoint", args->checkpoint,
                    "--mpi: k-means state written after every iteration and resumed from when present (the images "
                    "are read again); default <out>.checkpoint, deleted once the vocabulary is written")
      ->group("Distributed (MPI)");
  train->add_option("--stop-after-iterations", args->stop_after,
                    "--mpi: end this run after N iterations, keeping the checkpoint (batch schedulers' time limits); "
                    "0 = run to the end")
      ->capture_default_str()
      ->check(CLI::Range(0, 1000))
      ->group("Distributed (MPI)");
  train->add_flag(
      "--hamming,!--no-hamming", args->hamming,
      "also learn Hamming-embedding parameters (a random orthogonal projection to 64 bits, seeded by --seed, and "
      "per word the medians of the projected sample: Jegou et al. 2008), which searches use by default; adds 256 "
      "bytes per word to the file. On by default, also with --mpi (medians found exactly over all ranks' sample)");
  train->callback([args] {
    if (!args->mpi) {
      if (!args->checkpoint.empty() || args->stop_after != 0)
        throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), "--checkpoint and --stop-after-iterations need --mpi");
      RunVocabTrain(*args);
      return;
    }
    RunWithMpi([&](vocab::Communicator& comm) { RunVocabTrainMpi(*args, comm); });
  });

  auto hargs = std::make_shared<VocabTrainArgs>();
  auto* hamming = cmd->add_subcommand(
      "hamming",
      "Add Hamming-embedding parameters to an existing vocabulary (what 'vocab train --hamming' learns):\n"
      "a random orthogonal projection of descriptors to 64 bits (seeded by --seed) and, per word, the medians of\n"
      "the projected sample descriptors assigned to it (Jegou et al. 2008). Images are extracted with the extractor\n"
      "settings the vocabulary records (give the image flags it was trained with, e.g. --max-image-side).\n"
      "The result has a new fingerprint: index images with it.\n"
      "Example:\n"
      "  oxbow vocab hamming --vocab paris20k.oxvoc --images photos/ --out paris20k-he.oxvoc");
  hamming->add_option("--vocab", hargs->vocab_in, "vocabulary to extend (not modified)")->required();
  auto* hsource = hamming->add_option_group("source", "where the sample comes from (exactly one)");
  hsource->add_option("--images", hargs->images_dir, "folder of images, searched recursively");
  hsource->add_option("--list", hargs->list_file, "text file with one image path per line (a line starting with '#' is a comment)");
  hsource->add_option("--features", hargs->features_dir, "folder of .oxfeat feature files, searched recursively");
  hsource->require_option(1);
  hamming->add_option("--out", hargs->out, "vocabulary file to write (atomically; an existing file only if a vocabulary)")
      ->required()
      ->check(FileToWrite())
      ->check(VocabularyToWrite());
  hamming->add_option("--sample", hargs->sample, "maximum sample descriptors in total")->capture_default_str()->check(Positive());
  hamming->add_option("--per-image", hargs->per_image, "maximum descriptors kept per image")->capture_default_str()->check(Positive());
  hamming->add_option("--seed", hargs->seed, "seed of the sampling and of the projection")->check(NonNegative())->capture_default_str();
  AddThreadsFlag(hamming, &hargs->threads);
  AddImageFlags(hamming, &hargs->image);
  hamming->callback([hargs] { RunVocabHamming(*hargs); });

  auto path = std::make_shared<std::string>();
  auto* info = cmd->add_subcommand("info", "Print a vocabulary file's words, dimension, descriptor kind, extractor settings, "
                                           "fingerprint and size; refuses damaged files.");
  info->add_option("vocabulary", *path, "vocabulary file")->required();
  info->callback([path] {
    const vocab::Vocabulary v = ValueOrExit(vocab::Vocabulary::Read(*path));
    std::error_code ec;
    const auto bytes = fs::file_size(*path, ec);
    std::printf("%s\n  words        %zu\n  dimension    %d\n  descriptor   %s\n  extractor    %s\n"
                "  fingerprint  %016llx\n  lists        %zu (two-level quantiser)\n  hamming      %s\n"
                "  file size    %llu bytes (%.1f MiB)\n",
                path->c_str(), v.size(), v.dimension(), sift::DescriptorKindName(v.descriptor_kind()),
                v.extractor_settings().empty() ? "(unknown)" : v.extractor_settings().c_str(),
                static_cast<unsigned long long>(v.fingerprint()), v.num_lists(),
                v.has_hamming() ? "64-bit embedding" : "none", static_cast<unsigned long long>(bytes),
                static_cast<double>(bytes) / (1 << 20));
  });
}

const bool registered_vocab = RegisterCommand({"vocab", 20, &SetUpVocab});

}  // namespace
}  // namespace oxbow::cli
