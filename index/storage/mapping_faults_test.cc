// A file truncated under its mapping: reads of the pages it no longer holds see zeros instead of
// ending the process with SIGBUS (MappingFaultGuard, which MappedFile registers), copies of them are
// refused (MappedFile::Copy), and a SIGBUS anywhere else still ends the process.
#include "index/storage/mapping_faults.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "index/storage/checkpoint.h"
#include "tests/support/temp_dir.h"

namespace oxbow::index {
namespace {

namespace fs = std::filesystem;

constexpr size_t kFileBytes = size_t{64} << 10;
constexpr size_t kKeptBytes = size_t{4} << 10;  // what the truncation leaves: the first page

// A death test's child is a fresh run of this program that ends by _Exit or a signal, never removing a
// folder: it makes its own inside the parent's, named in this variable, which goes with the parent's.
constexpr char kParentDirVariable[] = "OXBOW_MAPPING_FAULTS_TEST_DIR";

class MappingFaultsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    // Each death test runs in a fresh process (the handler is installed once per process).
    GTEST_FLAG_SET(death_test_style, "threadsafe");
    if (const char* parent = std::getenv(kParentDirVariable); parent != nullptr) {
      temp_.emplace("oxbow-death-test", parent);
    } else {
      temp_.emplace();
      ASSERT_EQ(::setenv(kParentDirVariable, temp_->path().c_str(), 1), 0);
      in_parent_ = true;
    }
    dir_ = temp_->path();
  }
  void TearDown() override {
    if (in_parent_) ::unsetenv(kParentDirVariable);
  }
  // A file of kFileBytes bytes of 0xab.
  std::string MakeFile(const std::string& name) const {
    std::string path = (dir_ / name).string();
    std::ofstream(path, std::ios::binary) << std::string(kFileBytes, '\xab');
    return path;
  }
  std::optional<oxbow::testing::TempDir> temp_;
  bool in_parent_ = false;
  fs::path dir_;
};

// Whether a process ended as it would have without the handler: killed by SIGBUS, or, where a
// sanitizer installed its own SIGBUS handler first (the handler passes such faults on to it), ended
// by that handler's report (exit code 1).
bool EndedByTheBusError(int status) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  if (WIFEXITED(status) && WEXITSTATUS(status) == 1) return true;
#endif
  return WIFSIGNALED(status) && WTERMSIG(status) == SIGBUS;
}

// The byte at `offset` of `bytes`, read through a volatile pointer (a real load of the mapped page).
uint8_t Load(std::span<const uint8_t> bytes, size_t offset) {
  return *static_cast<const volatile uint8_t*>(bytes.data() + offset);
}

TEST_F(MappingFaultsTest, PagesATruncatedFileNoLongerHoldsReadAsZeros) {
  const std::string path = MakeFile("f");
  // In a child process: a SIGBUS not answered ends it, and the test fails instead of the whole binary.
  EXPECT_EXIT(
      {
        auto file = MappedFile::Open(path);
        if (!file) std::_Exit(2);
        const std::span<const uint8_t> bytes = (*file)->bytes();
        if (Load(bytes, kFileBytes - 1) != 0xab) std::_Exit(3);  // every page mapped and read once
        if (::truncate(path.c_str(), kKeptBytes) != 0) std::_Exit(4);
        const uint64_t faults = MappingFaultGuard::AnsweredFaults();
        if (Load(bytes, 0) != 0xab || Load(bytes, kKeptBytes - 1) != 0xab) std::_Exit(5);  // still held
        if (Load(bytes, kKeptBytes) != 0 || Load(bytes, kFileBytes - 1) != 0) std::_Exit(6);
        if (MappingFaultGuard::AnsweredFaults() < faults + 2) std::_Exit(7);
        std::_Exit(0);
      },
      ::testing::ExitedWithCode(0), "");
}

TEST_F(MappingFaultsTest, ACopyOfBytesTheFileNoLongerHoldsIsRefused) {
  const std::string path = MakeFile("f");
  EXPECT_EXIT(
      {
        auto file = MappedFile::Open(path);
        if (!file) std::_Exit(2);
        const std::span<const uint8_t> bytes = (*file)->bytes();
        std::vector<uint8_t> out(kKeptBytes);
        if (!(*file)->Copy(bytes.subspan(kFileBytes - kKeptBytes), out)) std::_Exit(3);
        if (out != std::vector<uint8_t>(kKeptBytes, 0xab)) std::_Exit(4);
        if (::truncate(path.c_str(), kKeptBytes) != 0) std::_Exit(5);
        if (!(*file)->Copy(bytes.first(kKeptBytes), out)) std::_Exit(6);                  // held: copied
        if ((*file)->Copy(bytes.subspan(kKeptBytes / 2, kKeptBytes), out)) std::_Exit(7);  // half past the end
        if ((*file)->Copy(bytes.subspan(kFileBytes - kKeptBytes), out)) std::_Exit(8);
        std::_Exit(0);
      },
      ::testing::ExitedWithCode(0), "");
}

// Many ranges at once (more than one block of the registry), registered and unregistered in any order:
// a fault is answered in each range registered, and only there.
TEST_F(MappingFaultsTest, FaultsAreAnsweredInEveryRegisteredRangeAndOnlyThere) {
  const std::string path = MakeFile("f");
  EXPECT_EXIT(
      {
        std::vector<std::shared_ptr<const MappedFile>> files;
        for (int i = 0; i < 200; ++i) {
          auto file = MappedFile::Open(path);
          if (!file) std::_Exit(2);
          files.push_back(*file);
        }
        for (size_t i = 0; i < files.size(); i += 2) files[i].reset();  // free every other slot
        for (int i = 0; i < 50; ++i) {
          auto file = MappedFile::Open(path);
          if (!file) std::_Exit(2);
          files.push_back(*file);
        }
        if (::truncate(path.c_str(), kKeptBytes) != 0) std::_Exit(3);
        for (const auto& file : files) {
          if (file && Load(file->bytes(), kFileBytes - 1) != 0) std::_Exit(4);
        }
        std::_Exit(0);
      },
      ::testing::ExitedWithCode(0), "");
  // A mapping of its own, not registered, of a file truncated under it: the default action ends the
  // process, as without the handler (which a MappedFile installed first).
  const std::string other = MakeFile("other");
  EXPECT_EXIT(
      {
        auto file = MappedFile::Open(path);
        if (!file) std::_Exit(2);
        const int fd = ::open(other.c_str(), O_RDONLY);
        void* data = ::mmap(nullptr, kFileBytes, PROT_READ, MAP_SHARED, fd, 0);
        if (data == MAP_FAILED) std::_Exit(3);
        if (::truncate(other.c_str(), kKeptBytes) != 0) std::_Exit(4);
        Load({static_cast<const uint8_t*>(data), kFileBytes}, kFileBytes - 1);
        std::_Exit(0);
      },
      EndedByTheBusError, "");
}

TEST_F(MappingFaultsTest, ASigbusSentByAnotherProcessStillEndsTheProcess) {
  const std::string path = MakeFile("f");
  EXPECT_EXIT(
      {
        auto file = MappedFile::Open(path);
        if (!file) std::_Exit(2);
        ::kill(::getpid(), SIGBUS);
        std::_Exit(0);
      },
      EndedByTheBusError, "");
}

}  // namespace
}  // namespace oxbow::index
