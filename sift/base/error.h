// Error handling shared by every oxbow module (three tiers, see ../shared/STYLE.md):
//  1. Expected failures (undecodable image, unknown id, damaged file, disk full) are values:
//     functions return Result<T> (std::expected<T, Error>) or Status, and are [[nodiscard]].
//  2. Broken invariants are programmer errors: OXBOW_CHECK throws oxbow::InvariantError.
//  3. The HTTP edge maps ErrorCode to a status code in exactly one place (api/).
#pragma once

#include <expected>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>

namespace oxbow {

// What went wrong, coarse enough to map onto exit codes and HTTP statuses.
enum class ErrorCode {
  kInvalidArgument,     // a parameter or request is malformed (HTTP 400, exit 2)
  kInvalidImage,        // bytes are not a decodable image, or empty/truncated (HTTP 400, exit 3)
  kImageTooLarge,       // declared pixel count or byte size over a limit (HTTP 413, exit 3)
  kUnsupportedFormat,   // understood but not supported (HTTP 415, exit 3)
  kNotFound,            // unknown id or missing file (HTTP 404, exit 4)
  kAlreadyExists,       // id taken (HTTP 409, exit 5)
  kCorruptData,         // a file fails its magic/version/checksum/size checks (HTTP 500, exit 6)
  kIncompatible,        // valid file from another vocabulary/extractor/version (HTTP 409, exit 6)
  kIoError,             // the OS refused a read/write/fsync/rename (HTTP 500, exit 7)
  kResourceExhausted,   // a queue or memory bound was hit (HTTP 503, exit 8)
  kUnauthenticated,     // missing or wrong API key (HTTP 401)
  kInternal,            // a bug; should never be seen (HTTP 500, exit 1)
};

// Stable lower-case name used in JSON error bodies and logs, e.g. "invalid_image".
std::string_view ErrorCodeName(ErrorCode code);

// Process exit code used by the CLI for an error of this kind (never 0).
int ExitCodeFor(ErrorCode code);

struct Error {
  ErrorCode code = ErrorCode::kInternal;
  std::string message;  // for a person: says what failed and, where possible, what to do

  // "code: message", for logs and the CLI.
  std::string ToString() const;
};

template <typename T>
using Result = std::expected<T, Error>;
using Status = std::expected<void, Error>;

// Builds the unexpected value to return from a function returning Result<T> or Status:
//   return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
inline std::unexpected<Error> Fail(ErrorCode code, std::string message) {
  return std::unexpected<Error>(Error{code, std::move(message)});
}

inline Status Ok() { return {}; }

// Thrown by OXBOW_CHECK: a broken invariant (a bug), never an expected failure.
class InvariantError : public std::logic_error {
 public:
  using std::logic_error::logic_error;
};

[[noreturn]] void ThrowInvariantError(const char* expression, const char* file, int line, std::string_view detail);

}  // namespace oxbow

// OXBOW_CHECK(cond) or OXBOW_CHECK(cond, "detail"): throws oxbow::InvariantError when cond is false.
#define OXBOW_CHECK(cond, ...)                                                              \
  do {                                                                                      \
    if (!(cond)) ::oxbow::ThrowInvariantError(#cond, __FILE__, __LINE__, "" __VA_ARGS__);  \
  } while (false)
