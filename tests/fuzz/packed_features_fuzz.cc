// Fuzz target: the per-image BLOB of the index catalogue (index::PackedFeatures::Deserialize, see
// index/storage/feature_store.h) and everything the index does with a BLOB that passed: dequantised keypoints,
// bag of words, bag inside a box. The first input byte picks the form: 0 the bytes as a BLOB; 1 a BLOB
// built around the input (i32 width, i32 height from the input, then the rest as packed features) with
// a correct header and CRC, so mutations reach the fields behind the checksum.
#include <array>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "index/storage/feature_store.h"
#include "sift/base/binary_io.h"
#include "tests/fuzz/fuzz_support.h"

namespace {

template <typename T>
void Append(std::vector<uint8_t>& out, T value) {
  const auto* p = reinterpret_cast<const uint8_t*>(&value);
  out.insert(out.end(), p, p + sizeof(T));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace oxbow;
  fuzz::InputSplitter input({data, size});
  const uint8_t mode = input.Byte() % 2;
  std::vector<uint8_t> blob;
  if (mode == 0) {
    const auto rest = input.Rest();
    blob.assign(rest.begin(), rest.end());
  } else {
    int32_t width = 0, height = 0;
    for (int i = 0; i < 4; ++i) width = static_cast<int32_t>((static_cast<uint32_t>(width) << 8) | input.Byte());
    for (int i = 0; i < 4; ++i) height = static_cast<int32_t>((static_cast<uint32_t>(height) << 8) | input.Byte());
    const auto packed = input.Rest();
    blob.insert(blob.end(), {'O', 'X', 'F', 'T'});
    Append<uint32_t>(blob, 1);
    Append<int32_t>(blob, width);
    Append<int32_t>(blob, height);
    Append<uint32_t>(blob, static_cast<uint32_t>(packed.size() / index::kPackedFeatureBytes));
    Append<uint32_t>(blob, io::Crc32(packed));
    blob.insert(blob.end(), packed.begin(), packed.end());
  }
  auto features = index::PackedFeatures::Deserialize(blob, "fuzz blob");
  if (!features) {
    if (features.error().code == ErrorCode::kInternal) std::abort();
    return 0;
  }
  if (features->width() <= 0 || features->height() <= 0) std::abort();
  const auto keypoints = features->Keypoints();
  const auto bag = features->Bag();
  if (keypoints.size() != features->size() || bag.total() != features->size()) std::abort();
  const std::array<float, 4> box = {0.0f, 0.0f, features->width() / 2.0f, features->height() / 2.0f};
  if (features->BagInside(box).total() > features->size()) std::abort();
  // A BLOB that deserialised has exactly count * (9 or 17) bytes behind a header, so it serialises back
  // to itself; except an empty record under the signed version (2), which oxbow never writes: with no
  // features there is nothing to tell signed from unsigned, and it serialises as version 1.
  const std::vector<uint8_t> again = features->Serialize();
  if (features->size() > 0) {
    if (again != blob) std::abort();
  } else {
    auto reread = index::PackedFeatures::Deserialize(again, "fuzz blob, serialised again");
    if (!reread || reread->size() != 0 || reread->width() != features->width() ||
        reread->height() != features->height() || reread->Serialize() != again) {
      std::abort();
    }
  }
  return 0;
}
