// Fuzz target: the feature file reader (sift/features_io.h) and the container it sits in
// (sift/base/binary_io.h). The first input byte picks how the rest is presented:
//   0: as a feature payload (DecodeFeaturePayload), past the container's CRC;
//   1: as a whole file (ReadFeatureFile -> ReadContainerFile: magic, version, byte order, lengths, CRCs);
//   2: as a payload wrapped in a valid container header (correct CRCs), so mutations reach the payload
//      parser through the file path too.
// A payload that decodes must re-encode to a payload that decodes to the same features.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "sift/base/binary_io.h"
#include "sift/features_io.h"
#include "tests/fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace oxbow;
  fuzz::InputSplitter input({data, size});
  const uint8_t mode = input.Byte() % 3;
  const auto rest = input.Rest();
  Result<sift::FeatureFile> file = std::unexpected(Error{ErrorCode::kInvalidArgument, "unset"});
  if (mode == 0) {
    file = sift::DecodeFeaturePayload(rest, "fuzz payload");
  } else if (mode == 1) {
    file = sift::ReadFeatureFile(fuzz::WriteScratchFile("features.oxfeat", rest));
  } else {
    const std::string path = (fuzz::ScratchDir() / "wrapped.oxfeat").string();
    fuzz::CheckSetup(io::WriteContainerFile(path, sift::kFeatureFileMagic, sift::kFeatureFileVersion, 0, rest),
                     "write container");
    file = sift::ReadFeatureFile(path);
  }
  if (!file) {
    if (file.error().code == ErrorCode::kInternal) std::abort();
    return 0;
  }
  const auto encoded = sift::EncodeFeaturePayload(*file);
  auto again = sift::DecodeFeaturePayload(encoded, "re-encoded payload");
  if (!again || again->features.keypoints.size() != file->features.keypoints.size() ||
      again->features.descriptors != file->features.descriptors ||
      again->extractor_description != file->extractor_description) {
    std::abort();
  }
  return 0;
}
