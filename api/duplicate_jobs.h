// Duplicate searches (api/duplicates.h) as background jobs of a server: started on a collection, asked
// for their progress and result, cancelled (POST /v1/collections/{name}/duplicates, GET and DELETE
// /v1/jobs/{job}).
//
// A job runs on its own thread at a low priority (nice 10, as adds extract: searches keep the CPU
// first), with DuplicateOptions::threads of the shared pool (1 by default). At most one job runs per
// collection. A job holds its collection open until it ends; Cancel and CancelCollection stop it at
// its next image and wait for it. The results of the last kKeptJobs finished jobs are kept in memory
// (not across restarts). Job ids are 16 random hex digits.
//
// Thread-safe.
#pragma once

#include <atomic>
#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>

#include "api/collections.h"
#include "api/duplicates.h"
#include "sift/base/error.h"

namespace oxbow::api {

struct JobStatus {
  std::string id;
  std::string collection;
  std::string state;                    // "running" | "done" | "failed" | "cancelled"
  uint64_t done = 0, total = 0;         // images searched so far, of all
  double elapsed_s = 0;
  std::optional<nlohmann::json> result; // when done: DuplicateReportToJson
  std::optional<Error> error;           // when failed
};

class DuplicateJobs {
 public:
  static constexpr size_t kKeptJobs = 16;

  DuplicateJobs() = default;
  ~DuplicateJobs();  // cancels and joins every job
  DuplicateJobs(const DuplicateJobs&) = delete;
  DuplicateJobs& operator=(const DuplicateJobs&) = delete;

  // Starts a job on `collection`; its id. kAlreadyExists when one runs on it; kInvalidArgument for bad options.
  [[nodiscard]] Result<std::string> Start(const CollectionRef& collection, const DuplicateOptions& options);
  std::optional<JobStatus> Get(const std::string& id) const;
  // Cancels a running job and waits for it to stop; false when there is no such job. A finished job is
  // forgotten.
  bool Cancel(const std::string& id);
  // Cancels the running jobs of `collection` and waits for them (before the collection is deleted).
  void CancelCollection(const std::string& collection);

 private:
  struct Job {
    JobStatus status;
    std::atomic<bool> cancel{false};
    std::atomic<uint64_t> done{0}, total{0};
    std::chrono::steady_clock::time_point started, finished;
    std::thread thread;
  };
  void Forget(std::unique_lock<std::mutex>& lock, const std::string& id);
  static JobStatus Snapshot(const Job& job);

  mutable std::mutex mutex_;               // guards jobs_ and each job's status
  std::map<std::string, std::shared_ptr<Job>> jobs_;
  std::vector<std::string> finished_order_;  // oldest first
};

}  // namespace oxbow::api
