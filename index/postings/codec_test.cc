// The posting codec (codec.h): the bytes of format 2 (the checkpoint files hold them as they are, so
// they must not change), round trips of edge values, the cursor, and format 1's checked decoder.
#include "index/postings/codec.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

namespace oxbow::index::postings {
namespace {

std::vector<uint8_t> Coded(uint32_t gap, uint32_t tf) {
  std::vector<uint8_t> out;
  PutPosting(&out, gap, tf);
  return out;
}

TEST(PostingCodec, Format2BytesAreFixed) {
  EXPECT_EQ(Coded(0, 1), (std::vector<uint8_t>{0x00, 0x00}));
  EXPECT_EQ(Coded(1, 1), (std::vector<uint8_t>{0x02, 0x00}));
  EXPECT_EQ(Coded(5, 2), (std::vector<uint8_t>{0x0B, 0x00, 0x00}));            // tf > 1: varint(tf - 2)
  EXPECT_EQ(Coded(0x7FFE, 1), (std::vector<uint8_t>{0xFC, 0xFF}));              // the largest inline gap
  EXPECT_EQ(Coded(0x7FFF, 1), (std::vector<uint8_t>{0xFE, 0xFF, 0xFF, 0x7F, 0x00, 0x00}));  // escaped
  // Escaped gap 70000 = 0x11170, tf 300: varint(298) = 0xAA 0x02.
  EXPECT_EQ(Coded(70000, 300), (std::vector<uint8_t>{0xFF, 0xFF, 0x70, 0x11, 0x01, 0x00, 0xAA, 0x02}));
}

TEST(PostingCodec, EdgeValuesRoundTrip) {
  const uint32_t kMax = std::numeric_limits<uint32_t>::max();
  for (const uint32_t gap : {0u, 1u, 2u, 0x7FFEu, 0x7FFFu, 0x8000u, 0xFFFFu, 0x10000u, kMax}) {
    for (const uint32_t tf : {1u, 2u, 3u, 129u, 130u, 16385u, kMax}) {
      const std::vector<uint8_t> bytes = Coded(gap, tf);
      EXPECT_EQ(bytes.size(), PostingSize(gap, tf)) << gap << " " << tf;
      const uint8_t* p = bytes.data();
      uint32_t got_gap = 0, got_tf = 0;
      GetPosting(p, &got_gap, &got_tf);
      EXPECT_EQ(p, bytes.data() + bytes.size()) << gap << " " << tf;
      EXPECT_EQ(got_gap, gap);
      EXPECT_EQ(got_tf, tf);
    }
  }
}

TEST(PostingCodec, CursorWalksAListToItsEnd) {
  // Images 7, 8, 40000, 40001 of a segment starting at image 5, with tf 1, 4, 1, 2.
  const std::vector<std::pair<uint32_t, uint32_t>> postings = {{7, 1}, {8, 4}, {40000, 1}, {40001, 2}};
  std::vector<uint8_t> list;
  uint32_t last = 5;
  for (const auto& [image, tf] : postings) {
    PutPosting(&list, image - last, tf);
    last = image;
  }
  PostingCursor cursor{list.data(), list.data() + list.size(), 5};
  for (const auto& [image, tf] : postings) {
    cursor.Advance();
    EXPECT_EQ(cursor.image, image);
    EXPECT_EQ(cursor.tf, tf);
  }
  cursor.Advance();
  EXPECT_EQ(cursor.image, std::numeric_limits<uint32_t>::max());
}

TEST(PostingCodec, Format1ListsDecodeWithBoundsChecks) {
  // (gap 3, tf 1), (gap 200, tf 2): varint(3 << 1), varint(200 << 1 | 1) varint(0).
  const std::vector<uint8_t> list = {0x06, 0x91, 0x03, 0x00};
  std::vector<std::pair<uint32_t, uint32_t>> got;
  const auto collect = [&](uint32_t gap, uint32_t tf) { got.emplace_back(gap, tf); };
  ASSERT_TRUE(ForEachFormat1Posting(list.data(), list.data() + list.size(), collect));
  EXPECT_EQ(got, (std::vector<std::pair<uint32_t, uint32_t>>{{3, 1}, {200, 2}}));
  // A varint that runs past the list's end.
  const std::vector<uint8_t> truncated = {0x06, 0x91};
  EXPECT_FALSE(ForEachFormat1Posting(truncated.data(), truncated.data() + truncated.size(), collect));
  // A tf varint missing after a unit that announces one.
  const std::vector<uint8_t> no_tf = {0x07};
  EXPECT_FALSE(ForEachFormat1Posting(no_tf.data(), no_tf.data() + no_tf.size(), collect));
  // A gap of 2^32 does not fit.
  const std::vector<uint8_t> wide = {0x80, 0x80, 0x80, 0x80, 0x20};  // (2^32) << 1
  EXPECT_FALSE(ForEachFormat1Posting(wide.data(), wide.data() + wide.size(), collect));
}

}  // namespace
}  // namespace oxbow::index::postings
