#include "eval/runner/server_process.h"

#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <fstream>
#include <future>
#include <regex>

#include "eval/runner/experiment.h"
#include "sift/base/log.h"

// After Eigen (via index/ and sift/ headers): httplib pulls in <resolv.h>, whose `_res` macro breaks
// Eigen's headers when they come later.
#include <httplib.h>

extern char** environ;

namespace oxbow::eval {

using Clock = std::chrono::steady_clock;

std::string JoinArgs(const std::vector<std::string>& args) {
  std::string s;
  for (const auto& a : args) s += (s.empty() ? "" : " ") + a;
  return s;
}

void RunChild(const std::vector<std::string>& args) {
  OXBOW_LOG(kInfo) << "eval: running " << JoinArgs(args);
  std::vector<char*> argv;
  argv.reserve(args.size() + 1);
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  pid_t pid;
  if (posix_spawn(&pid, argv[0], nullptr, nullptr, argv.data(), environ) != 0) {
    throw ExperimentError(1, "cannot start " + args[0]);
  }
  int status = 0;
  while (waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    throw ExperimentError(1, "'" + JoinArgs(args) + "' failed (status " + std::to_string(status) + ")");
  }
}

ServerProcess::ServerProcess(const std::string& exe, const std::string& index_dir, const std::string& log_path,
                             int threads) {
  int fds[2];
  if (pipe(fds) != 0) throw ExperimentError(1, "pipe failed");
  std::vector<std::string> args = {exe, "serve", "--index", index_dir, "--host", "127.0.0.1", "--port", "0"};
  if (threads > 0) args.insert(args.end(), {"--index-threads", std::to_string(threads)});
  OXBOW_LOG(kInfo) << "eval: starting " << JoinArgs(args);
  std::vector<char*> argv;
  argv.reserve(args.size() + 1);
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, fds[1], STDOUT_FILENO);
  posix_spawn_file_actions_adddup2(&actions, fds[1], STDERR_FILENO);
  posix_spawn_file_actions_addclose(&actions, fds[0]);
  const int rc = posix_spawn(&pid_, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  close(fds[1]);
  if (rc != 0) {
    close(fds[0]);
    throw ExperimentError(1, "cannot start the server");
  }
  // Drain the server's output into the log for its whole life (a full pipe would block it).
  std::promise<int> port_promise;
  auto port_future = port_promise.get_future();
  reader_ = std::thread([fd = fds[0], log_path, p = std::move(port_promise)]() mutable {
    std::ofstream log(log_path, std::ios::app);
    std::string pending;
    bool port_found = false;
    const std::regex listening(R"(listening on http://[^:/\s]+:(\d+))");
    char buf[4096];
    ssize_t n;
    while ((n = read(fd, buf, sizeof buf)) > 0) {
      log.write(buf, n);
      if (port_found) continue;
      pending.append(buf, static_cast<size_t>(n));
      std::smatch m;
      if (std::regex_search(pending, m, listening)) {
        port_found = true;
        p.set_value(std::stoi(m[1]));
      }
    }
    if (!port_found) p.set_value(-1);
    close(fd);
  });
  try {
    if (port_future.wait_for(std::chrono::seconds(300)) == std::future_status::ready) port_ = port_future.get();
    if (port_ <= 0) throw ExperimentError(1, "the server did not start; see " + log_path);
    // The server loads the index in the background: wait until /readyz says it is ready.
    httplib::Client client("127.0.0.1", port_);
    const auto deadline = Clock::now() + std::chrono::seconds(600);
    while (true) {
      auto ready = client.Get("/readyz");
      if (ready && ready->status == 200) break;
      if (Clock::now() > deadline) throw ExperimentError(1, "the server did not become ready; see " + log_path);
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  } catch (...) {
    Stop();  // no destructor runs for a constructor that throws
    throw;
  }
}

ServerProcess::~ServerProcess() { Stop(); }

void ServerProcess::Stop() {
  kill(pid_, SIGTERM);
  int status = 0;
  waitpid(pid_, &status, 0);
  if (reader_.joinable()) reader_.join();
}

}  // namespace oxbow::eval
