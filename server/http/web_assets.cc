#include "server/http/web_assets.h"

#include <cstdint>
#include <cstdio>
#include <map>

#include "sift/base/hash.h"

namespace oxbow::server {

std::string StrongEtag(std::string_view content) {
  const uint64_t hash = Fnv1a64(content);
  char buf[24];
  std::snprintf(buf, sizeof buf, "\"%016llx\"", static_cast<unsigned long long>(hash));
  return buf;
}

std::string ContentTypeFor(std::string_view path) {
  static const std::map<std::string_view, std::string_view> types = {
      {"html", "text/html; charset=utf-8"}, {"js", "text/javascript; charset=utf-8"},
      {"mjs", "text/javascript; charset=utf-8"}, {"css", "text/css; charset=utf-8"},
      {"svg", "image/svg+xml"}, {"png", "image/png"}, {"jpg", "image/jpeg"}, {"ico", "image/x-icon"},
      {"json", "application/json"}, {"txt", "text/plain; charset=utf-8"}};
  const size_t dot = path.rfind('.');
  if (dot == std::string_view::npos) return "application/octet-stream";
  auto it = types.find(path.substr(dot + 1));
  return it == types.end() ? "application/octet-stream" : std::string(it->second);
}

const WebAsset* FindWebAsset(std::string_view path) {
  static const std::map<std::string_view, WebAsset> assets = [] {
    std::map<std::string_view, WebAsset> map;
    for (const auto& file : EmbeddedFiles()) {
      map.emplace(file.path, WebAsset{file.content, ContentTypeFor(file.path), StrongEtag(file.content)});
    }
    return map;
  }();
  if (path.empty() || path.front() == '/' || path.find("..") != std::string_view::npos ||
      path.find('\\') != std::string_view::npos) {
    return nullptr;
  }
  auto it = assets.find(path);
  return it == assets.end() ? nullptr : &it->second;
}

}  // namespace oxbow::server
