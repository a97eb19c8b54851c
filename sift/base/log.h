// Logging to stderr with levels, and a progress bar for long work. Thread-safe.
// Usage: OXBOW_LOG(kInfo) << "indexed " << n << " images";
#pragma once

#include <chrono>
#include <cstdint>
#include <mutex>
#include <sstream>
#include <string>

namespace oxbow::log {

enum class Level { kDebug = 0, kInfo = 1, kWarning = 2, kError = 3, kOff = 4 };

void SetLevel(Level level);
Level GetLevel();
// Parses "debug" | "info" | "warning" | "error" | "off"; false if unknown.
bool ParseLevel(const std::string& text, Level* level);

// One log line, written atomically to stderr when destroyed: "2026-11-21T06:01:02Z I message".
class Line {
 public:
  explicit Line(Level level) : level_(level) {}
  ~Line();
  Line(const Line&) = delete;
  Line& operator=(const Line&) = delete;
  template <typename T>
  Line& operator<<(const T& value) {
    stream_ << value;
    return *this;
  }

 private:
  Level level_;
  std::ostringstream stream_;
};

// A progress bar on stderr for `total` units of work: done/total, rate, ETA. Redraws at most ~10 times
// a second, only when stderr is a terminal (otherwise one line every ~5 s); Advance() is thread-safe.
class Progress {
 public:
  Progress(std::string label, uint64_t total, std::string unit = "items");
  ~Progress();  // draws the final state and a newline
  void Advance(uint64_t n = 1);
  void SetStatus(std::string status);  // extra text after the counters (e.g. current objective)

 private:
  void DrawLocked(bool final);
  std::mutex mutex_;
  std::string label_, unit_, status_;
  uint64_t total_, done_ = 0;
  std::chrono::steady_clock::time_point start_, last_draw_;
  bool tty_;
};

}  // namespace oxbow::log

#define OXBOW_LOG(level)                                                       \
  if (::oxbow::log::Level::level < ::oxbow::log::GetLevel()) {                 \
  } else                                                                       \
    ::oxbow::log::Line(::oxbow::log::Level::level)
