// The `oxbow` command line: one binary, one subcommand per *_command.cc file in server/.
// Each command file registers itself at static-initialisation time:
//
//   namespace { const bool registered = oxbow::cli::RegisterCommand({"extract", 10, &SetUpExtract}); }
//
// SetUp adds a CLI11 subcommand to the app and sets its callback. A callback reports failure by
// throwing oxbow::cli::CommandError (exit code + message), which main() prints to stderr.
#pragma once

#include <CLI/CLI.hpp>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::cli {

struct CommandSpec {
  std::string name;                  // subcommand name, e.g. "extract"
  int order = 100;                   // position in --help (lower first)
  std::function<void(CLI::App&)> set_up;
};

bool RegisterCommand(CommandSpec spec);
const std::vector<CommandSpec>& RegisteredCommands();

// Thrown from a subcommand callback to end the program with a message and a non-zero exit code.
class CommandError : public std::runtime_error {
 public:
  CommandError(int exit_code, const std::string& message) : std::runtime_error(message), exit_code_(exit_code) {}
  explicit CommandError(const Error& error) : CommandError(ExitCodeFor(error.code), error.ToString()) {}
  int exit_code() const { return exit_code_; }

 private:
  int exit_code_;
};

// Returns the value or throws CommandError for the error.
template <typename T>
T ValueOrExit(Result<T> result) {
  if (!result) throw CommandError(result.error());
  return std::move(*result);
}
inline void OkOrExit(const Status& status) {
  if (!status) throw CommandError(status.error());
}

// A flag's numeric range check whose refusal names the real bounds ("must be in (0, 1], not 1.5"):
// CLI11's own checks print their bounds with std::to_string, 1e-9 as 0.000000 and the largest double
// with its 300 digits. `lo_open`: lo itself is refused; hi = infinity: no upper bound.
inline CLI::Validator NumberIn(double lo, double hi, bool lo_open = false) {
  const auto shown = [](double v) {
    char text[32];
    std::snprintf(text, sizeof text, "%g", v);
    return std::string(text);
  };
  std::string bounds, description;
  if (hi == std::numeric_limits<double>::infinity()) {
    bounds = (lo_open ? "greater than " : "at least ") + shown(lo);
    description = (lo_open ? "> " : ">= ") + shown(lo);
  } else {
    description = std::string(lo_open ? "(" : "[") + shown(lo) + ", " + shown(hi) + "]";
    bounds = "in " + description;
  }
  return CLI::Validator(
      [lo, hi, lo_open, bounds](std::string& text) -> std::string {
        char* end = nullptr;
        const double v = std::strtod(text.c_str(), &end);
        if (text.empty() || end != text.c_str() + text.size() || std::isnan(v)) return "'" + text + "' is not a number";
        if ((lo_open ? v > lo : v >= lo) && v <= hi) return std::string();
        return "must be " + bounds + ", not " + text;
      },
      description);
}
// A file a command writes: its folder must exist and the path must not be a folder. Checked when the
// flags are read, so that a mistyped path is refused before the work, not after it.
inline CLI::Validator FileToWrite() {
  return CLI::Validator(
      [](std::string& path) -> std::string {
        std::error_code ec;
        const std::filesystem::path file(path);
        if (std::filesystem::is_directory(file, ec)) return "'" + path + "' is a folder: give a file name";
        const std::filesystem::path folder = file.parent_path().empty() ? std::filesystem::path(".") : file.parent_path();
        if (!std::filesystem::is_directory(folder, ec)) {
          return "the folder '" + folder.string() + "' of '" + path + "' does not exist";
        }
        if (::access(folder.c_str(), W_OK) != 0) {
          return "the folder '" + folder.string() + "' of '" + path + "' is not writable";
        }
        return std::string();
      },
      "FILE");
}

// A folder a command writes into (created when missing): not a file.
inline CLI::Validator FolderToWrite() {
  return CLI::Validator(
      [](std::string& path) -> std::string {
        std::error_code ec;
        if (std::filesystem::exists(path, ec) && !std::filesystem::is_directory(path, ec)) {
          return "'" + path + "' is a file: give a folder (created when missing)";
        }
        return std::string();
      },
      "DIR");
}

// A file a command writes that may already exist: replaced only when its first bytes show it holds what
// the command writes (`is_own`), so that an --out naming a photo or a document by mistake cannot destroy
// it. An empty file is replaced.
inline CLI::Validator ReplacesOnly(const std::string& what, std::function<bool(std::string_view head)> is_own) {
  return CLI::Validator(
      [what, is_own](std::string& path) -> std::string {
        std::error_code ec;
        if (!std::filesystem::is_regular_file(path, ec)) return std::string();
        std::FILE* file = std::fopen(path.c_str(), "rb");
        if (file == nullptr) return std::string();  // the write reports what is wrong
        char head[64];
        const size_t n = std::fread(head, 1, sizeof head, file);
        std::fclose(file);
        if (n == 0 || is_own(std::string_view(head, n))) return std::string();
        return "'" + path + "' exists and is not " + what + ": it is replaced only when it is one; remove it or " +
               "give another file name";
      },
      "FILE");
}

// A vocabulary file a command writes (vocab/vocabulary.cc's container magic).
inline CLI::Validator VocabularyToWrite() {
  return ReplacesOnly("a vocabulary file", [](std::string_view head) { return head.starts_with("OXBWVOCB"); });
}

// A drawing a command writes: the extension names the format.
inline CLI::Validator DrawingFile() {
  return CLI::Validator(
      [](std::string& path) -> std::string {
        std::string ext = std::filesystem::path(path).extension().string();
        std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
        for (const char* known : {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm"}) {
          if (ext == known) return std::string();
        }
        return "'" + path + "': name the drawing's format by its extension, .png or .jpg (or .jpeg, .bmp, .tif, " +
               ".tiff, .webp, .ppm)";
      },
      "FILE");
}

// The files a command reads, by device and inode. An output path that names one of them (the same
// name, a link, another spelling) would overwrite it: RefuseOverwrite throws CommandError (exit 2).
class InputFiles {
 public:
  explicit InputFiles(const std::vector<std::string>& paths) {
    for (const std::string& path : paths) {
      if (const auto id = FileId(path)) ids_.push_back(*id);
    }
    std::sort(ids_.begin(), ids_.end());
  }
  void RefuseOverwrite(const std::string& output, const std::string& what) const {
    const auto id = FileId(output);
    if (id && std::binary_search(ids_.begin(), ids_.end(), *id)) {
      throw CommandError(2, what + " '" + output + "' is one of the input files: writing it would replace the input; "
                                   "give another name");
    }
  }

 private:
  static std::optional<std::pair<uint64_t, uint64_t>> FileId(const std::string& path) {
    struct stat st {};
    if (::stat(path.c_str(), &st) != 0) return std::nullopt;
    return std::pair<uint64_t, uint64_t>(st.st_dev, st.st_ino);
  }
  std::vector<std::pair<uint64_t, uint64_t>> ids_;
};

// SIGINT and SIGTERM for a command that stops cleanly between units of work (images, batches): while
// it lives, the first signal sets Interrupted() and the command finishes the unit in hand, says what
// is done and exits 130; a second signal ends the process at once, as without it.
class InterruptibleCommand {
 public:
  InterruptibleCommand() {
    interrupted_.store(false);
    struct sigaction action {};
    action.sa_handler = &OnSignal;
    sigemptyset(&action.sa_mask);
    action.sa_flags = SA_RESETHAND;  // the second signal takes the default action
    sigaction(SIGINT, &action, &old_int_);
    sigaction(SIGTERM, &action, &old_term_);
  }
  ~InterruptibleCommand() {
    sigaction(SIGINT, &old_int_, nullptr);
    sigaction(SIGTERM, &old_term_, nullptr);
  }
  InterruptibleCommand(const InterruptibleCommand&) = delete;
  InterruptibleCommand& operator=(const InterruptibleCommand&) = delete;

  static bool Interrupted() { return interrupted_.load(std::memory_order_relaxed); }
  static constexpr int kExitCode = 130;  // 128 + SIGINT, what a shell reports for Ctrl-C

 private:
  static void OnSignal(int) { interrupted_.store(true, std::memory_order_relaxed); }
  static inline std::atomic<bool> interrupted_{false};
  struct sigaction old_int_ {}, old_term_ {};
};

inline CLI::Validator Positive() { return NumberIn(0, std::numeric_limits<double>::infinity(), /*lo_open=*/true); }
inline CLI::Validator NonNegative() { return NumberIn(0, std::numeric_limits<double>::infinity()); }

}  // namespace oxbow::cli
