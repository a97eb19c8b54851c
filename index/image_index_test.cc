#include "index/image_index.h"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <numeric>
#include <optional>
#include <numbers>
#include <random>
#include <set>
#include <thread>

#include <csignal>
#include <functional>
#include <future>
#include <string_view>
#include <sched.h>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/storage/feature_store.h"
#include "index/search/pipeline.h"
#include "index/search/source.h"

namespace oxbow::index {
namespace {

namespace fs = std::filesystem;
constexpr int kWords = 256;

// Image `id`'s stored keypoints and words, as a search reads them (kNotFound).
Result<search::RegionFeatures> FeaturesOf(const ImageIndex& index, const std::string& id) {
  const std::unique_ptr<search::Source> source = index.OpenSearch();
  auto ref = source->Find(id);
  if (!ref) return std::unexpected(ref.error());
  if (!*ref) return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
  constexpr float kAll = std::numeric_limits<float>::infinity();
  const std::array<float, 4> everywhere = {-kAll, -kAll, kAll, kAll};
  auto features = source->Features(std::span(&**ref, 1), std::span(&everywhere, 1), {});
  if (!features) return std::unexpected(features.error());
  return std::move(features->front());
}

// A vocabulary of kWords random unit centroids; features are made by perturbing a centroid slightly so
// the quantiser is known to return that word.
class Fixture : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("oxbow_index_test_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    vocabulary_ = MakeVocabulary(1);
  }
  void TearDown() override { fs::remove_all(dir_); }

  static vocab::Vocabulary MakeVocabulary(uint64_t seed, const std::string& settings = "test-extractor/1") {
    std::mt19937_64 rng(seed);
    std::normal_distribution<float> g(0, 1);
    std::vector<float> c(static_cast<size_t>(kWords) * 128);
    for (int w = 0; w < kWords; ++w) {
      double n = 0;
      for (int d = 0; d < 128; ++d) {
        c[w * 128 + d] = g(rng);
        n += c[w * 128 + d] * c[w * 128 + d];
      }
      for (int d = 0; d < 128; ++d) c[w * 128 + d] /= static_cast<float>(std::sqrt(n));
    }
    auto v = vocab::Vocabulary::FromCentroids(std::move(c), 128, sift::DescriptorKind::kRootSift, settings);
    EXPECT_TRUE(v.has_value()) << (v ? "" : v.error().ToString());
    return *v;
  }

  // Features with the given words at the given keypoints.
  sift::FeatureSet Features(const std::vector<uint32_t>& words, const std::vector<sift::Keypoint>& keypoints,
                            int width = 640, int height = 480) const {
    sift::FeatureSet f;
    f.image_width = width;
    f.image_height = height;
    f.kind = sift::DescriptorKind::kRootSift;
    f.keypoints = keypoints;
    const auto centroids = vocabulary_.centroids();
    for (uint32_t w : words) {
      f.descriptors.insert(f.descriptors.end(), centroids.begin() + w * 128, centroids.begin() + (w + 1) * 128);
    }
    return f;
  }

  // An image of n random features (word, position, scale, orientation).
  sift::FeatureSet RandomImage(std::mt19937_64& rng, int n, int width = 640, int height = 480) const {
    std::uniform_int_distribution<uint32_t> word(0, kWords - 1);
    std::uniform_real_distribution<float> x(0, static_cast<float>(width - 1)), y(0, static_cast<float>(height - 1));
    std::uniform_real_distribution<float> s(1.5f, 12.0f), o(0, 6.28f);
    std::vector<uint32_t> words;
    std::vector<sift::Keypoint> kps;
    for (int i = 0; i < n; ++i) {
      words.push_back(word(rng));
      kps.push_back({x(rng), y(rng), s(rng), o(rng), 1.0f, 0});
    }
    return Features(words, kps, width, height);
  }

  // `count` images of n random features each (RandomImage).
  std::vector<sift::FeatureSet> RandomImages(std::mt19937_64& rng, int count, int n) const {
    std::vector<sift::FeatureSet> out;
    out.reserve(static_cast<size_t>(count));
    for (int i = 0; i < count; ++i) out.push_back(RandomImage(rng, n));
    return out;
  }

  std::unique_ptr<ImageIndex> CreateIndex(const IndexOptions& options = {}) {
    auto index = ImageIndex::Create(dir_.string(), vocabulary_, "test-extractor/1", options);
    EXPECT_TRUE(index.has_value()) << (index ? "" : index.error().ToString());
    return std::move(*index);
  }

  // An index of images "a" and "b" (80 random features each) and 10 noise images; *query gets 30 of
  // a's features on the left half (x < 300, DoG responses +-a_response) then 70 of b's on the right
  // half (+-b_response).
  std::unique_ptr<ImageIndex> TwoObjectIndex(sift::FeatureSet* query, float a_response, float b_response) {
    auto index = CreateIndex();
    std::mt19937_64 rng(4);
    const auto a = RandomImage(rng, 80), b = RandomImage(rng, 80);
    EXPECT_TRUE(index->Add("a", a, {}));
    EXPECT_TRUE(index->Add("b", b, {}));
    for (int i = 0; i < 10; ++i) EXPECT_TRUE(index->Add("noise" + std::to_string(i), RandomImage(rng, 80), {}));
    *query = Features({}, {}, 640, 480);
    auto append = [&](const sift::FeatureSet& src, size_t count, float x0, float response) {
      for (size_t i = 0; i < count; ++i) {
        sift::Keypoint k = src.keypoints[i];
        k.x = x0 + std::fmod(k.x, 290.0f);
        k.response = (i % 2 == 0 ? 1.0f : -1.0f) * response;  // the magnitude counts
        query->keypoints.push_back(k);
        const auto d = src.Descriptor(i);
        query->descriptors.insert(query->descriptors.end(), d.begin(), d.end());
      }
    };
    append(a, 30, 0, a_response);
    append(b, 70, 330, b_response);
    return index;
  }

  fs::path dir_;
  vocab::Vocabulary vocabulary_ = MakeVocabulary(1);
};

QueryOptions Opts(int top_k, int rerank_depth, bool query_expansion = false,
                  std::optional<std::array<float, 4>> region = std::nullopt) {
  QueryOptions o;
  o.top_k = top_k;
  o.rerank_depth = rerank_depth;
  o.query_expansion = query_expansion;
  o.region = region;
  return o;
}

ImageInfo Info(std::string source_path = "", std::string metadata_json = "", std::string settings = "") {
  ImageInfo info;
  info.source_path = std::move(source_path);
  info.metadata_json = std::move(metadata_json);
  info.extractor_settings = std::move(settings);
  return info;
}

std::map<std::string, double> ScoresById(const QueryResponse& r) {
  std::map<std::string, double> out;
  for (const auto& x : r.results) out[x.id] = x.score;
  return out;
}

// Both ways of holding a checkpoint file give its exact bytes; a missing file is kNotFound.
TEST(MappedFileTest, ResidentAndMappedFilesHoldTheFileBytes) {
  const fs::path dir = fs::temp_directory_path() / ("oxbow-mapped-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  std::string content(3u << 20, '\0');  // over a 2 MB huge page, not a multiple of it
  for (size_t i = 0; i < content.size(); ++i) content[i] = static_cast<char>((i * 2654435761u) >> 13);
  std::ofstream((dir / "f").string(), std::ios::binary) << content;
  std::ofstream((dir / "empty").string(), std::ios::binary).flush();
  for (const MappedFile::Use use : {MappedFile::Use::kRandom, MappedFile::Use::kResident}) {
    auto file = MappedFile::Open((dir / "f").string(), use);
    ASSERT_TRUE(file) << file.error().ToString();
    const auto bytes = (*file)->bytes();
    EXPECT_TRUE(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()) == content);
    auto empty = MappedFile::Open((dir / "empty").string(), use);
    ASSERT_TRUE(empty) << empty.error().ToString();
    EXPECT_TRUE((*empty)->bytes().empty());
    auto missing = MappedFile::Open((dir / "missing").string(), use);
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
  }
  fs::remove_all(dir);
}

TEST_F(Fixture, AddGetListRemove) {
  auto index = CreateIndex();
  std::mt19937_64 rng(1);
  ASSERT_TRUE(index->Add("b", RandomImage(rng, 50), Info("/x/b.jpg", R"({"k":1})")));
  ASSERT_TRUE(index->Add("a", RandomImage(rng, 40), {}));
  const auto dup = index->Add("a", RandomImage(rng, 10), {});
  ASSERT_FALSE(dup);
  EXPECT_EQ(dup.error().code, ErrorCode::kAlreadyExists);

  const auto b = index->Get("b");
  ASSERT_TRUE(b);
  EXPECT_EQ(b->source_path, "/x/b.jpg");
  EXPECT_EQ(b->metadata_json, R"({"k":1})");
  EXPECT_EQ(b->num_features, 50u);
  EXPECT_EQ(b->width, 640);
  EXPECT_GT(b->added_unix_ms, 0);

  const auto list = index->List(0, 10);
  ASSERT_TRUE(list);
  ASSERT_EQ(list->size(), 2u);
  EXPECT_EQ((*list)[0].id, "a");
  EXPECT_EQ(index->List(1, 10)->size(), 1u);

  const auto stats = index->Stats();
  EXPECT_EQ(stats.num_images, 2u);
  EXPECT_EQ(stats.num_features, 90u);
  EXPECT_GT(stats.bytes_per_feature, 0);

  ASSERT_TRUE(index->Remove("a"));
  EXPECT_EQ(index->Get("a").error().code, ErrorCode::kNotFound);
  EXPECT_EQ(index->Remove("a").error().code, ErrorCode::kNotFound);
  EXPECT_EQ(index->Stats().num_images, 1u);
}

TEST_F(Fixture, BadInputIsAnErrorValue) {
  auto index = CreateIndex();
  std::mt19937_64 rng(2);
  auto f = RandomImage(rng, 10);
  EXPECT_EQ(index->Add("", f, {}).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(index->Add("a\nb", f, {}).error().code, ErrorCode::kInvalidArgument);
  auto wrong_kind = f;
  wrong_kind.kind = sift::DescriptorKind::kSift;
  EXPECT_EQ(index->Add("x", wrong_kind, {}).error().code, ErrorCode::kIncompatible);
  auto short_desc = f;
  short_desc.descriptors.pop_back();
  EXPECT_EQ(index->Add("x", short_desc, {}).error().code, ErrorCode::kInvalidArgument);
  auto no_size = f;
  no_size.image_width = 0;
  EXPECT_EQ(index->Add("x", no_size, {}).error().code, ErrorCode::kInvalidArgument);
  const auto other = index->Add("x", f, Info("", "", "other-extractor/2"));
  ASSERT_FALSE(other);
  EXPECT_EQ(other.error().code, ErrorCode::kIncompatible);
  EXPECT_NE(other.error().message.find("other-extractor/2"), std::string::npos);
  EXPECT_EQ(index->Query(f, Opts(0, 0)).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(index->Query(f, Opts(20, 0, false, std::array<float, 4>{5, 5, 1, 1})).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(index->Stats().num_images, 0u);
  // A query on an empty index is an empty list.
  const auto r = index->Query(f, {});
  ASSERT_TRUE(r);
  EXPECT_TRUE(r->results.empty());
}

TEST_F(Fixture, CreateRefusesExistingIndexAndForeignExtractor) {
  CreateIndex();
  EXPECT_EQ(ImageIndex::Create(dir_.string(), vocabulary_, "test-extractor/1").error().code, ErrorCode::kAlreadyExists);
  const auto other = ImageIndex::Create((dir_ / "sub").string(), vocabulary_, "other/1");
  ASSERT_FALSE(other);
  EXPECT_EQ(other.error().code, ErrorCode::kIncompatible);
  EXPECT_EQ(ImageIndex::Open((dir_ / "missing").string()).error().code, ErrorCode::kNotFound);
}

TEST_F(Fixture, SpatialReRankingFindsTheTransformedImage) {
  // Without a stop list (a fraction of 1 drops no word, whatever the default), so that an image's own
  // query vector is its whole tf-idf vector (cosine 1); the end of the test shows the difference.
  IndexOptions no_stop_list;
  no_stop_list.max_document_frequency = 1.0;
  no_stop_list.stop_list_min_images = 0;
  auto index = CreateIndex(no_stop_list);
  std::mt19937_64 rng(3);
  std::vector<sift::FeatureSet> images;
  for (int i = 0; i < 30; ++i) {
    images.push_back(RandomImage(rng, 150));
    ASSERT_TRUE(index->Add("img" + std::to_string(i), images.back(), {}));
  }
  // Query: image 7 seen at scale 0.5, rotated 30 degrees and shifted, 60% of its features, plus clutter.
  const sift::FeatureSet& target = images[7];
  const double angle = std::numbers::pi / 6, scale = 0.5;
  const double ca = std::cos(angle) * scale, sa = std::sin(angle) * scale;
  std::vector<uint32_t> words;
  std::vector<sift::Keypoint> kps;
  std::vector<uint32_t> target_words(target.size());
  vocabulary_.Quantize(target.descriptors, target_words);
  for (size_t i = 0; i < target.size(); i += 5) {
    for (size_t j = i; j < std::min(target.size(), i + 3); ++j) {
      const auto& k = target.keypoints[j];
      sift::Keypoint q = k;
      q.x = static_cast<float>(ca * k.x - sa * k.y + 300);
      q.y = static_cast<float>(sa * k.x + ca * k.y + 50);
      q.scale = static_cast<float>(k.scale * scale);
      q.orientation = static_cast<float>(std::fmod(k.orientation + angle, 2 * std::numbers::pi));
      words.push_back(target_words[j]);
      kps.push_back(q);
    }
  }
  const auto clutter = RandomImage(rng, 60, 800, 800);
  std::vector<uint32_t> clutter_words(clutter.size());
  vocabulary_.Quantize(clutter.descriptors, clutter_words);
  words.insert(words.end(), clutter_words.begin(), clutter_words.end());
  kps.insert(kps.end(), clutter.keypoints.begin(), clutter.keypoints.end());
  const auto query = Features(words, kps, 800, 800);

  const auto r = index->Query(query, Opts(5, 30));
  ASSERT_TRUE(r) << r.error().ToString();
  ASSERT_FALSE(r->results.empty());
  const QueryResult& best = r->results[0];
  EXPECT_EQ(best.id, "img7");
  EXPECT_TRUE(best.verified);
  EXPECT_GE(best.inliers, 40);
  // db_from_query is the inverse similarity: scale 2, rotation -30 degrees.
  const auto& m = best.db_from_query.m;
  EXPECT_NEAR(std::hypot(m[0], m[3]), 1 / scale, 0.1);
  const Eigen::Vector2d p = best.db_from_query.Apply({ca * 100 - sa * 200 + 300, sa * 100 + ca * 200 + 50});
  EXPECT_NEAR(p.x(), 100, 3);
  EXPECT_NEAR(p.y(), 200, 3);
  for (size_t i = 1; i < r->results.size(); ++i) EXPECT_FALSE(r->results[i].verified) << r->results[i].id;
  EXPECT_GT(r->results[0].db_region[2], r->results[0].db_region[0]);

  // Query expansion keeps the verified image first.
  const auto qe = index->Query(query, Opts(5, 30, true));
  ASSERT_TRUE(qe);
  EXPECT_EQ(qe->results[0].id, "img7");

  // QuerySimilar: an image finds itself first.
  const auto self = index->QuerySimilar("img12", Opts(3, 200));
  ASSERT_TRUE(self);
  EXPECT_EQ(self->results[0].id, "img12");
  EXPECT_TRUE(self->results[0].verified);
  EXPECT_NEAR(self->results[0].score, 1.0, 1e-5);

  // With a stop list the query leaves out the words of more than 40% of the images (about half of
  // them here: 150 of 256 words per image) while the image's norm counts them: cosine below 1.
  IndexOptions stop_list = no_stop_list;
  stop_list.max_document_frequency = 0.4;
  auto stopped = ImageIndex::Create((dir_ / "stop-list").string(), vocabulary_, "test-extractor/1", stop_list);
  ASSERT_TRUE(stopped) << stopped.error().ToString();
  for (size_t i = 0; i < images.size(); ++i) ASSERT_TRUE((*stopped)->Add("img" + std::to_string(i), images[i], {}));
  const auto stopped_self = (*stopped)->QuerySimilar("img12", Opts(3, 200));
  ASSERT_TRUE(stopped_self);
  EXPECT_EQ(stopped_self->results[0].id, "img12");
  std::printf("self score without / with the stop list: %.4f / %.4f\n", self->results[0].score,
              stopped_self->results[0].score);
  EXPECT_LT(stopped_self->results[0].score, 0.95) << "the stop list dropped no query word";
}

// Moves keypoints by the similarity p -> s R(angle) p + (tx, ty).
std::vector<sift::Keypoint> Transformed(const std::vector<sift::Keypoint>& in, double angle, double scale, double tx,
                                        double ty) {
  const double ca = std::cos(angle) * scale, sa = std::sin(angle) * scale;
  std::vector<sift::Keypoint> out;
  for (const auto& k : in) {
    sift::Keypoint q = k;
    q.x = static_cast<float>(ca * k.x - sa * k.y + tx);
    q.y = static_cast<float>(sa * k.x + ca * k.y + ty);
    q.scale = static_cast<float>(k.scale * scale);
    q.orientation = static_cast<float>(std::fmod(k.orientation + angle + 2 * std::numbers::pi, 2 * std::numbers::pi));
    out.push_back(q);
  }
  return out;
}

TEST_F(Fixture, TransitiveVerificationReachesViewsThatOnlyMatchAResult) {
  // "hub" shows the whole object; the query shows its even features, "far" its odd ones (another
  // viewpoint, plus clutter). far and the query share no object feature, so only hub links them.
  std::mt19937_64 rng(11);
  auto index = CreateIndex();
  const sift::FeatureSet hub = RandomImage(rng, 240);
  std::vector<uint32_t> hub_words(hub.size());
  vocabulary_.Quantize(hub.descriptors, hub_words);
  ASSERT_TRUE(index->Add("hub", hub, {}));
  for (int i = 0; i < 25; ++i) ASSERT_TRUE(index->Add("other" + std::to_string(i), RandomImage(rng, 150), {}));
  std::vector<uint32_t> query_words, far_words;
  std::vector<sift::Keypoint> query_kps, far_kps;
  for (size_t i = 0; i < hub.size(); ++i) {
    (i % 2 == 0 ? query_words : far_words).push_back(hub_words[i]);
    (i % 2 == 0 ? query_kps : far_kps).push_back(hub.keypoints[i]);
  }
  far_kps = Transformed(far_kps, -0.4, 0.8, 120, 250);
  const sift::FeatureSet clutter = RandomImage(rng, 60, 800, 700);
  std::vector<uint32_t> clutter_words(clutter.size());
  vocabulary_.Quantize(clutter.descriptors, clutter_words);
  far_words.insert(far_words.end(), clutter_words.begin(), clutter_words.end());
  far_kps.insert(far_kps.end(), clutter.keypoints.begin(), clutter.keypoints.end());
  ASSERT_TRUE(index->Add("far", Features(far_words, far_kps, 800, 700), {}));
  const double angle = 0.5, scale = 1.2, tx = 300, ty = 20;
  const auto query = Features(query_words, Transformed(query_kps, angle, scale, tx, ty), 1100, 1000);

  QueryOptions direct = Opts(30, 30);
  direct.transitive_depth = 0;
  const auto plain = index->Query(query, direct);
  ASSERT_TRUE(plain) << plain.error().ToString();
  ASSERT_EQ(plain->results[0].id, "hub");
  ASSERT_TRUE(plain->results[0].verified);
  for (const auto& r : plain->results) {
    if (r.id == "far") {
      EXPECT_FALSE(r.verified);
    }
  }
  for (bool qe : {false, true}) {
    QueryOptions transitive = Opts(30, 30, qe);
    transitive.transitive_depth = 30;
    const auto r = index->Query(query, transitive);
    ASSERT_TRUE(r) << r.error().ToString();
    ASSERT_GE(r->results.size(), 2u);
    EXPECT_EQ(r->results[0].id, "hub");
    const QueryResult& second = r->results[1];
    EXPECT_EQ(second.id, "far") << "qe " << qe;
    EXPECT_TRUE(second.verified);
    EXPECT_GE(second.inliers, 40);
    for (size_t i = 2; i < r->results.size(); ++i) EXPECT_FALSE(r->results[i].verified) << r->results[i].id;
    // db_from_query goes through hub: query -> hub (inverse of the query's similarity) -> far.
    const sift::Keypoint p = Transformed({sift::Keypoint{200, 150, 2, 0, 1, 0}}, angle, scale, tx, ty)[0];
    const sift::Keypoint expected = Transformed({sift::Keypoint{200, 150, 2, 0, 1, 0}}, -0.4, 0.8, 120, 250)[0];
    const Eigen::Vector2d mapped = second.db_from_query.Apply({p.x, p.y});
    EXPECT_NEAR(mapped.x(), expected.x, 3);
    EXPECT_NEAR(mapped.y(), expected.y, 3);
  }
  // One attempt per candidate is enough here: far is hub's own best neighbour.
  QueryOptions one_attempt = Opts(30, 30);
  one_attempt.transitive_depth = 30;
  one_attempt.transitive_attempts = 1;
  const auto once = index->Query(query, one_attempt);
  ASSERT_TRUE(once) << once.error().ToString();
  ASSERT_GE(once->results.size(), 2u);
  EXPECT_EQ(once->results[1].id, "far");
  EXPECT_TRUE(once->results[1].verified);
  QueryOptions bad = Opts(5, 30);
  bad.transitive_anchors = 0;
  EXPECT_FALSE(index->Query(query, bad));
  const std::pair<const char*, int QueryOptions::*> fields[] = {{"transitive_attempts", &QueryOptions::transitive_attempts},
                                                                {"quantizer_probes", &QueryOptions::quantizer_probes}};
  for (const auto& [name, field] : fields) {
    for (int value : {0, 5000}) {
      QueryOptions out_of_range = Opts(5, 30);
      out_of_range.*field = value;
      const auto refused = index->Query(query, out_of_range);
      ASSERT_FALSE(refused) << name << " " << value;
      EXPECT_NE(refused.error().message.find(name), std::string::npos);
    }
  }
}

TEST_F(Fixture, MultipleAssignmentReachesTheSecondNearestWord) {
  // The query descriptor lies between centroids 10 and 20, nearer 10; "b" holds only word 20.
  auto index = CreateIndex();
  std::mt19937_64 rng(5);
  ASSERT_TRUE(index->Add("a", Features({10, 30}, {{10, 10, 2, 0, 1, 0}, {50, 50, 2, 0, 1, 0}}), {}));
  ASSERT_TRUE(index->Add("b", Features({20, 40}, {{10, 10, 2, 0, 1, 0}, {50, 50, 2, 0, 1, 0}}), {}));
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add("r" + std::to_string(i), RandomImage(rng, 30), {}));
  const auto c = vocabulary_.centroids();
  sift::FeatureSet query = Features({10}, {{10, 10, 2, 0, 1, 0}});
  for (size_t d = 0; d < 128; ++d) query.descriptors[d] = 0.55f * c[10 * 128 + d] + 0.45f * c[20 * 128 + d];
  QueryOptions hard = Opts(10, 0);
  const auto h = ScoresById(*index->Query(query, hard));
  EXPECT_GT(h.count("a") ? h.at("a") : 0.0, 0.0);
  EXPECT_EQ(h.count("b") ? h.at("b") : 0.0, 0.0);
  QueryOptions soft = hard;
  soft.query_assignments = 2;
  soft.assignment_sigma_sq = 0.5;
  const auto s = ScoresById(*index->Query(query, soft));
  ASSERT_TRUE(s.count("a") && s.count("b"));
  EXPECT_GT(s.at("b"), 0.0);
  EXPECT_GT(s.at("a"), s.at("b"));  // the nearer word weighs more
  // A tiny kernel gives the second word no weight: back to hard assignment.
  soft.assignment_sigma_sq = 1e-6;
  const auto tiny = ScoresById(*index->Query(query, soft));
  EXPECT_EQ(tiny.count("b") ? tiny.at("b") : 0.0, 0.0);
  EXPECT_NEAR(tiny.at("a"), h.at("a"), 1e-6);
  soft.query_assignments = 9;
  EXPECT_FALSE(index->Query(query, soft));
}

TEST_F(Fixture, RegionQueryUsesOnlyFeaturesInside) {
  // Query: a's features on the left half (x < 300), b's (more of them) on the right half.
  sift::FeatureSet q;
  auto index = TwoObjectIndex(&q, 1, 1);
  const auto whole = index->Query(q, Opts(3, 0));
  ASSERT_TRUE(whole);
  EXPECT_EQ(whole->results[0].id, "b");
  const auto left = index->Query(q, Opts(3, 0, false, std::array<float, 4>{0, 0, 300, 480}));
  ASSERT_TRUE(left);
  EXPECT_EQ(left->query_features, 30u);
  EXPECT_EQ(left->results[0].id, "a");
}

TEST_F(Fixture, MaxQueryFeaturesKeepsTheStrongestInsideTheRegion) {
  // Query: 30 of a's features (strong, on the left), then 70 of b's (weak, on the right).
  sift::FeatureSet q;
  auto index = TwoObjectIndex(&q, 0.05f, 0.01f);
  const auto expect_first = [&](int max_features, std::optional<std::array<float, 4>> region, uint32_t used,
                                const std::string& first) {
    QueryOptions o = Opts(3, 0, false, region);
    o.max_query_features = max_features;
    const auto r = index->Query(q, o);
    ASSERT_TRUE(r) << r.error().ToString();
    EXPECT_EQ(r->query_features, used) << max_features;
    EXPECT_EQ(r->results[0].id, first) << max_features;
  };
  expect_first(0, std::nullopt, 100, "b");
  expect_first(30, std::nullopt, 30, "a");
  // The limit applies to the features inside the region.
  expect_first(30, std::array<float, 4>{320, 0, 640, 480}, 30, "b");

  // SelectInRegion: the strongest, ties by index, in their order.
  sift::FeatureSet f = Features({}, {}, 640, 480);
  for (const float r : {0.5f, -0.9f, 0.5f, 0.1f, 0.5f}) {
    f.keypoints.push_back({static_cast<float>(f.keypoints.size()), 0, 2, 0, r, 0});
    f.descriptors.insert(f.descriptors.end(), sift::kDescriptorDim, static_cast<float>(f.keypoints.size()));
  }
  std::vector<sift::Keypoint> kept;
  std::vector<float> descriptors;
  search::SelectInRegion(f, std::nullopt, 3, &kept, &descriptors);
  ASSERT_EQ(kept.size(), 3u);
  EXPECT_EQ(kept[0].x, 0);  // 0.5, the first of the three ties kept
  EXPECT_EQ(kept[1].x, 1);  // |-0.9|
  EXPECT_EQ(kept[2].x, 2);  // 0.5
  ASSERT_EQ(descriptors.size(), 3u * sift::kDescriptorDim);
  EXPECT_EQ(descriptors[2 * sift::kDescriptorDim], 3.0f);
  kept.clear();
  descriptors.clear();
  search::SelectInRegion(f, std::nullopt, 0, &kept, &descriptors);
  EXPECT_EQ(kept.size(), 5u);
  QueryOptions bad = Opts(3, 0);
  bad.max_query_features = -1;
  EXPECT_FALSE(index->Query(q, bad));
  bad = Opts(3, 0);
  bad.max_tentative_matches = 1000001;
  const auto refused = index->Query(q, bad);
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().message.find("max_tentative_matches"), std::string::npos);
}

TEST_F(Fixture, MaxScoredPostingsCutsTheTfIdfPass) {
  sift::FeatureSet q;
  auto index = TwoObjectIndex(&q, 1, 1);
  const auto run = [&](int max_postings) {
    QueryOptions o = Opts(12, 0);
    o.max_scored_postings = max_postings;
    auto r = index->Query(q, o);
    EXPECT_TRUE(r) << r.error().ToString();
    return *r;
  };
  // 12 small images: a budget of a million postings is never reached, and the results are those
  // without one.
  const QueryResponse unlimited = run(0), roomy = run(1'000'000);
  ASSERT_EQ(unlimited.results.size(), roomy.results.size());
  for (size_t i = 0; i < unlimited.results.size(); ++i) {
    EXPECT_EQ(unlimited.results[i].id, roomy.results[i].id);
    EXPECT_EQ(unlimited.results[i].score, roomy.results[i].score);
  }
  // A budget of one posting scans one word: fewer images get a score.
  const QueryResponse one = run(1);
  EXPECT_LT(one.candidates, unlimited.candidates);
  EXPECT_GT(one.candidates, 0u);
  QueryOptions bad = Opts(3, 0);
  bad.max_scored_postings = -1;
  const auto refused = index->Query(q, bad);
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().message.find("max_scored_postings"), std::string::npos);
}

TEST_F(Fixture, AddRemoveSequenceEqualsFreshIndex) {
  std::mt19937_64 rng(5);
  std::map<std::string, sift::FeatureSet> live;
  {
    IndexOptions small_merges;
    small_merges.merge_factor = 2;
    auto index = CreateIndex(small_merges);
    int counter = 0;
    for (int step = 0; step < 120; ++step) {
      if (rng() % 4 == 0 && !live.empty()) {
        auto it = live.begin();
        std::advance(it, rng() % live.size());
        ASSERT_TRUE(index->Remove(it->first));
        live.erase(it);
      } else {
        const std::string id = "i" + std::to_string(counter++);
        live[id] = RandomImage(rng, 20 + static_cast<int>(rng() % 80));
        ASSERT_TRUE(index->Add(id, live[id], {}));
      }
    }
    const fs::path fresh_dir = dir_ / "fresh";
    auto fresh = ImageIndex::Create(fresh_dir.string(), vocabulary_, "test-extractor/1");
    ASSERT_TRUE(fresh);
    for (const auto& [id, f] : live) ASSERT_TRUE((*fresh)->Add(id, f, {}));
    for (int q = 0; q < 10; ++q) {
      const auto query = RandomImage(rng, 60);
      const QueryOptions options = Opts(1000, 0);
      const auto a = ScoresById(*index->Query(query, options));
      const auto b = ScoresById(*(*fresh)->Query(query, options));
      ASSERT_EQ(a.size(), b.size());
      for (const auto& [id, s] : b) EXPECT_NEAR(a.at(id), s, 1e-6) << id;
    }
  }
  // And after a restart (rebuild from the catalogue) the same scores again.
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  EXPECT_EQ((*reopened)->Stats().num_images, live.size());
  auto fresh = ImageIndex::Open((dir_ / "fresh").string());
  ASSERT_TRUE(fresh);
  const auto query = RandomImage(rng, 60);
  const QueryOptions options = Opts(1000, 0);
  const auto a = ScoresById(*(*reopened)->Query(query, options));
  const auto b = ScoresById(*(*fresh)->Query(query, options));
  ASSERT_EQ(a.size(), b.size());
  for (const auto& [id, s] : b) EXPECT_NEAR(a.at(id), s, 1e-6) << id;
}

TEST_F(Fixture, RestartGivesIdenticalResults) {
  std::mt19937_64 rng(6);
  std::vector<sift::FeatureSet> queries;
  std::vector<QueryResponse> before;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 25; ++i) ASSERT_TRUE(index->Add("img" + std::to_string(i), RandomImage(rng, 100), {}));
    ASSERT_TRUE(index->Remove("img3"));
    for (int q = 0; q < 5; ++q) {
      queries.push_back(RandomImage(rng, 80));
      before.push_back(*index->Query(queries.back(), Opts(10, 10)));
    }
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Stats().num_images, 24u);
  EXPECT_FALSE((*index)->Contains("img3"));
  EXPECT_EQ((*index)->vocabulary().fingerprint(), vocabulary_.fingerprint());
  EXPECT_EQ((*index)->extractor_settings(), "test-extractor/1");
  for (size_t q = 0; q < queries.size(); ++q) {
    const auto after = (*index)->Query(queries[q], Opts(10, 10));
    ASSERT_TRUE(after);
    ASSERT_EQ(after->results.size(), before[q].results.size());
    for (size_t i = 0; i < after->results.size(); ++i) {
      EXPECT_EQ(after->results[i].id, before[q].results[i].id);
      EXPECT_FLOAT_EQ(static_cast<float>(after->results[i].score), static_cast<float>(before[q].results[i].score));
      EXPECT_EQ(after->results[i].inliers, before[q].results[i].inliers);
    }
  }
}

TEST_F(Fixture, VocabularyMismatchIsRefused) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(7);
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
  }
  // Another vocabulary's file in place of the index's copy.
  ASSERT_TRUE(MakeVocabulary(99).Write((dir_ / "vocabulary.oxvoc").string()));
  const auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kIncompatible);
  EXPECT_NE(r.error().message.find("does not match"), std::string::npos) << r.error().message;
}

void ExecSql(const fs::path& db_path, const std::string& sql) {
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(db_path.c_str(), &db), SQLITE_OK);
  char* error = nullptr;
  EXPECT_EQ(sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &error), SQLITE_OK) << (error ? error : "");
  sqlite3_free(error);
  sqlite3_close(db);
}

TEST_F(Fixture, UnknownSchemaVersionIsRefused) {
  CreateIndex();
  ExecSql(dir_ / "catalogue.sqlite", "UPDATE meta SET value = '99' WHERE key = 'schema_version'");
  const auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kIncompatible);
  EXPECT_NE(r.error().message.find("schema version 99"), std::string::npos) << r.error().message;
}

// A damaged BLOB that a rebuild reads costs that image only: the others are served, the damaged one
// is dropped (its row deleted, logged) and its id can be added again.
TEST_F(Fixture, DamagedFeatureBlobCostsThatImageOnly) {
  std::mt19937_64 rng(8);
  const auto b = RandomImage(rng, 30);
  {
    auto index = CreateIndex();
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
    ASSERT_TRUE(index->Add("b", b, {}));
  }
  // Flip one byte inside the packed features (after the 24-byte header): the checksum must catch it
  // when Open reads the BLOBs (no checkpoint: a full rebuild).
  ExecSql(dir_ / "catalogue.sqlite",
          "UPDATE features SET blob = substr(blob, 1, 30) || x'ff' || substr(blob, 32) "
          "WHERE number = (SELECT number FROM images WHERE id = 'a'); DELETE FROM meta WHERE key = 'checkpoint'");
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ((*index)->Stats().num_images, 1u);
    EXPECT_EQ((*index)->Get("a").error().code, ErrorCode::kNotFound);
    const auto features = FeaturesOf(**index, "b");
    ASSERT_TRUE(features) << features.error().ToString();
    EXPECT_EQ(features->keypoints.size(), b.keypoints.size());
    EXPECT_TRUE((*index)->Add("a", RandomImage(rng, 30), {}));
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Stats().num_images, 2u);
}

std::string FileBytes(const fs::path& path);

// A damaged image record (an id changed in place in the file: the table and its id index disagree)
// is refused at open, not served under the wrong id.
TEST_F(Fixture, DamagedImageRecordIsRefused) {
  const std::string id = "image-with-a-long-recognisable-id";
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(8);
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add(id + std::to_string(i), RandomImage(rng, 30), {}));
  }
  std::string bytes = FileBytes(dir_ / "catalogue.sqlite");
  const size_t at = bytes.rfind(id + "3");  // the table's row or the index's entry: either disagrees
  ASSERT_NE(at, std::string::npos);
  bytes[at] = 'J';
  std::ofstream(dir_ / "catalogue.sqlite", std::ios::binary | std::ios::trunc).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  const auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kCorruptData) << r.error().ToString();
  EXPECT_NE(r.error().message.find("integrity check"), std::string::npos) << r.error().message;
}

// `oxbow index check` (CheckIndexFolder): every BLOB, those a checkpoint covers too (an open does not
// read them), checked; the damaged ones reported by id, and dropped on request.
TEST_F(Fixture, TheCheckFindsAndDropsDamagedBlobsThatAnOpenDoesNotRead) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(8);
    for (const char* id : {"a", "b", "c"}) ASSERT_TRUE(index->Add(id, RandomImage(rng, 30), {}));
  }
  ExecSql(dir_ / "catalogue.sqlite",
          "UPDATE features SET blob = substr(blob, 1, 30) || x'ff' || substr(blob, 32) "
          "WHERE number = (SELECT number FROM images WHERE id = 'b')");
  ASSERT_TRUE(ImageIndex::Open(dir_.string()));  // from the checkpoint: the BLOB is not read
  auto check = CheckIndexFolder(dir_.string(), /*drop_damaged=*/false);
  ASSERT_TRUE(check) << check.error().ToString();
  EXPECT_EQ(check->images, 3u);
  ASSERT_EQ(check->damaged.size(), 1u);
  EXPECT_EQ(check->damaged[0].id, "b");
  EXPECT_NE(check->damaged[0].why.find("checksum"), std::string::npos) << check->damaged[0].why;
  EXPECT_FALSE(check->dropped);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index);
    EXPECT_EQ((*index)->Stats().num_images, 3u);
    // A folder in use is refused.
    EXPECT_FALSE(CheckIndexFolder(dir_.string(), false));
  }
  check = CheckIndexFolder(dir_.string(), /*drop_damaged=*/true);
  ASSERT_TRUE(check) << check.error().ToString();
  EXPECT_TRUE(check->dropped);
  check = CheckIndexFolder(dir_.string(), false);
  ASSERT_TRUE(check) << check.error().ToString();
  EXPECT_TRUE(check->damaged.empty());
  EXPECT_EQ(check->images, 2u);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Stats().num_images, 2u);
  EXPECT_EQ((*index)->Get("b").error().code, ErrorCode::kNotFound);
}

TEST_F(Fixture, DamagedCatalogueAndVocabularyAreRefused) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(9);
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
  }
  const fs::path vocab_path = dir_ / "vocabulary.oxvoc";
  const fs::path backup = dir_ / "vocab.bak";
  fs::copy_file(vocab_path, backup);
  // Truncated vocabulary copy.
  fs::resize_file(vocab_path, fs::file_size(vocab_path) / 2);
  auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kCorruptData) << r.error().ToString();
  fs::copy_file(backup, vocab_path, fs::copy_options::overwrite_existing);
  ASSERT_TRUE(ImageIndex::Open(dir_.string()));
  // Garbage over the SQLite header.
  {
    std::fstream f(dir_ / "catalogue.sqlite", std::ios::in | std::ios::out | std::ios::binary);
    f.write("this is not a database file at all", 32);
  }
  r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kCorruptData) << r.error().ToString();
}

std::string FileBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// A catalogue.sqlite-wal that belongs to another index (here one on another vocabulary, with images)
// beside the catalogue: the open is refused, and closing the refused open must not checkpoint that WAL
// into catalogue.sqlite (a read-write connection would, overwriting every image of the index).
TEST_F(Fixture, ForeignWalIsRefusedAndLeavesTheCatalogueAlone) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(11);
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("a" + std::to_string(i), RandomImage(rng, 80), {}));
  }
  ASSERT_FALSE(fs::exists(dir_ / "catalogue.sqlite-wal"));  // a clean close checkpointed it
  const fs::path other_dir = dir_.string() + "_other";
  fs::remove_all(other_dir);
  std::string foreign_wal;
  {
    const vocab::Vocabulary other_vocabulary = MakeVocabulary(2);
    auto other = ImageIndex::Create(other_dir.string(), other_vocabulary, "test-extractor/1");
    ASSERT_TRUE(other) << other.error().ToString();
    std::mt19937_64 rng(12);
    ASSERT_TRUE((*other)->Add("b", RandomImage(rng, 10), {}));
    foreign_wal = FileBytes(other_dir / "catalogue.sqlite-wal");  // committed, not yet checkpointed
  }
  fs::remove_all(other_dir);
  ASSERT_GT(foreign_wal.size(), 32u);
  const std::string catalogue = FileBytes(dir_ / "catalogue.sqlite");
  std::ofstream(dir_ / "catalogue.sqlite-wal", std::ios::binary) << foreign_wal;

  const auto refused = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, ErrorCode::kIncompatible) << refused.error().ToString();
  EXPECT_TRUE(FileBytes(dir_ / "catalogue.sqlite") == catalogue) << "the refused open wrote to the catalogue";
  EXPECT_TRUE(FileBytes(dir_ / "catalogue.sqlite-wal") == foreign_wal) << "the foreign WAL changed";

  // Once the stray file is gone the index opens whole.
  fs::remove(dir_ / "catalogue.sqlite-wal");
  fs::remove(dir_ / "catalogue.sqlite-shm");
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  EXPECT_EQ((*reopened)->Stats().num_images, 20u);
  EXPECT_TRUE((*reopened)->Contains("a19"));
}

// Makes every insert of `id` into the catalogue fail, as a full disk or an I/O error would.
void FailInsertsOf(const fs::path& dir, const std::string& id) {
  ExecSql(dir / "catalogue.sqlite", "CREATE TRIGGER injected_failure BEFORE INSERT ON images WHEN NEW.id = '" + id +
                                        "' BEGIN SELECT RAISE(ABORT, 'injected insert failure'); END;");
}

TEST_F(Fixture, ReplaceIsOneTransactionOldOrNewNeverNeither) {
  std::mt19937_64 rng(13);
  const sift::FeatureSet old_image = RandomImage(rng, 40, 640, 480);
  const sift::FeatureSet new_image = RandomImage(rng, 70, 800, 600);
  ImageRecord old_record;
  {
    auto index = CreateIndex();
    auto added = index->Add("x", old_image, Info("/old.jpg"));
    ASSERT_TRUE(added);
    old_record = *added;
    ASSERT_TRUE(index->Add("other", RandomImage(rng, 40), {}));
    // Replace of an absent id adds it.
    ASSERT_TRUE(index->Replace("fresh", RandomImage(rng, 30), {}));
    EXPECT_EQ(index->Stats().num_images, 3u);
  }
  FailInsertsOf(dir_, "x");
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    // The removal of the old row succeeds, the insert of the new one fails: the whole replacement
    // rolls back, in the catalogue and in memory.
    const auto failed = (*index)->Replace("x", new_image, Info("/new.jpg"));
    ASSERT_FALSE(failed);
    EXPECT_NE(failed.error().message.find("injected insert failure"), std::string::npos) << failed.error().message;
    const auto kept = (*index)->Get("x");
    ASSERT_TRUE(kept) << "a failed replacement removed the image";
    EXPECT_EQ(*kept, old_record);
    const auto self = (*index)->Query(old_image, Opts(1, 0));
    ASSERT_TRUE(self);
    ASSERT_FALSE(self->results.empty());
    EXPECT_EQ(self->results[0].id, "x");
  }
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    const auto kept = (*index)->Get("x");
    ASSERT_TRUE(kept) << "the failed replacement removed the image from the catalogue";
    EXPECT_EQ(*kept, old_record);
    EXPECT_EQ((*index)->Stats().num_images, 3u);
  }
  ExecSql(dir_ / "catalogue.sqlite", "DROP TRIGGER injected_failure");
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    const auto replaced = (*index)->Replace("x", new_image, Info("/new.jpg"));
    ASSERT_TRUE(replaced) << replaced.error().ToString();
    EXPECT_EQ(replaced->num_features, 70u);
    EXPECT_EQ((*index)->Get("x")->source_path, "/new.jpg");
    EXPECT_EQ((*index)->Stats().num_images, 3u);
    const auto self = (*index)->Query(new_image, Opts(1, 0));
    ASSERT_TRUE(self);
    ASSERT_FALSE(self->results.empty());
    EXPECT_EQ(self->results[0].id, "x");
  }
  // After a restart: the new version only, and scores as an index built from scratch would give.
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Get("x")->num_features, 70u);
  EXPECT_EQ((*index)->Stats().num_images, 3u);
}

// A batch is one transaction and one snapshot: per-image errors leave the others, a catalogue failure
// leaves nothing, and the result equals adding the images one by one.
TEST_F(Fixture, AddBatchEqualsSingleAddsAndFailsPerImageOrAsAWhole) {
  std::mt19937_64 rng(21);
  std::vector<sift::FeatureSet> images;
  images.reserve(12);
  for (int i = 0; i < 12; ++i) images.push_back(RandomImage(rng, 30 + i * 5));
  sift::FeatureSet wrong_kind = images[0];
  wrong_kind.kind = sift::DescriptorKind::kSift;
  {
    auto index = CreateIndex();
    ASSERT_TRUE(index->Add("b0", images[0], {}));
    std::vector<BatchImage> batch;
    for (int i = 1; i < 12; ++i) batch.push_back({"b" + std::to_string(i), &images[i], Info("/p" + std::to_string(i)), {}, {}});
    batch.push_back({"b0", &images[1], {}, {}, {}});          // already indexed
    batch.push_back({"b5", &images[2], {}, {}, {}});          // repeated in the batch
    batch.push_back({"", &images[3], {}, {}, {}});            // bad id
    batch.push_back({"kind", &wrong_kind, {}, {}, {}});       // wrong descriptor kind
    const auto results = index->AddBatch(batch);
    ASSERT_EQ(results.size(), batch.size());
    for (size_t i = 0; i < 11; ++i) {
      ASSERT_TRUE(results[i]) << results[i].error().ToString();
      EXPECT_EQ(results[i]->id, batch[i].id);
      EXPECT_EQ(results[i]->source_path, batch[i].info.source_path);
    }
    EXPECT_EQ(results[11].error().code, ErrorCode::kAlreadyExists);
    EXPECT_EQ(results[12].error().code, ErrorCode::kAlreadyExists);
    EXPECT_EQ(results[13].error().code, ErrorCode::kInvalidArgument);
    EXPECT_EQ(results[14].error().code, ErrorCode::kIncompatible);
    EXPECT_EQ(index->Stats().num_images, 12u);
    EXPECT_EQ(index->Get("b5")->num_features, images[5].size());
  }
  // A catalogue failure on one row fails the whole batch and stores none of it.
  FailInsertsOf(dir_, "c2");
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    std::vector<BatchImage> batch;
    batch.reserve(4);
    for (int i = 0; i < 4; ++i) batch.push_back({"c" + std::to_string(i), &images[i], {}, {}, {}});
    for (const auto& r : (*index)->AddBatch(batch)) {
      ASSERT_FALSE(r);
      EXPECT_NE(r.error().message.find("injected insert failure"), std::string::npos) << r.error().message;
    }
    EXPECT_FALSE((*index)->Contains("c0"));
    EXPECT_EQ((*index)->Stats().num_images, 12u);
  }
  // After a restart the batch-built index scores as one built image by image.
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Stats().num_images, 12u);
  EXPECT_FALSE((*index)->Contains("c0"));
  auto single = ImageIndex::Create((dir_ / "single").string(), vocabulary_, "test-extractor/1");
  ASSERT_TRUE(single);
  for (int i = 0; i < 12; ++i) ASSERT_TRUE((*single)->Add("b" + std::to_string(i), images[i], {}));
  for (int q = 0; q < 5; ++q) {
    const auto query = RandomImage(rng, 60);
    const auto a = ScoresById(*(*index)->Query(query, Opts(100, 0)));
    const auto b = ScoresById(*(*single)->Query(query, Opts(100, 0)));
    ASSERT_EQ(a.size(), b.size());
    for (const auto& [id, s] : b) EXPECT_NEAR(a.at(id), s, 1e-6) << id;
  }
}

// AddBatch links a batch, while the catalogue commits it, on the numbers it expects the catalogue to
// give; when the catalogue gives others (here its number sequence was moved on between two opens), the
// batch is linked again on the numbers given: a later remove deletes the right row, and a reopen finds
// the same images and scores.
TEST_F(Fixture, AddBatchOnOtherNumbersThanExpectedLinksTheNumbersGiven) {
  std::mt19937_64 rng(24);
  std::vector<sift::FeatureSet> images;
  images.reserve(6);
  for (int i = 0; i < 6; ++i) images.push_back(RandomImage(rng, 40));
  {
    auto index = CreateIndex();
    ASSERT_TRUE(index->Add("a0", images[0], {}));
    ASSERT_TRUE(index->Add("a1", images[1], {}));
  }
  ExecSql(dir_ / "catalogue.sqlite", "UPDATE sqlite_sequence SET seq = seq + 10 WHERE name = 'images'");
  std::map<std::string, double> scores;
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    std::vector<BatchImage> batch;
    for (int i = 2; i < 6; ++i) batch.push_back({"b" + std::to_string(i), &images[i], {}, {}, {}});
    for (const auto& r : (*index)->AddBatch(batch)) ASSERT_TRUE(r) << r.error().ToString();
    ASSERT_TRUE((*index)->Remove("b3"));
    EXPECT_FALSE((*index)->Contains("b3"));
    EXPECT_EQ((*index)->Stats().num_images, 5u);
    for (const int i : {2, 4, 5}) {
      const auto found = (*index)->Query(images[i], Opts(1, 0));
      ASSERT_TRUE(found && !found->results.empty());
      EXPECT_EQ(found->results[0].id, "b" + std::to_string(i));
    }
    scores = ScoresById(*(*index)->Query(images[4], Opts(100, 0)));
  }
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  EXPECT_EQ((*reopened)->Stats().num_images, 5u);
  EXPECT_FALSE((*reopened)->Contains("b3"));
  const auto again = ScoresById(*(*reopened)->Query(images[4], Opts(100, 0)));
  ASSERT_EQ(again.size(), scores.size());
  for (const auto& [id, score] : scores) EXPECT_NEAR(again.at(id), score, 1e-6) << id;
}

// Pre-assigned words (BatchImage::words) skip quantisation and index exactly what quantising the
// descriptors would have.
TEST_F(Fixture, AddBatchWithAssignedWordsEqualsQuantising) {
  std::mt19937_64 rng(22);
  std::vector<std::vector<uint32_t>> words(6);
  std::vector<sift::FeatureSet> with_descriptors, without;
  std::uniform_int_distribution<uint32_t> word(0, kWords - 1);
  std::uniform_real_distribution<float> x(0, 600), scale(1.5f, 10.0f);
  for (auto& w : words) {
    std::vector<sift::Keypoint> kps;
    for (int i = 0; i < 50; ++i) {
      w.push_back(word(rng));
      kps.push_back(sift::Keypoint{.x = x(rng), .y = x(rng) * 0.7f, .scale = scale(rng), .orientation = 1.0f});
    }
    with_descriptors.push_back(Features(w, kps));
    without.push_back(with_descriptors.back());
    without.back().descriptors.clear();
  }
  auto quantised = CreateIndex();
  auto assigned = ImageIndex::Create((dir_ / "assigned").string(), vocabulary_, "test-extractor/1");
  ASSERT_TRUE(assigned);
  // With every image's words given, the catalogue takes the rows while later images are still
  // prepared: images refused between them (bad words, an id taken or repeated) must not shift them.
  ASSERT_TRUE((*assigned)->AddBatch(std::vector<BatchImage>{{"taken", &without[0], {}, words[0], {}}})[0]);
  const std::vector<uint32_t> outside(50, kWords);
  std::vector<BatchImage> a, b;
  std::vector<ErrorCode> refused;  // per entry of b: kInternal for an image that must be added
  for (size_t i = 0; i < words.size(); ++i) {
    a.push_back({"w" + std::to_string(i), &with_descriptors[i], {}, {}, {}});
    b.push_back({"w" + std::to_string(i), &without[i], {}, words[i], {}});
    refused.push_back(ErrorCode::kInternal);
    if (i == 1) {
      b.push_back({"outside", &without[0], {}, outside, {}});
      refused.push_back(ErrorCode::kInvalidArgument);
    } else if (i == 2) {
      b.push_back({"w1", &without[3], {}, words[3], {}});
      refused.push_back(ErrorCode::kAlreadyExists);
    } else if (i == 3) {
      b.push_back({"taken", &without[1], {}, words[1], {}});
      refused.push_back(ErrorCode::kAlreadyExists);
    }
  }
  b.push_back({"outside", &without[0], {}, outside, {}});
  refused.push_back(ErrorCode::kInvalidArgument);
  ASSERT_TRUE(quantised->AddBatch(std::vector<BatchImage>{{"taken", &with_descriptors[0], {}, {}, {}}})[0]);
  for (const auto& r : quantised->AddBatch(a)) ASSERT_TRUE(r) << r.error().ToString();
  const auto results = (*assigned)->AddBatch(b);
  ASSERT_EQ(results.size(), b.size());
  for (size_t i = 0; i < b.size(); ++i) {
    if (refused[i] == ErrorCode::kInternal) {
      ASSERT_TRUE(results[i]) << results[i].error().ToString();
      EXPECT_EQ(results[i]->id, b[i].id);
    } else {
      ASSERT_FALSE(results[i]) << i;
      EXPECT_EQ(results[i].error().code, refused[i]) << i;
    }
  }
  EXPECT_EQ((*assigned)->Get("w1")->num_features, without[1].size());
  for (const auto& query : with_descriptors) {
    const auto x1 = quantised->Query(query, Opts(10, 10));
    const auto x2 = (*assigned)->Query(query, Opts(10, 10));
    ASSERT_TRUE(x1 && x2);
    ASSERT_EQ(x1->results.size(), x2->results.size());
    for (size_t i = 0; i < x1->results.size(); ++i) {
      EXPECT_EQ(x1->results[i].id, x2->results[i].id);
      EXPECT_EQ(x1->results[i].score, x2->results[i].score);
      EXPECT_EQ(x1->results[i].inliers, x2->results[i].inliers);
    }
  }
}

// A folder the process may not write (permissions; root ignores them, so as root the check runs in a
// child that drops to user nobody) is an I/O problem, not damage, and the catalogue is left unchanged.
// The write sequence counts every committed insert and removal (a replacement is both), survives a
// restart (it is the catalogue's), and two indexes that applied the same writes in another order agree.
TEST_F(Fixture, WriteSequenceCountsCommittedWritesAndSurvivesARestart) {
  std::mt19937_64 rng(23);
  std::vector<sift::FeatureSet> images;
  images.reserve(6);
  for (int i = 0; i < 6; ++i) images.push_back(RandomImage(rng, 40));
  uint64_t expected = 0;
  {
    auto index = CreateIndex();
    EXPECT_EQ(index->write_sequence(), 0u);
    ASSERT_TRUE(index->Add("a", images[0], {}));
    ASSERT_TRUE(index->Add("b", images[1], {}));
    EXPECT_EQ(index->write_sequence(), 2u);
    EXPECT_FALSE(index->Add("a", images[2], {}));  // refused: nothing committed
    EXPECT_EQ(index->write_sequence(), 2u);
    ASSERT_TRUE(index->Replace("a", images[2], {}));
    EXPECT_EQ(index->write_sequence(), 4u);
    ASSERT_TRUE(index->Remove("b"));
    EXPECT_FALSE(index->Remove("b"));
    EXPECT_EQ(index->write_sequence(), 5u);
    std::vector<BatchImage> batch = {{"c", &images[3], {}, {}, {}}, {"d", &images[4], {}, {}, {}}, {"a", &images[5], {}, {}, {}}};
    const auto results = index->AddBatch(batch);
    EXPECT_FALSE(results[2]);  // "a" is taken
    EXPECT_EQ(index->write_sequence(), 7u);
    expected = index->write_sequence();
  }
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  EXPECT_EQ((*reopened)->write_sequence(), expected);
  // The same writes in another order: the same sequence.
  auto other = ImageIndex::Create((dir_ / "other").string(), vocabulary_, "test-extractor/1");
  ASSERT_TRUE(other);
  ASSERT_TRUE((*other)->Add("d", images[4], {}));
  ASSERT_TRUE((*other)->Add("b", images[1], {}));
  ASSERT_TRUE((*other)->Add("c", images[3], {}));
  ASSERT_TRUE((*other)->Remove("b"));
  ASSERT_TRUE((*other)->Add("a", images[0], {}));
  ASSERT_TRUE((*other)->Replace("a", images[2], {}));
  EXPECT_EQ((*other)->write_sequence(), expected);
}

// Commits do not copy SQLite's write-ahead log into the database file themselves: a thread of the
// catalogue does, beside them, and the log stays bounded (a transaction that finds it over 32 MiB waits
// for a copy of all of it first, and then starts it again from its beginning). 24 rows of 4 MiB, 96 MiB
// in all: the log never passes 32 MiB plus one transaction, the database file receives the rows while
// the catalogue is open, and every row reads back whole after a reopen.
TEST_F(Fixture, TheCatalogueLogIsCopiedBesideTheCommitsAndStaysBounded) {
  fs::create_directories(dir_);
  const std::string path = (dir_ / kCatalogueFile).string();
  CatalogueMeta meta;
  meta.vocabulary_size = kWords;
  meta.descriptor_kind = "rootsift";
  meta.extractor_settings = "test-extractor/1";
  constexpr int kRows = 24;
  constexpr size_t kBlob = size_t{4} << 20;
  std::vector<uint8_t> noise(kBlob);  // one random buffer, each row's copy marked with its number
  std::mt19937_64 rng(7);
  for (size_t k = 0; k < kBlob; k += 8) {
    const uint64_t r = rng();
    std::memcpy(noise.data() + k, &r, 8);
  }
  const auto blob_of = [&](int i) {
    std::vector<uint8_t> blob = noise;
    for (size_t k = 0; k < kBlob; k += 4096) blob[k] = static_cast<uint8_t>(i);
    return blob;
  };
  const auto size_of = [](const std::string& file) {
    std::error_code ec;
    const auto size = fs::file_size(file, ec);
    return ec ? uintmax_t{0} : size;
  };
  uintmax_t largest_log = 0;
  {
    auto catalogue = Catalogue::Create(path, meta);
    ASSERT_TRUE(catalogue) << catalogue.error().ToString();
    for (int i = 0; i < kRows; ++i) {
      ImageRecord record;
      record.id = "row" + std::to_string(i);
      record.num_features = 1;
      ASSERT_TRUE((*catalogue)->Insert(record, blob_of(i)));
      largest_log = std::max(largest_log, size_of(path + "-wal"));
    }
    // Copied while open: wait for the database file to hold most of the rows.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (size_of(path) < (kRows - 9) * kBlob && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    EXPECT_GE(size_of(path), (kRows - 9) * kBlob);
  }
  EXPECT_LE(largest_log, (size_t{32} << 20) + 2 * kBlob);  // 32 MiB, then at most one transaction more
  auto reopened = Catalogue::Open(path);
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  int rows = 0;
  ASSERT_TRUE((*reopened)->ForEach([&](CatalogueRow&& row) -> Status {
    EXPECT_EQ(row.record.id, "row" + std::to_string(rows));
    EXPECT_TRUE(row.features == blob_of(rows)) << row.record.id;
    ++rows;
    return Ok();
  }));
  EXPECT_EQ(rows, kRows);
}

TEST_F(Fixture, ReadOnlyFolderIsAnIoErrorNotDamage) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(14);
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
  }
  const std::string catalogue = FileBytes(dir_ / "catalogue.sqlite");
  fs::permissions(dir_, fs::perms::owner_write | fs::perms::group_write | fs::perms::others_write,
                  fs::perm_options::remove);
  for (const auto& file : fs::directory_iterator(dir_)) {
    fs::permissions(file.path(), fs::perms::owner_write | fs::perms::group_write | fs::perms::others_write,
                    fs::perm_options::remove);
  }
  int fds[2];
  ASSERT_EQ(pipe(fds), 0);
  std::fflush(nullptr);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    close(fds[0]);
    if (geteuid() == 0 && (setgid(65534) != 0 || setuid(65534) != 0)) _exit(99);
    const auto r = ImageIndex::Open(dir_.string());
    const std::string report = r ? std::string("opened") : r.error().ToString();
    if (write(fds[1], report.data(), report.size()) < 0) _exit(98);
    _exit(r ? 1 : (r.error().code == ErrorCode::kIoError ? 0 : 2));
  }
  close(fds[1]);
  std::string report;
  char buf[512];
  for (ssize_t n; (n = read(fds[0], buf, sizeof buf)) > 0;) report.append(buf, static_cast<size_t>(n));
  close(fds[0]);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  fs::permissions(dir_, fs::perms::owner_write, fs::perm_options::add);
  for (const auto& file : fs::directory_iterator(dir_)) fs::permissions(file.path(), fs::perms::owner_write, fs::perm_options::add);
  ASSERT_TRUE(WIFEXITED(status));
  if (WEXITSTATUS(status) == 99) GTEST_SKIP() << "running as root and cannot drop to user nobody (65534)";
  EXPECT_EQ(WEXITSTATUS(status), 0) << report;
  EXPECT_NE(report.find("read-only"), std::string::npos) << report;
  EXPECT_NE(report.find("permissions"), std::string::npos) << report;
  EXPECT_TRUE(FileBytes(dir_ / "catalogue.sqlite") == catalogue) << "the catalogue changed";
  ASSERT_TRUE(ImageIndex::Open(dir_.string()));
}

TEST_F(Fixture, PackedFeaturesRoundTrip) {
  std::mt19937_64 rng(10);
  const auto f = RandomImage(rng, 200, 1000, 700);
  std::vector<uint32_t> words(f.size());
  vocabulary_.Quantize(f.descriptors, words);
  const PackedFeatures packed = PackedFeatures::Pack(f.keypoints, words, 1000, 700);
  ASSERT_EQ(packed.size(), f.size());
  const auto blob = packed.Serialize();
  const auto back = PackedFeatures::Deserialize(blob, "test");
  ASSERT_TRUE(back);
  EXPECT_EQ(back->Words(), packed.Words());
  // Every original keypoint has a dequantised twin within the documented error.
  size_t matched = 0;
  for (size_t i = 0; i < f.size(); ++i) {
    for (size_t j = 0; j < back->size(); ++j) {
      const auto k = back->keypoint(j);
      if (back->word(j) == words[i] && std::abs(k.x - f.keypoints[i].x) < 0.01f &&
          std::abs(k.y - f.keypoints[i].y) < 0.01f) {
        EXPECT_NEAR(std::log2(k.scale / f.keypoints[i].scale), 0, 1.0 / 32 + 1e-6);
        double d = std::fmod(std::abs(k.orientation - f.keypoints[i].orientation), 2 * std::numbers::pi);
        d = std::min(d, 2 * std::numbers::pi - d);
        EXPECT_LE(d, std::numbers::pi / 256 + 1e-5);
        ++matched;
        break;
      }
    }
  }
  EXPECT_EQ(matched, f.size());
  auto damaged = blob;
  damaged[damaged.size() - 3] ^= 0x40;
  EXPECT_EQ(PackedFeatures::Deserialize(damaged, "test").error().code, ErrorCode::kCorruptData);
  auto truncated = blob;
  truncated.resize(blob.size() - 9);
  EXPECT_EQ(PackedFeatures::Deserialize(truncated, "test").error().code, ErrorCode::kCorruptData);
  auto future = blob;
  future[4] = 7;
  EXPECT_EQ(PackedFeatures::Deserialize(future, "test").error().code, ErrorCode::kIncompatible);
}

// Pack's bytes against the layout written out with libm's rounding and a stable sort: the radix sort
// and the rounding without libm must give exactly these. Words span all 24 bits (three radix passes)
// with many repeats (ties keep input order); coordinates include exact halves of a quantisation step.
TEST(PackedFeaturesLayout, BytesEqualTheReferenceLayout) {
  std::mt19937_64 rng(12);
  for (const uint32_t max_word : {7u, 100'000u, kMaxPackedWord}) {
    const int width = 65535, height = 480;  // x = m + 0.5 is then exactly half a quantisation step
    std::vector<sift::Keypoint> keypoints;
    std::vector<uint32_t> words;
    std::vector<uint64_t> signatures;
    std::uniform_real_distribution<float> unit(0.0f, 1.0f);
    for (int i = 0; i < 3000; ++i) {
      sift::Keypoint k;
      k.x = i % 7 == 0 ? static_cast<float>(i % 65534) + 0.5f : unit(rng) * width;
      k.y = i % 5 == 0 ? static_cast<float>(height) : unit(rng) * height * 1.1f - 0.05f * height;
      k.scale = i % 11 == 0 ? 0.01f : std::exp2(unit(rng) * 12.0f - 4.5f);
      k.orientation = (unit(rng) - 0.5f) * 20.0f;
      keypoints.push_back(k);
      words.push_back(i % 3 == 0 ? max_word : static_cast<uint32_t>(rng() % (max_word + 1)));
      signatures.push_back(rng());
    }
    const PackedFeatures packed = PackedFeatures::Pack(keypoints, words, width, height, signatures);
    std::vector<size_t> order(words.size());
    std::iota(order.begin(), order.end(), size_t{0});
    std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return words[a] < words[b]; });
    ASSERT_EQ(packed.bytes().size(), words.size() * kPackedFeatureBytes);
    int halves = 0;
    for (size_t j = 0; j < order.size(); ++j) {
      const size_t i = order[j];
      const sift::Keypoint& k = keypoints[i];
      const double qx = std::clamp(static_cast<double>(k.x) / width, 0.0, 1.0) * 65535.0;
      halves += qx - std::floor(qx) == 0.5 ? 1 : 0;
      const auto x = static_cast<uint16_t>(std::round(std::clamp(static_cast<double>(k.x) / width, 0.0, 1.0) * 65535.0));
      const auto y = static_cast<uint16_t>(std::round(std::clamp(static_cast<double>(k.y) / height, 0.0, 1.0) * 65535.0));
      const double log_scale = std::log2(static_cast<double>(k.scale));
      const int sc = static_cast<int>(std::clamp(std::round((log_scale + 4.0) * 16.0), 0.0, 255.0));
      double turns = static_cast<double>(k.orientation) / (2 * std::numbers::pi);
      turns -= std::floor(turns);
      const int o = static_cast<int>(std::lround(turns * 256.0)) & 255;
      const std::array<uint8_t, kPackedFeatureBytes> expected = {
          static_cast<uint8_t>(words[i]), static_cast<uint8_t>(words[i] >> 8), static_cast<uint8_t>(words[i] >> 16),
          static_cast<uint8_t>(x),        static_cast<uint8_t>(x >> 8),        static_cast<uint8_t>(y),
          static_cast<uint8_t>(y >> 8),   static_cast<uint8_t>(sc),            static_cast<uint8_t>(o)};
      const auto got = packed.bytes().subspan(j * kPackedFeatureBytes, kPackedFeatureBytes);
      ASSERT_TRUE(std::equal(got.begin(), got.end(), expected.begin())) << "feature " << j << ", max word " << max_word;
      ASSERT_EQ(packed.signature(j), signatures[i]) << "feature " << j;
    }
    EXPECT_GT(halves, 300) << "the exact halves this test relies on";
  }
}

// The BLOB a batch add makes in place (PackBlob) is what Serialize() of Pack gives, byte for byte, and
// the features it returns read as Pack's; the buffer has no byte left unwritten.
TEST(PackedFeaturesLayout, PackBlobWritesSerializeBytesInPlace) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  for (const bool with_signatures : {false, true}) {
    for (const size_t n : {size_t{0}, size_t{1}, size_t{2500}}) {
      std::vector<sift::Keypoint> keypoints(n);
      std::vector<uint32_t> words(n);
      std::vector<uint64_t> signatures;
      for (size_t i = 0; i < n; ++i) {
        keypoints[i].x = unit(rng) * 640;
        keypoints[i].y = unit(rng) * 480;
        keypoints[i].scale = std::exp2(unit(rng) * 6.0f);
        keypoints[i].orientation = unit(rng) * 6.0f;
        words[i] = static_cast<uint32_t>(rng() % 5000);
        if (with_signatures) signatures.push_back(rng());
      }
      const std::vector<uint8_t> expected = PackedFeatures::Pack(keypoints, words, 640, 480, signatures).Serialize();
      ASSERT_EQ(PackedFeatures::BlobBytes(n, with_signatures), expected.size());
      for (const uint8_t fill : {uint8_t{0x00}, uint8_t{0xA5}}) {
        auto buffer = std::make_shared<std::vector<uint8_t>>(expected.size(), fill);
        const PackedFeatures packed = PackedFeatures::PackBlob(keypoints, words, 640, 480, signatures, *buffer, buffer);
        EXPECT_EQ(*buffer, expected) << n << " features, signatures " << with_signatures << ", fill " << int{fill};
        const auto read = PackedFeatures::Deserialize(*buffer, "the test's BLOB");
        ASSERT_TRUE(read.has_value()) << read.error().message;
        ASSERT_EQ(packed.size(), n);
        EXPECT_EQ(packed.has_signatures(), with_signatures || n == 0);
        for (size_t i = 0; i < n; ++i) {
          ASSERT_EQ(packed.word(i), read->word(i));
          ASSERT_EQ(packed.keypoint(i).x, read->keypoint(i).x);
          if (with_signatures) ASSERT_EQ(packed.signature(i), read->signature(i));
        }
      }
    }
  }
}

TEST_F(Fixture, ReadersRunWhileWritersAdd) {
  auto index = CreateIndex();
  std::mt19937_64 rng(11);
  for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("seed" + std::to_string(i), RandomImage(rng, 60), {}));
  const std::vector<sift::FeatureSet> to_add = RandomImages(rng, 40, 60);
  const auto query = RandomImage(rng, 60);
  std::atomic<bool> done{false};
  std::atomic<int> started{0}, queries{0}, failures{0};
  std::vector<std::thread> readers;
  readers.reserve(2);
  for (int t = 0; t < 2; ++t) {
    readers.emplace_back([&] {
      ++started;
      while (!done) {
        const auto r = index->Query(query, Opts(50, 5));
        if (!r) {
          ++failures;
          continue;
        }
        // Every returned id resolves (a snapshot never shows half an image).
        for (const auto& x : r->results) {
          if (x.record.id != x.id || x.record.num_features != 60) ++failures;
        }
        ++queries;
      }
    });
  }
  // The writes start once both readers are querying; EXPECT (not ASSERT) while they run, so that a
  // failure still reaches the join below.
  while (started.load() < 2) std::this_thread::yield();
  for (int i = 0; i < 40; ++i) {
    EXPECT_TRUE(index->Add("new" + std::to_string(i), to_add[i], {})) << i;
    if (i % 3 == 0) {
      EXPECT_TRUE(index->Remove("seed" + std::to_string(i / 3))) << i;
    }
  }
  done = true;
  for (auto& t : readers) t.join();
  EXPECT_EQ(failures.load(), 0);
  EXPECT_GT(queries.load(), 0);
  EXPECT_EQ(index->Stats().num_images, 60u - 14u);
}


// A search's kept memory (accumulators, descriptors, transitive tables) is shared by the threads that
// search, one value per search at a time: searches of different images on many threads at once score
// exactly as the same searches one at a time.
TEST_F(Fixture, SearchesOnManyThreadsScoreAsOneAtATime) {
  auto index = CreateIndex();
  std::mt19937_64 rng(12);
  for (int i = 0; i < 40; ++i) ASSERT_TRUE(index->Add("img" + std::to_string(i), RandomImage(rng, 80), {}));
  const std::vector<sift::FeatureSet> queries = RandomImages(rng, 5, 80);
  QueryOptions options = Opts(40, 10, true);
  options.transitive_depth = 1;
  std::vector<std::vector<std::pair<std::string, float>>> expected;
  for (const auto& q : queries) {
    const auto r = index->Query(q, options);
    ASSERT_TRUE(r);
    ASSERT_FALSE(r->results.empty());
    expected.emplace_back();
    for (const auto& x : r->results) expected.back().emplace_back(x.id, x.score);
  }
  constexpr int kThreads = 6;
  std::atomic<int> mismatches{0}, runs{0};
  std::vector<std::thread> threads;
  threads.reserve(kThreads);
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      for (int i = 0; i < 20; ++i) {
        const size_t q = static_cast<size_t>(t + i) % queries.size();
        const auto r = index->Query(queries[q], options);
        std::vector<std::pair<std::string, float>> got;
        if (r) {
          for (const auto& x : r->results) got.emplace_back(x.id, x.score);
        }
        if (got != expected[q]) ++mismatches;
        ++runs;
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(runs.load(), kThreads * 20);
  EXPECT_EQ(mismatches.load(), 0);
}

// ==== Checkpoints (checkpoint.h) =====================================================================

// Checkpoint files in the index folder, sorted.
std::vector<std::string> CheckpointFiles(const fs::path& dir) {
  std::vector<std::string> out;
  for (const auto& item : fs::directory_iterator(dir)) {
    const std::string name = item.path().filename().string();
    if (name.find(".oxck") != std::string::npos) out.push_back(name);
  }
  std::sort(out.begin(), out.end());
  return out;
}

// CheckpointFiles without the postings' segment files (their number depends on merges), for tests of
// the geometry files and the manifest.
std::vector<std::string> HeadAndGeometryFiles(const fs::path& dir) {
  std::vector<std::string> out = CheckpointFiles(dir);
  std::erase_if(out, [](const std::string& name) { return name.starts_with("segment-"); });
  return out;
}

// The segment files among CheckpointFiles.
std::vector<std::string> SegmentFiles(const fs::path& dir) {
  std::vector<std::string> out = CheckpointFiles(dir);
  std::erase_if(out, [](const std::string& name) { return !name.starts_with("segment-"); });
  return out;
}

// The kill tests fork a child that opens the index, which starts threads: ThreadSanitizer cannot run a
// child starting threads after fork() in a multi-threaded process (it dies at once), so under it they
// are skipped, saying so; the normal and ASan builds run them.
#if defined(__SANITIZE_THREAD__)
#define SKIP_KILL_TEST_UNDER_TSAN() \
  GTEST_SKIP() << "fork() of a multi-threaded process: not supported by ThreadSanitizer (run in the normal and ASan builds)"
#else
#define SKIP_KILL_TEST_UNDER_TSAN() static_cast<void>(0)
#endif

class CheckpointFixture : public Fixture {
 protected:
  // Images i0..i(n-1), deterministic.
  sift::FeatureSet Image(int i) const {
    std::mt19937_64 rng(1000 + static_cast<uint64_t>(i));
    return RandomImage(rng, 30 + i % 50);
  }
  // In a child process: opens the index, runs `body`, then dies by SIGKILL (no close, no checkpoint),
  // at the end of body or at checkpoint stage `kill_at`.
  void InChildThenKill(const std::function<void(ImageIndex&)>& body, const std::string& kill_at = "",
                       const IndexOptions& options = {}) {
    const pid_t pid = fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      if (!kill_at.empty()) {
        SetCheckpointStageHookForTesting([kill_at](std::string_view stage) {
          if (stage == kill_at) ::raise(SIGKILL);
        });
      }
      auto index = ImageIndex::Open(dir_.string(), options);
      if (!index) ::_exit(2);
      body(**index);
      if (::testing::Test::HasFailure()) ::_exit(3);  // the parent's check of the exit status fails
      if (!kill_at.empty()) index->reset();  // close: writes the checkpoint, killed at `kill_at`
      ::raise(SIGKILL);
    }
    int status = 0;
    ASSERT_EQ(::waitpid(pid, &status, 0), pid);
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << "child status " << status;
  }
  // The scores of `index` equal those of a fresh index holding images `live` (exact statistics).
  void ExpectEqualsFresh(ImageIndex& index, const std::vector<int>& live) {
    const fs::path fresh_dir = dir_.string() + "_fresh";
    fs::remove_all(fresh_dir);
    {
      auto fresh = ImageIndex::Create(fresh_dir.string(), vocabulary_, "test-extractor/1");
      ASSERT_TRUE(fresh);
      for (const int i : live) ASSERT_TRUE((*fresh)->Add("i" + std::to_string(i), Image(i), {}));
      EXPECT_EQ(index.Stats().num_images, live.size());
      std::mt19937_64 rng(77);
      for (int q = 0; q < 5; ++q) {
        const auto query = RandomImage(rng, 60);
        const auto a = index.Query(query, Opts(1000, 10));
        const auto b = (*fresh)->Query(query, Opts(1000, 10));
        ASSERT_TRUE(a && b);
        ASSERT_EQ(a->results.size(), b->results.size());
        for (size_t k = 0; k < a->results.size(); ++k) {
          EXPECT_EQ(a->results[k].id, b->results[k].id);
          EXPECT_NEAR(a->results[k].score, b->results[k].score, 1e-6);
          EXPECT_EQ(a->results[k].inliers, b->results[k].inliers);
        }
      }
    }
    fs::remove_all(fresh_dir);
  }
  // Until the returned promise is set (or for 60 s), the checkpointer of the next index opened waits
  // before it verifies the geometry files; reset the hook (SetCheckpointStageHookForTesting) after.
  static std::promise<void> HoldBackGeometryVerification() {
    std::promise<void> release;
    std::shared_future<void> released = release.get_future().share();
    SetCheckpointStageHookForTesting([released](std::string_view stage) {
      if (stage == "verifying-geometry") released.wait_for(std::chrono::seconds(60));
    });
    return release;
  }
  // Body of DamagedGeometryDataIsFoundOnFirstUseAndNeverServed for geometry files of `version`.
  void ExpectDamagedGeometryDataNeverServed(uint32_t version);
  std::vector<int> Range(int begin, int end) {
    std::vector<int> out;
    for (int i = begin; i < end; ++i) out.push_back(i);
    return out;
  }
};

TEST_F(CheckpointFixture, CloseWritesACheckpointThatOpenUsesWithoutRebuilding) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  const std::vector<std::string> written = CheckpointFiles(dir_);
  EXPECT_EQ(written, (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck", "segment-1-0.oxck",
                                               "segment-1-1.oxck"}));
  // Reopened with nothing changed: no new checkpoint at open or close.
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ExpectEqualsFresh(**index, Range(0, 30));
  }
  EXPECT_EQ(CheckpointFiles(dir_), written);
}

// A checkpoint writes only the postings segments new since the previous one: a segment already in a
// file of the previous manifest is named again, the file left as it was (same inode, same bytes).
TEST_F(CheckpointFixture, CheckpointsWriteOnlyTheSegmentsNewSinceThePreviousOne) {
  IndexOptions options;
  options.checkpoint_changes = 5;
  std::vector<sift::FeatureSet> images;
  images.reserve(10);
  for (int i = 0; i < 10; ++i) images.push_back(Image(i));
  const auto batch_of = [&](int begin) {
    std::vector<BatchImage> batch;
    batch.reserve(5);
    for (int i = begin; i < begin + 5; ++i) batch.push_back({"i" + std::to_string(i), &images[i], {}, {}, {}});
    return batch;
  };
  // Waits (at most 60 s) for a checkpoint of generation `g`, then gives its segment files.
  const auto wait_for = [&](int g) {
    const std::string head = "postings-" + std::to_string(g) + ".oxck";
    for (int t = 0; t < 600 && !fs::exists(dir_ / head); ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_TRUE(fs::exists(dir_ / head)) << "no checkpoint " << g << " within 60 s";
    return SegmentFiles(dir_);
  };
  auto index = CreateIndex(options);
  for (const auto& r : index->AddBatch(batch_of(0))) ASSERT_TRUE(r) << r.error().ToString();
  const std::vector<std::string> first = wait_for(1);
  ASSERT_EQ(first, (std::vector<std::string>{"segment-1-0.oxck"}));
  struct stat before{};
  ASSERT_EQ(::stat((dir_ / first[0]).c_str(), &before), 0);
  for (const auto& r : index->AddBatch(batch_of(5))) ASSERT_TRUE(r) << r.error().ToString();
  EXPECT_EQ(wait_for(2), (std::vector<std::string>{"segment-1-0.oxck", "segment-2-0.oxck"}));
  struct stat after{};
  ASSERT_EQ(::stat((dir_ / first[0]).c_str(), &after), 0);
  EXPECT_EQ(after.st_ino, before.st_ino);
  EXPECT_EQ(after.st_mtim.tv_nsec, before.st_mtim.tv_nsec);
  index.reset();
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  ExpectEqualsFresh(**reopened, Range(0, 10));
}

TEST_F(CheckpointFixture, GeometryIsCheckedInSchedIdleAndCheckpointsAreNot) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  // sched_getscheduler(0) is the calling thread's policy on Linux.
  std::atomic<int> verifying_policy{-2};
  std::atomic<int> writing_policy{-2};
  SetCheckpointStageHookForTesting([&](std::string_view stage) {
    if (stage == "verifying-geometry") verifying_policy = sched_getscheduler(0);
    if (stage == "files-written") writing_policy = sched_getscheduler(0);
  });
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    for (int wait = 0; wait < 1000 && verifying_policy == -2; ++wait) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ASSERT_TRUE((*index)->Add("late", Image(30), {}));
  }  // closing writes a checkpoint with the new image
  SetCheckpointStageHookForTesting(nullptr);
  EXPECT_EQ(verifying_policy.load(), SCHED_IDLE);
  EXPECT_EQ(writing_policy.load(), SCHED_OTHER);
  EXPECT_EQ(sched_getscheduler(0), SCHED_OTHER);
}

// While a search runs, the check of the geometry files waits (it competes for the disk and the memory
// bus, which SCHED_IDLE does not share out). A search is held inside its filter; the check, let go
// while it is held, must not finish until the search does; then it finishes.
TEST_F(CheckpointFixture, GeometryCheckWaitsWhileASearchRuns) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  std::promise<void> start_check;
  std::shared_future<void> check_may_start = start_check.get_future().share();
  std::atomic<bool> checked{false};
  SetCheckpointStageHookForTesting([&, check_may_start](std::string_view stage) {
    if (stage == "verifying-geometry") check_may_start.wait_for(std::chrono::seconds(60));
    if (stage == "geometry-verified") checked = true;
  });
  class HoldingFilter final : public ImageFilter {
   public:
    std::promise<void> entered;
    std::shared_future<void> release;
    mutable std::once_flag once;
    bool Matches(const ImageRecord&) const override {
      std::call_once(once, [this] { const_cast<std::promise<void>&>(entered).set_value(); });
      release.wait_for(std::chrono::seconds(60));
      return true;
    }
  };
  std::promise<void> release_search;
  auto filter = std::make_shared<HoldingFilter>();
  filter->release = release_search.get_future().share();
  std::future<void> entered = filter->entered.get_future();
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    QueryOptions options;
    options.filter = filter;
    std::thread search([&] { EXPECT_TRUE((*index)->Query(Image(3), options)); });
    ASSERT_EQ(entered.wait_for(std::chrono::seconds(60)), std::future_status::ready);
    start_check.set_value();  // the search is running: the check starts now, and must wait for it
    // Unpaused, 30 images' files are checked in about a millisecond.
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    EXPECT_FALSE(checked.load()) << "the geometry check went on while a search ran";
    release_search.set_value();
    search.join();
    for (int wait = 0; wait < 6000 && !checked; ++wait) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    EXPECT_TRUE(checked.load()) << "the geometry check did not finish once the search had";
  }
  SetCheckpointStageHookForTesting(nullptr);
}

// Within a second of a search's end the check reads at most one block per 50 ms (VerifyParts): its first
// read comes no sooner than 50 ms after it starts (or a second after the search, whichever is first).
TEST_F(CheckpointFixture, GeometryCheckSlowsRightAfterASearch) {
  using Clock = std::chrono::steady_clock;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  std::promise<void> start_check;
  std::shared_future<void> check_may_start = start_check.get_future().share();
  std::mutex mutex;
  std::optional<Clock::time_point> released, first_read;
  std::atomic<bool> checked{false};
  SetCheckpointStageHookForTesting([&, check_may_start](std::string_view stage) {
    if (stage == "verifying-geometry") {
      check_may_start.wait_for(std::chrono::seconds(60));
      std::lock_guard<std::mutex> lock(mutex);
      released = Clock::now();
    }
    if (stage == "geometry-read") {
      std::lock_guard<std::mutex> lock(mutex);
      if (!first_read) first_read = Clock::now();
    }
    if (stage == "geometry-verified") checked = true;
  });
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    const Clock::time_point search_began = Clock::now();
    ASSERT_TRUE((*index)->Query(Image(3), {}));
    start_check.set_value();
    for (int wait = 0; wait < 6000 && !checked; ++wait) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    ASSERT_TRUE(checked.load()) << "the geometry check did not finish";
    std::lock_guard<std::mutex> lock(mutex);
    ASSERT_TRUE(released && first_read);
    const Clock::time_point earliest = std::min(*released + std::chrono::milliseconds(50), search_began + std::chrono::seconds(1));
    EXPECT_GE(*first_read, earliest - std::chrono::milliseconds(1))
        << "read " << std::chrono::duration<double, std::milli>(*first_read - *released).count()
        << " ms after the check started, right after a search";
  }
  SetCheckpointStageHookForTesting(nullptr);
}

// The check of a checkpoint file leaves the page cache as it found it: pages it held stay, pages it
// did not are not left there (a 16 GB check at 1M images would otherwise push the searches' pages out
// and fill memory; index/README.md). Seen with mincore on a mapping never touched.
TEST(CheckpointFileTest, TheCheckLeavesThePageCacheAsItWas) {
  // Beside the test binary, not in /tmp: pages of a tmpfs file are always in memory.
  const fs::path dir = fs::current_path() / ("oxbow_check_cache_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  std::mt19937_64 rng(5);
  std::vector<uint8_t> bytes((size_t{10} << 20) + 12345);  // more than two 4 MiB reads, a partial page at the end
  for (auto& b : bytes) b = static_cast<uint8_t>(rng());
  auto file = WriteCheckpointFile(dir.string(), "geometry-test.oxck",
                                  [&](const ByteSink& sink) { sink(std::span<const uint8_t>(bytes)); });
  ASSERT_TRUE(file) << file.error().ToString();
  const std::string path = (dir / file->name).string();
  const int fd = ::open(path.c_str(), O_RDONLY);
  ASSERT_GE(fd, 0);
  void* mapping = ::mmap(nullptr, bytes.size(), PROT_READ, MAP_SHARED, fd, 0);
  ASSERT_NE(mapping, MAP_FAILED);
  const auto page = static_cast<size_t>(::sysconf(_SC_PAGESIZE));
  const size_t pages = (bytes.size() + page - 1) / page;
  const auto resident = [&](size_t first, size_t last) {  // of pages [first, last)
    std::vector<unsigned char> in(pages);
    EXPECT_EQ(::mincore(mapping, bytes.size(), in.data()), 0);
    size_t count = 0;
    for (size_t p = first; p < last; ++p) count += in[p] & 1;
    return count;
  };
  ASSERT_EQ(::posix_fadvise(fd, 0, 0, POSIX_FADV_RANDOM), 0);  // this test's reads bring in only what they read
  const auto drop = [&] { ASSERT_EQ(::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED), 0); };
  drop();  // WriteCheckpointFile synced it: clean pages, dropped
  if (resident(0, pages) > pages / 2) {
    ::munmap(mapping, bytes.size());
    ::close(fd);
    fs::remove_all(dir);
    GTEST_SKIP() << "the file system of " << dir << " keeps files in memory (posix_fadvise dropped nothing)";
  }
  // Not held: read, checked, and not left in the cache.
  ASSERT_TRUE(VerifyCheckpointFile(dir.string(), *file));
  EXPECT_EQ(resident(0, pages), 0u) << "of " << pages << " pages";
  // Held in part (the first 3 MiB and the last 1 MiB, as a search's reads would leave them): those stay,
  // and only those.
  std::vector<uint8_t> scratch(bytes.size());
  const size_t head = size_t{3} << 20, tail_from = bytes.size() - (size_t{1} << 20);
  ASSERT_EQ(::pread(fd, scratch.data(), head, 0), static_cast<ssize_t>(head));
  ASSERT_EQ(::pread(fd, scratch.data(), bytes.size() - tail_from, static_cast<off_t>(tail_from)),
            static_cast<ssize_t>(bytes.size() - tail_from));
  const size_t held_before = resident(0, pages);
  ASSERT_GE(held_before, (head + bytes.size() - tail_from) / page);
  ASSERT_TRUE(VerifyCheckpointFile(dir.string(), *file));
  EXPECT_EQ(resident(0, head / page), head / page) << "pages held before the check were dropped";
  EXPECT_EQ(resident(tail_from / page + 1, pages), pages - tail_from / page - 1);
  EXPECT_EQ(resident(head / page, tail_from / page), 0u) << "the check left pages it read in the cache";
  EXPECT_LE(resident(0, pages), held_before) << "the check left pages it read in the cache";
  // Held whole: still held, and the check still finds a damaged file.
  ASSERT_EQ(::pread(fd, scratch.data(), bytes.size(), 0), static_cast<ssize_t>(bytes.size()));
  ASSERT_TRUE(VerifyCheckpointFile(dir.string(), *file));
  EXPECT_EQ(resident(0, pages), pages);
  CheckpointFile wrong = *file;
  wrong.checksum ^= 1;
  const Status damaged = VerifyCheckpointFile(dir.string(), wrong);
  ASSERT_FALSE(damaged);
  EXPECT_EQ(damaged.error().code, ErrorCode::kCorruptData);
  ::munmap(mapping, bytes.size());
  ::close(fd);
  fs::remove_all(dir);
}

TEST_F(CheckpointFixture, OpenReplaysChangesAfterTheCheckpointAndEqualsAFreshIndex) {
  SKIP_KILL_TEST_UNDER_TSAN();
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  // Killed after more adds, removes (of checkpointed and new images) and a replace: only the catalogue
  // has them.
  InChildThenKill([&](ImageIndex& index) {
    for (int i = 30; i < 45; ++i) ASSERT_TRUE(index.Add("i" + std::to_string(i), Image(i), {}));
    for (const int i : {3, 17, 40}) ASSERT_TRUE(index.Remove("i" + std::to_string(i)));
    ASSERT_TRUE(index.Replace("i5", Image(5), {}));
  });
  std::vector<int> live;
  for (int i = 0; i < 45; ++i) {
    if (i != 3 && i != 17 && i != 40) live.push_back(i);
  }
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ(CheckpointFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck",
                                                                "segment-1-0.oxck", "segment-1-1.oxck"}))
        << "open replays the delta instead of rebuilding";
    ExpectEqualsFresh(**index, live);
    EXPECT_FALSE((*index)->Contains("i3"));
  }
  // The close checkpointed the replayed changes: generation 2 adds geometry for the new numbers only,
  // and a segment file for the new segment; the segments of generation 1 are named again, not rewritten.
  EXPECT_EQ(CheckpointFiles(dir_),
            (std::vector<std::string>{"geometry-1-0.oxck", "geometry-2-0.oxck", "postings-2.oxck",
                                      "segment-1-0.oxck", "segment-1-1.oxck", "segment-2-0.oxck"}));
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, live);
}

TEST_F(CheckpointFixture, DamagedTruncatedOrMissingFilesAreRepairedFromTheCatalogue) {
  const std::vector<std::pair<std::string, std::function<void(const fs::path&)>>> damages = {
      {"flipped byte", [](const fs::path& p) {
         std::fstream f(p, std::ios::in | std::ios::out | std::ios::binary);
         f.seekg(40);
         const char c = static_cast<char>(f.get());
         f.seekp(40);
         f.put(static_cast<char>(c ^ 0x5a));
       }},
      {"truncated", [](const fs::path& p) { fs::resize_file(p, fs::file_size(p) / 2); }},
      {"missing", [](const fs::path& p) { fs::remove(p); }},
  };
  for (const std::string target : {"postings-1.oxck", "segment-1-0.oxck", "geometry-1-0.oxck"}) {
    for (const auto& [what, damage] : damages) {
      std::string trace = target;
      trace += " ";
      trace += what;
      SCOPED_TRACE(trace);
      fs::remove_all(dir_);
      {
        auto index = CreateIndex();
        for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
      }
      damage(dir_ / target);
      auto index = ImageIndex::Open(dir_.string());
      ASSERT_TRUE(index) << index.error().ToString();
      ExpectEqualsFresh(**index, Range(0, 20));
      // Rebuilt from the catalogue and checkpointed again (generation 2, in the background or at the
      // latest at close); the old files are gone.
      index->reset();
      EXPECT_EQ(CheckpointFiles(dir_),
                (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck", "segment-2-0.oxck"}));
    }
  }
}

// Every stored keypoint and word of images i0..i(n-1).
std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> AllFeatures(const ImageIndex& index, int n) {
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> out;
  for (int i = 0; i < n; ++i) {
    auto features = FeaturesOf(index, "i" + std::to_string(i));
    EXPECT_TRUE(features) << features.error().ToString();
    if (!features) return out;
    std::vector<float> keypoints;
    for (const sift::Keypoint& k : features->keypoints) keypoints.insert(keypoints.end(), {k.x, k.y, k.scale, k.orientation});
    out.emplace_back(std::move(keypoints), features->words);
  }
  return out;
}

// Inverts every byte of the second half of a geometry file's feature data (its image table intact).
void DamageGeometryData(const fs::path& path) {
  std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
  std::vector<char> bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  ASSERT_GT(bytes.size(), 4000u);
  for (size_t i = bytes.size() / 2; i < bytes.size(); ++i) bytes[i] = static_cast<char>(~bytes[i]);
  f.seekp(0);
  f.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

// Open checks a geometry file's size and image table only; its data is checked on use (each image's
// checksum, or the whole file for the versions without per-image sums that older builds wrote). Damaged
// feature data is never served: whichever comes first (a query's use, or the background verification
// after open), the images come from the catalogue, and the next checkpoint rewrites them.
TEST_F(CheckpointFixture, DamagedGeometryDataIsFoundOnFirstUseAndNeverServed) {
  for (const uint32_t version : {3u, 1u}) {
    SCOPED_TRACE("geometry format version " + std::to_string(version));
    fs::remove_all(dir_);
    ExpectDamagedGeometryDataNeverServed(version);
  }
}

void CheckpointFixture::ExpectDamagedGeometryDataNeverServed(uint32_t version) {
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> before;
  {
    SetGeometryFormatVersionForTesting(version);
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
    before = AllFeatures(*index, 20);
  }
  SetGeometryFormatVersionForTesting(3);
  ASSERT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"}));
  const std::vector<std::string> segments = SegmentFiles(dir_);
  DamageGeometryData(dir_ / "geometry-1-0.oxck");
  {
    // The background verification waits until the images were used: their use finds the damage.
    std::promise<void> used = HoldBackGeometryVerification();
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString() << " (open must not read the geometry data)";
    EXPECT_EQ(AllFeatures(**index, 20), before);
    ExpectEqualsFresh(**index, Range(0, 20));
    used.set_value();
    index->reset();
    SetCheckpointStageHookForTesting(nullptr);
  }
  // The damaged file was replaced by a new one holding its images (the postings were sound: their
  // segment files are kept).
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
  EXPECT_EQ(SegmentFiles(dir_), segments);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ(AllFeatures(**index, 20), before);
    ExpectEqualsFresh(**index, Range(0, 20));
  }
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
  EXPECT_EQ(SegmentFiles(dir_), segments);
}

// After a background checkpoint, the images it wrote view its geometry files instead of the copies
// Add kept in memory (an index that ingested 1M images would hold 17 GB of them): their
// memory leaves IndexStats::geometry_bytes, and features and searches stay the same. Damage to such a
// file is found on use and never served, and the next checkpoint rewrites it, as for a file an open loaded.
TEST_F(CheckpointFixture, ImagesViewTheGeometryFilesTheirCheckpointWrote) {
  IndexOptions options;
  options.checkpoint_changes = 20;
  std::promise<void> go;
  std::shared_future<void> may_commit = go.get_future().share();
  std::atomic<int> viewed{0};
  SetCheckpointStageHookForTesting([&, may_commit](std::string_view stage) {
    if (stage == "files-written") may_commit.wait_for(std::chrono::seconds(60));
    if (stage == "geometry-viewed") ++viewed;
  });
  {
    auto index = CreateIndex(options);
    std::vector<sift::FeatureSet> images;
    images.reserve(20);
    for (int i = 0; i < 20; ++i) images.push_back(Image(i));
    std::vector<BatchImage> batch;
    batch.reserve(20);
    for (int i = 0; i < 20; ++i) batch.push_back({"i" + std::to_string(i), &images[i], {}, {}, {}});
    for (const auto& r : index->AddBatch(batch)) ASSERT_TRUE(r) << r.error().ToString();
    // The checkpoint's files are written, not committed: the images are still in memory.
    const auto before = AllFeatures(*index, 20);
    size_t features = 0;
    for (const auto& image : images) features += image.keypoints.size();
    EXPECT_GE(index->Stats().geometry_bytes, features * kPackedFeatureBytes);
    go.set_value();
    for (int t = 0; t < 600 && viewed == 0; ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ASSERT_EQ(viewed.load(), 1) << "no checkpoint within 60 s";
    EXPECT_EQ(index->Stats().geometry_bytes, 20 * sizeof(PackedFeatures));
    EXPECT_EQ(AllFeatures(*index, 20), before);
    ExpectEqualsFresh(*index, Range(0, 20));
    // Damaged under the running index: each image's check finds it, the catalogue serves them.
    ASSERT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"}));
    DamageGeometryData(dir_ / "geometry-1-0.oxck");
    EXPECT_EQ(AllFeatures(*index, 20), before);
    ExpectEqualsFresh(*index, Range(0, 20));
  }
  SetCheckpointStageHookForTesting(nullptr);
  // Close wrote a checkpoint without the damaged file.
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  ExpectEqualsFresh(**reopened, Range(0, 20));
}

// A remove or replace of an image whose checkpoint data is damaged, before anything used it, takes
// its words from its catalogue row before deleting that row: the statistics stay exact.
TEST_F(CheckpointFixture, RemovingADamagedImageBeforeItsFirstUseKeepsTheIndexExact) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  DamageGeometryData(dir_ / "geometry-1-0.oxck");  // the data of the last images (i12 and i15 among them)
  std::vector<int> live = Range(0, 20);
  live.erase(live.begin() + 15);
  {
    std::promise<void> done = HoldBackGeometryVerification();
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_TRUE((*index)->Remove("i15"));
    EXPECT_TRUE((*index)->Replace("i12", Image(12), {}));
    ExpectEqualsFresh(**index, live);
    done.set_value();
    index->reset();
    SetCheckpointStageHookForTesting(nullptr);
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, live);
}

// Without any use, the checkpointer verifies every geometry file after open and rewrites a damaged
// one while the index stays open.
TEST_F(CheckpointFixture, GeometryFilesAreVerifiedInTheBackgroundAfterOpen) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  DamageGeometryData(dir_ / "geometry-1-0.oxck");
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  const std::vector<std::string> rewritten = {"geometry-2-0.oxck", "postings-2.oxck"};
  for (int i = 0; i < 600 && HeadAndGeometryFiles(dir_) != rewritten; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_EQ(HeadAndGeometryFiles(dir_), rewritten) << "no rewrite within 60 s of open";
  ExpectEqualsFresh(**index, Range(0, 20));
}

// Checkpoints do not wait for that check: on cores kept busy its SCHED_IDLE thread may not run for
// minutes (held back here). A checkpoint meanwhile keeps the geometry file not checked yet.
TEST_F(CheckpointFixture, CheckpointsDoNotWaitForTheBackgroundCheckOfTheGeometryFiles) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  ASSERT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"}));
  // A later checkpoint was committed (postings-1 deleted), and it kept the file not checked yet.
  const auto checkpointed = [&] {
    const std::vector<std::string> files = CheckpointFiles(dir_);
    return std::find(files.begin(), files.end(), "postings-1.oxck") == files.end() &&
           std::find(files.begin(), files.end(), "geometry-1-0.oxck") != files.end();
  };
  {
    std::promise<void> release = HoldBackGeometryVerification();
    IndexOptions options;
    options.checkpoint_changes = 1;
    auto index = ImageIndex::Open(dir_.string(), options);
    ASSERT_TRUE(index) << index.error().ToString();
    for (int i = 20; i < 25; ++i) ASSERT_TRUE((*index)->Add("i" + std::to_string(i), Image(i), {}));
    for (int i = 0; i < 300 && !checkpointed(); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_TRUE(checkpointed()) << "no checkpoint within 30 s while the geometry check waited";
    release.set_value();
    index->reset();
    SetCheckpointStageHookForTesting(nullptr);
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, Range(0, 25));
  EXPECT_TRUE(checkpointed());
}

// One process at a time in a folder (folder_lock.h): a second open, in this process or another, is
// refused while the first holds it, and works once it closed or died by kill -9 (no stale lock).
TEST_F(CheckpointFixture, AnIndexFolderIsOpenInOneProcessAtATime) {
  SKIP_KILL_TEST_UNDER_TSAN();
  const auto refused_by = [&](const std::string& holder) {
    auto second = ImageIndex::Open(dir_.string());
    if (second) return ::testing::AssertionFailure() << "a second open of the folder was allowed";
    const std::string& message = second.error().message;
    if (second.error().code != ErrorCode::kIoError || message.find("open in another process") == std::string::npos ||
        message.find("(pid " + holder + ")") == std::string::npos) {
      return ::testing::AssertionFailure() << second.error().ToString();
    }
    return ::testing::AssertionSuccess();
  };
  {
    auto index = CreateIndex();
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
    EXPECT_TRUE(refused_by(std::to_string(::getpid())));
    EXPECT_EQ(ImageIndex::Create(dir_.string(), vocabulary_, "test-extractor/1").error().code, ErrorCode::kAlreadyExists);
  }
  int ready[2];
  ASSERT_EQ(::pipe(ready), 0);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    auto index = ImageIndex::Open(dir_.string());
    if (!index) ::_exit(2);
    (void)!::write(ready[1], "o", 1);
    while (true) ::pause();  // holds the folder until killed
  }
  ::close(ready[1]);
  char byte = 0;
  ASSERT_EQ(::read(ready[0], &byte, 1), 1) << "the child could not open the index";
  ::close(ready[0]);
  EXPECT_TRUE(refused_by(std::to_string(pid)));
  ::kill(pid, SIGKILL);
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, Range(0, 5));
}

TEST_F(CheckpointFixture, KillAtEveryStageOfACheckpointLosesNothing) {
  SKIP_KILL_TEST_UNDER_TSAN();
  for (const std::string stage : {"file-unsynced", "segment-written", "files-written", "manifest-committed", "cleaned"}) {
    SCOPED_TRACE(stage);
    fs::remove_all(dir_);
    {
      auto index = CreateIndex();
      for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
    }
    InChildThenKill(
        [&](ImageIndex& index) {
          for (int i = 20; i < 30; ++i) ASSERT_TRUE(index.Add("i" + std::to_string(i), Image(i), {}));
          ASSERT_TRUE(index.Remove("i2"));
        },
        stage);
    std::vector<int> live = Range(0, 30);
    live.erase(live.begin() + 2);
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ExpectEqualsFresh(**index, live);
    // Whichever manifest is committed, the open deleted every file it does not name.
    // Segment files: those of generation 1 the new manifest still names, and new ones of generation 2.
    const bool committed = stage == "manifest-committed" || stage == "cleaned";
    const std::vector<std::string> expected =
        committed ? std::vector<std::string>{"geometry-1-0.oxck", "geometry-2-0.oxck", "postings-2.oxck"}
                  : std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"};
    EXPECT_EQ(HeadAndGeometryFiles(dir_), expected);
    for (const std::string& segment : SegmentFiles(dir_)) {
      EXPECT_TRUE(segment.starts_with("segment-1-") || (committed && segment.starts_with("segment-2-"))) << segment;
    }
  }
}

// A version-1 catalogue (features as the last column of `images`) as the previous code wrote it,
// made from a version-2 index's rows.
TEST_F(CheckpointFixture, VersionOneCatalogueIsMigratedInPlace) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 12; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
    ASSERT_TRUE(index->Remove("i11"));  // the sequence is above the highest number left
  }
  const fs::path v2 = dir_ / "v2.sqlite";
  fs::rename(dir_ / "catalogue.sqlite", v2);
  for (const auto& name : CheckpointFiles(dir_)) fs::remove(dir_ / name);
  ExecSql(dir_ / "catalogue.sqlite",
          "CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);"
          "CREATE TABLE images(number INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE,"
          " source_path TEXT NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL,"
          " num_features INTEGER NOT NULL, metadata_json TEXT NOT NULL, added_unix_ms INTEGER NOT NULL,"
          " features BLOB NOT NULL);"
          "ATTACH '" + v2.string() + "' AS v2;"
          "INSERT INTO meta SELECT key, value FROM v2.meta WHERE key != 'checkpoint';"
          "UPDATE meta SET value = '1' WHERE key = 'schema_version';"
          "INSERT INTO images SELECT i.*, f.blob FROM v2.images i JOIN v2.features f USING (number);"
          "UPDATE sqlite_sequence SET seq = (SELECT seq FROM v2.sqlite_sequence WHERE name = 'images');");
  fs::remove(v2);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ExpectEqualsFresh(**index, Range(0, 11));
    // Numbers continue above the removed one: a new image gets number 13.
    ASSERT_TRUE((*index)->Add("i12", Image(12), {}));
  }
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open((dir_ / "catalogue.sqlite").c_str(), &db), SQLITE_OK);
  sqlite3_stmt* stmt = nullptr;
  ASSERT_EQ(sqlite3_prepare_v2(db,
                               "SELECT (SELECT value FROM meta WHERE key = 'schema_version'),"
                               " (SELECT number FROM images WHERE id = 'i12'), (SELECT count(*) FROM features)",
                               -1, &stmt, nullptr),
            SQLITE_OK);
  ASSERT_EQ(sqlite3_step(stmt), SQLITE_ROW);
  EXPECT_STREQ(reinterpret_cast<const char*>(sqlite3_column_text(stmt, 0)), "2");
  EXPECT_EQ(sqlite3_column_int(stmt, 1), 13);
  EXPECT_EQ(sqlite3_column_int(stmt, 2), 12);
  sqlite3_finalize(stmt);
  sqlite3_close(db);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  std::vector<int> live = Range(0, 11);
  live.push_back(12);
  ExpectEqualsFresh(**index, live);
}

TEST_F(CheckpointFixture, BackgroundCheckpointWhileWritingIsConsistent) {
  SKIP_KILL_TEST_UNDER_TSAN();
  CreateIndex();
  IndexOptions options;
  options.checkpoint_changes = 4;
  InChildThenKill([&](ImageIndex& index) {
    for (int i = 0; i < 40; ++i) ASSERT_TRUE(index.Add("i" + std::to_string(i), Image(i), {}));
    ASSERT_TRUE(index.Remove("i7"));
    // Wait (at most 60 s) for a background checkpoint after the one of the open's rebuild (there was
    // none before), then die without closing.
    const auto later_checkpoint = [&] {
      const auto files = CheckpointFiles(dir_);
      return std::any_of(files.begin(), files.end(),
                         [](const std::string& f) { return f.starts_with("postings-") && f != "postings-1.oxck"; });
    };
    for (int t = 0; t < 600 && !later_checkpoint(); ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ASSERT_TRUE(later_checkpoint());
  }, "", options);
  std::vector<int> live = Range(0, 40);
  live.erase(live.begin() + 7);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  // Opened from a background checkpoint (no rebuild: no generation above the last one written).
  const auto files = CheckpointFiles(dir_);
  EXPECT_EQ(std::count_if(files.begin(), files.end(), [](const std::string& f) { return f.starts_with("postings-"); }), 1);
  ExpectEqualsFresh(**index, live);
}

// A damaged BLOB of an image added after the checkpoint (read by the replay) costs that image only.
TEST_F(CheckpointFixture, DamagedBlobAddedAfterTheCheckpointCostsThatImageOnly) {
  SKIP_KILL_TEST_UNDER_TSAN();
  {
    auto index = CreateIndex();
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
  }
  InChildThenKill([&](ImageIndex& index) { ASSERT_TRUE(index.Add("late", Image(9), {})); });
  ExecSql(dir_ / "catalogue.sqlite",
          "UPDATE features SET blob = substr(blob, 1, 30) || x'ff' || substr(blob, 32) "
          "WHERE number = (SELECT number FROM images WHERE id = 'late')");
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Get("late").error().code, ErrorCode::kNotFound);
  ExpectEqualsFresh(**index, Range(0, 5));
}

// Descriptors open in this process.
size_t OpenDescriptors() {
  size_t n = 0;
  for ([[maybe_unused]] const auto& item : fs::directory_iterator("/proc/self/fd")) ++n;
  return n;
}

// Add / replace / remove churn over a few ids with a checkpoint every few changes: the geometry files
// of removed and replaced images are dropped or compacted, so the files on disk and the descriptors
// their mappings keep stay bounded (each checkpoint wrote a new file that no later one dropped), and a
// reopen from the compacted checkpoint serves the same results.
TEST_F(CheckpointFixture, GeometryFilesAndDescriptorsStayBoundedUnderChurn) {
  IndexOptions options;
  options.checkpoint_changes = 4;
  std::atomic<int> checkpoints{0};
  SetCheckpointStageHookForTesting([&](std::string_view stage) {
    if (stage == "geometry-viewed") ++checkpoints;
  });
  const size_t descriptors_before = OpenDescriptors();
  const auto geometry_files = [&] {
    const std::vector<std::string> files = CheckpointFiles(dir_);
    return static_cast<size_t>(
        std::count_if(files.begin(), files.end(), [](const std::string& f) { return f.starts_with("geometry-"); }));
  };
  constexpr int kIds = 8;
  std::set<int> live;
  size_t most_files = 0, most_descriptors = 0;
  {
    auto index = CreateIndex(options);
    std::mt19937_64 rng(5);
    for (int round = 0; round < 50; ++round) {
      const int seen = checkpoints.load();
      for (int k = 0; k < 4; ++k) {
        const int i = static_cast<int>(rng() % kIds);
        const std::string id = "i" + std::to_string(i);
        if (!live.count(i)) {
          ASSERT_TRUE(index->Add(id, Image(i), {}));
          live.insert(i);
        } else if (rng() % 2 == 0) {
          ASSERT_TRUE(index->Replace(id, Image(i), {}));
        } else {
          ASSERT_TRUE(index->Remove(id));
          live.erase(i);
        }
      }
      for (int t = 0; t < 600 && checkpoints.load() == seen; ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      ASSERT_GT(checkpoints.load(), seen) << "no checkpoint within 60 s in round " << round;
      most_files = std::max(most_files, geometry_files());
      most_descriptors = std::max(most_descriptors, OpenDescriptors());
    }
    // At most one file per live image (each file kept is at least half live) and the newest one.
    EXPECT_LE(most_files, size_t{kIds} + 1);
    // The files' descriptors, the catalogue's and the folder lock's.
    EXPECT_LE(most_descriptors, descriptors_before + kIds + 1 + 8);
    ExpectEqualsFresh(*index, std::vector<int>(live.begin(), live.end()));
  }
  SetCheckpointStageHookForTesting(nullptr);
  EXPECT_LE(geometry_files(), size_t{kIds} + 1);
  auto index = ImageIndex::Open(dir_.string(), options);
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, std::vector<int>(live.begin(), live.end()));
}

// A geometry file truncated under the running index, after or before its background check, is never
// read past its end (through the mapping that would kill the process with SIGBUS): its images are
// served from the catalogue. Run in a child, whose death would fail the parent's check.
TEST_F(CheckpointFixture, AGeometryFileTruncatedUnderTheRunningIndexIsNeverReadPastItsEnd) {
  SKIP_KILL_TEST_UNDER_TSAN();
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> before;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
    before = AllFeatures(*index, 20);
  }
  const fs::path geometry = dir_ / "geometry-1-0.oxck";
  const fs::path copy = dir_.string() + "_geometry";
  fs::copy_file(geometry, copy, fs::copy_options::overwrite_existing);
  for (const bool checked_first : {true, false}) {
    SCOPED_TRACE(checked_first ? "truncated after the background check" : "truncated before it");
    fs::copy_file(copy, geometry, fs::copy_options::overwrite_existing);
    const pid_t pid = fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      std::promise<void> checked;
      std::shared_future<void> checked_future = checked.get_future().share();
      std::atomic<bool> released{false};
      SetCheckpointStageHookForTesting([&, checked_first](std::string_view stage) {
        if (stage == "geometry-verified" && checked_first && !released.exchange(true)) checked.set_value();
        if (stage == "verifying-geometry" && !checked_first) checked_future.wait_for(std::chrono::seconds(60));
      });
      auto index = ImageIndex::Open(dir_.string());
      if (!index) ::_exit(2);
      if (checked_first && checked_future.wait_for(std::chrono::seconds(60)) != std::future_status::ready) ::_exit(3);
      fs::resize_file(geometry, fs::file_size(geometry) / 2);
      if (AllFeatures(**index, 20) != before) ::_exit(4);
      auto similar = (*index)->QuerySimilar("i3", Opts(5, 10));
      if (!similar || similar->results.empty() || similar->results[0].id != "i3") ::_exit(5);
      if (!checked_first) checked.set_value();
      ::_exit(0);
    }
    int status = 0;
    ASSERT_EQ(::waitpid(pid, &status, 0), pid);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0)
        << "child " << (WIFSIGNALED(status) ? "killed by signal " + std::to_string(WTERMSIG(status))
                                            : "exit status " + std::to_string(WEXITSTATUS(status)));
  }
  fs::remove(copy);
}

// Geometry bytes changed on disk after the background check passed are not served either: each use
// of an image checks its own checksum.
TEST_F(CheckpointFixture, GeometryDamagedAfterItsBackgroundCheckIsNeverServed) {
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> before;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add("i" + std::to_string(i), Image(i), {}));
    before = AllFeatures(*index, 20);
  }
  std::promise<void> checked;
  std::atomic<bool> released{false};
  SetCheckpointStageHookForTesting([&](std::string_view stage) {
    if (stage == "geometry-verified" && !released.exchange(true)) checked.set_value();
  });
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ASSERT_EQ(checked.get_future().wait_for(std::chrono::seconds(60)), std::future_status::ready);
    DamageGeometryData(dir_ / "geometry-1-0.oxck");
    EXPECT_EQ(AllFeatures(**index, 20), before);
    ExpectEqualsFresh(**index, Range(0, 20));
  }
  SetCheckpointStageHookForTesting(nullptr);
  // The next checkpoint (at close) rewrote the damaged file.
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
}

}  // namespace
}  // namespace oxbow::index
