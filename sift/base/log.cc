#include "sift/base/log.h"

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>

namespace oxbow::log {
namespace {

std::atomic<Level> g_level{Level::kInfo};
std::atomic<Format> g_format{Format::kText};
std::mutex g_stderr_mutex;  // guards writes to stderr so lines never interleave

void WriteStderr(const std::string& text) {
  std::lock_guard<std::mutex> lock(g_stderr_mutex);
  std::fwrite(text.data(), 1, text.size(), stderr);
}

const char* LevelName(Level level) {
  switch (level) {
    case Level::kDebug: return "debug";
    case Level::kInfo: return "info";
    case Level::kWarning: return "warning";
    case Level::kError: return "error";
    case Level::kOff: return "off";
  }
  return "?";
}

// The JSON format's line: {"time":...,"level":...,"message":...<fields>}.
std::string JsonLine(Level level, std::string_view message, std::string_view fields) {
  const auto now = std::chrono::system_clock::now();
  const std::time_t seconds = std::chrono::system_clock::to_time_t(now);
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm tm{};
  gmtime_r(&seconds, &tm);
  char stamp[40];
  const size_t n = std::strftime(stamp, sizeof stamp, "%Y-%m-%dT%H:%M:%S", &tm);
  std::snprintf(stamp + n, sizeof stamp - n, ".%03dZ", static_cast<int>(ms));
  std::string line = "{\"time\":\"";
  line += stamp;
  line += "\",\"level\":\"";
  line += LevelName(level);
  line += "\",\"message\":";
  line += JsonString(message);
  line += fields;
  line += "}\n";
  return line;
}

// Six significant digits; JSON has no NaN or infinity.
std::string JsonNumber(double value) {
  if (!std::isfinite(value)) return "null";
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.6g", value);
  return buf;
}

// Length of the well-formed UTF-8 sequence at the start of `s` (Unicode 15, table 3-7), 0 if none.
size_t Utf8SequenceLength(std::string_view s) {
  const auto byte = [&](size_t i) { return static_cast<unsigned char>(s[i]); };
  const auto in = [&](size_t i, unsigned lo, unsigned hi) { return i < s.size() && byte(i) >= lo && byte(i) <= hi; };
  const unsigned b0 = byte(0);
  if (b0 < 0x80) return 1;
  if (b0 >= 0xC2 && b0 <= 0xDF) return in(1, 0x80, 0xBF) ? 2 : 0;
  if (b0 >= 0xE0 && b0 <= 0xEF) {
    const unsigned lo = b0 == 0xE0 ? 0xA0 : 0x80;
    const unsigned hi = b0 == 0xED ? 0x9F : 0xBF;  // ED A0..BF would be a surrogate
    return in(1, lo, hi) && in(2, 0x80, 0xBF) ? 3 : 0;
  }
  if (b0 >= 0xF0 && b0 <= 0xF4) {
    const unsigned lo = b0 == 0xF0 ? 0x90 : 0x80;
    const unsigned hi = b0 == 0xF4 ? 0x8F : 0xBF;  // above U+10FFFF otherwise
    return in(1, lo, hi) && in(2, 0x80, 0xBF) && in(3, 0x80, 0xBF) ? 4 : 0;
  }
  return 0;
}

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
void SetFormat(Format format) { g_format.store(format); }
Format GetFormat() { return g_format.load(); }

bool ParseFormat(const std::string& text, Format* format) {
  if (text == "text") *format = Format::kText;
  else if (text == "json") *format = Format::kJson;
  else return false;
  return true;
}

bool IsWellFormedUtf8(std::string_view text) {
  for (size_t i = 0; i < text.size();) {
    const size_t length = Utf8SequenceLength(text.substr(i));
    if (length == 0) return false;
    i += length;
  }
  return true;
}

std::string ToWellFormedUtf8(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (size_t i = 0; i < text.size();) {
    const size_t length = Utf8SequenceLength(text.substr(i));
    if (length == 0) {
      out += "\xEF\xBF\xBD";  // U+FFFD
      ++i;
    } else {
      out.append(text.substr(i, length));
      i += length;
    }
  }
  return out;
}

std::string JsonString(std::string_view text) {
  std::string out = "\"";
  out.reserve(text.size() + 2);
  for (size_t i = 0; i < text.size();) {
    const unsigned char c = static_cast<unsigned char>(text[i]);
    const size_t length = Utf8SequenceLength(text.substr(i));
    if (length == 0) {
      out += "\\ufffd";
      ++i;
      continue;
    }
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c == '\n') {
      out += "\\n";
    } else if (c == '\r') {
      out += "\\r";
    } else if (c == '\t') {
      out += "\\t";
    } else if (c < 0x20 || c == 0x7f) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", c);
      out += buf;
    } else {
      out.append(text.substr(i, length));
    }
    i += length;
  }
  out += '"';
  return out;
}

std::string TextSafe(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (const char ch : text) {
    const auto c = static_cast<unsigned char>(ch);
    if (c >= 0x20 && c != 0x7f) {
      out += ch;
    } else if (c == '\n') {
      out += "\\n";
    } else if (c == '\r') {
      out += "\\r";
    } else if (c == '\t') {
      out += "\\t";
    } else {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\x%02x", c);
      out += buf;
    }
  }
  return out;
}

Line::Line(Level level) : level_(level), json_(GetFormat() == Format::kJson) {}

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
  if (json_) {
    WriteStderr(JsonLine(level_, stream_.str(), json_fields_));
    return;
  }
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char stamp[32];
  std::strftime(stamp, sizeof stamp, "%Y-%m-%dT%H:%M:%SZ", &tm);
  WriteStderr(std::string(stamp) + " " + LevelLetter(level_) + " " + TextSafe(stream_.str()) + "\n");
}

Line& Line::RawField(std::string_view key, std::string_view json_value) {
  if (json_) {
    json_fields_ += ',';
    json_fields_ += JsonString(key);
    json_fields_ += ':';
    json_fields_ += json_value;
  }
  return *this;
}

Line& Line::Field(std::string_view key, std::string_view value) {
  return json_ ? RawField(key, JsonString(value)) : *this;
}

Line& Line::Field(std::string_view key, double value) { return json_ ? RawField(key, JsonNumber(value)) : *this; }

Line& Line::Field(std::string_view key, std::span<const std::pair<const char*, double>> numbers) {
  if (!json_) return *this;
  std::string object = "{";
  for (const auto& [name, value] : numbers) {
    if (object.size() > 1) object += ',';
    object += JsonString(name);
    object += ':';
    object += JsonNumber(value);
  }
  object += '}';
  return RawField(key, object);
}

Progress::Progress(std::string label, uint64_t total, std::string unit)
    : label_(std::move(label)),
      unit_(std::move(unit)),
      total_(total),
      start_(std::chrono::steady_clock::now()),
      last_draw_(start_),
      // A terminal gets a redrawn bar; JSON lines are never redrawn, whatever stderr is.
      tty_(::isatty(STDERR_FILENO) != 0 && GetFormat() == Format::kText) {}

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
  if (GetFormat() == Format::kJson) {
    WriteStderr(JsonLine(Level::kInfo, buf, ""));
    return;
  }
  std::lock_guard<std::mutex> lock(g_stderr_mutex);
  if (tty_) {
    std::fprintf(stderr, "\r\033[K%s%s", buf, final ? "\n" : "");
  } else {
    std::fprintf(stderr, "%s\n", buf);
  }
  std::fflush(stderr);
}

}  // namespace oxbow::log
