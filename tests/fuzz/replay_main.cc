// main() of the replay drivers built in every configuration (GCC, no libFuzzer): runs
// LLVMFuzzerTestOneInput once on every file named on the command line or found (recursively) in a
// folder named there, in sorted order, so the kept crash inputs of tests/fuzz/regressions/<target>/
// stay fixed in every CI build. Prints "<target>: N inputs replayed" and exits 0; a regression shows up
// as the crash, sanitizer report or abort itself (non-zero exit). Exit 2 when no input was found.
//
// The inputs run under the signal conditions of a fuzzing run, only denser: libFuzzer's -timeout starts
// a SIGALRM interval timer (every timeout/2 + 1 s) whose handler is installed without SA_RESTART, so a
// blocking call of the target (poll, recv, send, accept...) may fail with EINTR at any time. Here the
// timer fires every kAlarmIntervalUs (1 ms), so a target that takes an interrupted call for a real failure fails
// on every replay instead of once in a long fuzzing run (the http_request_fuzz "no answer within 20 s").
#include <sys/time.h>

#include <algorithm>
#include <csignal>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

namespace {

constexpr suseconds_t kAlarmIntervalUs = 1000;

void IgnoreAlarm(int, siginfo_t*, void*) {}

// What libFuzzer's SetTimer does (FuzzerUtilPosix.cpp): SA_SIGINFO, no SA_RESTART, ITIMER_REAL.
void StartAlarmTimer() {
  struct sigaction action {};
  action.sa_sigaction = IgnoreAlarm;
  action.sa_flags = SA_SIGINFO;
  sigemptyset(&action.sa_mask);
  sigaction(SIGALRM, &action, nullptr);
  const itimerval timer{{0, kAlarmIntervalUs}, {0, kAlarmIntervalUs}};
  setitimer(ITIMER_REAL, &timer, nullptr);
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::filesystem::path> files;
  for (int i = 1; i < argc; ++i) {
    const std::filesystem::path arg = argv[i];
    if (std::filesystem::is_directory(arg)) {
      for (const auto& entry : std::filesystem::recursive_directory_iterator(arg)) {
        if (entry.is_regular_file() && entry.path().filename().string().front() != '.') files.push_back(entry.path());
      }
    } else if (std::filesystem::is_regular_file(arg)) {
      files.push_back(arg);
    } else {
      std::fprintf(stderr, "replay: %s is neither a file nor a folder\n", argv[i]);
      return 2;
    }
  }
  std::sort(files.begin(), files.end());
  if (files.empty()) {
    std::fprintf(stderr, "replay: no input files given\n");
    return 2;
  }
  StartAlarmTimer();
  for (const auto& path : files) {
    std::ifstream in(path, std::ios::binary);
    std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::fprintf(stderr, "replay: %s (%zu bytes)\n", path.c_str(), bytes.size());
    LLVMFuzzerTestOneInput(bytes.data(), bytes.size());
  }
  std::printf("%s: %zu inputs replayed\n", std::filesystem::path(argv[0]).filename().c_str(), files.size());
  return 0;
}
