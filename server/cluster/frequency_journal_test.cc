// partition-frequencies.oxdf: what a journal writes reads back (counts and the pending batch, settled
// by what the index committed), and a damaged or foreign file is refused without changing the counts.
#include "server/cluster/frequency_journal.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <string>
#include <vector>

#include "tests/support/temp_dir.h"

namespace oxbow::cluster {
namespace {

namespace fs = std::filesystem;

constexpr uint64_t kFingerprint = 0x1234abcd5678ef00ull;
constexpr size_t kWords = 10;

class FrequencyJournalTest : public ::testing::Test {
 protected:
  std::string Path() const { return (temp_ / FrequencyJournal::kFile).string(); }
  // A journal of two counted images and a pending batch of two more.
  void WriteSample() {
    FrequencyJournal journal(Path(), kFingerprint, kWords);
    ASSERT_TRUE(journal.Prepare({{"a", {0, 3}}, {"b", {3, 9}}}));
    journal.Commit({true, true});
    ASSERT_TRUE(journal.Prepare({{"c", {1, 3}}, {"d", {2}}}));
  }
  static auto CommittedOf(std::set<std::string> ids) {
    return [ids = std::move(ids)](const std::string& id) { return ids.count(id) > 0; };
  }

  oxbow::testing::TempDir temp_;
};

TEST_F(FrequencyJournalTest, AMissingFileIsAnEmptyJournal) {
  FrequencyJournal journal(Path(), kFingerprint, kWords);
  ASSERT_TRUE(journal.Load(CommittedOf({})));
  EXPECT_EQ(journal.images(), 0u);
  EXPECT_EQ(journal.document_frequency(), std::vector<uint32_t>(kWords, 0));
}

TEST_F(FrequencyJournalTest, RoundTripCountsThePendingImagesTheIndexCommitted) {
  ASSERT_NO_FATAL_FAILURE(WriteSample());
  {
    FrequencyJournal journal(Path(), kFingerprint, kWords);
    ASSERT_TRUE(journal.Load(CommittedOf({"a", "b", "c"})));  // "d" never reached the index
    EXPECT_EQ(journal.images(), 3u);
    EXPECT_EQ(journal.document_frequency(), (std::vector<uint32_t>{1, 1, 0, 3, 0, 0, 0, 0, 0, 1}));
    // Written again (as a build does at its end), it holds the settled counts and no pending batch.
    ASSERT_TRUE(journal.Write());
  }
  FrequencyJournal again(Path(), kFingerprint, kWords);
  ASSERT_TRUE(again.Load(CommittedOf({})));
  EXPECT_EQ(again.images(), 3u);
  EXPECT_EQ(again.document_frequency(), (std::vector<uint32_t>{1, 1, 0, 3, 0, 0, 0, 0, 0, 1}));
}

TEST_F(FrequencyJournalTest, ATornOrDamagedFileIsRefusedAsCorrupt) {
  ASSERT_NO_FATAL_FAILURE(WriteSample());
  const auto size = fs::file_size(Path());
  std::string bytes(size, '\0');
  std::ifstream(Path(), std::ios::binary).read(bytes.data(), static_cast<std::streamsize>(size));
  for (const std::string& damaged : {bytes.substr(0, size - 5), bytes.substr(0, size / 2),
                                     std::string(bytes).replace(size - 9, 1, 1, static_cast<char>(bytes[size - 9] ^ 1))}) {
    std::ofstream(Path(), std::ios::binary | std::ios::trunc).write(damaged.data(), static_cast<std::streamsize>(damaged.size()));
    FrequencyJournal journal(Path(), kFingerprint, kWords);
    const Status loaded = journal.Load(CommittedOf({"a", "b", "c", "d"}));
    ASSERT_FALSE(loaded) << damaged.size() << " bytes";
    EXPECT_EQ(loaded.error().code, ErrorCode::kCorruptData) << loaded.error().ToString();
    EXPECT_EQ(journal.images(), 0u);  // nothing counted from a file it refused
  }
}

TEST_F(FrequencyJournalTest, AnotherVocabularysJournalIsRefused) {
  ASSERT_NO_FATAL_FAILURE(WriteSample());
  FrequencyJournal other_fingerprint(Path(), kFingerprint + 1, kWords);
  const Status a = other_fingerprint.Load(CommittedOf({}));
  ASSERT_FALSE(a);
  EXPECT_EQ(a.error().code, ErrorCode::kIncompatible);
  FrequencyJournal other_size(Path(), kFingerprint, kWords + 1);
  const Status b = other_size.Load(CommittedOf({}));
  ASSERT_FALSE(b);
  EXPECT_EQ(b.error().code, ErrorCode::kCorruptData);
}

}  // namespace
}  // namespace oxbow::cluster
