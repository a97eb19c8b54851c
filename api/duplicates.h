// Duplicates in a collection: which images show the same thing, found by searching the index with every
// image's stored features and verifying the geometry (oxbow index duplicates, POST .../duplicates).
//
// Method, per image A (in parallel over images, each on the index's current snapshot):
//   1. A's stored features search the index (tf-idf + Hamming embedding, spatial re-ranking of the
//      `candidates` best, no query expansion, no transitive verification): every other image B
//      verified against A gives a candidate pair with A's affine map into B.
//   2. The same with A's features mirrored (x -> width - x, orientation -> pi - orientation, each word
//      replaced by the word of its mirrored centroid: a SIFT descriptor of a mirrored patch is a
//      permutation of the original's), so that a mirrored copy is found without its pixels. Without
//      Hamming signatures (they do not mirror).
// Each pair is then measured once, on both images' stored features: the features of A that land
// within `inlier_tolerance` of a feature of B with the same word under the map (and at a consistent
// scale) are its inliers; `coverage_a` is the share of A's feature-bearing cells of an 8 x 8 grid
// that hold an inlier (the same for B); its density on each side is the share of the features inside
// the inliers' box that are inliers. A pair shares only an overlay (a logo, a caption, a frame) and is
// dropped when its inliers avoid the central cells of both images, when it is mirrored and covers less
// than 0.4 of both (a mirror copy matches most of a photo; a symmetric logo or frame matches itself
// mirrored in part), when its larger coverage is below `min_coverage`, or when it is dense (identical
// pixels: density at least `overlay_density` on one side) but covers less than `overlay_coverage` of
// both; the last two keep a match of distinct content (the median Hamming distance of its inliers'
// signatures above 6 bits: not pasted pixels) that has at least 10% of its inliers in the central cells
// of one image and 1% in those of the other and covers at least 0.05 of one (another photo of the same
// object often matches only that much). A direct match of twins (identical pixels at the same places: at
// least half its inliers, signatures alike or absent) around a block reaching the centre where both images
// hold features and none match (at least 0.2 of the cells they share) is one frame around two pictures,
// and dropped too. The kept pairs are:
//   exact       the same picture: equal sizes, the identity map, both covered at least 0.9, at least 98%
//               of the features identical (same word, place, scale and orientation), not mirrored;
//   near_copy   one image is the other resized, recompressed, cropped, rotated, mirrored, retouched or
//               overlaid: one of them covered at least `near_copy_coverage` under a similarity (axis
//               ratio of the map at most `max_anisotropy`);
//   same_scene  another photo of the same object or place.
// Groups are the connected components of the kept pairs.
//
// Thread-safe: runs on an index that serves searches and writes meanwhile (what a snapshot held at
// the start of each image's search shows; images added during the run may be missed, deleted ones
// are skipped).
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "index/image_index.h"
#include "sift/base/error.h"
#include "sift/verify.h"
#include "vocab/communicator.h"

namespace oxbow::api {

struct DuplicateOptions {
  // Best tf-idf candidates of each image that spatial verification checks (its re-ranking depth and
  // result count). An image with more copies than this may miss some (groups still connect them
  // through the copies found). [1, 1000].
  int candidates = 50;
  // Also find mirrored copies (a second search per image).
  bool mirrored = true;
  // A pair is dropped when both images' coverage is below this (their match is a small patch: a shared
  // logo or caption). [0, 1].
  double min_coverage = 0.25;
  // A dense match (at least `overlay_density` of the features inside the matched region are inliers,
  // on one side: identical pixels) that covers less than `overlay_coverage` of both images is a shared
  // overlay, not a duplicate. [0, 1] each.
  double overlay_coverage = 0.5;
  double overlay_density = 0.25;
  // A near copy: one image covered at least this much by the match. [0, 1].
  double near_copy_coverage = 0.6;
  // A near copy's map is a similarity: ratio of its singular values at most this. >= 1.
  double max_anisotropy = 1.3;
  // Inliers of the measure: distance under the map, as a fraction of the longer side of image B
  // (at least 4 px). (0, 1].
  double inlier_tolerance = 0.015;
  // Threads over images; 0 = all hardware threads. [0, 256].
  int threads = 0;

  std::optional<std::string> Check() const;
};

enum class DuplicateKind { kExact, kNearCopy, kSameScene };
const char* DuplicateKindName(DuplicateKind kind);  // "exact" | "near_copy" | "same_scene"

struct DuplicatePair {
  std::string a, b;                 // a < b
  DuplicateKind kind = DuplicateKind::kSameScene;
  bool mirrored = false;            // b matches a mirrored
  int inliers = 0;                  // the measure's inliers
  double coverage_a = 0, coverage_b = 0;
  std::array<float, 4> region_a{}, region_b{};  // boxes of the inliers, x1 y1 x2 y2 in pixels
  sift::Affine2D b_from_a;          // a pixels -> b pixels (determinant < 0 when mirrored)
  int group = 0;
};

struct DuplicateReport {
  uint64_t images = 0;
  std::vector<DuplicatePair> pairs;                 // by group, then a, then b
  std::vector<std::vector<std::string>> groups;     // ids sorted; groups by their first id
  double search_s = 0, measure_s = 0;
  uint64_t candidate_pairs = 0;                     // verified by the searches, before the measure
  uint64_t overlay_pairs = 0;                       // dropped as a shared overlay
};

// Progress: (images done, images in all), from the workers (thread-safe callers only).
using DuplicateProgress = std::function<void(uint64_t done, uint64_t total)>;

// Finds the duplicates of `index`. `stop` (may be empty) is asked between images: when it answers
// true the job ends with kResourceExhausted ("cancelled"). kInvalidArgument for bad options.
// With `comm` (oxbow index duplicates --mpi: every rank has the same index open, ImageIndex::OpenReadOnly),
// each rank searches every size()-th image and measures every size()-th pair, and every rank returns the
// whole report, the single process's; `progress` counts the rank's own images. Collective: every rank
// calls it with the same options, and a failure on one rank is every rank's.
[[nodiscard]] Result<DuplicateReport> FindDuplicates(const index::ImageIndex& index, const DuplicateOptions& options,
                                                     const DuplicateProgress& progress = {},
                                                     const std::function<bool()>& stop = {},
                                                     vocab::Communicator* comm = nullptr);

// The report as JSON: {"images", "settings", "pairs": [...], "groups": [{"group", "images"}], "timings_s"}.
nlohmann::json DuplicateReportToJson(const DuplicateReport& report, const DuplicateOptions& options);
// As CSV: a,b,kind,mirrored,inliers,coverage_a,coverage_b,group (header, then one row per pair).
std::string DuplicateReportToCsv(const DuplicateReport& report);

// A SIFT/RootSIFT descriptor (128 values, oxbow's and OpenCV's layout) of the mirrored patch: what the
// extractor computes at the mirrored keypoint of the horizontally mirrored image, up to sampling.
void MirrorDescriptor(const float* descriptor, float* mirrored);

}  // namespace oxbow::api
