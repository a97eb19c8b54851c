// `oxbow match A B`: extracts features from two images, matches them, verifies the matches geometrically
// and prints one JSON object (counts, transform, matched region, per-stage timings). See sift/match.h and
// sift/verify.h for the methods.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

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
  std::string model = "hough-affine";
  float ratio = 0.8f;
  bool mutual = false;
  std::string method = "brute";
  int kd_trees = 4;
  int kd_checks = 64;
  sift::DescriptorKind descriptor = sift::SiftOptions{}.descriptor;
  std::optional<int> max_features;
  ImageFlags image;
  double reprojection_px = 4.0;
  int min_inliers = 6;
  int num_threads = 0;
  std::string draw_path;
};

nlohmann::json MatrixJson(const Eigen::Matrix3d& m) {
  nlohmann::json rows = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({m(r, 0), m(r, 1), m(r, 2)});
  return rows;
}

void RunMatch(const MatchArgs& args) {
  using namespace oxbow::sift;
  const auto model = ParseGeometricModel(args.model);
  if (!model) throw CommandError(2, "unknown --model '" + args.model + "'");

  SiftOptions sift_options;
  sift_options.descriptor = args.descriptor;
  sift_options.max_features = args.max_features;
  sift_options.num_threads = args.num_threads;
  const SiftExtractor extractor = ValueOrExit(SiftExtractor::Create(sift_options));
  const DecodeOptions decode = args.image.ToDecodeOptions();

  auto start = Clock::now();
  const FeatureSet query = ValueOrExit(extractor.ExtractFromFile(args.query_path, decode));
  const double query_ms = MillisecondsSince(start);
  start = Clock::now();
  const FeatureSet db = ValueOrExit(extractor.ExtractFromFile(args.db_path, decode));
  const double db_ms = MillisecondsSince(start);

  MatchOptions match_options;
  match_options.method = args.method == "kdtree" ? MatchOptions::Method::kKdForest : MatchOptions::Method::kBruteForce;
  match_options.kd_trees = args.kd_trees;
  match_options.kd_checks = args.kd_checks;
  match_options.ratio = args.ratio;
  match_options.mutual = args.mutual;
  match_options.num_threads = args.num_threads;
  start = Clock::now();
  const std::vector<Match> matches = ValueOrExit(MatchDescriptors(query, db, match_options));
  const double match_ms = MillisecondsSince(start);

  const std::array<float, 4> query_region = {0, 0, static_cast<float>(query.image_width), static_cast<float>(query.image_height)};
  const std::array<int, 2> db_size = {db.image_width, db.image_height};
  bool verified = false;
  std::vector<uint32_t> inliers;
  Eigen::Matrix3d db_from_query = Eigen::Matrix3d::Identity();
  std::optional<std::array<float, 4>> db_region;
  int votes = 0;
  start = Clock::now();
  if (*model == GeometricModel::kHoughAffine) {
    HoughVerifyOptions hough;
    hough.min_inliers = args.min_inliers;
    if (auto problem = hough.Check()) throw CommandError(2, "--min-inliers: " + *problem);
    const VerificationResult v = VerifyHoughAffine(query.keypoints, db.keypoints, matches, query_region, db_size, hough);
    verified = v.verified;
    inliers = v.inliers;
    const auto& m = v.db_from_query.m;
    db_from_query << m[0], m[1], m[2], m[3], m[4], m[5], 0, 0, 1;
    if (v.num_inliers > 0) db_region = v.db_region;
    votes = v.num_votes;
  } else {
    RobustFitOptions robust;
    robust.reprojection_px = args.reprojection_px;
    const RobustFitResult fit = ValueOrExit(FitRobust(*model, query.keypoints, db.keypoints, matches, robust));
    verified = fit.success && fit.num_inliers >= args.min_inliers;
    inliers = fit.inliers;
    db_from_query = fit.db_from_query;
    if (fit.success && *model != GeometricModel::kFundamental) db_region = ProjectBox(db_from_query, query_region, db_size);
  }
  const double verify_ms = MillisecondsSince(start);

  nlohmann::json out;
  auto image_json = [](const std::string& path, const FeatureSet& f) {
    return nlohmann::json{{"path", path}, {"width", f.image_width}, {"height", f.image_height}, {"keypoints", f.size()}};
  };
  out["query"] = image_json(args.query_path, query);
  out["db"] = image_json(args.db_path, db);
  out["descriptor"] = DescriptorKindName(query.kind);
  out["method"] = args.method;
  out["ratio"] = std::round(double(args.ratio) * 1e6) / 1e6;  // the float, without float-to-double digits
  out["mutual"] = args.mutual;
  out["model"] = GeometricModelName(*model);
  out["tentative_matches"] = matches.size();
  out["inliers"] = inliers.size();
  out["verified"] = verified;
  if (*model == GeometricModel::kHoughAffine) out["hough_votes"] = votes;
  out[*model == GeometricModel::kFundamental ? "fundamental_matrix" : "db_from_query"] = MatrixJson(db_from_query);
  out["db_region"] = db_region ? nlohmann::json(*db_region) : nlohmann::json(nullptr);
  out["timings_ms"] = {{"query_decode_extract", query_ms}, {"db_decode_extract", db_ms}, {"match", match_ms},
                       {"verify", verify_ms}};

  if (!args.draw_path.empty()) {
    MatchDrawing drawing;
    drawing.query = query.keypoints;
    drawing.db = db.keypoints;
    drawing.matches = matches;
    drawing.inliers = inliers;
    if (*model != GeometricModel::kFundamental && !inliers.empty()) drawing.db_from_query = db_from_query;
    drawing.query_region = query_region;
    drawing.db_region = db_region;
    OkOrExit(DrawMatchesToFile(args.query_path, args.db_path, drawing, args.draw_path));
    out["drawing"] = args.draw_path;
  }
  std::printf("%s\n", out.dump(2).c_str());
}

void SetUpMatch(CLI::App& app) {
  auto args = std::make_shared<MatchArgs>();
  CLI::App* cmd = app.add_subcommand(
      "match",
      "Match two images: SIFT features, nearest neighbours with Lowe's ratio test, geometric verification.\n"
      "Prints JSON: keypoints per image, tentative matches, inliers, the transform db_from_query (query\n"
      "pixels -> db pixels), the db-image region the query maps onto, and per-stage timings in ms.");
  cmd->add_option("query", args->query_path, "first image (the query)")->required()->check(CLI::ExistingFile);
  cmd->add_option("db", args->db_path, "second image (the db image)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--model", args->model,
                  "geometric model: hough-affine (Lowe's pose clustering + affine, fast), similarity, affine, "
                  "homography (planar scenes) or fundamental (general 3D scenes)")
      ->check(CLI::IsMember({"hough-affine", "similarity", "affine", "homography", "fundamental"}))
      ->capture_default_str();
  cmd->add_option("--ratio", args->ratio, "Lowe's ratio test threshold, (0, 1]; 1 disables it")
      ->check(CLI::Range(0.0f, 1.0f))
      ->capture_default_str();
  cmd->add_flag("--mutual", args->mutual, "keep only mutual nearest neighbours");
  cmd->add_option("--method", args->method, "nearest-neighbour search: brute (exact) or kdtree (FLANN kd-forest)")
      ->check(CLI::IsMember({"brute", "kdtree"}))
      ->capture_default_str();
  cmd->add_option("--kd-trees", args->kd_trees, "kd-forest: number of randomised trees")->check(CLI::Range(1, 64))->capture_default_str();
  cmd->add_option("--kd-checks", args->kd_checks, "kd-forest: leaves visited per query")->check(CLI::Range(1, 1 << 20))->capture_default_str();
  AddDescriptorFlag(cmd, &args->descriptor);
  cmd->add_option("--max-features", args->max_features, "keep at most this many strongest keypoints per image")
      ->check(CLI::PositiveNumber);
  AddImageFlags(cmd, &args->image);
  cmd->add_option("--reprojection-px", args->reprojection_px,
                  "inlier threshold of the robust estimators (similarity/affine/homography/fundamental), pixels")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--min-inliers", args->min_inliers, "inliers needed for \"verified\": true")
      ->check(CLI::Range(3, 1 << 30))
      ->capture_default_str();
  AddThreadsFlag(cmd, &args->num_threads);
  cmd->add_option("--draw", args->draw_path,
                  "write the two images side by side: inliers green, rejected matches red, matched region outlined");
  cmd->callback([args] { RunMatch(*args); });
}

const bool registered = RegisterCommand({"match", 30, &SetUpMatch});

}  // namespace
}  // namespace oxbow::cli
