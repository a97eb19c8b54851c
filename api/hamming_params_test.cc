// The `hamming` search parameter (QueryOptions::hamming).
#include <gtest/gtest.h>

#include "api/params.h"

namespace oxbow::api {
namespace {

TEST(HammingParam, MapsOntoQueryOptionsAndIsABoolean) {
  index::QueryOptions defaults;
  EXPECT_TRUE(QueryParamNames().contains("hamming"));
  auto on = ParseQueryParams({{"hamming", "true"}}, defaults);
  ASSERT_TRUE(on) << on.error().message;
  EXPECT_TRUE(on->hamming);
  defaults.hamming = true;  // a server started with --hamming
  auto kept = ParseQueryParams({{"top_k", "3"}}, defaults);
  ASSERT_TRUE(kept);
  EXPECT_TRUE(kept->hamming);
  auto off = ParseQueryParams({{"hamming", "off"}}, defaults);
  ASSERT_TRUE(off);
  EXPECT_FALSE(off->hamming);
  auto refused = ParseQueryParams({{"hamming", "maybe"}}, defaults);
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, ErrorCode::kInvalidArgument);
  EXPECT_NE(refused.error().message.find("hamming"), std::string::npos) << refused.error().message;
}

}  // namespace
}  // namespace oxbow::api
