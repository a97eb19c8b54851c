#include "api/collections.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <random>
#include <thread>

#include <nlohmann/json.hpp>

#include "sift/base/binary_io.h"
#include "sift/base/log.h"

namespace oxbow::api {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr const char* kSettingsFile = "collection.json";
constexpr const char* kKeysFile = "keys.json";
constexpr const char* kCreatingPrefix = ".creating-";
constexpr const char* kDeletingPrefix = ".deleting-";
constexpr auto kDeleteWait = std::chrono::seconds(60);

std::string Join(const std::string& dir, const std::string& name) { return (fs::path(dir) / name).string(); }

std::string RandomSuffix() {
  std::random_device device;
  char buf[17];
  std::snprintf(buf, sizeof buf, "%08x%08x", device(), device());
  return buf;
}

// fsync of a folder, so that a rename or removal in it is durable.
Status SyncFolder(const std::string& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return Fail(ErrorCode::kIoError, "cannot open folder " + dir + " to sync it");
  const bool ok = ::fsync(fd) == 0;
  ::close(fd);
  if (!ok) return Fail(ErrorCode::kIoError, "cannot sync folder " + dir);
  return {};
}

json SettingsToJson(const CollectionSettings& s) {
  json out = {{"public", s.is_public}, {"max_images", nullptr}, {"max_bytes", nullptr}};
  if (s.max_images) out["max_images"] = *s.max_images;
  if (s.max_bytes) out["max_bytes"] = *s.max_bytes;
  return out;
}

Status WriteSettings(const std::string& dir, const CollectionSettings& settings) {
  const std::string text = SettingsToJson(settings).dump(2) + "\n";
  return io::WriteFileAtomically(Join(dir, kSettingsFile), {reinterpret_cast<const uint8_t*>(text.data()), text.size()});
}

Result<CollectionSettings> ReadSettings(const std::string& dir) {
  const std::string path = Join(dir, kSettingsFile);
  auto bytes = io::ReadWholeFile(path, uint64_t{1} << 20);
  if (!bytes) {
    if (bytes.error().code == ErrorCode::kNotFound) return CollectionSettings{};
    return std::unexpected(bytes.error());
  }
  const json doc = json::parse(bytes->begin(), bytes->end(), nullptr, /*allow_exceptions=*/false);
  auto corrupt = [&](const std::string& what) { return Fail(ErrorCode::kCorruptData, "settings file " + path + ": " + what); };
  if (doc.is_discarded() || !doc.is_object()) return corrupt("not a JSON object");
  CollectionSettings s;
  if (auto it = doc.find("public"); it != doc.end()) {
    if (!it->is_boolean()) return corrupt("\"public\" must be true or false");
    s.is_public = it->get<bool>();
  }
  for (const auto& [field, out] : {std::pair{"max_images", &s.max_images}, std::pair{"max_bytes", &s.max_bytes}}) {
    auto it = doc.find(field);
    if (it == doc.end() || it->is_null()) continue;
    if (!it->is_number_unsigned()) return corrupt(std::string("\"") + field + "\" must be a non-negative integer or null");
    *out = it->get<uint64_t>();
  }
  return s;
}

uint64_t FolderBytes(const std::string& dir) {
  uint64_t total = 0;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code size_ec;
    if (it->is_regular_file(size_ec)) {
      const auto size = it->file_size(size_ec);
      if (!size_ec) total += size;
    }
  }
  return total;
}

}  // namespace

bool Collections::IsValidName(std::string_view name) {
  if (name.empty() || name.size() > 64) return false;
  auto lower_or_digit = [](char c) { return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9'); };
  if (!lower_or_digit(name.front())) return false;
  return std::all_of(name.begin(), name.end(), [&](char c) { return lower_or_digit(c) || c == '_' || c == '-'; });
}

Collections::~Collections() = default;

std::shared_ptr<Collections> Collections::Single(std::shared_ptr<Service> service) {
  std::shared_ptr<Collections> set(new Collections("", service->options(), {}));
  set->collections_[kDefaultCollection] = Entry{std::move(service), CollectionSettings{}};
  return set;
}

Result<Collections::Entry> Collections::OpenCollection(const std::string& dir) const {
  auto settings = ReadSettings(dir);
  if (!settings) return std::unexpected(settings.error());
  auto service = Service::Open(dir, std::nullopt, service_options_, index_options_);
  if (!service) return std::unexpected(service.error());
  return Entry{std::shared_ptr<Service>(std::move(*service)), *settings};
}

Result<std::shared_ptr<Collections>> Collections::Open(const std::string& data_dir,
                                                       const std::optional<std::string>& default_vocabulary,
                                                       const ServiceOptions& service_options,
                                                       const index::IndexOptions& index_options) {
  std::error_code ec;
  fs::create_directories(data_dir, ec);
  if (ec || !fs::is_directory(data_dir)) {
    return Fail(ErrorCode::kIoError, "data folder " + data_dir + " cannot be created or is not a folder");
  }
  std::shared_ptr<Collections> set(new Collections(data_dir, service_options, index_options));
  auto keys = AccessKeys::Open(Join(data_dir, kKeysFile));
  if (!keys) return std::unexpected(keys.error());
  set->keys_ = std::move(*keys);

  std::vector<std::string> names;
  for (fs::directory_iterator it(data_dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.starts_with(kCreatingPrefix) || name.starts_with(kDeletingPrefix)) {
      OXBOW_LOG(kWarning) << "removing " << it->path().string() << ", left by a collection create or delete that did not finish";
      std::error_code removed;
      fs::remove_all(it->path(), removed);
      continue;
    }
    if (!it->is_directory()) continue;
    if (!IsValidName(name) || !index::ImageIndex::Exists(it->path().string())) {
      OXBOW_LOG(kWarning) << "data folder " << data_dir << ": ignoring " << name
                          << " (a collection is a folder named [a-z0-9][a-z0-9_-]{0,63} holding an index)";
      continue;
    }
    names.push_back(name);
  }
  if (ec) return Fail(ErrorCode::kIoError, "cannot list data folder " + data_dir + ": " + ec.message());
  std::sort(names.begin(), names.end());
  for (const std::string& name : names) {
    auto entry = set->OpenCollection(Join(data_dir, name));
    if (!entry) {
      return Fail(entry.error().code, "collection '" + name + "': " + entry.error().message);
    }
    set->collections_[name] = std::move(*entry);
  }
  if (default_vocabulary && !set->collections_.contains(kDefaultCollection)) {
    CreateCollectionRequest request;
    request.name = kDefaultCollection;
    request.vocabulary_path = *default_vocabulary;
    request.settings.is_public = true;
    if (auto created = set->Create(request); !created) return std::unexpected(created.error());
  }
  return set;
}

std::optional<CollectionRef> Collections::Find(const std::string& name) const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  auto it = collections_.find(name);
  if (it == collections_.end()) return std::nullopt;
  return CollectionRef{name, it->second.service, it->second.settings};
}

std::vector<std::string> Collections::Names() const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  std::vector<std::string> names;
  names.reserve(collections_.size());
  for (const auto& [name, entry] : collections_) names.push_back(name);
  return names;
}

Result<CollectionInfo> Collections::Describe(const std::string& name) const {
  auto found = Find(name);
  if (!found) return Fail(ErrorCode::kNotFound, "no collection named '" + name + "'");
  CollectionInfo info;
  info.name = name;
  info.settings = found->settings;
  info.stats = found->service->Stats();
  info.disk_bytes = FolderBytes(found->service->index().directory());
  const vocab::Vocabulary& vocabulary = found->service->index().vocabulary();
  info.descriptor = sift::DescriptorKindName(vocabulary.descriptor_kind());
  info.hamming = vocabulary.has_hamming();
  return info;
}

std::optional<std::string> Collections::CheckRoom(const CollectionRef& collection, uint64_t adding) {
  const CollectionSettings& s = collection.settings;
  if (s.max_images) {
    const uint64_t images = collection.service->index().Stats().num_images;
    if (images + adding > *s.max_images) {
      return "collection '" + collection.name + "' holds " + std::to_string(images) + " images; its limit is " +
             std::to_string(*s.max_images) + " (delete images, or recreate it with a larger max_images)";
    }
  }
  if (s.max_bytes) {
    const uint64_t bytes = FolderBytes(collection.service->index().directory());
    if (bytes >= *s.max_bytes) {
      return "collection '" + collection.name + "' holds " + std::to_string(bytes) + " bytes on disk; its limit is " +
             std::to_string(*s.max_bytes) + " (delete images, or recreate it with a larger max_bytes)";
    }
  }
  return std::nullopt;
}

Result<CollectionInfo> Collections::Create(const CreateCollectionRequest& request) {
  if (!manages_folders()) {
    return Fail(ErrorCode::kIncompatible, "this server serves one index folder (--index); start it with --data DIR to "
                                          "manage collections");
  }
  std::lock_guard<std::mutex> admin(admin_mutex_);
  return CreateLocked(request);
}

Result<CollectionInfo> Collections::CreateLocked(const CreateCollectionRequest& request) {
  if (!IsValidName(request.name)) {
    return Fail(ErrorCode::kInvalidArgument, "collection name '" + request.name +
                                                 "' is not valid: 1-64 characters of a-z, 0-9, '_' and '-', starting "
                                                 "with a letter or digit");
  }
  if (request.vocabulary_path.empty() == request.like.empty()) {
    return Fail(ErrorCode::kInvalidArgument, "give the new collection's vocabulary: a vocabulary file on the server, "
                                             "or {\"like\": \"<collection>\"} to use another collection's");
  }
  const std::string final_dir = Join(data_dir_, request.name);
  if (Find(request.name) || fs::exists(final_dir)) {
    return Fail(ErrorCode::kAlreadyExists, "collection '" + request.name + "' already exists");
  }
  std::string vocabulary = request.vocabulary_path;
  if (!request.like.empty()) {
    auto like = Find(request.like);
    if (!like) return Fail(ErrorCode::kNotFound, "no collection named '" + request.like + "' to take the vocabulary of");
    vocabulary = Join(like->service->index().directory(), "vocabulary.oxvoc");
  }
  if (!fs::is_regular_file(vocabulary)) return Fail(ErrorCode::kNotFound, "no vocabulary file at '" + vocabulary + "'");

  // Built aside and renamed into place complete.
  const std::string building = Join(data_dir_, std::string(kCreatingPrefix) + request.name + "-" + RandomSuffix());
  auto abandon = [&](const Error& error) -> Result<CollectionInfo> {
    std::error_code ec;
    fs::remove_all(building, ec);
    return std::unexpected(error);
  };
  {
    auto service = Service::Open(building, vocabulary, service_options_, index_options_);
    if (!service) return abandon(service.error());
  }  // closed before the rename: an open index writes by its folder's path
  if (auto s = WriteSettings(building, request.settings); !s) return abandon(s.error());
  if (auto s = keys_->DeleteCollection(request.name); !s) return abandon(s.error());  // none should exist
  std::error_code ec;
  fs::rename(building, final_dir, ec);
  if (ec) return abandon(Error{ErrorCode::kIoError, "cannot rename " + building + " to " + final_dir + ": " + ec.message()});
  if (auto s = SyncFolder(data_dir_); !s) return std::unexpected(s.error());
  auto entry = OpenCollection(final_dir);
  if (!entry) return std::unexpected(entry.error());
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    collections_[request.name] = std::move(*entry);
  }
  OXBOW_LOG(kInfo) << "created collection '" << request.name << "' (vocabulary " << vocabulary << ")";
  return Describe(request.name);
}

Status Collections::Delete(const std::string& name) {
  if (!manages_folders()) {
    return Fail(ErrorCode::kIncompatible, "this server serves one index folder (--index); start it with --data DIR to "
                                          "manage collections");
  }
  std::lock_guard<std::mutex> admin(admin_mutex_);
  Entry entry;
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    auto it = collections_.find(name);
    if (it == collections_.end()) return Fail(ErrorCode::kNotFound, "no collection named '" + name + "'");
    entry = std::move(it->second);
    collections_.erase(it);
  }
  // Requests that found it before hold the service; the folder is closed once they are done.
  const auto deadline = std::chrono::steady_clock::now() + kDeleteWait;
  while (entry.service.use_count() > 1 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  if (entry.service.use_count() > 1) {
    std::lock_guard<std::mutex> lock(map_mutex_);
    collections_[name] = std::move(entry);
    return Fail(ErrorCode::kResourceExhausted, "collection '" + name + "' is still in use after 60 s; not deleted, retry later");
  }
  const std::string dir = entry.service->index().directory();
  entry.service.reset();  // closes the index (its folder lock, its background checkpoints)
  // Its keys go first: a collection made later under this name must not inherit them.
  if (auto s = keys_->DeleteCollection(name); !s) return s;
  const std::string doomed = Join(data_dir_, std::string(kDeletingPrefix) + name + "-" + RandomSuffix());
  std::error_code ec;
  fs::rename(dir, doomed, ec);
  if (ec) return Fail(ErrorCode::kIoError, "cannot rename " + dir + " to delete it: " + ec.message());
  if (auto s = SyncFolder(data_dir_); !s) return s;
  fs::remove_all(doomed, ec);
  if (ec) {
    OXBOW_LOG(kWarning) << "collection '" << name << "' deleted, but " << doomed << " could not be removed: " << ec.message();
  }
  OXBOW_LOG(kInfo) << "deleted collection '" << name << "'";
  return {};
}

Result<index::BackupResult> Collections::Backup(const std::string& name, const std::string& out) const {
  auto found = Find(name);
  if (!found) return Fail(ErrorCode::kNotFound, "no collection named '" + name + "'");
  auto done = found->service->Backup(out);
  if (!done) return done;
  if (auto s = WriteSettings(out, found->settings); !s) return std::unexpected(s.error());
  return done;
}

void Collections::StopExtractions() {
  std::lock_guard<std::mutex> lock(map_mutex_);
  for (auto& [name, entry] : collections_) entry.service->StopExtractions();
}

}  // namespace oxbow::api
