// fuzz_seeds OUT_DIR: writes a seed corpus per fuzz target into OUT_DIR/<target>/ (scripts/fuzz.sh runs
// it before fuzzing). Seeds come from real files and real oxbow writers: opencv-doc photos downscaled
// and re-encoded in every format DecodeImage reads, feature files of features extracted from them, a
// vocabulary file, catalogue BLOBs, whole index catalogues built with the fuzz vocabulary, parameter
// maps; plus damaged copies of each (truncated, bit-flipped, zeroed). Deterministic (fixed seeds).
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cstddef>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "index/storage/feature_store.h"
#include "sift/base/binary_io.h"
#include "sift/features_io.h"
#include "sift/image.h"
#include "sift/sift.h"
#include "tests/fuzz/fuzz_support.h"
#include "tests/support/hostile_images.h"

namespace fs = std::filesystem;
using namespace oxbow;

namespace {

using Bytes = std::vector<uint8_t>;

void Write(const fs::path& dir, const std::string& name, const Bytes& bytes) {
  fs::create_directories(dir);
  std::ofstream out(dir / name, std::ios::binary);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
}

Bytes ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return Bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

Bytes Prefixed(uint8_t mode, const Bytes& bytes) {
  Bytes out{mode};
  out.insert(out.end(), bytes.begin(), bytes.end());
  return out;
}

// The seed itself plus damaged copies: cut in half, 8 bit flips, a zeroed run in the middle.
void WriteWithDamage(const fs::path& dir, const std::string& name, const Bytes& bytes, size_t keep_prefix = 0) {
  Write(dir, name, bytes);
  if (bytes.size() <= keep_prefix + 2) return;
  Write(dir, name + ".truncated", Bytes(bytes.begin(), bytes.begin() + static_cast<long>(keep_prefix + (bytes.size() - keep_prefix) / 2)));
  std::mt19937 rng(static_cast<uint32_t>(bytes.size()));
  Bytes flipped = bytes;
  std::uniform_int_distribution<size_t> at(keep_prefix, bytes.size() - 1);
  for (int i = 0; i < 8; ++i) flipped[at(rng)] ^= static_cast<uint8_t>(1u << (rng() % 8));
  Write(dir, name + ".flipped", flipped);
  Bytes zeroed = bytes;
  const size_t start = keep_prefix + (bytes.size() - keep_prefix) / 3;
  for (size_t i = start; i < std::min(bytes.size(), start + 64); ++i) zeroed[i] = 0;
  Write(dir, name + ".zeroed", zeroed);
}

Bytes Encode(const cv::Mat& image, const std::string& ext, const std::vector<int>& params = {}) {
  std::vector<uint8_t> out;
  if (!cv::imencode(ext, image, out, params)) {
    std::fprintf(stderr, "fuzz_seeds: cannot encode %s\n", ext.c_str());
    std::exit(1);
  }
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: fuzz_seeds OUT_DIR\n");
    return 2;
  }
  const fs::path out = argv[1];
  const fs::path photos = "/usr/share/doc/opencv-doc/examples/data";

  // Images: small re-encodings of real photos (grey and colour) in every decoded format.
  std::vector<Bytes> small_jpegs;
  int n = 0;
  for (const char* name : {"box.png", "graf1.png", "leuvenA.jpg", "butterfly.jpg"}) {
    cv::Mat image = cv::imread((photos / name).string(), cv::IMREAD_COLOR);
    if (image.empty()) {
      std::fprintf(stderr, "fuzz_seeds: cannot read %s (install opencv-doc)\n", (photos / name).c_str());
      return 1;
    }
    const double s = 72.0 / std::max(image.cols, image.rows);
    cv::resize(image, image, cv::Size(), s, s, cv::INTER_AREA);
    cv::Mat grey;
    cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    const fs::path dir = out / "image_decode_fuzz";
    const std::string stem = "photo" + std::to_string(n++);
    small_jpegs.push_back(Encode(image, ".jpg", {cv::IMWRITE_JPEG_QUALITY, 60}));
    WriteWithDamage(dir, stem + ".jpg", small_jpegs.back());
    WriteWithDamage(dir, stem + "_progressive.jpg", Encode(grey, ".jpg", {cv::IMWRITE_JPEG_PROGRESSIVE, 1}));
    WriteWithDamage(dir, stem + ".png", Encode(image, ".png"));
    WriteWithDamage(dir, stem + "_grey.png", Encode(grey, ".png"));
    WriteWithDamage(dir, stem + ".bmp", Encode(image, ".bmp"));
    WriteWithDamage(dir, stem + ".pgm", Encode(grey, ".pgm"));
    WriteWithDamage(dir, stem + ".ppm", Encode(image, ".ppm"));
    WriteWithDamage(dir, stem + ".tiff", Encode(image, ".tiff"));
    WriteWithDamage(dir, stem + ".webp", Encode(image, ".webp", {cv::IMWRITE_WEBP_QUALITY, 50}));
    if (n == 1) {
      // Hostile shapes: scan-heavy progressive JPEGs (valid scans over the limit, empty scans
      // over a large frame), TIFFs with repeated dimension tags and with a strip that does not decompress.
      const Bytes samples(grey.datastart, grey.dataend);
      WriteWithDamage(dir, stem + "_128_scans.jpg", sift::testing::ProgressiveJpegWithScans(samples, grey.cols, grey.rows, 128));
      WriteWithDamage(dir, stem + "_100_scans.jpg", sift::testing::ProgressiveJpegWithScans(samples, grey.cols, grey.rows, 100));
      Write(dir, "empty_scans.jpg", sift::testing::JpegOfEmptyScans(1500, 1500, 400));
      Write(dir, "tiff_repeated_dimensions_big_first.tiff", sift::testing::TiffWithRepeatedDimensions({32000, 32000}, {1, 1}));
      Write(dir, "tiff_repeated_dimensions_small_first.tiff", sift::testing::TiffWithRepeatedDimensions({8, 8}, {32000, 32000}));
      Write(dir, "tiff_garbage_deflate_strip.tiff", sift::testing::TiffWithGarbageDeflateStrip(64, 64));
    }
  }

  // Features of one photo (a few dozen keypoints): feature files and catalogue BLOBs.
  sift::SiftOptions sift_options;
  sift_options.max_features = 24;
  sift_options.num_threads = 1;
  sift_options.descriptor = sift::DescriptorKind::kRootSift;
  auto extractor = sift::SiftExtractor::Create(sift_options);
  auto features = extractor->ExtractFromBytes(small_jpegs[1]);
  if (!features || features->size() == 0) {
    std::fprintf(stderr, "fuzz_seeds: extraction failed\n");
    return 1;
  }
  {
    const fs::path dir = out / "feature_file_fuzz";
    sift::FeatureFile file{*features, sift_options.Fingerprint(), sift_options.Describe()};
    const Bytes payload = sift::EncodeFeaturePayload(file);
    WriteWithDamage(dir, "payload", Prefixed(0, payload), 1);
    WriteWithDamage(dir, "wrapped", Prefixed(2, payload), 1);
    const fs::path path = fuzz::ScratchDir() / "seed.oxfeat";
    fuzz::CheckSetup(sift::WriteFeatureFile(path.string(), file), "write feature file");
    WriteWithDamage(dir, "file", Prefixed(1, ReadBytes(path)), 1);
  }
  {
    const fs::path dir = out / "vocabulary_file_fuzz";
    const fs::path path = fuzz::ScratchDir() / "seed.oxvoc";
    std::vector<float> centroids(features->descriptors.begin(), features->descriptors.begin() + 6 * sift::kDescriptorDim);
    auto vocabulary = vocab::Vocabulary::FromCentroids(centroids, sift::kDescriptorDim, sift::DescriptorKind::kRootSift,
                                                       sift_options.Describe());
    fuzz::CheckSetup(vocabulary ? vocabulary->Write(path.string()) : Status(std::unexpected(vocabulary.error())),
                     "write vocabulary");
    const Bytes file = ReadBytes(path);
    WriteWithDamage(dir, "file", Prefixed(0, file), 1);
    WriteWithDamage(dir, "wrapped", Prefixed(1, Bytes(file.begin() + io::kHeaderBytes, file.end())), 1);
  }
  {
    const fs::path dir = out / "packed_features_fuzz";
    std::vector<uint32_t> words(features->size());
    fuzz::FuzzVocabulary().Quantize(features->descriptors, words);
    const Bytes blob =
        index::PackedFeatures::Pack(features->keypoints, words, features->image_width, features->image_height).Serialize();
    WriteWithDamage(dir, "blob", Prefixed(0, blob), 1);
    Bytes wrapped{1};
    for (int v : {features->image_width, features->image_height}) {
      for (int shift = 24; shift >= 0; shift -= 8) wrapped.push_back(static_cast<uint8_t>(v >> shift));
    }
    wrapped.insert(wrapped.end(), blob.begin() + 24, blob.end());
    WriteWithDamage(dir, "wrapped", wrapped, 9);
  }
  {
    // Whole catalogues: an empty index and one with three images, each built with the fuzz vocabulary.
    const fs::path dir = out / "index_catalogue_fuzz";
    for (int images : {0, 3}) {
      const fs::path index_dir = fuzz::ScratchDir() / ("seed-index-" + std::to_string(images));
      auto index = index::ImageIndex::Create(index_dir.string(), fuzz::FuzzVocabulary(),
                                             fuzz::FuzzVocabulary().extractor_settings());
      if (!index) fuzz::CheckSetup(std::unexpected(index.error()), "create index");
      sift::FeatureSet query = fuzz::FuzzQueryFeatures();
      for (int i = 0; i < images; ++i) {
        auto added = (*index)->Add("image-" + std::to_string(i), query, index::ImageInfo{"seed.jpg", R"({"n":1})", ""});
        if (!added) fuzz::CheckSetup(std::unexpected(added.error()), "add image");
        query.keypoints.pop_back();
        query.descriptors.resize(query.descriptors.size() - sift::kDescriptorDim);
      }
      index->reset();
      WriteWithDamage(dir, "catalogue" + std::to_string(images) + ".sqlite", ReadBytes(index_dir / "catalogue.sqlite"));
    }
  }
  {
    const fs::path dir = out / "api_params_fuzz";
    auto pairs = [](std::vector<std::pair<uint8_t, std::string>> list) {
      Bytes b;
      for (const auto& [name, value] : list) {
        b.push_back(name);
        b.push_back(static_cast<uint8_t>(value.size()));
        b.insert(b.end(), value.begin(), value.end());
      }
      return b;
    };
    Write(dir, "search", pairs({{0, "10"}, {1, "true"}, {2, "10,20,30.5,40"}, {3, "1"}, {4, "5"}}));
    Write(dir, "add", pairs({{5, "img-1"}, {6, "no"}, {7, R"({"title":"x","tags":[1,2.5,null,{"a":true}]})"}}));
    Write(dir, "list", pairs({{8, "100"}, {9, "1000"}}));
    Write(dir, "match", pairs({{10, "homography"}, {11, "0.8"}, {12, "on"}, {13, "kdtree"}}));
  }
  {
    // Raw HTTP requests for every route, multipart ones carrying a small real JPEG.
    const fs::path dir = out / "http_request_fuzz";
    auto text = [](const std::string& t) { return Bytes(t.begin(), t.end()); };
    auto multipart = [&](const std::string& head, const std::vector<std::pair<std::string, Bytes>>& parts) {
      const std::string boundary = "oxbowfuzzboundary";
      Bytes body;
      for (const auto& [name, value] : parts) {
        const std::string disposition = name == "image" || name == "a" || name == "b"
                                            ? "form-data; name=\"" + name + "\"; filename=\"x.jpg\""
                                            : "form-data; name=\"" + name + "\"";
        const std::string part_head = "--" + boundary + "\r\nContent-Disposition: " + disposition + "\r\n\r\n";
        body.insert(body.end(), part_head.begin(), part_head.end());
        body.insert(body.end(), value.begin(), value.end());
        body.push_back('\r');
        body.push_back('\n');
      }
      const std::string tail = "--" + boundary + "--\r\n";
      body.insert(body.end(), tail.begin(), tail.end());
      Bytes request = text(head + "\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=" + boundary +
                           "\r\nContent-Length: " + std::to_string(body.size()) + "\r\n\r\n");
      request.insert(request.end(), body.begin(), body.end());
      return request;
    };
    const Bytes& jpeg = small_jpegs[0];
    Write(dir, "healthz", text("GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n"));
    Write(dir, "list", text("GET /v1/images?offset=0&limit=5 HTTP/1.1\r\nHost: x\r\n\r\n"));
    Write(dir, "get", text("GET /v1/images/box HTTP/1.1\r\nHost: x\r\n\r\n"));
    Write(dir, "similar", text("GET /v1/images/box/similar?top_k=3&rerank=10&bbox=1,2,50,60&qe=false HTTP/1.1\r\nHost: x\r\n\r\n"));
    Write(dir, "delete", text("DELETE /v1/images/nothere HTTP/1.1\r\nHost: x\r\n\r\n"));
    Write(dir, "stats", text("GET /v1/stats HTTP/1.1\r\nHost: x\r\n\r\n"));
    Write(dir, "search", multipart("POST /v1/search?top_k=5 HTTP/1.1", {{"image", jpeg}, {"bbox", text("0,0,40,40")}}));
    Write(dir, "add", multipart("POST /v1/images HTTP/1.1",
                                {{"id", text("new")}, {"replace", text("true")}, {"metadata", text(R"({"a":[1,{"b":null}]})")}, {"image", jpeg}}));
    Write(dir, "match", multipart("POST /v1/match?model=similarity HTTP/1.1", {{"a", jpeg}, {"b", small_jpegs[1]}}));
    Bytes raw = text("POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: image/jpeg\r\nContent-Length: " +
                     std::to_string(jpeg.size()) + "\r\n\r\n");
    raw.insert(raw.end(), jpeg.begin(), jpeg.end());
    Write(dir, "search_raw", raw);
    // Framing and flood shapes the server refuses before httplib parses them (server/http/request_guard.h).
    Bytes chunked = text("POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: image/jpeg\r\nTransfer-Encoding: chunked\r\n\r\n");
    for (size_t at = 0; at < jpeg.size(); at += 4096) {
      const size_t chunk = std::min<size_t>(4096, jpeg.size() - at);
      char size_line[32];
      std::snprintf(size_line, sizeof size_line, "%zx\r\n", chunk);
      const Bytes line = text(size_line);
      chunked.insert(chunked.end(), line.begin(), line.end());
      chunked.insert(chunked.end(), jpeg.begin() + static_cast<std::ptrdiff_t>(at), jpeg.begin() + static_cast<std::ptrdiff_t>(at + chunk));
      chunked.push_back('\r');
      chunked.push_back('\n');
    }
    const Bytes last = text("0\r\n\r\n");
    chunked.insert(chunked.end(), last.begin(), last.end());
    Write(dir, "search_chunked", chunked);
    Write(dir, "gzip_body", text("POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Encoding: gzip\r\nContent-Length: 10\r\n\r\n"
                                 "\x1f\x8b\x08" "deflate"));
    Write(dir, "duplicate_length", text("POST /v1/search HTTP/1.1\r\nContent-Length: 4\r\nContent-Length: 40\r\n\r\nabcd"));
    Write(dir, "length_and_chunked", text("POST /v1/search HTTP/1.1\r\nContent-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n"));
    std::string flood = "GET /v1/stats HTTP/1.1\r\n";
    for (int i = 0; i < 150; ++i) flood += "X-Flood-" + std::to_string(i) + ": " + std::string(40, 'a') + "\r\n";
    Write(dir, "header_flood", text(flood + "\r\n"));
  }
  std::printf("fuzz_seeds: corpora written to %s\n", out.c_str());
  return 0;
}
