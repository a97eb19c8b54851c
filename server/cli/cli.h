// The `oxbow` command line: one binary, one subcommand per *_command.cc file in server/.
// Each command file registers itself at static-initialisation time:
//
//   namespace { const bool registered = oxbow::cli::RegisterCommand({"extract", 10, &SetUpExtract}); }
//
// SetUp adds a CLI11 subcommand to the app and sets its callback. A callback reports failure by
// throwing oxbow::cli::CommandError (exit code + message), which main() prints to stderr.
#pragma once

#include <CLI/CLI.hpp>

#include <functional>
#include <stdexcept>
#include <string>
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

}  // namespace oxbow::cli
