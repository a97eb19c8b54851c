// Fuzz target: the HTTP API's parameter parsing without HTTP (api/params.h) and the metadata JSON
// mapping (api/json.h). The input is a list of (name, value) pairs: one byte picks a known parameter
// name (or, past the list, the next length-prefixed piece is the name), then a length-prefixed value.
// The same map goes through every route's parser (search, add, list, match), and the values through
// the scalar parsers. Expected: typed options that pass their Check(), or kInvalidArgument; a name
// given twice is refused by every route; stored metadata within the size and depth limits.
#include <array>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "api/json.h"
#include "api/params.h"
#include "tests/fuzz/fuzz_support.h"

namespace {

constexpr std::array<const char*, 14> kNames = {"top_k", "rerank", "bbox",  "qe",    "qe_images", "id",    "replace",
                                                "metadata", "offset", "limit", "model", "ratio",     "mutual", "method"};

template <typename T>
void ExpectValidOrInvalidArgument(const oxbow::Result<T>& result) {
  if (!result && result.error().code != oxbow::ErrorCode::kInvalidArgument) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace oxbow;
  fuzz::InputSplitter input({data, size});
  api::Params params;
  while (!input.empty()) {
    const uint8_t pick = input.Byte();
    std::string name = pick < kNames.size() ? std::string(kNames[pick]) : std::string(input.Piece());
    std::string value(input.Piece());
    ExpectValidOrInvalidArgument(api::ParseInt(name, value, -1000, 1000000));
    ExpectValidOrInvalidArgument(api::ParseBool(name, value));
    auto box = api::ParseBox(name, value);
    ExpectValidOrInvalidArgument(box);
    if (box && !((*box)[0] < (*box)[2] && (*box)[1] < (*box)[3])) std::abort();
    (void)api::MetadataToJson(value);
    params.emplace(std::move(name), std::move(value));
  }
  bool repeated = false;
  for (auto it = params.begin(); it != params.end(); ++it) repeated |= params.count(it->first) > 1;
  auto query = api::ParseQueryParams(params, index::QueryOptions{});
  ExpectValidOrInvalidArgument(query);
  if (query && query->Check()) std::abort();  // parsed options must be valid options
  auto add = api::ParseAddParams(params);
  ExpectValidOrInvalidArgument(add);
  if (add) {
    if (!api::CheckImageId(add->id)) std::abort();
    if (add->metadata_json.size() > api::kMaxMetadataBytes) std::abort();
    if (api::JsonNestingDepth(add->metadata_json) > api::kMaxJsonDepth) std::abort();
    (void)api::MetadataToJson(add->metadata_json).dump();
  }
  auto list = api::ParseListParams(params);
  ExpectValidOrInvalidArgument(list);
  auto match = api::ParseMatchParams(params);
  ExpectValidOrInvalidArgument(match);
  if (repeated && (query || add || list || match)) std::abort();
  return 0;
}
