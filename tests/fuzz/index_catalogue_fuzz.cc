// Fuzz target: opening an index whose catalogue.sqlite is damaged (index::ImageIndex::Open over fuzzed
// SQLite bytes, beside a valid copy of the fuzz vocabulary), then, when it opened, a query, a listing
// and a similar-image query for every listed image. Expected: an index that works, or a clean error
// (kCorruptData, kIncompatible, ...), never a crash, hang or kInternal. Seeds (fuzz_seeds) are real
// catalogues built with FuzzVocabulary() plus damaged copies.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <string>

#include "index/image_index.h"
#include "tests/fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace oxbow;
  static const std::filesystem::path dir = [] {
    auto d = fuzz::ScratchDir() / "index";
    std::filesystem::create_directories(d);
    fuzz::CheckSetup(fuzz::FuzzVocabulary().Write((d / "vocabulary.oxvoc").string()), "write vocabulary");
    return d;
  }();
  static const sift::FeatureSet query = fuzz::FuzzQueryFeatures();
  // A previous execution's write-ahead log or shared-memory file must not leak into this one.
  std::error_code ec;
  std::filesystem::remove(dir / "catalogue.sqlite-wal", ec);
  std::filesystem::remove(dir / "catalogue.sqlite-shm", ec);
  std::filesystem::remove(dir / "catalogue.sqlite-journal", ec);
  fuzz::WriteScratchFile("index/catalogue.sqlite", {data, size});

  index::IndexOptions options;
  options.num_threads = 1;
  auto opened = index::ImageIndex::Open(dir.string(), options);
  if (!opened) {
    if (opened.error().code == ErrorCode::kInternal) std::abort();
    return 0;
  }
  index::QueryOptions query_options;
  query_options.top_k = 5;
  query_options.rerank_depth = 5;
  auto response = (*opened)->Query(query, query_options);
  if (!response && response.error().code == ErrorCode::kInternal) std::abort();
  auto listed = (*opened)->List(0, 20);
  if (!listed) std::abort();  // listing an index that opened cannot fail
  for (const auto& record : *listed) {
    auto similar = (*opened)->QuerySimilar(record.id, query_options);
    if (!similar && similar.error().code == ErrorCode::kInternal) std::abort();
  }
  return 0;
}
