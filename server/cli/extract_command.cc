// `oxbow extract IMAGE...`: SIFT features of each image to a feature file (oxbow binary or COLMAP
// text), optionally a drawing of the keypoints; and `oxbow features info FILE...` to inspect feature
// files. See sift/sift.h (the method) and sift/features_io.h (the formats).
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "sift/base/parallel.h"
#include "sift/draw.h"
#include "sift/features_io.h"
#include "sift/base/log.h"
#include "sift/sift.h"

namespace oxbow::cli {
namespace {

namespace fs = std::filesystem;

struct ExtractArgs {
  std::vector<std::string> images;
  std::string out_dir = ".";
  std::string format = "oxbow";
  std::optional<std::string> draw;
  sift::DescriptorKind descriptor = sift::SiftOptions{}.descriptor;
  bool no_upsample = false;
  bool ignore_exif = false;
  bool upright = false;
  bool refine_in_scale = false;
  std::optional<int> max_features;
  ImageFlags image;
  double contrast_threshold = sift::SiftOptions{}.contrast_threshold;
  double edge_threshold = sift::SiftOptions{}.edge_threshold;
  sift::SiftOptions window;  // descriptor_magnification, descriptor_row_step and descriptor_sampling
  int num_threads = 0;
  int thread_cache_mib = sift::SiftOptions{}.thread_cache_mib;
};

// out.png with several images -> out_<image stem>.png
std::string DrawPath(const std::string& draw, const std::string& image, bool several) {
  if (!several) return draw;
  const fs::path p(draw);
  return (p.parent_path() / (p.stem().string() + "_" + fs::path(image).stem().string() + p.extension().string())).string();
}

void RunExtract(const ExtractArgs& args) {
  sift::SiftOptions options;
  options.descriptor = args.descriptor;
  options.max_features = args.max_features;
  options.upsample_first_octave = !args.no_upsample;
  options.contrast_threshold = args.contrast_threshold;
  options.edge_threshold = args.edge_threshold;
  options.upright = args.upright;
  options.refine_in_scale = args.refine_in_scale;
  options.descriptor_magnification = args.window.descriptor_magnification;
  options.descriptor_row_step = args.window.descriptor_row_step;
  options.descriptor_sampling = args.window.descriptor_sampling;
  const ThreadSplit split = SplitThreads(args.num_threads, args.images.size());
  options.num_threads = split.per_item;
  options.thread_cache_mib = args.thread_cache_mib;
  const sift::SiftExtractor extractor = ValueOrExit(sift::SiftExtractor::Create(options));
  sift::DecodeOptions decode = args.image.ToDecodeOptions();
  decode.apply_exif_orientation = !args.ignore_exif;
  if (auto message = decode.Check()) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), *message);

  // Every output is named before the work: none may replace an input, or another image's output.
  const auto feature_file = [&](const std::string& image) {
    const std::string name = fs::path(image).filename().string();
    return (fs::path(args.out_dir) / (name + (args.format == "colmap" ? ".txt" : ".oxfeat"))).string();
  };
  {
    const InputFiles inputs(args.images);
    std::map<std::string, std::string> writer;  // output -> the image that writes it
    auto claim = [&](const std::string& out, const std::string& image, const std::string& what) {
      inputs.RefuseOverwrite(out, what);
      const auto [it, added] = writer.emplace(fs::path(out).lexically_normal().string(), image);
      if (!added && it->second != image) {
        throw CommandError(2, "'" + it->second + "' and '" + image + "' would both write " + what + " '" + out +
                                  "' (the name is the image's file name): extract them into different --out folders");
      }
    };
    for (const std::string& image : args.images) {
      claim(feature_file(image), image, "the feature file");
      if (args.draw) claim(DrawPath(*args.draw, image, args.images.size() > 1), image, "the drawing");
    }
  }

  std::error_code ec;
  fs::create_directories(args.out_dir, ec);
  if (ec) throw CommandError(ExitCodeFor(ErrorCode::kIoError), "cannot create output folder '" + args.out_dir + "': " + ec.message());

  std::optional<Error> first_failure;
  int failures = 0;
  auto report = [&](const Error& error) {
    ++failures;
    if (!first_failure) first_failure = error;
    if (args.images.size() > 1) std::fprintf(stderr, "oxbow: %s\n", error.ToString().c_str());
  };
  // Images in parallel (split.workers at a time, each with split.per_item threads); outputs are written
  // and reported in the order given.
  struct Extracted {
    Result<sift::DecodedImage> decoded = std::unexpected(Error{});
    sift::FeatureSet features;
    double ms = 0;
  };
  const size_t batch = static_cast<size_t>(split.workers);
  const InterruptibleCommand interruptible;  // Ctrl-C: the images in hand are finished and written
  size_t done = 0;
  for (size_t begin = 0; begin < args.images.size(); begin += batch) {
    if (InterruptibleCommand::Interrupted()) break;
    const size_t n = std::min(batch, args.images.size() - begin);
    std::vector<Extracted> extracted(n);
    ParallelFor(n, split.workers, 1, [&](size_t lo, size_t hi, int) {
      for (size_t i = lo; i < hi; ++i) {
        const auto start = std::chrono::steady_clock::now();
        extracted[i].decoded = sift::ReadImage(args.images[begin + i], decode);
        if (extracted[i].decoded) extracted[i].features = extractor.ExtractFromDecoded(*extracted[i].decoded);
        extracted[i].ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
      }
    });
    for (size_t i = 0; i < n; ++i) {
      const std::string& image = args.images[begin + i];
      const Extracted& e = extracted[i];
      if (!e.decoded) {
        report(e.decoded.error());
        continue;
      }
      const sift::FeatureSet& features = e.features;
      const std::string out = feature_file(image);
      Status written = args.format == "colmap"
                           ? sift::WriteColmapFeatures(out, features)
                           : sift::WriteFeatureFile(out, {features, options.Fingerprint(), options.Describe()});
      if (!written) {
        report(written.error());
        continue;
      }
      std::string drawn;
      if (args.draw) {
        drawn = DrawPath(*args.draw, image, args.images.size() > 1);
        if (auto status = sift::DrawKeypoints(e.decoded->gray, features, 1.0 / e.decoded->scale_to_original, drawn);
            !status) {
          report(status.error());
          drawn.clear();
        }
      }
      std::printf("%s: %dx%d, %zu keypoints, %.1f ms -> %s%s%s\n", image.c_str(), features.image_width,
                  features.image_height, features.size(), e.ms, out.c_str(), drawn.empty() ? "" : ", ", drawn.c_str());
    }
    done = begin + n;
  }
  if (InterruptibleCommand::Interrupted() && done < args.images.size()) {
    std::fflush(stdout);
    throw CommandError(InterruptibleCommand::kExitCode,
                       "interrupted after " + std::to_string(done) + " of " + std::to_string(args.images.size()) +
                           " images: the feature files listed above are complete; the rest were not extracted");
  }
  if (first_failure) {
    if (args.images.size() == 1) throw CommandError(*first_failure);
    throw CommandError(ExitCodeFor(first_failure->code), std::to_string(failures) + " of " + std::to_string(args.images.size()) +
                                                             " images failed; the first: " + first_failure->ToString());
  }
}

void SetUpExtract(CLI::App& app) {
  auto* cmd = app.add_subcommand("extract",
                                 "Extract SIFT features (Lowe 2004) from images into feature files, RootSIFT by default.\n"
                                 "Writes <out>/<image name>.oxfeat (oxbow's versioned binary format; inspect with\n"
                                 "'oxbow features info') or, with --format colmap, <out>/<image name>.txt in COLMAP's\n"
                                 "text format ('N 128', then 'x y scale orientation d1..d128' per keypoint, descriptors\n"
                                 "0..255), ready for 'colmap feature_importer' (use --descriptor sift for COLMAP). Images\n"
                                 "are extracted in parallel; prints one line per image, in the order given.\n"
                                 "Example: oxbow extract photos/*.jpg --out feats --max-image-side 1024");
  auto args = std::make_shared<ExtractArgs>();
  cmd->add_option("images", args->images, "image files (JPEG, PNG, PPM/PGM, WebP, TIFF, BMP)")->required();
  cmd->add_option("--out", args->out_dir, "output folder (created if missing)")->check(FolderToWrite())->capture_default_str();
  cmd->add_option("--format", args->format, "feature file format: oxbow (binary) or colmap (text)")
      ->check(CLI::IsMember({"oxbow", "colmap"}))
      ->capture_default_str();
  AddDescriptorFlag(cmd, &args->descriptor);
  cmd->add_option("--max-features", args->max_features, "keep only the N strongest keypoints (by DoG contrast)")
      ->check(Positive());
  AddImageFlags(cmd, &args->image);
  cmd->add_flag("--no-upsample", args->no_upsample,
                "do not double the image size for the first octave (about 3x faster, finds fewer small features)");
  cmd->add_option("--contrast-threshold", args->contrast_threshold,
                  "minimum DoG contrast, divided by the 3 scales per octave as OpenCV does; lower finds more, weaker keypoints")
      ->check(NumberIn(0, 1))
      ->capture_default_str();
  cmd->add_option("--edge-threshold", args->edge_threshold, "edge rejection ratio r (Lowe's r = 10); higher keeps more edge-like keypoints")
      ->check(NumberIn(1, 1e6, /*lo_open=*/true))
      ->capture_default_str();
  AddDescriptorWindowFlags(cmd, &args->window);
  cmd->add_flag("--upright", args->upright,
                "upright features (Perdoch et al. 2009): every keypoint's orientation is the image's x axis, one keypoint "
                "per extremum. Better on collections photographed upright (buildings), much worse where objects turn "
                "in the picture; a vocabulary trained on these files makes index build and serve extract the same way");
  cmd->add_flag("--refine-in-scale", args->refine_in_scale,
                "the keypoint refinement also moves in scale, as `oxbow match` extracts: its homography on graf 1 -> 3 "
                "came out nearer the true one; off by default, as the index extracts (it retrieved less well on the Paris subset)");
  cmd->add_flag("--ignore-exif", args->ignore_exif, "use the pixels as stored, ignoring the EXIF orientation tag");
  AddThreadsFlag(cmd, &args->num_threads);
  cmd->add_option("--thread-cache-mib", args->thread_cache_mib,
                  "pyramid buffers kept between images, MiB (0 = free after every image; output unchanged)")
      ->check(CLI::Range(0, 65536))
      ->capture_default_str();
  cmd->add_option("--draw", args->draw,
                  "also write the image with its keypoints drawn (circle radius = 3 x scale, line = orientation); with "
                  "several images, out.png becomes out_<image stem>.png")
      ->check(FileToWrite())
      ->check(DrawingFile());
  cmd->callback([args] { RunExtract(*args); });
}

void SetUpFeatures(CLI::App& app) {
  auto* cmd = app.add_subcommand("features", "Inspect feature files written by 'oxbow extract'.");
  cmd->require_subcommand(1);
  auto* info = cmd->add_subcommand("info", "Print the header of each feature file and its first keypoints; refuses damaged files.");
  auto files = std::make_shared<std::vector<std::string>>();
  auto show = std::make_shared<int>(5);
  info->add_option("files", *files, "feature files (.oxfeat)")->required();
  info->add_option("--show", *show, "number of keypoints to print")->capture_default_str()->check(NonNegative());
  info->callback([files, show] {
    for (const std::string& path : *files) {
      const sift::FeatureFile file = ValueOrExit(sift::ReadFeatureFile(path));
      const sift::FeatureSet& f = file.features;
      std::printf("%s: format %u, image %dx%d, %zu keypoints, %s descriptors\n  extractor %016llx %s\n", path.c_str(),
                  sift::kFeatureFileVersion, f.image_width, f.image_height, f.size(), sift::DescriptorKindName(f.kind),
                  static_cast<unsigned long long>(file.extractor_fingerprint), file.extractor_description.c_str());
      for (size_t i = 0; i < std::min<size_t>(f.size(), static_cast<size_t>(*show)); ++i) {
        const sift::Keypoint& k = f.keypoints[i];
        std::printf("  #%zu x %.2f y %.2f scale %.2f orientation %.3f response %.4f octave %d\n", i, k.x, k.y, k.scale,
                    k.orientation, k.response, k.octave);
      }
    }
  });
}

const bool registered_extract = RegisterCommand({"extract", 10, &SetUpExtract});
const bool registered_features = RegisterCommand({"features", 11, &SetUpFeatures});

}  // namespace
}  // namespace oxbow::cli
