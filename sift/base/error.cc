#include "sift/base/error.h"

namespace oxbow {

std::string_view ErrorCodeName(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument: return "invalid_argument";
    case ErrorCode::kInvalidImage: return "invalid_image";
    case ErrorCode::kImageTooLarge: return "image_too_large";
    case ErrorCode::kUnsupportedFormat: return "unsupported_format";
    case ErrorCode::kNotFound: return "not_found";
    case ErrorCode::kAlreadyExists: return "already_exists";
    case ErrorCode::kCorruptData: return "corrupt_data";
    case ErrorCode::kIncompatible: return "incompatible";
    case ErrorCode::kIoError: return "io_error";
    case ErrorCode::kResourceExhausted: return "resource_exhausted";
    case ErrorCode::kUnauthenticated: return "unauthenticated";
    case ErrorCode::kInternal: return "internal";
  }
  return "internal";
}

int ExitCodeFor(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument: return 2;
    case ErrorCode::kInvalidImage:
    case ErrorCode::kImageTooLarge:
    case ErrorCode::kUnsupportedFormat: return 3;
    case ErrorCode::kNotFound: return 4;
    case ErrorCode::kAlreadyExists: return 5;
    case ErrorCode::kCorruptData:
    case ErrorCode::kIncompatible: return 6;
    case ErrorCode::kIoError: return 7;
    case ErrorCode::kResourceExhausted: return 8;
    case ErrorCode::kUnauthenticated: return 9;
    case ErrorCode::kInternal: return 1;
  }
  return 1;
}

std::string Error::ToString() const { return std::string(ErrorCodeName(code)) + ": " + message; }

void ThrowInvariantError(const char* expression, const char* file, int line, std::string_view detail) {
  std::string what = std::string("invariant violated: ") + expression + " at " + file + ":" + std::to_string(line);
  if (!detail.empty()) what += " (" + std::string(detail) + ")";
  throw InvariantError(what);
}

}  // namespace oxbow
