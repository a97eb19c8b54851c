// Logging to stderr with levels, and a progress bar for long work. Thread-safe.
// Usage: OXBOW_LOG(kInfo) << "indexed " << n << " images";
//        OXBOW_LOG(kInfo).Field("status", 200).Field("route", "/v1/search") << "http ...";
// Two formats (SetFormat): text lines for people, or one JSON object per line for log collectors, where
// every line written here (progress included) is a complete JSON object.
#pragma once

#include <chrono>
#include <concepts>
#include <cstdint>
#include <mutex>
#include <span>
#include <sstream>
#include <string>
#include <string_view>
#include <utility>

namespace oxbow::log {

enum class Level { kDebug = 0, kInfo = 1, kWarning = 2, kError = 3, kOff = 4 };

void SetLevel(Level level);
Level GetLevel();
// Parses "debug" | "info" | "warning" | "error" | "off"; false if unknown.
bool ParseLevel(const std::string& text, Level* level);

// kText: "2026-11-21T06:01:02Z I message" (the message through TextSafe). kJson:
// {"time":"2026-11-21T06:01:02.345Z","level":"info","message":"message", ...the line's fields}, one
// object per line. Set it before logging starts (lines already being built keep the format they started
// with).
enum class Format { kText, kJson };
void SetFormat(Format format);
Format GetFormat();
// Parses "text" | "json"; false if unknown.
bool ParseFormat(const std::string& text, Format* format);

// `text` as a JSON string literal, quotes included: '"', '\\' and control characters (U+0000..U+001F,
// U+007F) escaped, and every byte that is not part of well-formed UTF-8 replaced by U+FFFD, so that any
// bytes (a client's path, an id) give valid JSON.
std::string JsonString(std::string_view text);

// Whether `text` is well-formed UTF-8 (RFC 3629: no overlong forms, no surrogates, nothing above
// U+10FFFF).
bool IsWellFormedUtf8(std::string_view text);

// `text` with every byte that is not part of well-formed UTF-8 replaced by U+FFFD; other bytes kept.
std::string ToWellFormedUtf8(std::string_view text);

// `text` for one line of the text format: every control character (U+0000..U+001F, U+007F) written as
// an escape ("\n", "\r", "\t", "\x01"), so that bytes a client chose (a path, an id) can neither end
// the line nor start one that looks like the server's. Other bytes are kept.
std::string TextSafe(std::string_view text);

// One log line, written atomically to stderr when destroyed. Fields are structured data for the JSON
// format, where each becomes a member after time, level and message, in the order given (keys other than
// those three, each once); the text format shows only the message, so a field's value must also be in
// the message where text readers need it.
class Line {
 public:
  explicit Line(Level level);
  ~Line();
  Line(const Line&) = delete;
  Line& operator=(const Line&) = delete;
  template <typename T>
  Line& operator<<(const T& value) {
    stream_ << value;
    return *this;
  }

  Line& Field(std::string_view key, std::string_view value);
  template <std::integral T>
    requires(!std::same_as<T, bool>)
  Line& Field(std::string_view key, T value) {
    return RawField(key, std::to_string(value));
  }
  // Six significant digits; NaN and infinities become null.
  Line& Field(std::string_view key, double value);
  // An object of numbers: {"extract": 12.1, "quantize": 0.4}.
  Line& Field(std::string_view key, std::span<const std::pair<const char*, double>> numbers);

 private:
  Line& RawField(std::string_view key, std::string_view json_value);

  Level level_;
  bool json_;
  std::string json_fields_;  // ',"key":value' for each field (JSON format only)
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
