#include "api/duplicate_jobs.h"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cstdio>
#include <random>

#include "sift/base/log.h"

namespace oxbow::api {
namespace {

std::string NewJobId() {
  std::random_device device;
  char buf[17];
  std::snprintf(buf, sizeof buf, "%08x%08x", device(), device());
  return buf;
}

double Seconds(std::chrono::steady_clock::duration d) { return std::chrono::duration<double>(d).count(); }

}  // namespace

DuplicateJobs::~DuplicateJobs() {
  std::vector<std::shared_ptr<Job>> all;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto& [id, job] : jobs_) {
      job->cancel.store(true);
      all.push_back(job);
    }
  }
  for (auto& job : all) {
    if (job->thread.joinable()) job->thread.join();
  }
}

JobStatus DuplicateJobs::Snapshot(const Job& job) {
  JobStatus s = job.status;
  s.done = job.done.load();
  s.total = job.total.load();
  const auto end = s.state == "running" ? std::chrono::steady_clock::now() : job.finished;
  s.elapsed_s = Seconds(end - job.started);
  return s;
}

Result<std::string> DuplicateJobs::Start(const CollectionRef& collection, const DuplicateOptions& options) {
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, "duplicate options: " + *message);
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [id, job] : jobs_) {
    if (job->status.collection == collection.name && job->status.state == "running") {
      std::string message = "a duplicate search already runs on collection '";
      message.append(collection.name).append("': job ").append(id).append(" (GET /v1/jobs/").append(id).append(")");
      return Fail(ErrorCode::kAlreadyExists, message);
    }
  }
  std::string id;
  do {
    id = NewJobId();
  } while (jobs_.contains(id));
  auto job = std::make_shared<Job>();
  job->status.id = id;
  job->status.collection = collection.name;
  job->status.state = "running";
  job->started = std::chrono::steady_clock::now();
  job->total.store(collection.service->index().Stats().num_images);
  jobs_[id] = job;
  std::shared_ptr<Service> service = collection.service;
  job->thread = std::thread([this, job, service, options] {
    // Low priority (Linux: per thread): searches and adds keep the CPU first.
    (void)setpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid)), 10);
    auto report = FindDuplicates(
        service->index(), options,
        [&](uint64_t done, uint64_t total) {
          job->done.store(std::max(job->done.load(), done));
          job->total.store(total);
        },
        [&] { return job->cancel.load(); });
    std::lock_guard<std::mutex> done_lock(mutex_);
    job->finished = std::chrono::steady_clock::now();
    if (job->cancel.load()) {
      job->status.state = "cancelled";
    } else if (!report) {
      job->status.state = "failed";
      job->status.error = report.error();
      OXBOW_LOG(kWarning) << "duplicate job " << job->status.id << " on '" << job->status.collection
                          << "' failed: " << report.error().ToString();
    } else {
      job->status.state = "done";
      job->status.result = DuplicateReportToJson(*report, options);
      OXBOW_LOG(kInfo) << "duplicate job " << job->status.id << " on '" << job->status.collection << "' done: "
                       << report->pairs.size() << " pairs in " << report->groups.size() << " groups, "
                       << Seconds(job->finished - job->started) << " s";
    }
    finished_order_.push_back(job->status.id);
  });
  // Old finished jobs go (their results are large).
  while (finished_order_.size() > kKeptJobs) {
    auto it = jobs_.find(finished_order_.front());
    if (it != jobs_.end() && it->second->thread.joinable()) it->second->thread.join();
    if (it != jobs_.end()) jobs_.erase(it);
    finished_order_.erase(finished_order_.begin());
  }
  OXBOW_LOG(kInfo) << "duplicate job " << id << " started on collection '" << collection.name << "'";
  return id;
}

std::optional<JobStatus> DuplicateJobs::Get(const std::string& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return std::nullopt;
  return Snapshot(*it->second);
}

void DuplicateJobs::Forget(std::unique_lock<std::mutex>& lock, const std::string& id) {
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return;
  it->second->cancel.store(true);
  std::thread thread = std::move(it->second->thread);  // joined by this caller only
  jobs_.erase(it);
  std::erase(finished_order_, id);
  lock.unlock();  // the job takes the lock to finish
  if (thread.joinable()) thread.join();
  lock.lock();
  std::erase(finished_order_, id);  // pushed by the job as it ended
}

bool DuplicateJobs::Cancel(const std::string& id) {
  std::unique_lock<std::mutex> lock(mutex_);
  if (!jobs_.contains(id)) return false;
  Forget(lock, id);
  return true;
}

void DuplicateJobs::CancelCollection(const std::string& collection) {
  std::unique_lock<std::mutex> lock(mutex_);
  std::vector<std::string> ids;
  for (const auto& [id, job] : jobs_) {
    if (job->status.collection == collection) ids.push_back(id);
  }
  for (const auto& id : ids) Forget(lock, id);
}

}  // namespace oxbow::api
