// Child processes of the evaluation runner: a command run to completion, and a running `oxbow serve`.
#pragma once

#include <sys/types.h>

#include <string>
#include <thread>
#include <vector>

namespace oxbow::eval {

// Runs a child process to completion, inheriting stdout/stderr; throws ExperimentError on a non-zero exit.
void RunChild(const std::vector<std::string>& args);

// A running `oxbow serve --index DIR` on an ephemeral loopback port, stopped with SIGTERM when
// destroyed. Its output goes to a log file; the port is read from its "listening on http://HOST:PORT"
// line. The constructor returns once /readyz answers 200; throws ExperimentError when the server does
// not start or become ready.
class ServerProcess {
 public:
  ServerProcess(const std::string& exe, const std::string& index_dir, const std::string& log_path, int threads);
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;
  int port() const { return port_; }

 private:
  void Stop();  // SIGTERM, wait for the exit, drain the rest of the output

  pid_t pid_ = -1;
  int port_ = -1;
  std::thread reader_;
};

std::string JoinArgs(const std::vector<std::string>& args);

}  // namespace oxbow::eval
