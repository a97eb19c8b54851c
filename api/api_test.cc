// Unit tests of the transport-free pieces of the API: parameter parsing, extractor-settings round trip,
// JSON mapping. (The HTTP status mapping and the metrics text: server/http/errors_test.cc, metrics_test.cc.)
#include <gtest/gtest.h>

#include <set>
#include <utility>
#include <vector>

#include "api/json.h"
#include "api/params.h"
#include "api/service.h"

namespace oxbow::api {
namespace {

TEST(Params, IntegersAreCheckedCompletely) {
  EXPECT_EQ(ParseInt("k", "42", 1, 100).value(), 42);
  EXPECT_EQ(ParseInt("k", "+7", 1, 100).value(), 7);
  for (const char* bad : {"", "4x", "x", "1.5", " 3", "101", "0", "-1", "99999999999999999999999"}) {
    auto r = ParseInt("k", bad, 1, 100);
    ASSERT_FALSE(r) << bad;
    EXPECT_EQ(r.error().code, ErrorCode::kInvalidArgument);
    EXPECT_NE(r.error().message.find("'k'"), std::string::npos);
  }
  // An integer beyond 64 bits is out of range, not "not an integer".
  for (const char* big : {"99999999999999999999999", "9223372036854775808", "-9223372036854775809"}) {
    EXPECT_NE(ParseInt("k", big, 1, 100).error().message.find("must be in [1, 100]"), std::string::npos) << big;
  }
  EXPECT_NE(ParseInt("k", "1e99", 1, 100).error().message.find("must be an integer"), std::string::npos);
}

TEST(Params, BoolsAndBoxes) {
  EXPECT_TRUE(ParseBool("qe", "").value());
  EXPECT_TRUE(ParseBool("qe", "true").value());
  EXPECT_FALSE(ParseBool("qe", "0").value());
  EXPECT_FALSE(ParseBool("qe", "maybe"));
  auto box = ParseBox("bbox", "1,2.5,30,40");
  ASSERT_TRUE(box);
  EXPECT_FLOAT_EQ((*box)[1], 2.5f);
  EXPECT_FLOAT_EQ((*box)[3], 40.f);
  for (const char* bad : {"", "1,2,3", "1,2,3,4,5", "3,2,1,4", "1,4,3,2", "a,b,c,d", "1,2,3,inf", "1,,3,4", "1,2,3,4,"}) {
    EXPECT_FALSE(ParseBox("bbox", bad)) << bad;
  }
}

TEST(Params, QueryParamsOverrideDefaultsAndRefuseUnknownNames) {
  index::QueryOptions defaults;
  auto q = ParseQueryParams({{"top_k", "5"}, {"rerank", "50"}, {"bbox", "0,0,10,10"}, {"qe", "true"}}, defaults);
  ASSERT_TRUE(q) << q.error().message;
  EXPECT_EQ(q->top_k, 5);
  EXPECT_EQ(q->rerank_depth, 50);
  EXPECT_TRUE(q->query_expansion);
  ASSERT_TRUE(q->region.has_value());
  EXPECT_FLOAT_EQ(q->region.value()[2], 10.f);

  auto off = ParseQueryParams({{"rerank", "false"}}, defaults);
  ASSERT_TRUE(off);
  EXPECT_EQ(off->rerank_depth, 0);
  auto on = ParseQueryParams({{"rerank", "true"}}, defaults);
  ASSERT_TRUE(on);
  EXPECT_EQ(on->rerank_depth, defaults.rerank_depth);
  // A server started with --rerank 0: rerank=true means the library's default depth (one definition).
  index::QueryOptions no_rerank = defaults;
  no_rerank.rerank_depth = 0;
  auto on_default = ParseQueryParams({{"rerank", "true"}}, no_rerank);
  ASSERT_TRUE(on_default);
  EXPECT_EQ(on_default->rerank_depth, index::QueryOptions{}.rerank_depth);

  auto none = ParseQueryParams({}, defaults);
  ASSERT_TRUE(none);
  EXPECT_EQ(none->top_k, defaults.top_k);
  EXPECT_FALSE(none->region.has_value());

  auto typo = ParseQueryParams({{"topk", "5"}}, defaults);
  ASSERT_FALSE(typo);
  EXPECT_NE(typo.error().message.find("topk"), std::string::npos);
  EXPECT_FALSE(ParseQueryParams({{"top_k", "0"}}, defaults));
  EXPECT_FALSE(ParseQueryParams({{"qe", "1"}, {"rerank", "0"}}, defaults));
  auto exponent = ParseQueryParams({{"hamming_norm_exponent", "0.5"}}, defaults);
  ASSERT_TRUE(exponent);
  EXPECT_EQ(exponent->hamming_norm_exponent, 0.5);
  EXPECT_EQ(none->hamming_norm_exponent, index::QueryOptions{}.hamming_norm_exponent);
  for (const char* bad : {"1.5", "-0.1", "", "0.5x", "nan"}) {
    auto refused = ParseQueryParams({{"hamming_norm_exponent", bad}}, defaults);
    ASSERT_FALSE(refused) << bad;
    EXPECT_NE(refused.error().message.find("hamming_norm_exponent"), std::string::npos);
  }
  // QE on by default (as `oxbow serve` ships) does not make a tf-idf-only search an error: it is off there.
  index::QueryOptions qe_default = defaults;
  qe_default.query_expansion = true;
  auto tfidf_only = ParseQueryParams({{"rerank", "0"}}, qe_default);
  ASSERT_TRUE(tfidf_only);
  EXPECT_FALSE(tfidf_only->query_expansion);
  auto kept = ParseQueryParams({{"top_k", "3"}}, qe_default);
  ASSERT_TRUE(kept);
  EXPECT_TRUE(kept->query_expansion);
}

TEST(Params, SearchOptionParamsMapOntoQueryOptions) {
  const index::QueryOptions defaults;
  auto q = ParseQueryParams({{"transitive_depth", "0"},
                             {"transitive_anchors", "7"},
                             {"transitive_neighbours", "11"},
                             {"transitive_attempts", "3"},
                             {"query_assignments", "2"},
                             {"quantizer_probes", "32"},
                             {"max_pairs_per_word", "1"},
                             {"min_inliers", "9"},
                             {"qe_images", "4"},
                             {"max_query_features", "0"},
                             {"max_tentative_matches", "250"},
                             {"max_scored_postings", "2000000000"}},
                            defaults);
  ASSERT_TRUE(q) << q.error().message;
  EXPECT_EQ(q->transitive_depth, 0);
  EXPECT_EQ(q->transitive_anchors, 7);
  EXPECT_EQ(q->transitive_neighbours, 11);
  EXPECT_EQ(q->transitive_attempts, 3);
  EXPECT_EQ(q->query_assignments, 2);
  EXPECT_EQ(q->quantizer_probes, 32);
  EXPECT_EQ(q->max_pairs_per_word, 1);
  EXPECT_EQ(q->verify.min_inliers, 9);
  EXPECT_EQ(q->qe_images, 4);
  EXPECT_EQ(q->max_query_features, 0);
  EXPECT_EQ(q->max_tentative_matches, 250);
  EXPECT_EQ(q->max_scored_postings, 2000000000);
  // Untouched fields keep the defaults.
  EXPECT_EQ(q->rerank_depth, defaults.rerank_depth);
  EXPECT_EQ(q->top_k, defaults.top_k);

  // Out of range or not an integer: an error naming the parameter.
  const std::vector<std::pair<std::string, std::string>> bad = {
      {"transitive_depth", "-1"},      {"transitive_depth", "10001"}, {"transitive_anchors", "0"},
      {"transitive_anchors", "1001"},  {"transitive_neighbours", "0"}, {"transitive_attempts", "0"},
      {"transitive_attempts", "1001"}, {"query_assignments", "9"},    {"quantizer_probes", "0"},
      {"quantizer_probes", "4097"},    {"max_pairs_per_word", "101"}, {"min_inliers", "2"},
      {"qe_images", "0"},              {"transitive_depth", "2.5"},   {"quantizer_probes", "many"},
      {"max_query_features", "-1"},    {"max_query_features", "1000001"}, {"max_tentative_matches", "-5"},
      {"max_scored_postings", "-1"},   {"max_scored_postings", "2000000001"}};
  for (const auto& [name, value] : bad) {
    auto refused = ParseQueryParams({{name, value}}, defaults);
    ASSERT_FALSE(refused) << name << "=" << value;
    EXPECT_EQ(refused.error().code, ErrorCode::kInvalidArgument);
    EXPECT_NE(refused.error().message.find(name), std::string::npos) << refused.error().message;
  }
  // Every parameter is known, near misses are not.
  for (const char* name : {"transitive_depth", "transitive_anchors", "transitive_neighbours", "transitive_attempts",
                           "query_assignments", "quantizer_probes", "max_pairs_per_word", "min_inliers",
                           "max_query_features", "max_tentative_matches", "max_scored_postings"}) {
    EXPECT_TRUE(QueryParamNames().contains(name)) << name;
  }
  EXPECT_FALSE(ParseQueryParams({{"transitive_neighbors", "5"}}, defaults));
  EXPECT_FALSE(ParseQueryParams({{"probes", "5"}}, defaults));
}

TEST(Params, AddParams) {
  auto add = ParseAddParams({{"id", "a b"}, {"replace", "true"}, {"metadata", R"({"k": [1, 2]})"}});
  ASSERT_TRUE(add) << add.error().message;
  EXPECT_EQ(add->id, "a b");
  EXPECT_TRUE(add->replace);
  EXPECT_EQ(add->metadata_json, R"({"k":[1,2]})");
  EXPECT_FALSE(ParseAddParams({}));                                  // id required
  EXPECT_FALSE(ParseAddParams({{"id", ""}}));
  EXPECT_FALSE(ParseAddParams({{"id", std::string(257, 'x')}}));
  EXPECT_FALSE(ParseAddParams({{"id", "a\nb"}}));
  EXPECT_FALSE(ParseAddParams({{"id", "a"}, {"metadata", "{not json"}}));
}

TEST(Params, BatchAddParams) {
  auto items = ParseBatchAddParams({"a", "x/similar", "batch", "d", "e"}, {R"({"k": 1})", "", "", "{nope", ""}, 5, {});
  ASSERT_TRUE(items) << items.error().message;
  ASSERT_EQ(items->size(), 5u);
  EXPECT_TRUE((*items)[0].status);
  EXPECT_EQ((*items)[0].metadata_json, R"({"k":1})");
  EXPECT_FALSE((*items)[1].status);  // the sub-route and batch rules of a new id
  EXPECT_FALSE((*items)[2].status);
  ASSERT_FALSE((*items)[3].status);  // bad metadata fails that image alone
  EXPECT_NE((*items)[3].status.error().message.find("metadata part 4"), std::string::npos)
      << (*items)[3].status.error().message;
  EXPECT_TRUE((*items)[4].status);
  EXPECT_EQ((*items)[4].metadata_json, "");
  EXPECT_TRUE(ParseBatchAddParams({"a", "b"}, {}, 2, {}));      // metadata is optional
  EXPECT_FALSE(ParseBatchAddParams({"a"}, {}, 2, {}));           // one id per image
  EXPECT_FALSE(ParseBatchAddParams({"a", "b"}, {""}, 2, {}));    // none or one metadata per image
  EXPECT_FALSE(ParseBatchAddParams({}, {}, 0, {}));              // no image
  EXPECT_FALSE(ParseBatchAddParams({"a"}, {}, 1, {{"replace", "true"}}));  // no other parameter
  EXPECT_FALSE(ParseAddParams({{"id", "batch"}}));
  EXPECT_TRUE(ParseAddParams({{"id", "batch2"}}));
}

// A repeated parameter (`top_k=5&top_k=500000`, `id=dupA&id=dupB`) is ambiguous: every route refuses a
// repeated name, naming it (the transport collects the query string and multipart fields together).
TEST(Params, RepeatedNamesAreRefused) {
  const index::QueryOptions defaults;
  auto search = ParseQueryParams({{"top_k", "5"}, {"top_k", "500000"}}, defaults);
  ASSERT_FALSE(search);
  EXPECT_EQ(search.error().code, ErrorCode::kInvalidArgument);
  EXPECT_NE(search.error().message.find("'top_k' is given 2 times"), std::string::npos) << search.error().message;
  auto add = ParseAddParams({{"id", "dupA"}, {"id", "dupB"}});
  ASSERT_FALSE(add);
  EXPECT_NE(add.error().message.find("'id'"), std::string::npos) << add.error().message;
  EXPECT_FALSE(ParseAddParams({{"id", "a"}, {"replace", "false"}, {"replace", "false"}}));  // even when equal
  EXPECT_FALSE(ParseListParams({{"limit", "5"}, {"limit", "6"}}));
  EXPECT_FALSE(ParseMatchParams({{"model", "affine"}, {"model", "homography"}}));
  // A repeated unknown name is refused too (as repeated: the first problem found).
  EXPECT_FALSE(CheckKnownParams({{"size", "1"}, {"size", "2"}}, {"size"}));
  EXPECT_TRUE(CheckKnownParams({{"size", "1"}}, {"size"}));
}

// Metadata nested ~74,000 deep would overflow a worker's stack in the recursive dump. The depth
// and the size are checked on the text before it is parsed.
TEST(Params, MetadataDepthAndSizeAreLimitedBeforeParsing) {
  auto nested = [](int depth, const std::string& open = "[", const std::string& close = "]") {
    std::string text;
    for (int i = 0; i < depth; ++i) text += open;
    for (int i = 0; i < depth; ++i) text += close;
    return text;
  };
  // The shape of the crash (195 KiB), and one under the size limit that nests too deep.
  for (const std::string& deep : {nested(100000), nested(kMaxJsonDepth + 1), nested(kMaxJsonDepth + 1, "{\"a\":", "}")}) {
    auto add = ParseAddParams({{"id", "a"}, {"metadata", deep}});
    ASSERT_FALSE(add) << deep.size();
    EXPECT_EQ(add.error().code, ErrorCode::kInvalidArgument);
  }
  EXPECT_NE(ParseAddParams({{"id", "a"}, {"metadata", nested(kMaxJsonDepth + 1)}}).error().message.find("64 levels"),
            std::string::npos);
  auto deepest = ParseAddParams({{"id", "a"}, {"metadata", nested(kMaxJsonDepth)}});
  ASSERT_TRUE(deepest) << deepest.error().message;
  EXPECT_EQ(deepest->metadata_json, nested(kMaxJsonDepth));
  // Brackets inside strings, escaped quotes included, are text, not nesting.
  const std::string quoted = R"({"a":"\"[[[[)" + nested(200) + R"(\\","b":[1]})";
  auto text = ParseAddParams({{"id", "a"}, {"metadata", quoted}});
  ASSERT_TRUE(text) << text.error().message;
  EXPECT_EQ(JsonNestingDepth(quoted), 2);
  // Size: the limit itself passes, one byte more does not.
  const std::string padding = R"({"a":")";
  const std::string at_limit = padding + std::string(kMaxMetadataBytes - padding.size() - 2, 'x') + R"("})";
  ASSERT_EQ(at_limit.size(), kMaxMetadataBytes);
  EXPECT_TRUE(ParseAddParams({{"id", "a"}, {"metadata", at_limit}}));
  auto big = ParseAddParams({{"id", "a"}, {"metadata", padding + std::string(kMaxMetadataBytes, 'x') + R"("})"}});
  ASSERT_FALSE(big);
  EXPECT_NE(big.error().message.find("at most 16384 bytes"), std::string::npos) << big.error().message;
}

TEST(Json, NestingDepthIsCountedWithoutParsing) {
  EXPECT_EQ(JsonNestingDepth("1"), 0);
  EXPECT_EQ(JsonNestingDepth("[]"), 1);
  EXPECT_EQ(JsonNestingDepth(R"({"a":[{"b":[]}],"c":{}})"), 4);
  EXPECT_EQ(JsonNestingDepth(R"(["]", "[", "\"[", "\\", [1]])"), 2);
  // Counting stops past the limit: linear at most, whatever the input.
  EXPECT_EQ(JsonNestingDepth(std::string(1000000, '['), 10), 11);
  EXPECT_EQ(JsonNestingDepth(std::string(100, ']') + "[[", 64), 2);  // stray closers do not go below zero
}

// Metadata stored deeper than the limit (by an older server or `oxbow index add --metadata`) comes back
// as its text, never parsed into a document whose dump would recurse once per level.
TEST(Json, DeepStoredMetadataIsReturnedAsText) {
  const std::string deep = std::string(100000, '[') + std::string(100000, ']');
  const auto json = MetadataToJson(deep);
  ASSERT_TRUE(json.is_string());
  EXPECT_EQ(json.dump().size(), deep.size() + 2);
  EXPECT_EQ(MetadataToJson(R"([[1]])")[0][0], 1);
}

// An id ending in /similar or /thumbnail cannot be fetched by GET /v1/images/{id}, so new ones
// are refused; CheckImageId (used by GET and DELETE too) keeps accepting stored ones.
TEST(Params, IdsThatReadAsSubresourcesAreRefusedOnAdd) {
  for (const char* id : {"a/similar", "a/thumbnail", "x/y/thumbnail"}) {
    auto add = ParseAddParams({{"id", id}});
    ASSERT_FALSE(add) << id;
    EXPECT_NE(add.error().message.find("must not end in '/similar' or '/thumbnail'"), std::string::npos);
    EXPECT_TRUE(CheckImageId(id)) << id;
  }
  for (const char* id : {"similar", "thumbnail", "a/similar.jpg", "a/thumbnails", "dir/photo.jpg"}) {
    EXPECT_TRUE(ParseAddParams({{"id", id}})) << id;
  }
}

TEST(Params, ListAndMatchParams) {
  auto list = ParseListParams({{"offset", "10"}, {"limit", "5"}});
  ASSERT_TRUE(list);
  EXPECT_EQ(list->offset, 10u);
  EXPECT_EQ(list->limit, 5u);
  EXPECT_FALSE(ParseListParams({{"limit", "0"}}));
  EXPECT_FALSE(ParseListParams({{"limit", "1001"}}));
  EXPECT_FALSE(ParseListParams({{"offset", "-1"}}));

  auto match = ParseMatchParams({{"model", "homography"}, {"ratio", "0.7"}, {"mutual", "1"}, {"method", "kdtree"}});
  ASSERT_TRUE(match) << match.error().message;
  EXPECT_EQ(match->model, sift::GeometricModel::kHomography);
  EXPECT_FLOAT_EQ(match->match.ratio, 0.7f);
  EXPECT_TRUE(match->match.mutual);
  EXPECT_EQ(match->match.method, sift::MatchOptions::Method::kKdForest);
  EXPECT_FALSE(ParseMatchParams({{"model", "banana"}}));
  EXPECT_FALSE(ParseMatchParams({{"ratio", "1.5"}}));
  EXPECT_FALSE(ParseMatchParams({{"ratio", "0"}}));
  EXPECT_FALSE(ParseMatchParams({{"method", "fast"}}));
  EXPECT_EQ(ParseMatchParams({})->min_inliers, 6);
  EXPECT_EQ(ParseMatchParams({{"min_inliers", "12"}})->min_inliers, 12);
  EXPECT_FALSE(ParseMatchParams({{"min_inliers", "2"}}));
}

TEST(Settings, RoundTripsEveryDescribedOption) {
  sift::SiftOptions options;
  options.upsample_first_octave = false;
  options.sigma = 1.7;
  options.contrast_threshold = 0.03;
  options.max_features = 1234;
  options.descriptor = sift::DescriptorKind::kRootSift;
  options.max_octaves = 5;
  auto parsed = sift::SiftOptions::FromDescription(options.Describe());
  ASSERT_TRUE(parsed) << parsed.error().message;
  EXPECT_EQ(parsed->Describe(), options.Describe());
  EXPECT_EQ(parsed->max_features, 1234);
  EXPECT_EQ(parsed->descriptor, sift::DescriptorKind::kRootSift);

  auto defaults = sift::SiftOptions::FromDescription(sift::SiftOptions{}.Describe());
  ASSERT_TRUE(defaults);
  EXPECT_EQ(defaults->Describe(), sift::SiftOptions{}.Describe());

  for (const std::string& bad : {std::string(""), std::string("other-sift/1;sigma=1"),
                                sift::SiftOptions{}.Describe() + ";future_field=3",
                                std::string("oxbow-sift/1;sigma=abc")}) {
    auto r = sift::SiftOptions::FromDescription(bad);
    ASSERT_FALSE(r) << bad;
    EXPECT_EQ(r.error().code, ErrorCode::kIncompatible);
  }
}

TEST(Json, SearchResponseCarriesEveryDocumentedField) {
  SearchResponse response;
  response.options.top_k = 3;
  response.options.region = std::array<float, 4>{1, 2, 3, 4};
  response.query_width = 640;
  response.query_height = 480;
  response.decode_extract_ms = 12.5;
  index::QueryResult r;
  r.id = "box_in_scene";
  r.score = 0.5;
  r.verified = true;
  r.inliers = 17;
  r.db_from_query.m = {2, 0, 10, 0, 2, 20};
  r.db_region = {5, 6, 7, 8};
  r.record.width = 512;
  r.record.metadata_json = R"({"title":"box"})";
  response.index.results.push_back(r);
  index::QueryResult unverified = r;  // tf-idf only: no transform, no region (as POST /v1/match)
  unverified.id = "graf1";
  unverified.verified = false;
  response.index.results.push_back(unverified);
  response.index.timings.verify_ms = 3;
  const auto json = SearchResponseToJson(response);
  ASSERT_EQ(json["results"].size(), 2u);
  EXPECT_TRUE(json["results"][1]["transform"].is_null());
  EXPECT_TRUE(json["results"][1]["region"].is_null());
  const auto& first = json["results"][0];
  EXPECT_EQ(first["id"], "box_in_scene");
  EXPECT_EQ(first["rank"], 1);
  EXPECT_EQ(first["inliers"], 17);
  EXPECT_EQ(first["transform"][0][2], 10.0);
  EXPECT_EQ(first["region"][3], 8.0);
  EXPECT_EQ(first["metadata"]["title"], "box");
  EXPECT_EQ(json["query"]["bbox"][0], 1.0);
  EXPECT_EQ(json["params"]["top_k"], 3);
  for (const char* stage : {"decode_extract", "quantize", "score", "verify", "qe", "total"}) {
    EXPECT_TRUE(json["timings_ms"].contains(stage)) << stage;
  }
  EXPECT_EQ(json["timings_ms"]["verify"], 3.0);
  EXPECT_TRUE(MetadataToJson("").is_null());
  EXPECT_EQ(MetadataToJson("not json"), "not json");
}

TEST(ServiceOptions, CheckRefusesOutOfRangeValues) {
  ServiceOptions options;
  EXPECT_FALSE(options.Check().has_value());
  options.max_image_side_px = 8;
  EXPECT_TRUE(options.Check().has_value());
  options = {};
  options.max_concurrent_extractions = -1;
  EXPECT_TRUE(options.Check().has_value());
  options = {};
  options.default_query.top_k = 0;
  EXPECT_TRUE(options.Check().has_value());
  EXPECT_GT(ResidentMemoryBytes(), 0u);
}

}  // namespace
}  // namespace oxbow::api
