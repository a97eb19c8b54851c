// Keys of collections (api/collections.h): each grants read, or read and write, access to one collection.
//
// A key is shown once, when it is made: "oxk_<id>_<secret>", where <id> (12 hex digits) names the key
// (listing, revoking, log lines) and <secret> is 32 random bytes as 64 hex digits. The key file keeps,
// per key, its id, collection, access, creation time (UTC, ISO 8601), a random 16-byte salt and
// SHA-256(salt || secret): never the secret, so a copy of the file grants nothing. A presented key is
// looked up by its id and its hash compared in constant time.
//
// The file (JSON, DATA/keys.json) is written atomically (temp file, fsync, rename) on every change and
// read at open and on Reload (oxbow serve re-reads it on SIGHUP, e.g. after an edit that revokes keys by
// hand). A file that is not valid is refused at open and on Reload (the keys in memory stay as they were).
//
// Thread-safe: every member may be called concurrently.
#pragma once

#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::api {

enum class KeyAccess { kRead, kWrite };

const char* KeyAccessName(KeyAccess access);                        // "read" | "write"
std::optional<KeyAccess> ParseKeyAccess(std::string_view name);      // nullopt for anything else

struct KeyInfo {
  std::string id;            // 12 hex digits
  std::string collection;
  KeyAccess access = KeyAccess::kRead;
  std::string created;       // "2026-12-02T10:11:12Z"
};

struct NewKey {
  KeyInfo info;
  std::string key;           // "oxk_<id>_<secret>": shown to its maker once, stored nowhere
};

class AccessKeys {
 public:
  // Reads `path` (JSON as above); a missing file is an empty set. kCorruptData for a file that is not valid.
  [[nodiscard]] static Result<std::unique_ptr<AccessKeys>> Open(const std::string& path);

  // Re-reads the file; on failure the keys in memory stay unchanged.
  [[nodiscard]] Status Reload();
  // Makes a key of `collection` (durable when it returns). kIoError when the file cannot be written.
  [[nodiscard]] Result<NewKey> Create(const std::string& collection, KeyAccess access);
  // The keys of `collection`, oldest first.
  std::vector<KeyInfo> List(const std::string& collection) const;
  // Revokes a key of `collection`. kNotFound when it has none with this id.
  [[nodiscard]] Status Delete(const std::string& collection, const std::string& id);
  // Revokes every key of `collection` (the collection is deleted).
  [[nodiscard]] Status DeleteCollection(const std::string& collection);
  // The entry of a valid key; nullopt for anything else (unknown id, wrong secret, not a key's shape).
  std::optional<KeyInfo> Find(std::string_view key) const;

 private:
  struct Entry {
    KeyInfo info;
    std::string salt_hex;      // 32 hex digits
    std::string hash_hex;      // SHA-256(salt || secret), 64 hex digits
  };
  explicit AccessKeys(std::string path) : path_(std::move(path)) {}
  static Result<std::vector<Entry>> Read(const std::string& path);
  Status Write(const std::vector<Entry>& entries) const;  // caller holds mutex_

  const std::string path_;
  mutable std::mutex mutex_;   // guards entries_ and the file
  std::vector<Entry> entries_;
};

}  // namespace oxbow::api
