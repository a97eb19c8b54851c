// `oxbow vocab train` (k-means visual vocabulary from images, an image list or feature files) and
// `oxbow vocab info` (print a vocabulary file's header). See vocab/vocabulary.h.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <vector>

#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "sift/features_io.h"
#include "sift/base/log.h"
#include "sift/sift.h"
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
};

// Files under `dir` (recursively, sorted by path: the sample depends on this order) that `keep` accepts.
std::vector<std::string> ListFolder(const std::string& dir, const std::function<bool(const std::string&)>& keep) {
  return ValueOrExit(sift::ListFiles(dir, keep));
}

void RunVocabTrain(const VocabTrainArgs& args) {
  const int sources = args.images_dir.has_value() + args.list_file.has_value() + args.features_dir.has_value();
  if (sources != 1)
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), "give exactly one of --images, --list, --features");
  vocab::SampleOptions sample;
  sample.max_total = args.sample;
  sample.max_per_image = args.per_image;
  sample.seed = args.seed;
  if (auto problem = sample.Check()) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), *problem);
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
  if (args.sample < args.words)
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument),
                       "--sample (" + std::to_string(args.sample) + ") must be at least --words (" +
                           std::to_string(args.words) + ")");

  vocab::DescriptorSampler sampler(sample, sift::kDescriptorDim);
  const sift::DescriptorKind kind = args.descriptor;
  std::string settings;
  size_t failures = 0;
  if (args.features_dir) {
    const auto files = ListFolder(*args.features_dir, [](const std::string& p) { return fs::path(p).extension() == ".oxfeat"; });
    if (files.empty()) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "no .oxfeat files in '" + *args.features_dir + "'");
    log::Progress progress("sampling feature files", files.size(), "files");
    for (size_t i = 0; i < files.size(); ++i) {
      sift::FeatureFile file = ValueOrExit(sift::ReadFeatureFile(files[i]));
      if (i == 0) {
        settings = file.extractor_description;
      } else if (file.extractor_description != settings) {
        throw CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                           "'" + files[i] + "' was extracted with other settings (" + file.extractor_description +
                               ") than '" + files[0] + "' (" + settings + "); a vocabulary needs one extractor");
      }
      if (file.features.kind != kind) {
        if (file.features.kind == sift::DescriptorKind::kRootSift)
          throw CommandError(ExitCodeFor(ErrorCode::kIncompatible),
                             "'" + files[i] + "' holds RootSIFT descriptors; raw SIFT cannot be recovered from them: "
                             "train with --descriptor rootsift");
        for (size_t r = 0; r < file.features.size(); ++r)  // SIFT files, RootSIFT asked: convert
          sift::ToRootSift({file.features.descriptors.data() + r * sift::kDescriptorDim, size_t{sift::kDescriptorDim}});
      }
      sampler.AddImage(file.features.descriptors);
      progress.Advance();
    }
    // The vocabulary records the extractor whose output it was trained on, so that `index build` and
    // `serve` extract the same way. SIFT files converted to RootSIFT: the files' extractor with the
    // RootSIFT descriptor, which extracts exactly what the conversion produced.
    sift::SiftOptions extractor = ValueOrExit(sift::SiftOptions::FromDescription(settings));
    extractor.descriptor = kind;
    settings = extractor.Describe();
  } else {
    std::vector<std::string> images;
    if (args.images_dir) {
      images = ListFolder(*args.images_dir, sift::IsImageFile);
    } else {
      std::ifstream in(*args.list_file);
      if (!in) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "cannot read the list '" + *args.list_file + "'");
      for (std::string line; std::getline(in, line);) {
        while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.pop_back();
        if (!line.empty() && line[0] != '#') images.push_back(line);
      }
    }
    if (images.empty()) throw CommandError(ExitCodeFor(ErrorCode::kNotFound), "no images to train on");
    sift::SiftOptions options;
    options.descriptor = kind;
    options.num_threads = args.threads;
    const sift::SiftExtractor extractor = ValueOrExit(sift::SiftExtractor::Create(options));
    settings = options.Describe();
    const sift::DecodeOptions decode = args.image.ToDecodeOptions();
    log::Progress progress("extracting and sampling", images.size(), "images");
    for (const std::string& path : images) {
      auto features = extractor.ExtractFromFile(path, decode);
      progress.Advance();
      if (!features) {
        ++failures;
        OXBOW_LOG(kWarning) << "skipping " << path << ": " << features.error().ToString();
        continue;
      }
      sampler.AddImage(features->descriptors);
    }
  }
  OXBOW_LOG(kInfo) << "sampled " << sampler.size() << " of " << sampler.rows_seen() << " descriptors from "
                   << sampler.images_seen() << " images" << (failures ? " (" + std::to_string(failures) + " unreadable)" : "");
  if (sampler.size() < args.words)
    throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument),
                       "only " + std::to_string(sampler.size()) + " descriptors for " + std::to_string(args.words) +
                           " words: add images, raise --per-image or lower --words");
  const std::vector<float> descriptors = sampler.TakeDescriptors();
  vocab::TrainReport report;
  const vocab::Vocabulary vocabulary =
      ValueOrExit(vocab::Train(descriptors, sift::kDescriptorDim, kind, settings, train, &report));
  OkOrExit(vocabulary.Write(args.out));
  std::printf("%s: %zu words, %s, %zu iterations%s, objective %.6g, %.1f s (seeding %.1f s), fingerprint %016llx\n",
              args.out.c_str(), vocabulary.size(), sift::DescriptorKindName(kind), report.iterations.size(),
              report.converged ? " (converged)" : "", report.iterations.empty() ? 0.0 : report.iterations.back().objective,
              report.total_seconds, report.seeding_seconds, static_cast<unsigned long long>(vocabulary.fingerprint()));
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
  source->add_option("--list", args->list_file, "text file with one image path per line ('#' starts a comment)");
  source->add_option("--features", args->features_dir, "folder of .oxfeat feature files from 'oxbow extract', searched recursively");
  source->require_option(1);
  train->add_option("--words", args->words, "vocabulary size k (number of visual words)")->required()->check(CLI::PositiveNumber);
  train->add_option("--out", args->out, "vocabulary file to write (atomically)")->required();
  AddDescriptorFlag(train, &args->descriptor);  // with --features, SIFT files are converted to RootSIFT
  train->add_option("--sample", args->sample, "maximum training descriptors in total")->capture_default_str()->check(CLI::PositiveNumber);
  train->add_option("--per-image", args->per_image, "maximum descriptors kept per image")->capture_default_str()->check(CLI::PositiveNumber);
  train->add_option("--iterations", args->iterations, "maximum Lloyd iterations")->capture_default_str()->check(CLI::Range(1, 1000));
  train->add_option("--seed", args->seed, "seed of the sampling, the seeding and the search structures")->capture_default_str();
  AddThreadsFlag(train, &args->threads);
  train->add_option("--assignment", args->assignment, "nearest-centroid search in the iterations: auto, exact, ivf, kdforest")
      ->capture_default_str()
      ->check(CLI::IsMember({"auto", "exact", "ivf", "kdforest"}));
  train->add_option("--quantizer-probes", args->probes,
                    "ivf assignment: coarse lists probed per descriptor in the iterations")
      ->capture_default_str()
      ->check(CLI::Range(1, 1 << 20));
  AddImageFlags(train, &args->image);
  train->callback([args] { RunVocabTrain(*args); });

  auto path = std::make_shared<std::string>();
  auto* info = cmd->add_subcommand("info", "Print a vocabulary file's words, dimension, descriptor kind, extractor settings, "
                                           "fingerprint and size; refuses damaged files.");
  info->add_option("vocabulary", *path, "vocabulary file")->required();
  info->callback([path] {
    const vocab::Vocabulary v = ValueOrExit(vocab::Vocabulary::Read(*path));
    std::error_code ec;
    const auto bytes = fs::file_size(*path, ec);
    std::printf("%s\n  words        %zu\n  dimension    %d\n  descriptor   %s\n  extractor    %s\n"
                "  fingerprint  %016llx\n  lists        %zu (two-level quantiser)\n  file size    %llu bytes (%.1f MiB)\n",
                path->c_str(), v.size(), v.dimension(), sift::DescriptorKindName(v.descriptor_kind()),
                v.extractor_settings().empty() ? "(unknown)" : v.extractor_settings().c_str(),
                static_cast<unsigned long long>(v.fingerprint()), v.num_lists(), static_cast<unsigned long long>(bytes),
                static_cast<double>(bytes) / (1 << 20));
  });
}

const bool registered = RegisterCommand({"vocab", 20, &SetUpVocab});

}  // namespace
}  // namespace oxbow::cli
