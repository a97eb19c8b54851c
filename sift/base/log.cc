#include "sift/base/log.h"

#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstdio>
#include <ctime>

namespace oxbow::log {
namespace {

std::atomic<Level> g_level{Level::kInfo};
std::mutex g_stderr_mutex;  // guards writes to stderr so lines never interleave

char LevelLetter(Level level) {
  switch (level) {
    case Level::kDebug: return 'D';
    case Level::kInfo: return 'I';
    case Level::kWarning: return 'W';
    case Level::kError: return 'E';
    case Level::kOff: return '-';
  }
  return '?';
}

std::string FormatDuration(double seconds) {
  char buf[32];
  if (seconds < 0 || seconds > 1e7) return "?";
  const int s = static_cast<int>(std::lround(seconds));
  if (s >= 3600) {
    std::snprintf(buf, sizeof buf, "%dh%02dm", s / 3600, (s / 60) % 60);
  } else {
    std::snprintf(buf, sizeof buf, "%dm%02ds", s / 60, s % 60);
  }
  return buf;
}

}  // namespace

void SetLevel(Level level) { g_level.store(level); }
Level GetLevel() { return g_level.load(); }

bool ParseLevel(const std::string& text, Level* level) {
  if (text == "debug") *level = Level::kDebug;
  else if (text == "info") *level = Level::kInfo;
  else if (text == "warning" || text == "warn") *level = Level::kWarning;
  else if (text == "error") *level = Level::kError;
  else if (text == "off" || text == "quiet") *level = Level::kOff;
  else return false;
  return true;
}

Line::~Line() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char stamp[32];
  std::strftime(stamp, sizeof stamp, "%Y-%m-%dT%H:%M:%SZ", &tm);
  const std::string text = std::string(stamp) + " " + LevelLetter(level_) + " " + stream_.str() + "\n";
  std::lock_guard<std::mutex> lock(g_stderr_mutex);
  std::fwrite(text.data(), 1, text.size(), stderr);
}

Progress::Progress(std::string label, uint64_t total, std::string unit)
    : label_(std::move(label)),
      unit_(std::move(unit)),
      total_(total),
      start_(std::chrono::steady_clock::now()),
      last_draw_(start_),
      tty_(::isatty(STDERR_FILENO) != 0) {}

Progress::~Progress() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (GetLevel() <= Level::kInfo) DrawLocked(true);
}

void Progress::Advance(uint64_t n) {
  std::lock_guard<std::mutex> lock(mutex_);
  done_ += n;
  const auto now = std::chrono::steady_clock::now();
  const auto interval = tty_ ? std::chrono::milliseconds(100) : std::chrono::milliseconds(5000);
  if (now - last_draw_ >= interval && GetLevel() <= Level::kInfo) {
    last_draw_ = now;
    DrawLocked(false);
  }
}

void Progress::SetStatus(std::string status) {
  std::lock_guard<std::mutex> lock(mutex_);
  status_ = std::move(status);
}

void Progress::DrawLocked(bool final) {
  const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  const double rate = elapsed > 0 ? done_ / elapsed : 0;
  const double eta = rate > 0 && total_ > done_ ? (total_ - done_) / rate : 0;
  const double fraction = total_ > 0 ? static_cast<double>(done_) / total_ : 1.0;
  constexpr int kWidth = 24;
  const int filled = static_cast<int>(fraction * kWidth);
  std::string bar(static_cast<size_t>(std::min(filled, kWidth)), '#');
  bar.resize(kWidth, '.');
  char buf[512];
  std::snprintf(buf, sizeof buf, "%s [%s] %llu/%llu %s %5.1f%% %.1f %s/s elapsed %s%s%s%s", label_.c_str(),
                bar.c_str(), static_cast<unsigned long long>(done_), static_cast<unsigned long long>(total_),
                unit_.c_str(), 100.0 * fraction, rate, unit_.c_str(), FormatDuration(elapsed).c_str(),
                final ? "" : (" ETA " + FormatDuration(eta)).c_str(), status_.empty() ? "" : " ",
                status_.c_str());
  std::lock_guard<std::mutex> lock(g_stderr_mutex);
  if (tty_) {
    std::fprintf(stderr, "\r\033[K%s%s", buf, final ? "\n" : "");
  } else {
    std::fprintf(stderr, "%s\n", buf);
  }
  std::fflush(stderr);
}

}  // namespace oxbow::log
