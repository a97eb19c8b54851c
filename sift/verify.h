// Geometric verification of tentative matches between a query image and a db image.
//
// 1. VerifyHoughAffine: Lowe's pose clustering (Lowe 2004, "Distinctive image features from
//    scale-invariant keypoints", IJCV 60(2), sec. 7.3-7.4). Every match predicts a similarity pose
//    (rotation, scale, and the position in the db image of the query region's centre) from its two
//    keypoints' orientation, scale and position, and votes into the two nearest bins of each of the four
//    pose dimensions (16 votes). Bins: 30 degrees of rotation, a factor 2 of scale, and a quarter of the
//    projected size of the query region (the "model" whose pose in the db image is sought; for a retrieval
//    query that is the query crop, the object) in location. Bins are kept in a hash map (memory
//    O(matches), never a dense 4D array). Clusters with at least `min_cluster_votes` votes are verified
//    in decreasing vote order: a least-squares affine fit (closed form, Eigen), iterative removal of
//    matches farther than half a location bin from the fit (and re-fit), then Lowe's top-down step: every
//    tentative match that agrees with the fit is added back and the fit repeated, shrinking the tolerance
//    to `residual_px`. A match agrees when its projected position is within the tolerance and, if
//    `check_keypoint_pose`, its keypoint orientation and scale agree with the fit within half a bin.
//    Acceptance rule (instead of Lowe's probabilistic test, which needs the model's feature density):
//    at least `min_inliers` agreeing matches AND a plausible affine (orientation-preserving, singular
//    values within [min_scale, max_scale], anisotropy at most max_anisotropy) AND inliers that span an
//    area, not a line (min_inlier_spread). Among all verified clusters the one with the most inliers is
//    returned.
//
// 2. FitRobust: full models for users that need them, via OpenCV calib3d's robust estimators
//    (we do not re-implement RANSAC): similarity = cv::estimateAffinePartial2D (RANSAC + LM refine; it
//    has no USAC variant in OpenCV 4.6), affine = cv::estimateAffine2D, homography = cv::findHomography,
//    fundamental = cv::findFundamentalMat; the last three with USAC MAGSAC++ (Barath et al. 2020) by
//    default, which is threshold-robust and needs fewer iterations than classic RANSAC, or with classic
//    RANSAC on request. OpenCV starts both samplers from a fixed state, so results are reproducible.
//
// Both expect one-to-one matches (see EnforceOneToOne in match.h): many-to-one matches inflate inlier
// counts on repeated structure (colmap/colmap#288).
//
// Coordinates: pixels, origin at the centre of the top-left pixel, x right, y down (as Keypoint).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "sift/base/error.h"
#include "sift/match.h"
#include "sift/types.h"

namespace oxbow::sift {

// A 2D affine map x' = A x + t, stored row-major as {a11, a12, tx, a21, a22, ty}. Default: identity.
struct Affine2D {
  std::array<double, 6> m = {1, 0, 0, 0, 1, 0};

  Eigen::Vector2d Apply(const Eigen::Vector2d& p) const {
    return {m[0] * p.x() + m[1] * p.y() + m[2], m[3] * p.x() + m[4] * p.y() + m[5]};
  }
  double Determinant() const { return m[0] * m[4] - m[1] * m[3]; }
  // The inverse map, or nullopt when A is singular (|det A| <= 1e-12 * max|a_ij|^2) or not finite.
  std::optional<Affine2D> Inverse() const;
};

struct HoughVerifyOptions {
  // --- Hough bins (Lowe 2004 sec. 7.3)
  double orientation_bin_deg = 30;     // rotation bin width, degrees, [1, 180]; rounded so that a whole number
                                       // of bins covers 360 degrees
  double scale_bin_factor = 2;         // scale bin width as a factor, [1.1, 16]
  double location_bin_fraction = 0.25;  // location bin width as a fraction of the projected size
                                        // (max(width, height) of the query region times the bin's scale), (0, 1]
  int min_cluster_votes = 3;           // a bin is verified when it holds at least this many matches, >= 3
                                       // (an affine needs 3 points)
  int max_clusters_to_verify = 32;     // verify at most this many bins (largest first), >= 1; bins that are
                                       // mostly inliers of the best fit so far are skipped and not counted
  double early_stop_fraction = 0.25;   // once a cluster is verified with K inliers, stop at the first bin with
                                       // fewer than this * K votes: the peak bin of a pose supported by more
                                       // than K matches holds a good share of them. [0, 1]; 0 = never stop early
  // --- Fit and outlier removal (Lowe 2004 sec. 7.4)
  double initial_residual_bin_fraction = 0.5;  // first tolerance, as a fraction of the cluster's location
                                               // bin (Lowe: half a bin), (0, 4]
  double residual_px = 12;             // final tolerance on |fit(query) - db|, db-image pixels, > 0
  int max_refine_iterations = 8;       // re-fit / re-select rounds per cluster, >= 1
  bool check_keypoint_pose = true;     // also require each inlier's orientation (within half an orientation
                                       // bin) and scale (within sqrt(scale_bin_factor)) to agree with the fit
  // --- Acceptance rule
  int min_inliers = 6;                 // verified needs at least this many inliers, >= 3. 6 = twice the
                                       // minimal affine sample: three points always fit exactly, six rarely
                                       // do by chance within residual_px (see verify_test negatives)
  double min_scale = 1.0 / 32;         // each singular value of A must lie in [min_scale, max_scale], > 0
  double max_scale = 32;
  double max_anisotropy = 6;           // ratio of A's singular values at most this, >= 1
                                       // (a 6:1 squash is ~80 degrees of viewpoint change)
  double min_inlier_spread = 3.5;      // the inliers' spread across their principal axis (standard deviation
                                       // of their positions) in each image, in their median keypoint scale,
                                       // at least this; >= 0, 0 = no test. Inliers along a line (a word matched
                                       // to the same word in another text) leave the affine undetermined across
                                       // it; another view of an object spreads its inliers over an area
  double min_firm_aspect = 0.2;        // VerificationResult::firm also needs the inliers' standard deviation
                                       // across their principal axis at least this fraction of that along it,
                                       // in each image, [0, 1]; 0 = no test. A matched line of text is long
                                       // and thin however many letters it holds

  std::optional<std::string> Check() const;  // empty when valid, else a message naming the field
};

struct VerificationResult {
  bool verified = false;          // accepted by the rule in HoughVerifyOptions (min_inliers, plausible A)
  int num_inliers = 0;            // == inliers.size()
  std::vector<uint32_t> inliers;  // indices into the `matches` span given to the verifier, ascending
  Affine2D db_from_query;         // maps query-image pixels to db-image pixels (identity if no fit)
  std::array<float, 4> db_region = {0, 0, 0, 0};  // x1,y1,x2,y2: axis-aligned box in the db image that the
                                  // query region maps onto, clipped to the db image; zeros if no fit
  int num_votes = 0;              // votes of the Hough bin the result grew from (0 if none had enough)
  bool firm = false;              // verified, and the inliers still span an area (min_inlier_spread) without
                                  // the one farthest from their principal axis in each image (not a line of
                                  // matches plus one stray point), and not a thin band (min_firm_aspect).
                                  // A search chains transitive verification only from firm results
};

// Lowe's Hough pose clustering + affine verification (see the file comment).
// query / db: the two images' keypoints; matches: tentative matches (any order; indices into query and
// db, assumed one-to-one). Matches with an out-of-range index, a non-finite keypoint or a keypoint scale
// <= 0 are ignored and never reported as inliers.
// query_region: x1,y1,x2,y2 of the query object in query pixels (the whole image: 0,0,w,h).
// db_size: width,height of the db image in pixels (used to clip db_region).
// Invalid options (Check() non-empty) or an empty/non-finite region give an unverified, empty result;
// never throws for bad input; the output is always finite.
// Thread-safe (thread-local scratch, no shared state). Cost O(16 n) for voting plus O(n) per verified
// cluster; 0.3-0.4 ms CPU for 1000 matches on one core (match_benchmark, boat 1->2). Deterministic.
VerificationResult VerifyHoughAffine(std::span<const Keypoint> query, std::span<const Keypoint> db,
                                     std::span<const Match> matches, const std::array<float, 4>& query_region,
                                     const std::array<int, 2>& db_size, const HoughVerifyOptions& options = {});

enum class GeometricModel {
  kHoughAffine,  // VerifyHoughAffine (region = keypoint bounding boxes)
  // VerifyHoughAffine decides (its inliers, its plausible-affine test); when it verifies, a homography
  // fitted to the tentative matches (as kHomography) replaces the affine transform and the inliers if
  // it keeps at least half of the Hough inliers and has at least hough.min_inliers inliers of its own
  // (HomographyAgreeingWith), so a verified answer never reports fewer. Affine maps cannot follow a
  // perspective change: graf 1 -> 3 corner error 48.2 px with kHoughAffine, 1.04 px with this and
  // `oxbow match`'s extractor (eval/results/matching.md).
  kHoughHomography,
  kSimilarity,   // 4 dof: rotation, uniform scale, translation (cv::estimateAffinePartial2D)
  kAffine,       // 6 dof (cv::estimateAffine2D)
  kHomography,   // 8 dof, planar scenes (cv::findHomography)
  kFundamental,  // 7 dof epipolar geometry, general 3D scenes (cv::findFundamentalMat)
};
const char* GeometricModelName(GeometricModel model);  // "hough-affine", "similarity", "affine", ...
std::optional<GeometricModel> ParseGeometricModel(std::string_view name);

struct RobustFitOptions {
  enum class Estimator {
    kMagsac,  // USAC MAGSAC++ (affine, homography, fundamental); similarity falls back to RANSAC
    kRansac,  // classic RANSAC (Fischler & Bolles 1981) as implemented by OpenCV
  };
  Estimator estimator = Estimator::kMagsac;
  double reprojection_px = 4.0;  // inlier threshold, pixels, > 0: reprojection error in the db image
                                 // (similarity/affine/homography) or distance to the epipolar line
                                 // (fundamental); for MAGSAC++ the upper bound of its noise scale
  double confidence = 0.999;     // desired probability of having drawn an all-inlier sample, (0, 1)
  int max_iterations = 10000;    // sampling iterations at most, >= 1
  int refine_iterations = 10;    // Levenberg-Marquardt refinement (similarity/affine RANSAC), >= 0
  HoughVerifyOptions hough;      // used by GeometricModel::kHoughAffine

  std::optional<std::string> Check() const;
};

struct RobustFitResult {
  GeometricModel model = GeometricModel::kHomography;
  bool success = false;           // the estimator returned a model with at least its minimal sample of
                                  // inliers (kHoughAffine: VerificationResult::verified)
  int num_inliers = 0;
  std::vector<uint32_t> inliers;  // indices into `matches`, ascending
  Eigen::Matrix3d db_from_query = Eigen::Matrix3d::Identity();  // 3x3; similarity/affine in the top two
                                  // rows (last row 0 0 1); homography normalised to H(2,2) = 1;
                                  // fundamental: F with x_db^T F x_query = 0
};

// Fits `model` to the tentative matches with a robust estimator (see the file comment).
// Errors (kInvalidArgument): invalid options, a match index out of range, non-finite keypoints.
// Too few matches for the model (similarity 2, affine 3, homography 4, fundamental 8) is not an error:
// success == false. Thread-safe (OpenCV may use its own thread pool). Deterministic.
[[nodiscard]] Result<RobustFitResult> FitRobust(GeometricModel model, std::span<const Keypoint> query,
                                                std::span<const Keypoint> db, std::span<const Match> matches,
                                                const RobustFitOptions& options = {});

// A homography fitted to `matches` (FitRobust with kHomography and `options`) when it succeeds, keeps
// at least half of `hough_inliers` (indices into `matches`, e.g. VerificationResult::inliers) among its
// own inliers and has at least options.hough.min_inliers inliers; nullopt otherwise (the affine answer
// stands). Errors as FitRobust's.
[[nodiscard]] Result<std::optional<RobustFitResult>> HomographyAgreeingWith(std::span<const Keypoint> query,
                                                                            std::span<const Keypoint> db,
                                                                            std::span<const Match> matches,
                                                                            std::span<const uint32_t> hough_inliers,
                                                                            const RobustFitOptions& options);

// Maps the box x1,y1,x2,y2 through a 3x3 projective/affine transform and returns the axis-aligned
// bounding box of its four corners clipped to [0, width] x [0, height]; zeros when a corner maps to
// infinity (or behind the camera for a homography) or the transform is not finite.
std::array<float, 4> ProjectBox(const Eigen::Matrix3d& target_from_source, const std::array<float, 4>& box,
                                const std::array<int, 2>& target_size);

}  // namespace oxbow::sift
