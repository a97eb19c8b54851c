// SIFT: the Scale-Invariant Feature Transform (Lowe 2004), oxbow's own implementation.
//
// ==== Overview ====================================================================================
//
// SIFT finds blob-like structures that can be re-detected in another photo of the same object taken at
// another scale, rotation and (moderately) viewpoint, and describes the image patch around each with a
// 128-dimensional histogram of gradient orientations. References:
//   [L04]  D. G. Lowe, "Distinctive Image Features from Scale-Invariant Keypoints", IJCV 60(2), 2004.
//   [AZ12] R. Arandjelovic, A. Zisserman, "Three things everyone should know to improve object
//          retrieval", CVPR 2012 (RootSIFT).
//   [M05]  K. Mikolajczyk et al., "A Comparison of Affine Region Detectors", IJCV 65, 2005 (the
//          repeatability / matching-score protocol the tests use).
//   [P09]  M. Perdoch, O. Chum, J. Matas, "Efficient Representation of Local Geometry for Large Scale
//          Object Retrieval", CVPR 2009 (upright features: the gravity vector as the orientation).
// The parameters and conventions follow OpenCV's cv::SIFT (which follows [L04]); with
// KeypointStyle::kOpenCv the keypoints of the two agree (sift_test.cc measures it), and the default
// KeypointStyle::kVlfeat refines keypoints and assigns orientations as VLFeat's vl_sift does (steps 5
// and 6), which repeats and matches more of them across views (eval/results/sift.md).
//
// 1. Input. A grey image I(x, y) in [0, 1] (DecodeImage). The camera is assumed to have blurred it
//    with a Gaussian of sigma_n = assumed_blur (0.5 px).
//
// 2. Gaussian scale space [L04 sec. 3]. L(x, y, s) = G(s) * I. With upsample_first_octave the image is
//    first enlarged 2x (bilinear), so octave -1 works at half-pixel resolution and finds the small
//    blobs a 1x start would miss (sigma_n becomes 2 * 0.5). The base image of the first octave is blurred
//    to sigma0 = `sigma` (1.6): by sqrt(sigma0^2 - (2 sigma_n)^2). Each octave o holds S + 3 images
//    (S = `intervals` = 3) at sigma_i = sigma0 * k^i, k = 2^(1/S), i = 0..S+2, each obtained from the
//    previous one by an incremental blur sqrt(sigma_i^2 - sigma_{i-1}^2). The next octave starts from
//    image i = S (sigma = 2 sigma0) subsampled by 2. Octaves are added while the smaller image side is
//    at least 2 * (border + 1) pixels; the count is round(log2(min side)) - 2 (+1 with upsampling).
//    Gaussian kernels are truncated at `kernel_radius_sigmas` (4) sigma, as OpenCV does for floats.
//
// 3. Difference of Gaussians [L04 sec. 3]: D_i = L_{i+1} - L_i, i = 0..S+1, approximates
//    (k - 1) sigma^2 * Laplacian, the scale-normalised blob detector.
//
// 4. Extrema [L04 sec. 3.1]. A sample of D_1..D_S is a candidate when it is strictly larger (or
//    smaller) than all 26 neighbours in space and scale, and |D| > 0.5 * contrast_threshold / S.
//
// 5. Refinement [L04 sec. 4]. Fit a 3D quadratic to D around the sample (finite differences), solve for
//    the offset (dx, dy, ds) = -H^-1 grad D. When a component exceeds 0.5 move to the neighbouring
//    sample and repeat, at most 5 times; give up when it does not converge or leaves the image. Reject
//    when |D(offset)| * S < contrast_threshold (low contrast), and when the 2x2 spatial Hessian has
//    tr^2 / det >= (r + 1)^2 / r with r = edge_threshold (10): an edge, poorly localised along it.
//    The keypoint scale is sigma0 * 2^((s + ds) / S) * 2^o, its position (x + dx) * 2^o.
//    This is KeypointStyle::kOpenCv. The default, KeypointStyle::kVlfeat (as VLFeat's vl_sift), moves
//    the sample in space only (when |dx| or |dy| > 0.6), keeps the fit at the last sample after 5 moves,
//    rejects offsets of 1.5 or more, and takes steps 6 and 7 at the Gaussian level nearest s + ds:
//    fewer extrema are lost, so more keypoints repeat across views.
//
// 6. Orientation [L04 sec. 5]. In a window of radius 3 * 1.5 * sigma around the keypoint (at the level
//    nearest its scale), accumulate gradient magnitudes weighted by a Gaussian of 1.5 * sigma into 36
//    bins of 10 degrees, smooth the histogram ([1 4 6 4 1] / 16), and take every local peak >= 80% of
//    the highest; interpolate each by a parabola through it and its neighbours. Each such peak gives a
//    keypoint (so a location can have several orientations). KeypointStyle::kVlfeat takes the
//    gradients in a circular window of radius floor(3 * 1.5 * sigma) centred on the sub-pixel position,
//    shares each vote linearly between the two nearest bins and smooths by six passes of [1 1 1] / 3.
//    With `upright` (the gravity-vector assumption of [P09]) no histogram is made: every keypoint has
//    the one orientation 0 (the image's +x axis).
//
// 7. Descriptor [L04 sec. 6]. Rotate a window of 4 x 4 cells, each 3 sigma wide, to the keypoint
//    orientation; add each sample's gradient magnitude, weighted by a Gaussian of half the window
//    width, into 8 orientation bins of its cell with trilinear interpolation (x, y, angle)
//    (`descriptor_magnification` sets the cell width, `descriptor_row_step` which rows are sampled;
//    DescriptorSampling::kGrid takes the gradients at a fixed grid of points instead). Normalise to
//    unit L2 norm, clip at 0.2 (reduces the effect of non-linear illumination changes), renormalise.
//    RootSIFT [AZ12]: L1-normalise, then take the element-wise square root, so that the Euclidean
//    distance between RootSIFTs is the Hellinger kernel between the SIFT histograms.
//
// 8. Output. Coordinates and scales are in input-image pixels (the octave -1 / downscaling factors are
//    undone); the strongest max_features by |response| are kept when a limit is set.
//
// With KeypointStyle::kOpenCv the keypoints follow cv::SIFT's; differences from cv::SIFT (4.6), all small: (a) positions are pixel-centre exact: the 2x upsampling
// maps input x to 2x + 0.5, so we report x_up / 2 - 0.25 where OpenCV reports x_up / 2; (b) the
// descriptor window is centred on the sub-pixel keypoint position (OpenCV rounds it to the nearest
// pixel); (c) gradient directions use a degree-9 polynomial atan2 (error < 0.001 degrees). Keypoint
// sets otherwise agree: on graf1.png 99.9% of cv::SIFT's 2665 keypoints have a counterpart within
// 0.5 px / 5% scale / 3 degrees, and the same extrema pre-filter (0.5 * contrast / S quantised to 8-bit
// grey levels, as OpenCV) and non-strict 26-neighbour comparison are used.
//
// ==== Usage =========================================================================================
//
//   sift::SiftOptions options;                         // Lowe's detector settings, VLFeat-style keypoints; RootSIFT
//   auto extractor = sift::SiftExtractor::Create(options);       // Result<SiftExtractor>
//   if (!extractor) return extractor.error();
//   auto features = extractor->ExtractFromFile("photo.jpg");      // Result<FeatureSet>
//   // or: sift::FeatureSet f = extractor->Extract(gray_image);
//
// Performance: the separable Gaussian blurs (four output rows per vertical sweep), the DoG and the
// extrema pre-check, the orientation histograms and the descriptors (gradients, bins and trilinear
// weights 8 or 16 samples at a time; with AVX-512 all 128 descriptor bins stay in registers, otherwise
// only the non-zero terms are added through memory) are vectorised (AVX-512 when the build targets it,
// AVX2+FMA when compiled with it or chosen at run time, with a scalar path computing the same formula,
// including the same fused multiply-adds). Each octave is cut into horizontal strips, one per thread; a
// strip blurs its Gaussian levels a few rows at a time just ahead of its extrema scan, so rows are re-read
// from cache rather than memory, and makes the upsampled image row by row as its first blur reads it
// (the rows just beyond the strip that it reads it computes again on its own). Keypoints are split over
// threads with per-item outputs, so the result is bit-identical for any num_threads.
// The parallel loops run on the process-wide persistent worker pool (sift/parallel.h), and each calling thread keeps
// its pyramid buffers between calls (SiftOptions::thread_cache_mib), so a thread extracting image after
// image does not pay the page faults of ~100 MB of fresh memory per image.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "sift/base/error.h"
#include "sift/image.h"
#include "sift/types.h"

namespace oxbow::sift {

// How extrema are refined into keypoints and how their orientations are found (steps 5 and 6 above).
enum class KeypointStyle : uint8_t {
  // As cv::SIFT 4.6 (and [L04]): the quadratic fit moves the sample in space and scale whenever an
  // offset exceeds 0.5, and an extremum that has not settled after 5 moves is dropped. Orientation:
  // a square window centred on the sample, each gradient voting into its nearest bin, the histogram
  // smoothed once by [1 4 6 4 1] / 16. Keypoints agree with cv::SIFT's (sift_test).
  kOpenCv = 0,
  // As VLFeat's vl_sift: the fit moves the sample in space only, when an offset exceeds 0.6, and keeps
  // the last fit after 5 moves if every offset is below 1.5, so fewer extrema are lost; orientation
  // and descriptor are taken at the Gaussian level nearest the refined scale. Orientation: a circular
  // window (radius floor(4.5 sigma)) centred on the sub-pixel position, each vote shared linearly
  // between the two nearest bins, the histogram smoothed by six passes of [1 1 1] / 3. On the Oxford
  // affine pairs this finds ~16% more keypoints, repeats them more often and gives more correct
  // matches than kOpenCv (eval/results/sift.md).
  kVlfeat = 1,
};

// Where the descriptor takes its gradients (step 7).
enum class DescriptorSampling : uint8_t {
  // At every pixel of the rotated window, as [L04], VLFeat and cv::SIFT: about 500-2,300 gradients per
  // keypoint with cells 3 sigmas wide, and more with wider cells.
  kPixels = 0,
  // At a fixed 16 x 16 grid of points in the keypoint's frame, about one sigma apart with cells 3 sigmas
  // wide, sampled bilinearly from the level (already blurred by a sigma) with a ring of points around
  // them for central differences along the frame's axes: 256 gradients per keypoint whatever its scale
  // and cell width. The same trilinear histogram, Gaussian, normalisation and clipping. The extraction
  // takes about a quarter less time and the Oxford affine pairs match as well (eval/results/sift.md),
  // but retrieval is lower: over three vocabulary seeds groups_hard mAP 0.033 and Paris 0.020 below the
  // pixels' (eval/results/accuracy.md, "Descriptor sampling"), and `oxbow match`'s homographies on
  // graf 1 -> 3 and boat 1 -> 4 came out farther from the true ones (eval/results/matching.md). An
  // option where extraction time counts most.
  kGrid = 1,
};

struct SiftOptions {
  // ---- Behaviour: these change the output and are part of Describe()/Fingerprint(). ----

  // Keypoint refinement and orientation assignment (see KeypointStyle). A description without a
  // `keypoints` field means kOpenCv.
  KeypointStyle keypoint_style = KeypointStyle::kVlfeat;

  // Enlarge the input 2x before building the first octave (octave -1), as Lowe and OpenCV do; finds
  // ~3-4x more (small) keypoints at ~4x the pyramid cost. [L04 sec. 3.3]
  bool upsample_first_octave = true;
  // Blur of the base image of every octave, in that octave's pixels (sigma0 [L04 sec. 3.3]). (0.5, 10].
  double sigma = 1.6;
  // Blur assumed already present in the input image (camera / anti-aliasing), pixels. [0, sigma).
  double assumed_blur = 0.5;
  // Scales sampled per octave (S [L04 sec. 3.2]); each octave has S+3 Gaussians and S+2 DoGs. [1, 8].
  int intervals = 3;
  // Minimum |DoG| contrast at the refined extremum, before division by `intervals` (OpenCV's
  // contrastThreshold; the effective threshold is contrast_threshold / intervals, for image values in
  // [0, 1]). [L04 sec. 4] uses 0.03 with S = 3 in different units; cv::SIFT's default is 0.04. 0.034
  // measured better than 0.04 on the three retrieval dev sets (eval/results/accuracy.md, "Extractor
  // settings"), for 10-20% more features. [0, 1].
  double contrast_threshold = 0.034;
  // r in the edge test tr(H)^2 / det(H) < (r+1)^2 / r on the 2x2 spatial Hessian [L04 sec. 4.1]. > 1.
  double edge_threshold = 10.0;
  // Keep only the this many keypoints with the largest |response| (ties broken by position, so the
  // result is deterministic). Unset: keep all. >= 1 when set.
  std::optional<int> max_features;
  // Descriptor form written into FeatureSet::descriptors. RootSIFT [AZ12] is the product default (every
  // command, the server, eval): it retrieves and matches better in every measurement here (README). Raw
  // SIFT (kSift) is for formats that demand it, e.g. COLMAP's feature_importer (`--descriptor sift`).
  DescriptorKind descriptor = DescriptorKind::kRootSift;
  // A peak of the orientation histogram >= this fraction of the highest gives its own keypoint
  // [L04 sec. 5]. (0, 1].
  double orientation_peak_ratio = 0.8;
  // Gaussian kernels are truncated at this many sigmas (radius = ceil(k * sigma)). OpenCV uses 4 for
  // float images. 3 gives the blurs about a quarter fewer taps but the extraction only 1-3% less CPU time,
  // with slightly different keypoints (eval/results/sift.md). [2.5, 6].
  double kernel_radius_sigmas = 4.0;
  // Upper bound on octaves (counting octave -1 when upsampling); unset = until the image is too small.
  std::optional<int> max_octaves;
  // Upright features [P09]: every keypoint takes orientation 0 (the image's +x axis) instead of its
  // dominant gradient directions, so one keypoint per extremum and descriptors that tell a shape from
  // its rotation. For collections photographed upright (buildings, street views): it raised the Paris
  // subset's mAP and lowered the rotated objects of groups_dev and groups_hard a lot
  // (eval/results/accuracy.md, "Upright features"), hence off by default. Written as `upright=1` in
  // Describe(); absent means off.
  bool upright = false;
  // Width of each of the descriptor's 4 x 4 cells in keypoint sigmas (step 7; VLFeat's `magnif`; Lowe's
  // 3). 4 gives 3-21% more correct matches on the Oxford affine pairs and a higher groups_hard mAP with
  // each of three vocabulary seeds, at a slower search (eval/results/accuracy.md, "Descriptor window").
  // 3 is written as no field in Describe(): a description without the field means 3. [1, 10].
  double descriptor_magnification = 3.0;
  // The descriptor samples every this-many rows of its window (every column of a sampled row). With
  // cells 4 sigmas wide (at least ~6 pixels) every second row gives the same matching scores as every
  // row at half the cost. 1 (every row) is written as no field in Describe(). [1, 4].
  int descriptor_row_step = 1;
  // Where the descriptor takes its gradients (see DescriptorSampling). descriptor_row_step applies to
  // kPixels only; Check() refuses another value with kGrid. Written as `sampling=grid` in Describe();
  // absent means kPixels.
  DescriptorSampling descriptor_sampling = DescriptorSampling::kPixels;
  // With KeypointStyle::kVlfeat, the refinement also moves the sample one scale layer while the scale
  // offset exceeds 0.6 (within the octave's layers 1..intervals), as it moves one pixel in space;
  // candidates that converge onto the same sample are kept once. Pair matching extracts with it
  // (api::PairMatchExtractorOptions): `oxbow match`'s homography on graf 1 -> 3 came out 1.04 px from
  // the true one at the corners, against 3.44 px without (eval/results/matching.md). The index's
  // extractor leaves it off: with the default vocabulary seed the Paris subset's mAP was 0.035 lower;
  // over three seeds the mean mAP was 0.012 lower on Paris, level on groups_dev and 0.008 higher on
  // groups_hard (also in eval/results/matching.md). kOpenCv always moves in scale; Check() refuses
  // true with it. Written as `refine_scale=1` in Describe(); absent means off.
  bool refine_in_scale = false;

  // ---- Performance: does not change the output. ----

  // Worker threads; 0 = all hardware threads. The output is identical for every value. [0, 256].
  int num_threads = 0;
  // Each thread that calls Extract keeps its pyramid buffers (28 * W * H floats with upsampling and 3
  // intervals: ~88 MB for a 1024x768 image) for its next call, unless they exceed this many MiB; 0
  // frees them after every call. Reuse saves the page faults (and kernel zeroing) of fresh memory where the
  // allocator hands freed memory back to the kernel; under sift_benchmark's policy, which keeps freed
  // memory in the process, a cold call measured 0.93-1.05x a warm one (eval/results/sift.md, "Time"). [0, 65536].
  int thread_cache_mib = 256;

  // Error message for an invalid setting, or nullopt.
  [[nodiscard]] std::optional<std::string> Check() const;
  // Canonical "key=value;..." of every setting that changes the output (not num_threads), prefixed by
  // the implementation version, e.g. "oxbow-sift/1;upsample=1;sigma=1.6;...".
  std::string Describe() const;
  // FNV-1a 64-bit hash of Describe(); stable across runs, machines and builds. vocab/ and index/ store
  // it to refuse mixing features from different extractor settings.
  uint64_t Fingerprint() const;
  // Parses a Describe() text back into options (performance fields keep their defaults; an absent
  // `keypoints` field is kOpenCv). kIncompatible,
  // with a message, for text this build does not describe identically (another version, an unknown or
  // malformed field, values Check() refuses): the round trip Describe(FromDescription(d)) == d holds.
  [[nodiscard]] static Result<SiftOptions> FromDescription(const std::string& description);
};

// A caller's signal to abandon an extraction (a deadline passed, the client hung up, the server stops).
// Polled on the extracting thread between stages: after decoding, every 64 rows of the calling thread's
// strip of each octave's blurs and extrema scan, and before the orientations and the descriptors of
// every octave, so a stop takes effect
// within one stage: measured at most ~0.35 s on one core for a 1600 x 1200 image of fine noise (72,000
// keypoints, 1.2 s in all); a photo's stages are shorter. The decode itself is not interrupted (its own
// limits bound it, image.h). Must be cheap, callable from that thread, and monotonic: once true it
// stays true.
using StopRequested = std::function<bool()>;

// Extracts SIFT keypoints and descriptors. Immutable after Create; Extract* are thread-safe (may be
// called concurrently from several threads; each calling thread has its own scratch memory, kept
// between its calls up to SiftOptions::thread_cache_mib).
//
// Cost: O(W * H) time and memory for the pyramid (with upsampling 4 * W * H floats per plane of octave
// -1, intervals + 4 such planes = 28 * W * H floats at peak with the default 3 intervals), plus
// O(keypoints) for orientations and descriptors.
class SiftExtractor {
 public:
  // kInvalidArgument when options.Check() fails.
  [[nodiscard]] static Result<SiftExtractor> Create(const SiftOptions& options);

  // Keypoints (in `image` pixel coordinates) and descriptors (options().descriptor form). Deterministic
  // and identical for any num_threads. Images too small for one octave (< 8 pixels on a side) give
  // an empty set; an empty image gives an empty set.
  FeatureSet Extract(const GrayImage& image) const;

  // Decodes then extracts; keypoint coordinates and scales are mapped back to the ORIGINAL image (before
  // DecodeOptions::max_image_side_px downscaling, after EXIF orientation), and image_width/height are
  // the original size. Errors as DecodeImage, and kResourceExhausted when `stop` (may be empty) turned
  // true before the extraction finished (the caller knows why and says so).
  [[nodiscard]] Result<FeatureSet> ExtractFromBytes(std::span<const uint8_t> bytes, const DecodeOptions& decode = {},
                                                    const StopRequested& stop = {}) const;
  [[nodiscard]] Result<FeatureSet> ExtractFromFile(const std::string& path, const DecodeOptions& decode = {}) const;
  // Extracts from an already decoded image; coordinates mapped to the original image as above.
  FeatureSet ExtractFromDecoded(const DecodedImage& decoded) const;

  const SiftOptions& options() const { return options_; }

 private:
  explicit SiftExtractor(const SiftOptions& options) : options_(options) {}
  SiftOptions options_;
};

// Converts one SIFT descriptor (L2-normalised, non-negative) in place to RootSIFT: divide by its L1
// norm, take the square root of each element. The result has unit L2 norm. An all-zero descriptor stays
// zero. [AZ12]
void ToRootSift(std::span<float> descriptor);

// Converts every descriptor of `features` to bytes: out[i] = min(255, round(512 * d[i])), the scaling
// OpenCV and COLMAP use (SIFT elements are <= ~0.45 after clipping and renormalisation, RootSIFT
// elements likewise small, so saturation is rare). `out` is resized to size() * kDescriptorDim.
void DescriptorsToUint8(const FeatureSet& features, std::vector<uint8_t>* out);

}  // namespace oxbow::sift
