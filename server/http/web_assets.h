// The web page's files (server/web/: index.html, app.js, style.css), compiled into the binary by
// cmake/EmbedFiles.cmake, so `oxbow serve` needs nothing beside it and never fetches from the network.
// The HTTP server serves index.html at / and every file at /static/<name>.
//
// Thread safety: all functions read immutable data (built once, on first use).
#pragma once

#include <span>
#include <string>
#include <string_view>

namespace oxbow::server {

struct EmbeddedFile {
  std::string_view path;     // relative to server/web/, e.g. "app.js"
  std::string_view content;  // the file's bytes (static storage)
};

// Defined by the generated web_assets_data.cc.
std::span<const EmbeddedFile> EmbeddedFiles();

struct WebAsset {
  std::string_view content;
  std::string content_type;  // from the extension, e.g. "text/javascript; charset=utf-8"
  std::string etag;          // StrongEtag(content)
};

// The embedded file at `path` (as in EmbeddedFile::path), or nullptr. Paths with "..", a leading "/"
// or a backslash never match. O(number of files).
const WebAsset* FindWebAsset(std::string_view path);

// A strong HTTP ETag for `content`: "\"<16 hex digits>\"" (FNV-1a 64 of the bytes). O(size).
std::string StrongEtag(std::string_view content);

// MIME type for a file name's extension (html, js, mjs, css, svg, png, jpg, ico, json, txt);
// application/octet-stream otherwise.
std::string ContentTypeFor(std::string_view path);

}  // namespace oxbow::server
