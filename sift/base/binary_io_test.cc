#include "sift/base/binary_io.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "tests/support/temp_dir.h"

namespace oxbow::io {
namespace {

class BinaryIoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    path_ = (dir_ / "file.bin").string();
  }

  std::vector<uint8_t> Payload() const {
    std::vector<uint8_t> payload(1000);
    for (size_t i = 0; i < payload.size(); ++i) payload[i] = static_cast<uint8_t>(i * 7 + 3);
    return payload;
  }
  void FlipByte(size_t offset) {
    std::fstream f(path_, std::ios::in | std::ios::out | std::ios::binary);
    f.seekg(static_cast<std::streamoff>(offset));
    char c;
    f.get(c);
    f.seekp(static_cast<std::streamoff>(offset));
    f.put(static_cast<char>(c ^ 0x40));
  }

  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  std::filesystem::path dir_{temp_.path()};
  std::string path_;
};

TEST(Crc32, MatchesKnownValue) {
  const std::string text = "123456789";  // the standard CRC-32 check value
  EXPECT_EQ(Crc32(std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(text.data()), text.size())),
            0xCBF43926u);
}

// Checksums are chained over pieces (a file header, then its payload): the running value carries over,
// and an empty piece (possibly a null pointer) leaves it unchanged.
TEST(Crc32, ChainsOverPiecesAndSkipsEmptyOnes) {
  const std::string text = "123456789";
  const auto bytes = std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(text.data()), text.size());
  const uint32_t head = Crc32(bytes.first(4));
  EXPECT_EQ(Crc32(bytes.subspan(4), head), 0xCBF43926u);
  EXPECT_EQ(Crc32(std::span<const uint8_t>(), head), head);
  EXPECT_EQ(Crc32(std::span<const uint8_t>()), 0u);
}

TEST_F(BinaryIoTest, RoundTrip) {
  ASSERT_TRUE(WriteContainerFile(path_, "OXBWTEST", 3, 5, Payload()));
  auto read = ReadContainerFile(path_, "OXBWTEST", 1, 3);
  ASSERT_TRUE(read) << read.error().ToString();
  EXPECT_EQ(read->version, 3u);
  EXPECT_EQ(read->flags, 5u);
  EXPECT_EQ(read->payload, Payload());
  // No temporary files are left behind.
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir_), std::filesystem::directory_iterator()), 1);
}

TEST_F(BinaryIoTest, RefusesWrongMagicVersionTruncationAndDamage) {
  ASSERT_TRUE(WriteContainerFile(path_, "OXBWTEST", 3, 0, Payload()));
  auto foreign = ReadContainerFile(path_, "OXBWOTHR", 1, 3);
  ASSERT_FALSE(foreign);
  EXPECT_EQ(foreign.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(foreign.error().message.find("wrong magic"), std::string::npos);

  auto too_new = ReadContainerFile(path_, "OXBWTEST", 1, 2);
  ASSERT_FALSE(too_new);
  EXPECT_EQ(too_new.error().code, ErrorCode::kIncompatible);

  std::filesystem::resize_file(path_, kHeaderBytes + 500);
  auto truncated = ReadContainerFile(path_, "OXBWTEST", 1, 3);
  ASSERT_FALSE(truncated);
  EXPECT_EQ(truncated.error().code, ErrorCode::kCorruptData);

  ASSERT_TRUE(WriteContainerFile(path_, "OXBWTEST", 3, 0, Payload()));
  FlipByte(kHeaderBytes + 123);
  auto damaged = ReadContainerFile(path_, "OXBWTEST", 1, 3);
  ASSERT_FALSE(damaged);
  EXPECT_NE(damaged.error().message.find("checksum"), std::string::npos);

  ASSERT_TRUE(WriteContainerFile(path_, "OXBWTEST", 3, 0, Payload()));
  FlipByte(17);  // inside payload_bytes
  auto bad_header = ReadContainerFile(path_, "OXBWTEST", 1, 3);
  ASSERT_FALSE(bad_header);
  EXPECT_NE(bad_header.error().message.find("header"), std::string::npos);
}

TEST_F(BinaryIoTest, MissingFileIsNotFoundAndEmptyFileIsCorrupt) {
  auto missing = ReadContainerFile(path_, "OXBWTEST", 1, 1);
  ASSERT_FALSE(missing);
  EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
  std::ofstream(path_).close();
  auto empty = ReadContainerFile(path_, "OXBWTEST", 1, 1);
  ASSERT_FALSE(empty);
  EXPECT_EQ(empty.error().code, ErrorCode::kCorruptData);
}

TEST(ByteReader, ReadsBackAndDetectsTruncation) {
  ByteWriter writer;
  writer.Put<uint32_t>(42);
  writer.PutString("hello");
  const std::vector<float> values = {1.5f, -2.0f};
  writer.PutArray(std::span<const float>(values));
  auto bytes = writer.Release();
  ByteReader reader(bytes, "test record");
  EXPECT_EQ(*reader.Get<uint32_t>(), 42u);
  EXPECT_EQ(*reader.GetString(), "hello");
  std::vector<float> back(2);
  ASSERT_TRUE(reader.GetArray(std::span<float>(back)));
  EXPECT_EQ(back, values);
  auto past_end = reader.Get<uint8_t>();
  ASSERT_FALSE(past_end);
  EXPECT_NE(past_end.error().message.find("test record"), std::string::npos);
}

}  // namespace
}  // namespace oxbow::io
