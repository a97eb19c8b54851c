// `oxbow match A B`: extracts features from two images and runs the match-then-verify pipeline of
// POST /v1/match on them (api/pair_match.h), printing the same JSON (plus the paths and the drawing).
#include <chrono>
#include <cstdio>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "api/pair_match.h"
#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "sift/draw_matches.h"
#include "sift/match.h"
#include "sift/sift.h"
#include "sift/verify.h"

namespace oxbow::cli {
namespace {

using Clock = std::chrono::steady_clock;

double MillisecondsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

struct MatchArgs {
  std::string query_path;
  std::string db_path;
  std::string model = sift::GeometricModelName(api::PairMatchOptions{}.model);
  float ratio = sift::MatchOptions{}.ratio;
  bool mutual = sift::MatchOptions{}.mutual;
  std::string method = "brute";
  int kd_trees = sift::MatchOptions{}.kd_trees;
  int kd_checks = sift::MatchOptions{}.kd_checks;
  sift::DescriptorKind descriptor = sift::SiftOptions{}.descriptor;
  std::optional<int> max_features;
  sift::SiftOptions window;  // descriptor_magnification, descriptor_row_step and descriptor_sampling
  ImageFlags image;
  double reprojection_px = sift::RobustFitOptions{}.reprojection_px;
  int min_inliers = api::PairMatchOptions{}.min_inliers;
  int num_threads = 0;
  std::string draw_path;
};

void RunMatch(const MatchArgs& args) {
  using namespace oxbow::sift;
  const auto model = ParseGeometricModel(args.model);
  if (!model) throw CommandError(2, "unknown --model '" + args.model + "'");
  if (!args.draw_path.empty()) InputFiles({args.query_path, args.db_path}).RefuseOverwrite(args.draw_path, "--draw");

  SiftOptions sift_options;
  sift_options.descriptor = args.descriptor;
  sift_options.max_features = args.max_features;
  sift_options.descriptor_magnification = args.window.descriptor_magnification;
  sift_options.descriptor_row_step = args.window.descriptor_row_step;
  sift_options.descriptor_sampling = args.window.descriptor_sampling;
  sift_options.num_threads = args.num_threads;
  const SiftExtractor extractor = ValueOrExit(SiftExtractor::Create(api::PairMatchExtractorOptions(sift_options)));
  const DecodeOptions decode = args.image.ToDecodeOptions();

  const auto begin = Clock::now();
  auto start = begin;
  const FeatureSet query = ValueOrExit(extractor.ExtractFromFile(args.query_path, decode));
  const double query_ms = MillisecondsSince(start);
  start = Clock::now();
  const FeatureSet db = ValueOrExit(extractor.ExtractFromFile(args.db_path, decode));
  const double db_ms = MillisecondsSince(start);

  api::PairMatchOptions options;
  options.model = *model;
  options.match.method = args.method == "kdtree" ? MatchOptions::Method::kKdForest : MatchOptions::Method::kBruteForce;
  options.match.kd_trees = args.kd_trees;
  options.match.kd_checks = args.kd_checks;
  options.match.ratio = args.ratio;
  options.match.mutual = args.mutual;
  options.match.num_threads = args.num_threads;
  options.fit.reprojection_px = args.reprojection_px;
  options.min_inliers = args.min_inliers;
  const api::PairMatchResult result = ValueOrExit(api::MatchPair(query, db, options));

  nlohmann::json out = api::PairMatchToJson(
      result, {.decode_extract_a = query_ms, .decode_extract_b = db_ms, .total = MillisecondsSince(begin)});
  out["a"]["path"] = args.query_path;
  out["b"]["path"] = args.db_path;
  if (!args.draw_path.empty()) {
    MatchDrawing drawing;
    drawing.query = query.keypoints;
    drawing.db = db.keypoints;
    drawing.matches = result.matches;
    drawing.inliers = result.inliers;
    if (*model != GeometricModel::kFundamental) drawing.db_from_query = result.transform;
    drawing.query_region = {0, 0, static_cast<float>(query.image_width), static_cast<float>(query.image_height)};
    drawing.db_region = result.region;
    OkOrExit(DrawMatchesToFile(args.query_path, args.db_path, drawing, args.draw_path));
    out["drawing"] = args.draw_path;
  }
  std::printf("%s\n", out.dump(2).c_str());
}

void SetUpMatch(CLI::App& app) {
  auto args = std::make_shared<MatchArgs>();
  CLI::App* cmd = app.add_subcommand(
      "match",
      "Match two images: SIFT features, nearest neighbours with Lowe's ratio test, geometric verification\n"
      "(the pipeline of POST /v1/match). Prints its JSON: verified, inliers, tentative matches, the transform\n"
      "(a pixels -> b pixels) and the region of b that image a maps onto (null unless verified), a and b\n"
      "(path, size, keypoints) and per-stage timings in ms.");
  cmd->add_option("query", args->query_path, "image a (the query)")->required()->check(CLI::ExistingFile);
  cmd->add_option("db", args->db_path, "image b (the db image)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--model", args->model,
                  "geometric model: hough-homography (Lowe's pose clustering + affine decides, then a homography "
                  "that agrees with it gives the transform: accurate under perspective), hough-affine (the affine "
                  "only, as search re-ranking), similarity, affine, homography (planar scenes) or fundamental "
                  "(general 3D scenes)")
      ->check(CLI::IsMember({"hough-homography", "hough-affine", "similarity", "affine", "homography", "fundamental"}))
      ->capture_default_str();
  cmd->add_option("--ratio", args->ratio, "Lowe's ratio test threshold, (0, 1]; 1 disables it")
      ->check(NumberIn(0, 1, /*lo_open=*/true))
      ->capture_default_str();
  cmd->add_flag("--mutual", args->mutual, "keep only mutual nearest neighbours");
  cmd->add_option("--method", args->method, "nearest-neighbour search: brute (exact) or kdtree (FLANN kd-forest)")
      ->check(CLI::IsMember({"brute", "kdtree"}))
      ->capture_default_str();
  const CLI::Option* trees = cmd->add_option("--kd-trees", args->kd_trees, "kd-forest (--method kdtree): number of randomised trees")
                                 ->check(CLI::Range(1, 64))
                                 ->capture_default_str();
  const CLI::Option* checks = cmd->add_option("--kd-checks", args->kd_checks, "kd-forest (--method kdtree): leaves visited per query")
                                  ->check(CLI::Range(1, 1 << 20))
                                  ->capture_default_str();
  AddDescriptorFlag(cmd, &args->descriptor);
  AddDescriptorWindowFlags(cmd, &args->window);
  cmd->add_option("--max-features", args->max_features, "keep at most this many strongest keypoints per image")
      ->check(Positive());
  AddImageFlags(cmd, &args->image);
  cmd->add_option("--reprojection-px", args->reprojection_px,
                  "inlier threshold of the robust estimators (similarity/affine/homography/fundamental), pixels")
      ->check(Positive())
      ->capture_default_str();
  cmd->add_option("--min-inliers", args->min_inliers, "inliers needed for \"verified\": true (every model)")
      ->check(CLI::Range(3, 1000000))
      ->capture_default_str();
  AddThreadsFlag(cmd, &args->num_threads);
  cmd->add_option("--draw", args->draw_path,
                  "write the two images side by side: inliers green, rejected matches red, matched region outlined")
      ->check(FileToWrite())
      ->check(DrawingFile());
  cmd->callback([args, trees, checks] {
    if (args->method != "kdtree" && (trees->count() > 0 || checks->count() > 0)) {
      throw CommandError(2, "--kd-trees and --kd-checks tune --method kdtree; the search is --method " + args->method);
    }
    RunMatch(*args);
  });
}

const bool registered_match = RegisterCommand({"match", 30, &SetUpMatch});

}  // namespace
}  // namespace oxbow::cli
