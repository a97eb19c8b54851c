// Image ids must be valid UTF-8 (they are returned in JSON bodies); found by tests/fuzz/http_request_fuzz.
#include <string>

#include <gtest/gtest.h>

#include "api/params.h"

namespace oxbow::api {
namespace {

TEST(CheckImageId, AcceptsUtf8Ids) {
  EXPECT_TRUE(CheckImageId("plain-id_01.jpg"));
  EXPECT_TRUE(CheckImageId("Sacr\xC3\xA9-C\xC5\x93ur"));          // 2-byte sequences
  EXPECT_TRUE(CheckImageId("\xE6\x9D\xB1\xE4\xBA\xAC"));           // 3-byte sequences
  EXPECT_TRUE(CheckImageId("photo-\xF0\x9F\x93\xB7"));             // 4-byte sequence (U+1F4F7)
}

TEST(CheckImageId, RefusesMalformedUtf8) {
  for (const std::string& id : {std::string("no\x94\x94"),          // stray continuation bytes
                                std::string("cut\xC3"),             // truncated 2-byte sequence
                                std::string("\xE6\x9D"),            // truncated 3-byte sequence
                                std::string("\xC0\xAF"),            // overlong '/'
                                std::string("\xE0\x80\xAF"),        // overlong 3-byte
                                std::string("\xED\xA0\x80"),        // UTF-16 surrogate U+D800
                                std::string("\xF4\x90\x80\x80"),    // above U+10FFFF
                                std::string("\xFF")}) {
    auto checked = CheckImageId(id);
    ASSERT_FALSE(checked) << "accepted an id of " << id.size() << " bytes";
    EXPECT_EQ(checked.error().code, ErrorCode::kInvalidArgument);
    EXPECT_NE(checked.error().message.find("UTF-8"), std::string::npos) << checked.error().message;
  }
}

TEST(ParseAddParams, RefusesNonUtf8Id) {
  auto parsed = ParseAddParams({{"id", "x\xFFy"}});
  ASSERT_FALSE(parsed);
  EXPECT_EQ(parsed.error().code, ErrorCode::kInvalidArgument);
}

}  // namespace
}  // namespace oxbow::api
