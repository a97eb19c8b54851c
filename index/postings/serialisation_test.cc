// The checkpoint form of the postings (serialisation.h): round trips whole and in parts, postings read in
// place, the format-1 fixture, damaged files.
#include "index/postings/serialisation.h"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "index/postings/testing.h"

namespace oxbow::index {
namespace {

using postings::testing::AllScores;
using postings::testing::SerializedBytes;

// The bags of testdata/postings_format1.oxif, a postings file of format 1 (varint postings) that
// the build before format 2 (1d18dfc) wrote: Build over these bags, then WithAdded of images 300 and
// 420, then WithRemoved of image 14 (so two segments, one with the postings of a removed image).
bool Format1FixtureBag(uint32_t image, BagOfWords* bag) {
  const bool near = image % 7 == 0;
  const bool far = image == 150 || image == 151 || image == 299;
  if (!near && !far) return false;
  for (uint32_t w = 0; w < 64; ++w) {
    const uint32_t h = (image * 2654435761u) ^ (w * 40503u);
    if ((h >> 7) % 3 != 0 && !(far && w < 4)) continue;
    bag->words.push_back(w);
    bag->counts.push_back(1 + ((h >> 13) % 7 == 0 ? (h >> 17) % 300 : 0));  // tf up to 300
  }
  return !bag->words.empty();
}

std::vector<uint8_t> ReadFileBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// With an owner (a checkpoint file's mapping in ImageIndex) the postings are read in place: the same
// scores and bytes as a copy, and the owner is held by every version that still uses them.
TEST(PostingsSerialisation, PostingsReadInPlaceKeepTheirOwner) {
  InvertedFile built = InvertedFile::Build(64, {}, 300, Format1FixtureBag);
  BagOfWords a;
  a.words = {1, 5, 9};
  a.counts = {1, 2, 1};
  const std::vector<uint32_t> added = {300};
  const std::vector<const BagOfWords*> added_bags = {&a};
  built = built.WithAdded(added, added_bags);  // a second segment
  auto owner = std::make_shared<std::vector<uint8_t>>();
  built.Serialize([&](std::span<const uint8_t> part) { owner->insert(owner->end(), part.begin(), part.end()); });

  auto copy = InvertedFile::Deserialize(*owner, 64, {});
  ASSERT_TRUE(copy) << copy.error().ToString();
  EXPECT_EQ(owner.use_count(), 1);
  auto in_place = InvertedFile::Deserialize(*owner, 64, {}, nullptr, owner);
  ASSERT_TRUE(in_place) << in_place.error().ToString();
  EXPECT_GT(owner.use_count(), 1);
  for (uint32_t q = 0; q < 40; ++q) {
    BagOfWords query;
    if (!Format1FixtureBag(q * 7, &query)) continue;
    const auto expected = AllScores(*copy, query);
    EXPECT_FALSE(expected.empty());
    EXPECT_EQ(AllScores(*in_place, query), expected) << "query " << q;
  }
  std::vector<uint8_t> again;
  in_place->Serialize([&](std::span<const uint8_t> part) { again.insert(again.end(), part.begin(), part.end()); });
  EXPECT_TRUE(again == *owner);

  // A later version that removes an image rewrites only the lists it touches; once no version uses
  // the read segments, the owner is released.
  BagOfWords removed;
  ASSERT_TRUE(Format1FixtureBag(14, &removed));
  const std::vector<uint32_t> gone = {14};
  const std::vector<const BagOfWords*> gone_bags = {&removed};
  std::optional<InvertedFile> next = in_place->WithRemoved(gone, gone_bags);
  BagOfWords probe;
  ASSERT_TRUE(Format1FixtureBag(21, &probe));
  const auto expected = AllScores(copy->WithRemoved(gone, gone_bags), probe);
  const std::weak_ptr<std::vector<uint8_t>> weak = owner;
  owner.reset();
  in_place = Fail(ErrorCode::kNotFound, "dropped");
  EXPECT_FALSE(weak.expired()) << "the segments `next` shares with the dropped version hold the bytes";
  EXPECT_EQ(AllScores(*next, probe), expected);
  next.reset();
  EXPECT_TRUE(weak.expired());
}

// The split form (a head naming a file per segment) reads back as the whole form does, each segment
// in place with its own owner; a segment file that is missing, of another vocabulary, truncated or
// named out of order is refused.
TEST(PostingsSerialisation, HeadAndSegmentFilesReadBackAsTheWholeFile) {
  InvertedFile built = InvertedFile::Build(64, {}, 300, Format1FixtureBag);
  BagOfWords a, b;
  a.words = {1, 5, 9};
  a.counts = {1, 2, 1};
  b.words = {5, 63};
  b.counts = {3, 1};
  const std::vector<uint32_t> first = {300}, second = {301};
  const std::vector<const BagOfWords*> first_bags = {&a}, second_bags = {&b};
  built = built.WithAdded(first, first_bags).WithAdded(second, second_bags);
  ASSERT_EQ(built.num_segments(), 3u);
  const auto bytes_of = [](const auto& serialize) {
    std::vector<uint8_t> out;
    serialize([&](std::span<const uint8_t> part) { out.insert(out.end(), part.begin(), part.end()); });
    return out;
  };
  std::map<std::string, std::shared_ptr<std::vector<uint8_t>>> files;
  std::vector<std::string> names;
  for (size_t i = 0; i < built.num_segments(); ++i) {
    names.push_back("segment-" + std::to_string(i));
    files[names.back()] = std::make_shared<std::vector<uint8_t>>(
        bytes_of([&](const auto& write) { built.SerializeSegment(i, write); }));
  }
  const std::vector<uint8_t> head = bytes_of([&](const auto& write) { built.SerializeHead(names, write); });
  std::vector<std::string> asked;
  const InvertedFile::SegmentSource source =
      [&](const std::string& name) -> Result<std::pair<std::span<const uint8_t>, std::shared_ptr<const void>>> {
    asked.push_back(name);
    const auto it = files.find(name);
    if (it == files.end()) return Fail(ErrorCode::kNotFound, "no such file");
    return std::pair{std::span<const uint8_t>(*it->second), std::shared_ptr<const void>(it->second)};
  };

  auto read = InvertedFile::Deserialize(head, 64, {}, nullptr, nullptr, source);
  ASSERT_TRUE(read) << read.error().ToString();
  EXPECT_EQ(asked, names);
  for (const auto& [name, file] : files) EXPECT_GT(file.use_count(), 1) << name << " is read in place";
  // The same state: the whole form of both is the same bytes, and so are the scores.
  EXPECT_TRUE(bytes_of([&](const auto& w) { read->Serialize(w); }) ==
              bytes_of([&](const auto& w) { built.Serialize(w); }));
  for (uint32_t q = 0; q < 40; ++q) {
    BagOfWords query;
    if (!Format1FixtureBag(q * 7, &query)) continue;
    EXPECT_EQ(AllScores(*read, query), AllScores(built, query)) << "query " << q;
  }
  // Segment identity survives a change that leaves a segment alone.
  const InvertedFile next = read->WithAdded(std::vector<uint32_t>{302}, first_bags);
  EXPECT_EQ(next.SegmentHandle(0), read->SegmentHandle(0));

  EXPECT_EQ(InvertedFile::Deserialize(head, 64, {}).error().code, ErrorCode::kInvalidArgument)
      << "a head without its segment files";
  auto missing = files;
  files.erase("segment-1");
  EXPECT_EQ(InvertedFile::Deserialize(head, 64, {}, nullptr, nullptr, source).error().code, ErrorCode::kNotFound);
  files = missing;
  std::swap(files["segment-0"], files["segment-2"]);
  EXPECT_EQ(InvertedFile::Deserialize(head, 64, {}, nullptr, nullptr, source).error().code, ErrorCode::kCorruptData)
      << "segments out of order";
  files = missing;
  files["segment-2"] = std::make_shared<std::vector<uint8_t>>(files["segment-2"]->begin(), files["segment-2"]->end() - 1);
  EXPECT_EQ(InvertedFile::Deserialize(head, 64, {}, nullptr, nullptr, source).error().code, ErrorCode::kCorruptData)
      << "a truncated segment file";
  files = missing;
  InvertedFile other = InvertedFile::Build(65, {}, 300, Format1FixtureBag);
  files["segment-0"] = std::make_shared<std::vector<uint8_t>>(
      bytes_of([&](const auto& write) { other.SerializeSegment(0, write); }));
  EXPECT_EQ(InvertedFile::Deserialize(head, 64, {}, nullptr, nullptr, source).error().code, ErrorCode::kCorruptData)
      << "a segment file of another vocabulary";
}

TEST(PostingsSerialisation, ReadsFormat1PostingsAndRecodesThem) {
  const std::vector<uint8_t> bytes = ReadFileBytes(OXBOW_SOURCE_DIR "/index/postings/testdata/postings_format1.oxif");
  ASSERT_GT(bytes.size(), 1000u);
  bool recoded = false;
  auto old = InvertedFile::Deserialize(bytes, 64, {}, &recoded);
  ASSERT_TRUE(old) << old.error().ToString();
  EXPECT_TRUE(recoded);

  // The same operations with this build.
  InvertedFile fresh = InvertedFile::Build(64, {}, 300, Format1FixtureBag);
  BagOfWords a, b, removed;
  a.words = {1, 5, 9};
  a.counts = {1, 2, 1};
  b.words = {5, 63};
  b.counts = {400, 1};
  const std::vector<uint32_t> added = {300, 420};
  const std::vector<const BagOfWords*> added_bags = {&a, &b};
  fresh = fresh.WithAdded(added, added_bags);
  ASSERT_TRUE(Format1FixtureBag(14, &removed));
  const std::vector<uint32_t> gone = {14};
  const std::vector<const BagOfWords*> gone_bags = {&removed};
  fresh = fresh.WithRemoved(gone, gone_bags);

  // The re-coded postings are this build's coding of the same lists: the saved files below have the
  // same size. Scores agree to 1e-6, not bit for bit: the file's per-image norm sums are the old
  // build's doubles, and whether a multiply-add is fused depends on the build's flags.
  EXPECT_EQ(old->num_images(), fresh.num_images());
  EXPECT_EQ(old->Stats().num_postings, fresh.Stats().num_postings);
  EXPECT_EQ(old->Stats().num_segments, fresh.Stats().num_segments);
  // Saved again, it is format 2, reads back without re-coding and scores as before.
  std::vector<uint8_t> again, own;
  old->Serialize([&](std::span<const uint8_t> part) { again.insert(again.end(), part.begin(), part.end()); });
  fresh.Serialize([&](std::span<const uint8_t> part) { own.insert(own.end(), part.begin(), part.end()); });
  EXPECT_EQ(again.size(), own.size());
  auto reread = InvertedFile::Deserialize(again, 64, {}, &recoded);
  ASSERT_TRUE(reread);
  EXPECT_FALSE(recoded);
  const auto near = [](const std::map<uint32_t, double>& got, const std::map<uint32_t, double>& want) {
    if (got.size() != want.size()) return false;
    for (const auto& [image, score] : want) {
      const auto it = got.find(image);
      if (it == got.end() || std::abs(it->second - score) > 1e-6) return false;
    }
    return true;
  };
  for (uint32_t q = 0; q < 40; ++q) {
    BagOfWords query;
    if (!Format1FixtureBag(q * 7, &query)) continue;
    const auto expected = AllScores(fresh, query);
    EXPECT_FALSE(expected.empty());
    EXPECT_TRUE(near(AllScores(*old, query), expected)) << "query " << q;
    EXPECT_TRUE(near(AllScores(*reread, query), expected)) << "query " << q;
  }

  // A damaged format-1 list (its last varint continues past the list's end) is refused, not decoded.
  std::vector<uint8_t> damaged = bytes;
  damaged.back() |= 0x80;
  const auto bad = InvertedFile::Deserialize(damaged, 64, {});
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, ErrorCode::kCorruptData);
  // A format newer than this build's is refused as incompatible.
  std::vector<uint8_t> future = own;
  future[4] = 4;
  const auto newer = InvertedFile::Deserialize(future, 64, {});
  ASSERT_FALSE(newer);
  EXPECT_EQ(newer.error().code, ErrorCode::kIncompatible);
}

// Every truncation of a postings file, and of a segment file its head names, is refused: never read as
// a smaller index.
TEST(PostingsSerialisation, TruncatedFilesAreRefused) {
  InvertedFile built = InvertedFile::Build(64, {}, 300, Format1FixtureBag);
  BagOfWords a;
  a.words = {1, 5, 9};
  a.counts = {1, 2, 1};
  built = built.WithAdded(std::vector<uint32_t>{300}, std::vector<const BagOfWords*>{&a});
  ASSERT_EQ(built.num_segments(), 2u);
  const std::vector<uint8_t> whole = SerializedBytes(built);
  ASSERT_TRUE(InvertedFile::Deserialize(whole, 64, {}));
  for (size_t n = 0; n < whole.size(); n += 1 + n / 128) {
    EXPECT_FALSE(InvertedFile::Deserialize(std::span(whole).first(n), 64, {})) << n << " of " << whole.size() << " bytes";
  }

  std::vector<uint8_t> segment;
  built.SerializeSegment(1, [&](std::span<const uint8_t> part) { segment.insert(segment.end(), part.begin(), part.end()); });
  std::vector<uint8_t> first;
  built.SerializeSegment(0, [&](std::span<const uint8_t> part) { first.insert(first.end(), part.begin(), part.end()); });
  const std::vector<std::string> names = {"first", "second"};
  std::vector<uint8_t> head;
  built.SerializeHead(names, [&](std::span<const uint8_t> part) { head.insert(head.end(), part.begin(), part.end()); });
  for (size_t n = 0; n <= segment.size(); ++n) {
    const InvertedFile::SegmentSource source =
        [&](const std::string& name) -> Result<std::pair<std::span<const uint8_t>, std::shared_ptr<const void>>> {
      if (name == "first") return std::pair{std::span<const uint8_t>(first), std::shared_ptr<const void>()};
      return std::pair{std::span<const uint8_t>(segment).first(n), std::shared_ptr<const void>()};
    };
    const auto read = InvertedFile::Deserialize(head, 64, {}, nullptr, nullptr, source);
    EXPECT_EQ(read.has_value(), n == segment.size()) << n << " of " << segment.size() << " bytes";
  }
}

}  // namespace
}  // namespace oxbow::index
