// Helpers of the end-to-end tests in tests/: a shell command's output, a running `oxbow serve` child
// process (OXBOW_BINARY), a vocabulary of random centroids (instant; for tests of limits and
// durability, not of accuracy), textured test pictures and raw client sockets (for requests sent piece
// by piece). Header-only; tests only.
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <httplib.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <regex>
#include <string>
#include <thread>
#include <random>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/base/error.h"
#include "tests/support/temp_dir.h"
#include "vocab/vocabulary.h"

namespace oxbow::testing {

// `words` random unit centroids of RootSIFT-shaped (non-negative) descriptors, labelled with
// `extractor_settings` (sift::SiftOptions::Describe()). Identical images quantise identically, which is
// all the limit and durability tests need.
inline Result<vocab::Vocabulary> RandomVocabulary(const std::string& extractor_settings, size_t words = 256) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0, 1);
  std::vector<float> centroids(words * 128);
  for (size_t w = 0; w < words; ++w) {
    double norm = 0;
    for (size_t d = 0; d < 128; ++d) norm += std::pow(centroids[w * 128 + d] = u(rng), 2.0);
    for (size_t d = 0; d < 128; ++d) centroids[w * 128 + d] /= static_cast<float>(std::sqrt(norm));
  }
  vocab::QuantizerBuildOptions build;
  build.num_threads = 1;
  return vocab::Vocabulary::FromCentroids(std::move(centroids), 128, sift::DescriptorKind::kRootSift,
                                          extractor_settings, build);
}

// A textured grey picture: the crop of an opencv-doc photo (`sample`, e.g. "graf1.png") at (x, y)
// resized to width x height; seeded blurred noise when the photo is not installed.
inline cv::Mat Texture(int width, int height, const std::string& sample = "graf1.png", int x = 0, int y = 0) {
  cv::Mat grey = cv::imread("/usr/share/doc/opencv-doc/examples/data/" + sample, cv::IMREAD_GRAYSCALE);
  if (grey.empty()) {
    grey = cv::Mat(480, 640, CV_8UC1);
    cv::setRNGSeed(x * 7919 + y);
    cv::randu(grey, 0, 255);
    cv::GaussianBlur(grey, grey, cv::Size(0, 0), 3);
  }
  const cv::Rect crop(std::min(x, grey.cols / 2), std::min(y, grey.rows / 2), grey.cols - std::min(x, grey.cols / 2),
                      grey.rows - std::min(y, grey.rows / 2));
  cv::Mat out;
  cv::resize(grey(crop), out, cv::Size(width, height), 0, 0, cv::INTER_AREA);
  return out;
}

// A TCP connection to 127.0.0.1:port, or -1.
inline int ConnectTo(int port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    close(fd);
    return -1;
  }
  return fd;
}

inline bool SendAll(int fd, const std::string& text) {
  for (size_t sent = 0; sent < text.size();) {
    const ssize_t n = send(fd, text.data() + sent, text.size() - sent, MSG_NOSIGNAL);
    if (n <= 0) return false;
    sent += static_cast<size_t>(n);
  }
  return true;
}

// Reads until `text` holds `end` (true), or the peer closes, or `deadline` passes (false).
inline bool ReadUntil(int fd, const std::string& end, std::string* text,
                      std::chrono::seconds deadline = std::chrono::seconds(60)) {
  const auto until = std::chrono::steady_clock::now() + deadline;
  char buf[4096];
  while (text->find(end) == std::string::npos) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - std::chrono::steady_clock::now());
    pollfd p{fd, POLLIN, 0};
    if (left.count() <= 0 || poll(&p, 1, static_cast<int>(left.count())) <= 0) return false;
    const ssize_t n = recv(fd, buf, sizeof buf, 0);
    if (n <= 0) return false;
    text->append(buf, static_cast<size_t>(n));
  }
  return true;
}

// The value of response header `name` exactly as the server wrote it (httplib's client decodes some
// header values), for `request` sent whole to 127.0.0.1:port; empty when absent or on no answer.
inline std::string RawResponseHeader(int port, const std::string& request, const std::string& name) {
  const int fd = ConnectTo(port);
  if (fd < 0) return "";
  std::string answer;
  const bool read = SendAll(fd, request) && ReadUntil(fd, "\r\n\r\n", &answer);
  close(fd);
  if (!read) return "";
  const std::string key = "\r\n" + name + ": ";
  const size_t at = answer.find(key);
  if (at == std::string::npos || at > answer.find("\r\n\r\n")) return "";
  const size_t begin = at + key.size();
  return answer.substr(begin, answer.find("\r\n", begin) - begin);
}

// The interim response a server sends to `Expect: 100-continue` once a worker has read the headers.
inline constexpr const char* kContinue = "HTTP/1.1 100 Continue\r\n\r\n";

// `env` prefix for a child that runs MPI (`--mpi`, as a singleton or under mpirun). Open MPI refuses to
// run as root (CI) unless told otherwise. Under ASan, leak checking is off for that child only: Open MPI
// 4.1 leaves allocations of its dlopen'ed components at MPI_Finalize, which LeakSanitizer reports from
// modules already unloaded (so no suppression can name them). The same training and build code runs
// leak-checked without MPI in distributed_train_test and the CLI tests.
inline constexpr const char* kMpiChildEnvironment =
    "env OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 "
#if defined(__SANITIZE_ADDRESS__)
    "LSAN_OPTIONS=detect_leaks=0 "
#endif
    ;

// Runs `command` with the shell and returns its stdout; *exit_code gets its exit status (-1 when it
// did not exit normally).
inline std::string RunCommand(const std::string& command, int* exit_code) {
  std::string out;
  FILE* pipe = popen(command.c_str(), "r");
  if (!pipe) return out;
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof(buf), pipe)) > 0) out.append(buf, n);
  const int status = pclose(pipe);
  *exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return out;
}

class ServerProcess {
 public:
  ServerProcess(const std::vector<std::string>& args, const std::string& log_path) : log_path_(log_path) {
    int out[2];
    if (pipe(out) != 0) return;
    pid_ = fork();
    if (pid_ == 0) {
      dup2(out[1], STDOUT_FILENO);
      const int log = open(log_path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
      if (log >= 0) dup2(log, STDERR_FILENO);
      close(out[0]);
      close(out[1]);
      std::vector<std::string> full = {OXBOW_BINARY};
      full.insert(full.end(), args.begin(), args.end());
      std::vector<char*> argv;
      argv.reserve(full.size() + 1);
      for (auto& a : full) argv.push_back(a.data());
      argv.push_back(nullptr);
      execv(argv[0], argv.data());
      _exit(127);
    }
    close(out[1]);
    // Read stdout until the listening line (or EOF: the server failed to start).
    std::string text;
    char buf[256];
    const std::regex listening(R"(listening on http://127\.0\.0\.1:(\d+))");
    std::smatch m;
    while (true) {
      const ssize_t n = read(out[0], buf, sizeof buf);
      if (n <= 0) break;
      text.append(buf, static_cast<size_t>(n));
      if (std::regex_search(text, m, listening)) {
        port_ = std::stoi(m[1]);
        break;
      }
    }
    stdout_fd_ = out[0];
  }
  ~ServerProcess() {
    if (pid_ > 0 && !exited_) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
    if (stdout_fd_ >= 0) close(stdout_fd_);
  }
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  int port() const { return port_; }
  pid_t pid() const { return pid_; }
  httplib::Client Client() const {
    httplib::Client client("127.0.0.1", port_);
    client.set_read_timeout(60, 0);
    client.set_write_timeout(60, 0);
    return client;
  }
  // Polls /readyz until 200 (true) or the deadline passes.
  bool WaitReady(std::chrono::seconds deadline = std::chrono::seconds(60)) const {
    const auto end = std::chrono::steady_clock::now() + deadline;
    auto client = Client();
    while (std::chrono::steady_clock::now() < end) {
      auto res = client.Get("/readyz");
      if (res && res->status == 200) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return false;
  }
  // Sends `signal` and waits for the exit; returns the exit status (or 128 + signal).
  int Stop(int signal = SIGTERM) {
    Signal(signal);
    return Wait();
  }
  void Signal(int signal) const {
    if (pid_ > 0 && !exited_) kill(pid_, signal);
  }
  // Waits for the exit; returns the exit status (or 128 + signal).
  int Wait() {
    if (pid_ <= 0 || exited_) return -1;
    int status = 0;
    waitpid(pid_, &status, 0);
    exited_ = true;
    return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  }
  // Polls the log until it contains `text` (true) or `deadline` passes.
  bool WaitForLog(const std::string& text, std::chrono::seconds deadline = std::chrono::seconds(60)) const {
    const auto end = std::chrono::steady_clock::now() + deadline;
    while (Log().find(text) == std::string::npos) {
      if (std::chrono::steady_clock::now() >= end) return false;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return true;
  }
  std::string Log() const { return FileBytes(log_path_); }
  // The address of the shard port (`serve --grpc-port`) that the log names, "" when it names none.
  std::string GrpcAddress() const {
    std::smatch m;
    const std::string log = Log();
    if (!std::regex_search(log, m, std::regex(R"(gRPC\) on (127\.0\.0\.1:\d+))"))) return "";
    return m[1];
  }

 private:
  pid_t pid_ = -1;
  int port_ = 0;
  int stdout_fd_ = -1;
  bool exited_ = false;
  std::string log_path_;
};

}  // namespace oxbow::testing
