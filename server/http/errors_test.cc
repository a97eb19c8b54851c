// The HTTP status of every error code and the one shape of an error body.
#include <gtest/gtest.h>

#include <utility>
#include <vector>

#include "server/http/errors.h"

namespace oxbow::server {
namespace {

TEST(Errors, EveryCodeMapsToAnErrorStatus) {
  const std::vector<std::pair<ErrorCode, int>> expected = {
      {ErrorCode::kInvalidArgument, 400}, {ErrorCode::kInvalidImage, 400},   {ErrorCode::kImageTooLarge, 413},
      {ErrorCode::kUnsupportedFormat, 415}, {ErrorCode::kNotFound, 404},     {ErrorCode::kAlreadyExists, 409},
      {ErrorCode::kCorruptData, 500},     {ErrorCode::kIncompatible, 409},   {ErrorCode::kIoError, 500},
      {ErrorCode::kResourceExhausted, 503}, {ErrorCode::kUnauthenticated, 401}, {ErrorCode::kInternal, 500}};
  for (const auto& [code, status] : expected) {
    EXPECT_EQ(HttpStatusFor(code), status) << ErrorCodeName(code);
    const HttpError e = ToHttpError(Error{code, "m"});
    EXPECT_GE(e.status, 400);
    EXPECT_EQ(e.code, ErrorCodeName(code));
  }
}

TEST(Errors, BodyHasTheOneShape) {
  const auto body = ErrorBody(ToHttpError(Error{ErrorCode::kNotFound, "no image 'x'"}), "req-1");
  ASSERT_TRUE(body.contains("error"));
  EXPECT_EQ(body["error"]["code"], "not_found");
  EXPECT_EQ(body["error"]["message"], "no image 'x'");
  EXPECT_EQ(body["error"]["request_id"], "req-1");
  EXPECT_EQ(body.size(), 1u);
  EXPECT_EQ(MethodNotAllowed("PUT", "/v1/search", "POST").status, 405);
  EXPECT_EQ(PermissionDenied("x").status, 403);
  EXPECT_EQ(RouteNotFound("GET", "/nope").status, 404);
}

}  // namespace
}  // namespace oxbow::server
