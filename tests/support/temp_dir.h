// The one temporary folder of the tests: a fresh empty folder under the system's temporary directory
// ($TMPDIR when set, else /tmp), unique to the process and the test (mkdtemp), named after the test that
// makes it, and removed with everything in it when the TempDir is destroyed. Header-only; tests and the fuzz harness
// only (the harness names its folders itself, so it links no GoogleTest).
//
//   oxbow::testing::TempDir dir;                       // oxbow-<Suite>.<Test>-XXXXXX
//   oxbow::testing::TempDir suite_dir("oxbow-http");    // a prefix of one's own (e.g. in SetUpTestSuite)
//   oxbow::testing::TempDir disk_dir("oxbow-pages", std::filesystem::current_path());  // elsewhere (not tmpfs)
//   const std::string index = dir.path() + "/index";   // or dir / "index"
//   const std::string bytes = oxbow::testing::FileBytes(dir / "photo.png");
#pragma once

#include <gtest/gtest.h>
#include <stdlib.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <stdexcept>
#include <string>
#include <system_error>

namespace oxbow::testing {

class TempDir {
 public:
  // Named "oxbow-<suite>.<test>" after the running test ("oxbow-test" outside one).
  TempDir() : TempDir(CurrentTestPrefix()) {}
  // Named `prefix`-XXXXXX under `parent` (the system's temporary directory unless given). Needs no
  // GoogleTest library: the fuzz harness uses this one.
  explicit TempDir(const std::string& prefix,
                   const std::filesystem::path& parent = std::filesystem::temp_directory_path()) {
    std::string pattern = (parent / (prefix + "-XXXXXX")).string();
    if (mkdtemp(pattern.data()) == nullptr) {
      throw std::runtime_error("cannot make a temporary folder " + pattern + ": " +
                               std::generic_category().message(errno));
    }
    path_ = pattern;
  }
  ~TempDir() {
    std::error_code ignored;
    std::filesystem::remove_all(path_, ignored);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  const std::string& path() const { return path_; }
  std::filesystem::path operator/(const std::filesystem::path& name) const { return std::filesystem::path(path_) / name; }

 private:
  static std::string CurrentTestPrefix() {
    const ::testing::TestInfo* test = ::testing::UnitTest::GetInstance()->current_test_info();
    std::string prefix =
        test == nullptr ? "oxbow-test" : std::string("oxbow-") + test->test_suite_name() + "." + test->name();
    for (char& c : prefix) {
      if (c == '/') c = '_';  // parameterised tests: "Suite/0", "Name/1"
    }
    return prefix;
  }

  std::string path_;
};

// The bytes of the file at `path` ("" when it cannot be read).
inline std::string FileBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

}  // namespace oxbow::testing
