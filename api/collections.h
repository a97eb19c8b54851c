// Named collections served by one process (oxbow serve --data DIR): each is an ordinary index folder
// DIR/<name>/ (what `oxbow index build` makes and `oxbow serve --index` serves) with its own vocabulary,
// opened as its own api::Service. Collections whose vocabularies are the same file content hold one copy
// of it in memory (vocab::Vocabulary::Read shares identical vocabularies).
//
// The data folder:
//   DIR/<name>/                 an index folder; <name> matches [a-z0-9][a-z0-9_-]{0,63}
//   DIR/<name>/collection.json  its settings: {"public": bool, "max_images": n|null, "max_bytes": n|null};
//                               a folder without it (an index put there by hand) is public, without limits
//   DIR/keys.json               the collections' keys (api/access_keys.h)
//   DIR/.creating-* .deleting-* what a create or delete cut short by a crash left; removed at open
// Folders and files of other names are ignored (with a log line).
//
// Create builds the new index in DIR/.creating-<name>-<random> and renames it into place when complete,
// so a crash leaves either the whole collection or none. Delete takes the collection out of service,
// waits (at most 60 s) for the requests holding it, closes it, renames its folder to .deleting-... and
// then removes it.
//
// The collection named "default" is the one the routes without a collection prefix act on. Single()
// makes a set of exactly that collection over one index folder (oxbow serve --index), which cannot
// create or delete collections.
//
// Thread-safe: Find, Names, Describe and CheckRoom may run concurrently with everything; Create and
// Delete serialise among themselves.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "api/access_keys.h"
#include "api/service.h"
#include "index/image_index.h"
#include "sift/base/error.h"

namespace oxbow::api {

inline constexpr const char* kDefaultCollection = "default";

struct CollectionSettings {
  bool is_public = true;                     // reads need no key
  std::optional<uint64_t> max_images;        // adds refused at this many live images
  std::optional<uint64_t> max_bytes;         // adds refused once the folder holds this many bytes on disk
};

struct CollectionInfo {
  std::string name;
  CollectionSettings settings;
  ServiceStats stats;
  uint64_t disk_bytes = 0;                   // bytes of the collection's folder
  std::string descriptor;                    // "rootsift" | "sift"
  bool hamming = false;                      // the vocabulary has Hamming-embedding parameters
};

struct CreateCollectionRequest {
  std::string name;
  std::string vocabulary_path;               // a vocabulary file on the server; or
  std::string like;                          // the name of a collection whose vocabulary to use
  CollectionSettings settings;
};

// A collection as a request holds it: the service stays open while the pointer lives.
struct CollectionRef {
  std::string name;
  std::shared_ptr<Service> service;
  CollectionSettings settings;
};

class Collections {
 public:
  // True for a valid collection name ([a-z0-9][a-z0-9_-]{0,63}).
  static bool IsValidName(std::string_view name);

  // The collection "default" over an open service of one index folder; no keys, no create or delete.
  static std::shared_ptr<Collections> Single(std::shared_ptr<Service> service);
  // Opens every collection of `data_dir` (created when missing). With `default_vocabulary`, creates the
  // collection "default" (public) with it when there is none. Fails on the first collection that does
  // not open, and on a key file that is not valid.
  [[nodiscard]] static Result<std::shared_ptr<Collections>> Open(const std::string& data_dir,
                                                                 const std::optional<std::string>& default_vocabulary,
                                                                 const ServiceOptions& service_options,
                                                                 const index::IndexOptions& index_options);
  ~Collections();
  Collections(const Collections&) = delete;
  Collections& operator=(const Collections&) = delete;

  // Whether this set manages a data folder (create, delete, keys); false for Single.
  bool manages_folders() const { return !data_dir_.empty(); }
  const std::string& data_dir() const { return data_dir_; }

  std::optional<CollectionRef> Find(const std::string& name) const;
  std::vector<std::string> Names() const;                      // sorted
  // Settings and statistics. kNotFound for an unknown collection.
  [[nodiscard]] Result<CollectionInfo> Describe(const std::string& name) const;
  // kInvalidArgument (name, settings, both or neither of vocabulary_path and like), kAlreadyExists,
  // kNotFound (vocabulary file or `like` collection), the index's errors; kIncompatible on a Single set.
  [[nodiscard]] Result<CollectionInfo> Create(const CreateCollectionRequest& request);
  // kNotFound; kResourceExhausted when requests still hold it after 60 s (it then stays in service).
  [[nodiscard]] Status Delete(const std::string& name);
  // Why an add of `adding` images to `collection` would pass its limits (a message for the client), or
  // nullopt when it fits. Checked before the add: concurrent adds may each pass it.
  static std::optional<std::string> CheckRoom(const CollectionRef& collection, uint64_t adding);
  // Backs up the collection's index (Service::Backup) and its settings into the new folder `out`.
  [[nodiscard]] Result<index::BackupResult> Backup(const std::string& name, const std::string& out) const;
  // The keys of this data folder; null for Single.
  AccessKeys* keys() const { return keys_.get(); }
  // Service::StopExtractions on every collection (shutdown).
  void StopExtractions();

 private:
  struct Entry {
    std::shared_ptr<Service> service;
    CollectionSettings settings;
  };
  Collections(std::string data_dir, const ServiceOptions& service_options, const index::IndexOptions& index_options)
      : data_dir_(std::move(data_dir)), service_options_(service_options), index_options_(index_options) {}
  Result<Entry> OpenCollection(const std::string& dir) const;
  Result<CollectionInfo> CreateLocked(const CreateCollectionRequest& request);

  const std::string data_dir_;               // "" for Single
  const ServiceOptions service_options_;
  const index::IndexOptions index_options_;
  std::unique_ptr<AccessKeys> keys_;
  std::mutex admin_mutex_;                   // serialises Create and Delete
  mutable std::mutex map_mutex_;             // guards collections_ (pointer copies only)
  std::map<std::string, Entry> collections_;
};

}  // namespace oxbow::api
