#include "api/access_keys.h"

#include <gtest/gtest.h>

#include <fstream>

#include "tests/support/temp_dir.h"

namespace oxbow::api {
namespace {

using oxbow::testing::FileBytes;

TEST(AccessKeysTest, KeysGrantTheirCollectionAndAreStoredOnlyAsSaltedHashes) {
  oxbow::testing::TempDir dir("oxbow-access-keys-test");
  const std::string path = dir.path() + "/keys.json";
  auto keys = AccessKeys::Open(path);
  ASSERT_TRUE(keys) << keys.error().ToString();
  auto write = (*keys)->Create("paris", KeyAccess::kWrite);
  auto read = (*keys)->Create("paris", KeyAccess::kRead);
  auto other = (*keys)->Create("tokyo", KeyAccess::kRead);
  ASSERT_TRUE(write && read && other);
  EXPECT_EQ(write->key.size(), 4u + 12 + 1 + 64);
  EXPECT_NE(write->key, read->key);

  auto found = (*keys)->Find(write->key);
  ASSERT_TRUE(found);
  EXPECT_EQ(found->collection, "paris");
  EXPECT_EQ(found->access, KeyAccess::kWrite);
  EXPECT_EQ((*keys)->Find(other->key)->collection, "tokyo");
  // A wrong secret under a real id, a truncated key, junk: nothing.
  std::string forged = write->key;
  forged.back() = forged.back() == '0' ? '1' : '0';
  EXPECT_FALSE((*keys)->Find(forged));
  EXPECT_FALSE((*keys)->Find(write->key.substr(0, write->key.size() - 1)));
  EXPECT_FALSE((*keys)->Find("oxk_"));
  EXPECT_FALSE((*keys)->Find(""));

  // The file holds no secret, and a fresh open of it grants the same.
  const std::string text = FileBytes(path);
  EXPECT_EQ(text.find(write->key.substr(17)), std::string::npos);
  EXPECT_NE(text.find(write->info.id), std::string::npos);
  auto reopened = AccessKeys::Open(path);
  ASSERT_TRUE(reopened);
  EXPECT_EQ((*reopened)->Find(read->key)->access, KeyAccess::kRead);
  EXPECT_EQ((*reopened)->List("paris").size(), 2u);

  // Revoked keys stop working; so do a deleted collection's.
  ASSERT_TRUE((*keys)->Delete("paris", read->info.id));
  EXPECT_FALSE((*keys)->Find(read->key));
  EXPECT_EQ((*keys)->Delete("tokyo", read->info.id).error().code, ErrorCode::kNotFound);
  ASSERT_TRUE((*keys)->DeleteCollection("tokyo"));
  EXPECT_FALSE((*keys)->Find(other->key));
  EXPECT_TRUE((*keys)->Find(write->key));

  // Reload picks up an edit; a damaged file is refused and the keys stay.
  ASSERT_TRUE((*reopened)->Reload());
  EXPECT_FALSE((*reopened)->Find(read->key));
  { std::ofstream(path, std::ios::trunc) << "{\"keys\": [{\"id\": 1}]}"; }
  EXPECT_EQ((*reopened)->Reload().error().code, ErrorCode::kCorruptData);
  EXPECT_TRUE((*reopened)->Find(write->key));
  EXPECT_EQ(AccessKeys::Open(path).error().code, ErrorCode::kCorruptData);
}

}  // namespace
}  // namespace oxbow::api
