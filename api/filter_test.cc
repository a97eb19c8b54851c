#include "api/filter.h"

#include <gtest/gtest.h>

#include <string>

#include "api/params.h"

namespace oxbow::api {
namespace {

bool Matches(const std::string& filter, const std::string& metadata) {
  auto parsed = ParseFilter(filter, "parameter 'filter'");
  if (!parsed || *parsed == nullptr) {
    ADD_FAILURE() << filter << ": " << (parsed ? "no filter" : parsed.error().message);
    return false;
  }
  index::ImageRecord record;
  record.metadata_json = metadata;
  return (*parsed)->Matches(record);
}

// The message of a refused filter (kInvalidArgument), "" when it parses.
std::string Refusal(const std::string& filter) {
  auto parsed = ParseFilter(filter, "parameter 'filter'");
  if (parsed) return "";
  EXPECT_EQ(parsed.error().code, ErrorCode::kInvalidArgument);
  return parsed.error().message;
}

TEST(FilterTest, EqualityOnStringsNumbersAndBooleans) {
  EXPECT_TRUE(Matches(R"({"city": "Paris"})", R"({"city":"Paris","year":2004})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"city":"Lyon"})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"city":"paris"})"));
  EXPECT_TRUE(Matches(R"({"year": 2004})", R"({"year":2004.0})"));
  EXPECT_TRUE(Matches(R"({"year": 2004.0})", R"({"year":2004})"));
  EXPECT_TRUE(Matches(R"({"public": true})", R"({"public":true})"));
  EXPECT_FALSE(Matches(R"({"public": true})", R"({"public":false})"));
  // Keys are ANDed.
  EXPECT_TRUE(Matches(R"({"city": "Paris", "year": 2004})", R"({"city":"Paris","year":2004})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris", "year": 2005})", R"({"city":"Paris","year":2004})"));
}

TEST(FilterTest, TypeMismatchesAndMissingKeysDoNotMatch) {
  EXPECT_FALSE(Matches(R"({"year": 2004})", R"({"year":"2004"})"));
  EXPECT_FALSE(Matches(R"({"year": "2004"})", R"({"year":2004})"));
  EXPECT_FALSE(Matches(R"({"public": true})", R"({"public":1})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"city":null})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"city":["Paris"]})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"town":"Paris"})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", ""));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"(["city", "Paris"])"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"("Paris")"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", "not json"));
  EXPECT_FALSE(Matches(R"({"year": {"gte": 2000}})", R"({"year":"2004"})"));
  EXPECT_FALSE(Matches(R"({"date": {"gte": "2000"}})", R"({"date":2004})"));
}

TEST(FilterTest, EscapedTextsMatchAsTheirValues) {
  // Written with escapes (another serialiser): the quick text test must not reject them.
  EXPECT_TRUE(Matches(R"({"city": "Z\u00fcrich"})", R"({"city":"Z\u00fcrich"})"));
  EXPECT_TRUE(Matches(R"({"city": "Zürich"})", R"({"city":"Z\u00fcrich"})"));
  EXPECT_TRUE(Matches(R"({"city": "Paris"})", R"({"note":"a\"b","city":"Paris"})"));
  EXPECT_TRUE(Matches(R"({"name": "a\"b"})", R"({"name":"a\"b"})"));
  EXPECT_TRUE(Matches(R"({"name": {"in": ["x", "tab\there"]}})", R"({"name":"tab\there"})"));
  // The value's text elsewhere (a key, another member) is not a match.
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"Paris":"x","city":"Lyon"})"));
  EXPECT_FALSE(Matches(R"({"public": true})", R"({"public":false,"other":true})"));
}

TEST(FilterTest, KeysAreLiteralTopLevelMembers) {
  EXPECT_FALSE(Matches(R"({"place.city": "Paris"})", R"({"place":{"city":"Paris"}})"));
  EXPECT_TRUE(Matches(R"({"place.city": "Paris"})", R"({"place.city":"Paris"})"));
  EXPECT_FALSE(Matches(R"({"city": "Paris"})", R"({"place":{"city":"Paris"}})"));
}

TEST(FilterTest, InOperator) {
  const std::string filter = R"({"city": {"in": ["Paris", "Lyon", 7]}})";
  EXPECT_TRUE(Matches(filter, R"({"city":"Paris"})"));
  EXPECT_TRUE(Matches(filter, R"({"city":"Lyon"})"));
  EXPECT_TRUE(Matches(filter, R"({"city":7.0})"));
  EXPECT_FALSE(Matches(filter, R"({"city":"Nice"})"));
  EXPECT_FALSE(Matches(filter, R"({"city":"7"})"));
}

TEST(FilterTest, IntegersCompareExactly) {
  // 2^53 + 1 has no double: compared as doubles it would equal 2^53.
  EXPECT_FALSE(Matches(R"({"n": 9007199254740993})", R"({"n":9007199254740992})"));
  EXPECT_FALSE(Matches(R"({"n": 9007199254740992})", R"({"n":9007199254740993})"));
  EXPECT_TRUE(Matches(R"({"n": 9007199254740993})", R"({"n":9007199254740993})"));
  EXPECT_FALSE(Matches(R"({"n": {"in": [9007199254740993, 1]}})", R"({"n":9007199254740992})"));
  EXPECT_TRUE(Matches(R"({"n": {"in": [9007199254740993, 1]}})", R"({"n":9007199254740993})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": 9007199254740992}})", R"({"n":9007199254740993})"));
  EXPECT_TRUE(Matches(R"({"n": {"lt": 9007199254740993}})", R"({"n":9007199254740992})"));
  EXPECT_FALSE(Matches(R"({"n": {"lte": 9007199254740992}})", R"({"n":9007199254740993})"));
  // The ends of int64 and uint64.
  EXPECT_FALSE(Matches(R"({"n": 18446744073709551615})", R"({"n":18446744073709551614})"));
  EXPECT_TRUE(Matches(R"({"n": 18446744073709551615})", R"({"n":18446744073709551615})"));
  EXPECT_FALSE(Matches(R"({"n": -9223372036854775808})", R"({"n":-9223372036854775807})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": 9223372036854775807}})", R"({"n":9223372036854775808})"));
  EXPECT_FALSE(Matches(R"({"n": {"lt": -1}})", R"({"n":18446744073709551615})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": -9223372036854775808, "lt": 18446744073709551615}})", R"({"n":0})"));
  // An integer against a double compares with the double's exact value.
  EXPECT_FALSE(Matches(R"({"n": 9007199254740993})", R"({"n":9007199254740992.0})"));
  EXPECT_TRUE(Matches(R"({"n": 9007199254740992})", R"({"n":9007199254740992.0})"));
  EXPECT_TRUE(Matches(R"({"n": 9007199254740992.0})", R"({"n":9007199254740992})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": 9007199254740992.0}})", R"({"n":9007199254740993})"));
  EXPECT_FALSE(Matches(R"({"n": 18446744073709551615})", R"({"n":1.8446744073709552e19})"));  // 2^64
  EXPECT_TRUE(Matches(R"({"n": {"lt": 1.8446744073709552e19}})", R"({"n":18446744073709551615})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": -9.3e18}})", R"({"n":-9223372036854775808})"));
  EXPECT_TRUE(Matches(R"({"n": {"gte": 1e300}})", R"({"n":1e300})"));
  EXPECT_FALSE(Matches(R"({"n": {"gte": 1e300}})", R"({"n":18446744073709551615})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": 0, "lt": 0.5}})", R"({"n":0.25})"));
  EXPECT_FALSE(Matches(R"({"n": {"gt": 0, "lt": 0.5}})", R"({"n":0})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": -0.5}})", R"({"n":0})"));
  EXPECT_FALSE(Matches(R"({"n": {"gt": -0.5}})", R"({"n":-1})"));
  EXPECT_TRUE(Matches(R"({"n": {"lt": -0.5}})", R"({"n":-1})"));
  EXPECT_TRUE(Matches(R"({"n": -0.0})", R"({"n":0})"));
  EXPECT_TRUE(Matches(R"({"n": {"in": [1.5, 2]}})", R"({"n":2.0})"));
  EXPECT_TRUE(Matches(R"({"n": {"in": [1.5, 2]}})", R"({"n":1.5})"));
  EXPECT_FALSE(Matches(R"({"n": {"in": [1.5, 2]}})", R"({"n":1})"));
}

// A long "in" list is a hash set built once with the filter: every value matches, nothing else does,
// whatever the mix of types (its cost per document does not grow with the list: server/README.md,
// Filtered search, and filter_benchmark).
TEST(FilterTest, LongInListsMatchExactlyTheirValues) {
  std::string values;
  for (size_t i = 0; i + 1 < kMaxFilterValues; ++i) {  // and true: kMaxFilterValues in all
    if (i > 0) values += ",";
    values += i % 3 == 0 ? "\"v" + std::to_string(i) + "\"" : std::to_string(i);
  }
  const std::string filter = R"({"k": {"in": [)" + values + ", true]}}";
  ASSERT_LE(filter.size(), kMaxFilterBytes);
  for (size_t i = 0; i + 1 < kMaxFilterValues; i += 37) {
    const std::string member = i % 3 == 0 ? "\"v" + std::to_string(i) + "\"" : std::to_string(i);
    const std::string other = i % 3 == 0 ? std::to_string(i) : "\"v" + std::to_string(i) + "\"";
    EXPECT_TRUE(Matches(filter, R"({"k":)" + member + "}")) << member;
    EXPECT_FALSE(Matches(filter, R"({"k":)" + other + "}")) << other;
  }
  EXPECT_TRUE(Matches(filter, R"({"k":true})"));
  EXPECT_FALSE(Matches(filter, R"({"k":false})"));
  EXPECT_FALSE(Matches(filter, R"({"k":"v1"})"));
  EXPECT_FALSE(Matches(filter, R"({"k":1000})"));
  EXPECT_FALSE(Matches(filter, R"({"other":"v0"})"));
  // Strings only, past the quick text test's few values: the parse decides, escapes included.
  std::string strings = R"({"city": {"in": [)";
  for (int i = 0; i < 20; ++i) strings += "\"city-" + std::to_string(i) + "\",";
  strings += R"("Z\u00fcrich"]}})";
  EXPECT_TRUE(Matches(strings, R"({"city":"city-19"})"));
  EXPECT_TRUE(Matches(strings, R"({"city":"Zürich"})"));
  EXPECT_TRUE(Matches(strings, R"({"city":"Z\u00fcrich","x":"a\\b"})"));
  EXPECT_FALSE(Matches(strings, R"({"city":"city-20"})"));
  EXPECT_FALSE(Matches(strings, R"({"x":"city-1","city":"Lyon"})"));
}

TEST(FilterTest, RangesOnNumbersAndStrings) {
  const std::string decade = R"({"year": {"gte": 2000, "lt": 2010}})";
  EXPECT_TRUE(Matches(decade, R"({"year":2000})"));
  EXPECT_TRUE(Matches(decade, R"({"year":2009.5})"));
  EXPECT_FALSE(Matches(decade, R"({"year":2010})"));
  EXPECT_FALSE(Matches(decade, R"({"year":1999})"));
  EXPECT_TRUE(Matches(R"({"year": {"gt": 2000, "lte": 2010}})", R"({"year":2010})"));
  EXPECT_FALSE(Matches(R"({"year": {"gt": 2000, "lte": 2010}})", R"({"year":2000})"));
  EXPECT_TRUE(Matches(R"({"n": {"gt": -1.5}})", R"({"n":-1})"));
  // Strings compare by bytes: ISO dates order as dates.
  const std::string spring = R"({"date": {"gte": "2024-03-01", "lt": "2024-06-01"}})";
  EXPECT_TRUE(Matches(spring, R"({"date":"2024-03-01T10:00:00Z"})"));
  EXPECT_TRUE(Matches(spring, R"({"date":"2024-05-31"})"));
  EXPECT_FALSE(Matches(spring, R"({"date":"2024-06-01"})"));
  EXPECT_FALSE(Matches(spring, R"({"date":"2024-02-29"})"));
  // Operators of one key are ANDed with each other, "in" included.
  EXPECT_TRUE(Matches(R"({"year": {"in": [1999, 2004, 2012], "gte": 2000, "lt": 2010}})", R"({"year":2004})"));
  EXPECT_FALSE(Matches(R"({"year": {"in": [1999, 2004, 2012], "gte": 2000, "lt": 2010}})", R"({"year":2012})"));
}

TEST(FilterTest, EmptyObjectIsNoFilter) {
  auto parsed = ParseFilter("{}", "parameter 'filter'");
  ASSERT_TRUE(parsed);
  EXPECT_EQ(*parsed, nullptr);
}

TEST(FilterTest, MalformedFiltersAreRefusedNamingTheProblem) {
  EXPECT_NE(Refusal("{\"city\": ").find("is not valid JSON"), std::string::npos);
  EXPECT_NE(Refusal(R"(["city"])").find("must be a JSON object of metadata keys, got array"), std::string::npos);
  EXPECT_NE(Refusal(R"("Paris")").find("got string"), std::string::npos);
  EXPECT_NE(Refusal(R"({"city": null})").find("key 'city' must be a string, number, boolean or an object of operators"),
            std::string::npos);
  EXPECT_NE(Refusal(R"({"city": ["Paris"]})").find("got array"), std::string::npos);
  EXPECT_NE(Refusal(R"({"city": {"eq": "Paris"}})").find("unknown operator 'eq' for key 'city'"), std::string::npos);
  EXPECT_NE(Refusal(R"({"city": {}})").find("needs at least one of"), std::string::npos);
  EXPECT_NE(Refusal(R"({"city": {"in": "Paris"}})").find("operator 'in' of key 'city' needs an array"),
            std::string::npos);
  EXPECT_NE(Refusal(R"({"city": {"in": []}})").find("needs an array of 1 to 1000 values"), std::string::npos);
  EXPECT_NE(Refusal(R"({"city": {"in": [null]}})").find("takes strings, numbers and booleans, got null"),
            std::string::npos);
  EXPECT_NE(Refusal(R"({"year": {"gt": true}})").find("operator 'gt' of key 'year' needs a number or a string"),
            std::string::npos);
  EXPECT_NE(Refusal(R"({"year": {"gt": 2000, "lt": "2010"}})").find("mix numbers and strings"), std::string::npos);
  EXPECT_NE(Refusal(R"({"a": {"in": [[1]]}})").find("nests deeper than 3 levels"), std::string::npos);
  EXPECT_NE(Refusal(std::string(10000, '[')).find("nests deeper"), std::string::npos);
  EXPECT_NE(Refusal("{\"k\": \"" + std::string(kMaxFilterBytes, 'x') + "\"}").find("must be at most 16384 bytes"),
            std::string::npos);
  std::string many = R"({"k0":1)";
  for (size_t i = 1; i <= kMaxFilterKeys; ++i) many.append(",\"k").append(std::to_string(i)).append("\":1");
  EXPECT_NE(Refusal(many + "}").find("has 65 keys, at most 64"), std::string::npos);
  std::string values = R"({"k": {"in": [)";
  for (size_t i = 0; i <= kMaxFilterValues; ++i) values.append(i ? "," : "").append(std::to_string(i));
  EXPECT_NE(Refusal(values + "]}}").find("needs an array of 1 to 1000 values"), std::string::npos);
  // The label names where the filter came from.
  auto cli = ParseFilter("[]", "--filter");
  ASSERT_FALSE(cli);
  EXPECT_EQ(cli.error().message.rfind("--filter: ", 0), 0u) << cli.error().message;
}

TEST(FilterTest, SearchParameter) {
  const Params ok = {{"filter", R"({"city": "Paris"})"}};
  auto options = ParseQueryParams(ok, index::QueryOptions{});
  ASSERT_TRUE(options) << options.error().message;
  ASSERT_NE(options->filter, nullptr);
  index::ImageRecord paris;
  paris.metadata_json = R"({"city":"Paris"})";
  EXPECT_TRUE(options->filter->Matches(paris));
  EXPECT_EQ(ParseQueryParams({}, index::QueryOptions{})->filter, nullptr);

  auto bad = ParseQueryParams({{"filter", R"({"city": {"like": "P%"}})"}}, index::QueryOptions{});
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, ErrorCode::kInvalidArgument);
  EXPECT_NE(bad.error().message.find("parameter 'filter': unknown operator 'like'"), std::string::npos);
}

}  // namespace
}  // namespace oxbow::api
