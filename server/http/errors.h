// The HTTP edge of oxbow's error model (../shared/STYLE.md, tier 3): api/ and the index report
// transport-free oxbow::ErrorCodes; here one function maps an ErrorCode to an HTTP status, one builds
// the JSON error body every route returns (server/http and the cluster front, server/cluster/front_http):
//
//   {"error": {"code": "invalid_image", "message": "...", "request_id": "..."}}
//
// No HTTP library here, only status numbers and JSON. Thread-safe (pure functions).
#pragma once

#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "sift/base/error.h"

namespace oxbow::server {

// An error as the HTTP layer reports it.
struct HttpError {
  int status = 500;        // HTTP status code, always >= 400
  std::string code;        // stable machine-readable name, e.g. "not_found" (ErrorCodeName for ErrorCodes)
  std::string message;     // for a person
};

// The status for an error code. The single place where ErrorCode meets HTTP:
//   invalid_argument, invalid_image -> 400; unauthenticated -> 401; not_found -> 404;
//   already_exists, incompatible -> 409; image_too_large -> 413; unsupported_format -> 415;
//   corrupt_data, io_error, internal -> 500; resource_exhausted -> 503.
int HttpStatusFor(ErrorCode code);

// HttpError{HttpStatusFor(error.code), ErrorCodeName(error.code), error.message}.
HttpError ToHttpError(const Error& error);

// Errors that exist only at the HTTP level (no ErrorCode): 403 wrong API key, 404 unknown route,
// 405 wrong method, 503 server busy / not ready, 507 collection full.
HttpError PermissionDenied(std::string message);   // 403 "permission_denied"
// 404 "not_found"; route_without_slash: the route `path` names with a trailing slash added, if any.
HttpError RouteNotFound(std::string_view method, std::string_view path, std::string_view route_without_slash = {});
HttpError MethodNotAllowed(std::string_view method, std::string_view path, std::string_view allowed);  // 405
HttpError Unavailable(std::string message);        // 503 "unavailable"
HttpError CollectionFull(std::string message);     // 507 "collection_full": a collection's limit reached

// {"error": {"code", "message", "request_id"}}.
nlohmann::json ErrorBody(const HttpError& error, std::string_view request_id);

}  // namespace oxbow::server
