#include "api/access_keys.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/rand.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <ctime>

#include <nlohmann/json.hpp>

#include "sift/base/binary_io.h"

namespace oxbow::api {
namespace {

using nlohmann::json;

constexpr std::string_view kKeyPrefix = "oxk_";
constexpr size_t kIdHexDigits = 12;
constexpr size_t kSecretBytes = 32;
constexpr size_t kSaltBytes = 16;

std::string Hex(const uint8_t* bytes, size_t n) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string out(2 * n, '0');
  for (size_t i = 0; i < n; ++i) {
    out[2 * i] = kDigits[bytes[i] >> 4];
    out[2 * i + 1] = kDigits[bytes[i] & 15];
  }
  return out;
}

bool IsLowerHex(std::string_view text, size_t digits) {
  return text.size() == digits &&
         std::all_of(text.begin(), text.end(), [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

Result<std::string> RandomHex(size_t bytes) {
  std::vector<uint8_t> buffer(bytes);
  if (RAND_bytes(buffer.data(), static_cast<int>(buffer.size())) != 1) {
    return Fail(ErrorCode::kInternal, "the system's random generator failed (OpenSSL RAND_bytes)");
  }
  return Hex(buffer.data(), buffer.size());
}

// SHA-256(salt || secret) as hex; both are hex text as stored and presented.
std::string SaltedHash(std::string_view salt_hex, std::string_view secret_hex) {
  std::array<uint8_t, EVP_MAX_MD_SIZE> digest{};
  unsigned int size = 0;
  EVP_MD_CTX* context = EVP_MD_CTX_new();
  const bool ok = context != nullptr && EVP_DigestInit_ex(context, EVP_sha256(), nullptr) == 1 &&
                  EVP_DigestUpdate(context, salt_hex.data(), salt_hex.size()) == 1 &&
                  EVP_DigestUpdate(context, secret_hex.data(), secret_hex.size()) == 1 &&
                  EVP_DigestFinal_ex(context, digest.data(), &size) == 1;
  EVP_MD_CTX_free(context);
  return ok ? Hex(digest.data(), size) : std::string();
}

std::string UtcNow() {
  const std::time_t now = std::time(nullptr);
  std::tm utc{};
  gmtime_r(&now, &utc);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &utc);
  return buf;
}

}  // namespace

const char* KeyAccessName(KeyAccess access) { return access == KeyAccess::kWrite ? "write" : "read"; }

std::optional<KeyAccess> ParseKeyAccess(std::string_view name) {
  if (name == "read") return KeyAccess::kRead;
  if (name == "write") return KeyAccess::kWrite;
  return std::nullopt;
}

Result<std::unique_ptr<AccessKeys>> AccessKeys::Open(const std::string& path) {
  auto entries = Read(path);
  if (!entries) return std::unexpected(entries.error());
  std::unique_ptr<AccessKeys> keys(new AccessKeys(path));
  keys->entries_ = std::move(*entries);
  return keys;
}

Result<std::vector<AccessKeys::Entry>> AccessKeys::Read(const std::string& path) {
  auto bytes = io::ReadWholeFile(path, uint64_t{64} << 20);
  if (!bytes) {
    if (bytes.error().code == ErrorCode::kNotFound) return std::vector<Entry>{};
    return std::unexpected(bytes.error());
  }
  auto corrupt = [&](const std::string& what) { return Fail(ErrorCode::kCorruptData, "key file " + path + ": " + what); };
  const json doc = json::parse(bytes->begin(), bytes->end(), nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded() || !doc.is_object() || !doc.contains("keys") || !doc["keys"].is_array()) {
    return corrupt("not a JSON object with a \"keys\" array");
  }
  std::vector<Entry> entries;
  for (const json& k : doc["keys"]) {
    Entry e;
    if (!k.is_object()) return corrupt("a key entry is not an object");
    auto text = [&](const char* field, std::string* out) {
      auto it = k.find(field);
      if (it == k.end() || !it->is_string()) return false;
      *out = it->get<std::string>();
      return true;
    };
    std::string access;
    if (!text("id", &e.info.id) || !text("collection", &e.info.collection) || !text("access", &access) ||
        !text("created", &e.info.created) || !text("salt", &e.salt_hex) || !text("sha256", &e.hash_hex)) {
      return corrupt("a key entry lacks one of id, collection, access, created, salt, sha256");
    }
    const auto parsed = ParseKeyAccess(access);
    if (!parsed) return corrupt("key " + e.info.id + ": access must be \"read\" or \"write\"");
    e.info.access = *parsed;
    if (!IsLowerHex(e.info.id, kIdHexDigits) || !IsLowerHex(e.salt_hex, 2 * kSaltBytes) || !IsLowerHex(e.hash_hex, 64)) {
      return corrupt("key " + e.info.id + ": id, salt or sha256 is not lower-case hex of its length");
    }
    entries.push_back(std::move(e));
  }
  return entries;
}

Status AccessKeys::Write(const std::vector<Entry>& entries) const {
  json keys = json::array();
  for (const Entry& e : entries) {
    keys.push_back({{"id", e.info.id}, {"collection", e.info.collection}, {"access", KeyAccessName(e.info.access)},
                    {"created", e.info.created}, {"salt", e.salt_hex}, {"sha256", e.hash_hex}});
  }
  const std::string text = json{{"format", "oxbow collection keys, salted SHA-256"}, {"keys", keys}}.dump(2) + "\n";
  return io::WriteFileAtomically(path_, {reinterpret_cast<const uint8_t*>(text.data()), text.size()});
}

Status AccessKeys::Reload() {
  auto entries = Read(path_);
  if (!entries) return std::unexpected(entries.error());
  std::lock_guard<std::mutex> lock(mutex_);
  entries_ = std::move(*entries);
  return {};
}

Result<NewKey> AccessKeys::Create(const std::string& collection, KeyAccess access) {
  auto secret = RandomHex(kSecretBytes);
  if (!secret) return std::unexpected(secret.error());
  auto salt = RandomHex(kSaltBytes);
  if (!salt) return std::unexpected(salt.error());
  std::lock_guard<std::mutex> lock(mutex_);
  std::string id;
  do {
    auto drawn = RandomHex(kIdHexDigits / 2);
    if (!drawn) return std::unexpected(drawn.error());
    id = *drawn;
  } while (std::any_of(entries_.begin(), entries_.end(), [&](const Entry& e) { return e.info.id == id; }));
  Entry entry{{id, collection, access, UtcNow()}, *salt, SaltedHash(*salt, *secret)};
  if (entry.hash_hex.empty()) return Fail(ErrorCode::kInternal, "SHA-256 failed (OpenSSL)");
  std::vector<Entry> next = entries_;
  next.push_back(entry);
  if (auto s = Write(next); !s) return std::unexpected(s.error());
  entries_ = std::move(next);
  return NewKey{entry.info, std::string(kKeyPrefix) + id + "_" + *secret};
}

std::vector<KeyInfo> AccessKeys::List(const std::string& collection) const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<KeyInfo> out;
  for (const Entry& e : entries_) {
    if (e.info.collection == collection) out.push_back(e.info);
  }
  return out;
}

Status AccessKeys::Delete(const std::string& collection, const std::string& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<Entry> next;
  for (const Entry& e : entries_) {
    if (!(e.info.collection == collection && e.info.id == id)) next.push_back(e);
  }
  if (next.size() == entries_.size()) {
    return Fail(ErrorCode::kNotFound, "collection '" + collection + "' has no key with id '" + id + "'");
  }
  if (auto s = Write(next); !s) return s;
  entries_ = std::move(next);
  return {};
}

Status AccessKeys::DeleteCollection(const std::string& collection) {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<Entry> next;
  for (const Entry& e : entries_) {
    if (e.info.collection != collection) next.push_back(e);
  }
  if (next.size() == entries_.size()) return {};
  if (auto s = Write(next); !s) return s;
  entries_ = std::move(next);
  return {};
}

std::optional<KeyInfo> AccessKeys::Find(std::string_view key) const {
  // "oxk_" + 12 hex + "_" + 64 hex.
  if (key.size() != kKeyPrefix.size() + kIdHexDigits + 1 + 2 * kSecretBytes || !key.starts_with(kKeyPrefix) ||
      key[kKeyPrefix.size() + kIdHexDigits] != '_') {
    return std::nullopt;
  }
  const std::string_view id = key.substr(kKeyPrefix.size(), kIdHexDigits);
  const std::string_view secret = key.substr(kKeyPrefix.size() + kIdHexDigits + 1);
  if (!IsLowerHex(id, kIdHexDigits) || !IsLowerHex(secret, 2 * kSecretBytes)) return std::nullopt;
  std::lock_guard<std::mutex> lock(mutex_);
  for (const Entry& e : entries_) {
    if (e.info.id != id) continue;
    const std::string hash = SaltedHash(e.salt_hex, secret);
    if (hash.size() == e.hash_hex.size() && CRYPTO_memcmp(hash.data(), e.hash_hex.data(), hash.size()) == 0) return e.info;
    return std::nullopt;
  }
  return std::nullopt;
}

}  // namespace oxbow::api
