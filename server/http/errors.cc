#include "server/http/errors.h"

namespace oxbow::server {

int HttpStatusFor(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument:
    case ErrorCode::kInvalidImage: return 400;
    case ErrorCode::kUnauthenticated: return 401;
    case ErrorCode::kNotFound: return 404;
    case ErrorCode::kAlreadyExists:
    case ErrorCode::kIncompatible: return 409;
    case ErrorCode::kImageTooLarge: return 413;
    case ErrorCode::kUnsupportedFormat: return 415;
    case ErrorCode::kCorruptData:
    case ErrorCode::kIoError:
    case ErrorCode::kInternal: return 500;
    case ErrorCode::kResourceExhausted: return 503;
  }
  return 500;
}

HttpError ToHttpError(const Error& error) {
  return HttpError{HttpStatusFor(error.code), std::string(ErrorCodeName(error.code)), error.message};
}

HttpError PermissionDenied(std::string message) { return HttpError{403, "permission_denied", std::move(message)}; }

HttpError RouteNotFound(std::string_view method, std::string_view path, std::string_view route_without_slash) {
  std::string message = "no route " + std::string(method) + " " + std::string(path);
  if (!route_without_slash.empty()) {
    message += "; the route is " + std::string(route_without_slash) + ", without the trailing slash";
  } else {
    message += " (GET /v1 lists the routes)";
  }
  return HttpError{404, "not_found", std::move(message)};
}

HttpError MethodNotAllowed(std::string_view method, std::string_view path, std::string_view allowed) {
  return HttpError{405, "method_not_allowed",
                   std::string(method) + " is not allowed on " + std::string(path) + "; allowed: " +
                       std::string(allowed)};
}

HttpError Unavailable(std::string message) { return HttpError{503, "unavailable", std::move(message)}; }

HttpError CollectionFull(std::string message) { return HttpError{507, "collection_full", std::move(message)}; }

nlohmann::json ErrorBody(const HttpError& error, std::string_view request_id) {
  return {{"error", {{"code", error.code}, {"message", error.message}, {"request_id", std::string(request_id)}}}};
}

}  // namespace oxbow::server
