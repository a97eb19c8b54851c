// The ImageIndex facade: add, add a batch, replace, remove, get, list, query (re-ranking, transitive
// verification, regions, budgets), restart, concurrent readers and writers.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

#include <array>
#include <filesystem>
#include <fstream>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

class ImageIndexTest : public IndexFixture {};
TEST_F(ImageIndexTest, AddGetListRemove) {
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

TEST_F(ImageIndexTest, BadInputIsAnErrorValue) {
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

TEST_F(ImageIndexTest, CreateRefusesExistingIndexAndForeignExtractor) {
  CreateIndex();
  EXPECT_EQ(ImageIndex::Create(dir_.string(), vocabulary_, "test-extractor/1").error().code, ErrorCode::kAlreadyExists);
  const auto other = ImageIndex::Create((dir_ / "sub").string(), vocabulary_, "other/1");
  ASSERT_FALSE(other);
  EXPECT_EQ(other.error().code, ErrorCode::kIncompatible);
  EXPECT_EQ(ImageIndex::Open((dir_ / "missing").string()).error().code, ErrorCode::kNotFound);
}

// A folder of other files (a mistyped --out) is refused and left as it was; what a creation that did not
// finish leaves (the lock and the vocabulary copy) is taken.
TEST_F(ImageIndexTest, CreateRefusesAFolderOfOtherFiles) {
  const std::filesystem::path photos = dir_ / "photos";
  std::filesystem::create_directories(photos);
  std::ofstream(photos / "holiday.jpg") << "not an index";
  const auto refused = ImageIndex::Create(photos.string(), vocabulary_, "test-extractor/1");
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, ErrorCode::kAlreadyExists) << refused.error().ToString();
  size_t entries = 0;
  for ([[maybe_unused]] const auto& entry : std::filesystem::directory_iterator(photos)) ++entries;
  EXPECT_EQ(entries, 1u);
  const std::filesystem::path unfinished = dir_ / "unfinished";
  std::filesystem::create_directories(unfinished / "lost+found");  // a volume mounted there
  std::ofstream(unfinished / ".keep") << "";
  std::ofstream(unfinished / "LOCK") << "1";
  ASSERT_TRUE(vocabulary_.Write((unfinished / "vocabulary.oxvoc").string()));
  const auto created = ImageIndex::Create(unfinished.string(), vocabulary_, "test-extractor/1");
  EXPECT_TRUE(created) << created.error().ToString();
}

TEST_F(ImageIndexTest, SpatialReRankingFindsTheTransformedImage) {
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
    ASSERT_TRUE(index->Add(NumberedId("img", i), images.back(), {}));
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
  for (size_t i = 0; i < images.size(); ++i) ASSERT_TRUE((*stopped)->Add(NumberedId("img", i), images[i], {}));
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

TEST_F(ImageIndexTest, TransitiveVerificationReachesViewsThatOnlyMatchAResult) {
  // "hub" shows the whole object; the query shows its even features, "far" its odd ones (another
  // viewpoint, plus clutter). far and the query share no object feature, so only hub links them.
  std::mt19937_64 rng(11);
  auto index = CreateIndex();
  const sift::FeatureSet hub = RandomImage(rng, 240);
  std::vector<uint32_t> hub_words(hub.size());
  vocabulary_.Quantize(hub.descriptors, hub_words);
  ASSERT_TRUE(index->Add("hub", hub, {}));
  for (int i = 0; i < 25; ++i) ASSERT_TRUE(index->Add(NumberedId("other", i), RandomImage(rng, 150), {}));
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
  EXPECT_EQ(plain->results[0].via, "");  // verified against the query itself
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
    EXPECT_EQ(second.via, "hub") << "far shares nothing with the query: hub's region verified it";
    EXPECT_EQ(r->results[0].via, "");
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

TEST_F(ImageIndexTest, TransitiveVerificationOnlyChainsFromFirmResults) {
  // The query matches "hub" only along a thin band (a line of text): verified, but not firm, so hub
  // anchors no chain and "far", which shares hub's other features, stays unverified. With sixteen of
  // hub's features over an area added to the query, hub anchors the chain to far.
  std::mt19937_64 rng(12);
  auto index = CreateIndex();
  sift::FeatureSet hub = RandomImage(rng, 240);
  constexpr size_t kBand = 16, kArea = 32;
  for (size_t i = 0; i < kBand; ++i) {
    sift::Keypoint& k = hub.keypoints[i];
    k.x = 100.0f + 25.0f * static_cast<float>(i);
    k.y = 200.0f + 12.0f * std::array{-1.0f, -0.33f, 0.33f, 1.0f}[i % 4];
    k.scale = 1.5f;
  }
  std::vector<uint32_t> hub_words(hub.size());
  vocabulary_.Quantize(hub.descriptors, hub_words);
  ASSERT_TRUE(index->Add("hub", hub, {}));
  for (int i = 0; i < 25; ++i) ASSERT_TRUE(index->Add(NumberedId("other", i), RandomImage(rng, 150), {}));
  const std::vector<uint32_t> far_words(hub_words.begin() + kArea, hub_words.end());
  const std::vector<sift::Keypoint> far_kps(hub.keypoints.begin() + kArea, hub.keypoints.end());
  ASSERT_TRUE(index->Add("far", Features(far_words, Transformed(far_kps, -0.4, 0.8, 120, 250), 800, 700), {}));
  const auto query_of = [&](size_t n) {
    const std::vector<uint32_t> words(hub_words.begin(), hub_words.begin() + static_cast<std::ptrdiff_t>(n));
    const std::vector<sift::Keypoint> kps(hub.keypoints.begin(), hub.keypoints.begin() + static_cast<std::ptrdiff_t>(n));
    return Features(words, Transformed(kps, 0.5, 1.2, 300, 20), 1100, 1000);
  };
  QueryOptions transitive = Opts(30, 30);
  transitive.transitive_depth = 30;
  const auto band = index->Query(query_of(kBand), transitive);
  ASSERT_TRUE(band) << band.error().ToString();
  ASSERT_FALSE(band->results.empty());
  EXPECT_EQ(band->results[0].id, "hub");
  EXPECT_TRUE(band->results[0].verified) << "the band spans min_inlier_spread: hub is verified";
  for (const auto& r : band->results) {
    if (r.id == "far") {
      EXPECT_FALSE(r.verified) << "far verified via '" << r.via << "'";
    }
  }
  const auto area = index->Query(query_of(kArea), transitive);
  ASSERT_TRUE(area) << area.error().ToString();
  ASSERT_GE(area->results.size(), 2u);
  EXPECT_EQ(area->results[0].id, "hub");
  EXPECT_EQ(area->results[1].id, "far");
  EXPECT_TRUE(area->results[1].verified);
  EXPECT_EQ(area->results[1].via, "hub");
}

TEST_F(ImageIndexTest, MultipleAssignmentReachesTheSecondNearestWord) {
  // The query descriptor lies between centroids 10 and 20, nearer 10; "b" holds only word 20.
  auto index = CreateIndex();
  std::mt19937_64 rng(5);
  ASSERT_TRUE(index->Add("a", Features({10, 30}, {{10, 10, 2, 0, 1, 0}, {50, 50, 2, 0, 1, 0}}), {}));
  ASSERT_TRUE(index->Add("b", Features({20, 40}, {{10, 10, 2, 0, 1, 0}, {50, 50, 2, 0, 1, 0}}), {}));
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add(NumberedId("r", i), RandomImage(rng, 30), {}));
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

TEST_F(ImageIndexTest, RegionQueryUsesOnlyFeaturesInside) {
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

TEST_F(ImageIndexTest, MaxQueryFeaturesKeepsTheStrongestInsideTheRegion) {
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

TEST_F(ImageIndexTest, MaxScoredPostingsCutsTheTfIdfPass) {
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

TEST_F(ImageIndexTest, AddRemoveSequenceEqualsFreshIndex) {
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
        const std::string id = NumberedId("i", counter++);
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

TEST_F(ImageIndexTest, RestartGivesIdenticalResults) {
  std::mt19937_64 rng(6);
  std::vector<sift::FeatureSet> queries;
  std::vector<QueryResponse> before;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 25; ++i) ASSERT_TRUE(index->Add(NumberedId("img", i), RandomImage(rng, 100), {}));
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

// Makes every insert of `id` into the catalogue fail, as a full disk or an I/O error would.
void FailInsertsOf(const fs::path& dir, const std::string& id) {
  ExecSql(dir / "catalogue.sqlite", "CREATE TRIGGER injected_failure BEFORE INSERT ON images WHEN NEW.id = '" + id +
                                        "' BEGIN SELECT RAISE(ABORT, 'injected insert failure'); END;");
}

TEST_F(ImageIndexTest, ReplaceIsOneTransactionOldOrNewNeverNeither) {
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
TEST_F(ImageIndexTest, AddBatchEqualsSingleAddsAndFailsPerImageOrAsAWhole) {
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
    for (int i = 1; i < 12; ++i) batch.push_back({NumberedId("b", i), &images[i], Info("/p" + std::to_string(i)), {}, {}});
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
    for (int i = 0; i < 4; ++i) batch.push_back({NumberedId("c", i), &images[i], {}, {}, {}});
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
  for (int i = 0; i < 12; ++i) ASSERT_TRUE((*single)->Add(NumberedId("b", i), images[i], {}));
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
TEST_F(ImageIndexTest, AddBatchOnOtherNumbersThanExpectedLinksTheNumbersGiven) {
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
    for (int i = 2; i < 6; ++i) batch.push_back({NumberedId("b", i), &images[i], {}, {}, {}});
    for (const auto& r : (*index)->AddBatch(batch)) ASSERT_TRUE(r) << r.error().ToString();
    ASSERT_TRUE((*index)->Remove("b3"));
    EXPECT_FALSE((*index)->Contains("b3"));
    EXPECT_EQ((*index)->Stats().num_images, 5u);
    for (const int i : {2, 4, 5}) {
      const auto found = (*index)->Query(images[i], Opts(1, 0));
      ASSERT_TRUE(found && !found->results.empty());
      EXPECT_EQ(found->results[0].id, NumberedId("b", i));
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
TEST_F(ImageIndexTest, AddBatchWithAssignedWordsEqualsQuantising) {
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
    a.push_back({NumberedId("w", i), &with_descriptors[i], {}, {}, {}});
    b.push_back({NumberedId("w", i), &without[i], {}, words[i], {}});
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
TEST_F(ImageIndexTest, WriteSequenceCountsCommittedWritesAndSurvivesARestart) {
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

TEST_F(ImageIndexTest, ReadersRunWhileWritersAdd) {
  auto index = CreateIndex();
  std::mt19937_64 rng(11);
  for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("seed", i), RandomImage(rng, 60), {}));
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
    EXPECT_TRUE(index->Add(NumberedId("new", i), to_add[i], {})) << i;
    if (i % 3 == 0) {
      EXPECT_TRUE(index->Remove(NumberedId("seed", i / 3))) << i;
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
TEST_F(ImageIndexTest, SearchesOnManyThreadsScoreAsOneAtATime) {
  auto index = CreateIndex();
  std::mt19937_64 rng(12);
  for (int i = 0; i < 40; ++i) ASSERT_TRUE(index->Add(NumberedId("img", i), RandomImage(rng, 80), {}));
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

}  // namespace
}  // namespace oxbow::index
