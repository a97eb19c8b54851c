// Entry point of the `oxbow` binary: global flags, then the registered subcommands (see cli.h).
#include <algorithm>
#include <csignal>
#include <cstdio>
#include <exception>
#include <malloc.h>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "server/cli/cli.h"
#include "sift/base/log.h"

namespace oxbow::cli {

namespace {
std::vector<CommandSpec>& Registry() {
  static std::vector<CommandSpec> commands;
  return commands;
}
}  // namespace

bool RegisterCommand(CommandSpec spec) {
  Registry().push_back(std::move(spec));
  return true;
}

const std::vector<CommandSpec>& RegisteredCommands() { return Registry(); }

}  // namespace oxbow::cli

namespace {
// A failed command's last line: as it always was in the text format; under `serve --log-format json` an
// error-level log line, so that every stderr line stays JSON (never filtered by --log-level).
void PrintError(const std::string& text) {
  if (oxbow::log::GetFormat() == oxbow::log::Format::kJson) {
    oxbow::log::Line(oxbow::log::Level::kError) << text;
  } else {
    std::fprintf(stderr, "%s\n", text.c_str());
  }
}
// CLI11's help formatter without the value a flag's negated name sets: "--qe, --no-qe" rather than
// "--qe,--no-qe{false}", which reads as if the flag were off by default. The descriptions say which form
// is the default.
class HelpFormatter : public CLI::Formatter {
 public:
  std::string make_option_name(const CLI::Option* option, bool is_positional) const override {
    std::string name = CLI::Formatter::make_option_name(option, is_positional);
    if (is_positional || option->get_items_expected() != 0) return name;
    std::string out;
    bool in_value = false;
    for (const char c : name) {
      if (c == '{') in_value = true;
      if (!in_value) out += c;
      if (c == '}') in_value = false;
    }
    return out;
  }
};

// When argv names a command that does not exist ("oxbow index bild"), the error for it: the word and
// the commands there are. CLI11 itself only says that a command is required. The words before the
// first command that has no sub-commands are read; of the options among them only --log-level takes a
// value.
std::optional<std::string> UnknownCommand(CLI::App& app, int argc, char** argv) {
  CLI::App* at = &app;
  std::string path = "oxbow";
  for (int i = 1; i < argc; ++i) {
    const std::string word = argv[i];
    if (word.empty() || word[0] == '-') {
      if (word == "--log-level") ++i;  // its value is no command (the flag falls through to every command)
      continue;
    }
    // Option groups (`vocab train`'s sources) are CLI11 sub-apps too, but no commands.
    const std::vector<CLI::App*> commands =
        at->get_subcommands([](CLI::App* c) { return dynamic_cast<CLI::Option_group*>(c) == nullptr; });
    if (commands.empty()) return std::nullopt;
    const auto named = std::find_if(commands.begin(), commands.end(), [&](CLI::App* c) { return c->check_name(word); });
    if (named == commands.end()) {
      std::string message = "'";
      message.append(word).append("' is not a command of ").append(path).append("; the commands are: ");
      for (size_t k = 0; k < commands.size(); ++k) message.append(k == 0 ? "" : ", ").append(commands[k]->get_name());
      return message.append(" (").append(path).append(" --help describes them)");
    }
    at = *named;
    path += " " + word;
  }
  return std::nullopt;
}

}  // namespace

int main(int argc, char** argv) {
  using oxbow::cli::CommandError;
  // A write past the file size limit (ulimit -f, RLIMIT_FSIZE) then fails with EFBIG, which the writer
  // reports as an error (an io_error answer, a failed command), instead of killing the process with
  // SIGXFSZ in the middle of it.
  std::signal(SIGXFSZ, SIG_IGN);
#ifdef __GLIBC__
  // Memory freed after one image is kept for the next. glibc's defaults move both thresholds with the
  // sizes freed so far: with small photos, blocks of a few MiB (an image's pixels, its descriptors, a
  // feature file's bytes) are then mapped fresh or trimmed back to the kernel after each image, and every
  // image pays the page faults and zeroing of ~7 MiB again (a quarter of the CPU of `oxbow extract` over
  // 800 x 640 photos).
  // Blocks of 8 MiB and more are still mapped and returned at once, and at most 16 MiB of free memory
  // at the top of a heap is kept: the peak memory of a many-image extraction grows by 2-3%, where a
  // 32 MiB threshold added 30% (eval/results/sift.md, "Many images in one process").
  mallopt(M_MMAP_THRESHOLD, 8 << 20);
  mallopt(M_TRIM_THRESHOLD, 16 << 20);
#endif
  CLI::App app{
      "oxbow: instance-level image retrieval (SIFT, visual words, TF-IDF, spatial verification).\n"
      "Run 'oxbow <command> --help' for the options of a command."};
  app.formatter(std::make_shared<HelpFormatter>());  // before the commands: each copies its parent's
  app.require_subcommand(1);
  app.fallthrough();  // --log-level and -q may follow the command too ("oxbow index info --index x -q")
  app.set_version_flag("--version", "oxbow " OXBOW_VERSION);  // project(VERSION) in CMakeLists.txt
  std::string log_level = "info";
  app.add_option("--log-level", log_level, "stderr log level: debug, info, warning, error, off")
      ->capture_default_str();
  app.add_flag_callback("-q,--quiet", [&] { log_level = "warning"; }, "only warnings and errors on stderr");
  app.parse_complete_callback([&] {
    oxbow::log::Level level;
    if (!oxbow::log::ParseLevel(log_level, &level)) throw CLI::ValidationError("--log-level", "unknown level '" + log_level + "'");
    oxbow::log::SetLevel(level);
  });

  auto commands = oxbow::cli::RegisteredCommands();
  std::sort(commands.begin(), commands.end(), [](const auto& a, const auto& b) { return a.order < b.order; });
  for (const auto& command : commands) command.set_up(app);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (dynamic_cast<const CLI::RequiredError*>(&e) != nullptr) {
      if (const auto unknown = UnknownCommand(app, argc, argv)) {
        PrintError("oxbow: error: " + *unknown);
        return e.get_exit_code();
      }
    }
    return app.exit(e);
  } catch (const CommandError& e) {
    PrintError(std::string("oxbow: error: ") + e.what());
    return e.exit_code();
  } catch (const std::exception& e) {
    PrintError(std::string("oxbow: internal error: ") + e.what());
    return 1;
  }
  return 0;
}
