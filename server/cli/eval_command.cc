// `oxbow eval`: from images and ground truth to a report. The flags map onto eval::ExperimentOptions;
// the runner (eval/runner/experiment.h) trains, indexes, serves and queries every configuration; this
// command writes the report and prints the summary table.
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>

#include "eval/report.h"
#include "eval/runner/experiment.h"
#include "index/image_index.h"
#include "server/cli/cli.h"

namespace oxbow::cli {
namespace {

namespace fs = std::filesystem;

std::string SelfExe() {
  std::error_code ec;
  const fs::path p = fs::read_symlink("/proc/self/exe", ec);
  if (ec) throw CommandError(1, "cannot find the oxbow binary (/proc/self/exe): " + ec.message());
  return p.string();
}

void Run(eval::ExperimentOptions a, const std::string& command_line) {
  a.oxbow_binary = SelfExe();
  eval::Experiments experiments;
  try {
    experiments = eval::RunExperiments(a);
  } catch (const eval::ExperimentError& e) {
    throw CommandError(e.exit_code(), e.what());
  }
  const std::vector<eval::RunResult>& runs = experiments.runs;
  OkOrExit(eval::WriteReport(a.out, runs, command_line));
  std::printf("%-28s %-36s %8s %9s %13s %10s\n", "protocol", "configuration", "mAP", "recall@1", "top-4 (max)",
              "p50 ms");
  for (const auto& run : runs) {
    std::printf("%-28s %-36s %8.4f %9.4f %5.2f (%5.2f) %10.1f\n", run.protocol.c_str(), run.label.c_str(), run.map,
                run.recall_at_1, run.top4, run.top4_ceiling, run.query_p50_ms);
  }
  std::printf("AP: %s\n", eval::ApDefinitionName(experiments.ap));
  std::printf("report: %s/report.md\n", a.out.c_str());
}

void SetUp(CLI::App& app) {
  auto args = std::make_shared<eval::ExperimentOptions>();
  auto command_line = std::make_shared<std::string>();
  CLI::App* cmd = app.add_subcommand(
      "eval",
      "Evaluate retrieval accuracy (mAP) on a data set with ground truth and write a report.\n"
      "Trains a vocabulary and builds an index per configuration (cached in --work), serves it on an\n"
      "ephemeral loopback port and runs every query through the HTTP API.\n"
      "Example (the Paris subset, restricted protocol):\n"
      "  oxbow eval --protocol restricted --images ../shared/data/paris6k/images \\\n"
      "             --gt ../shared/data/paris6k/gt --out eval-report\n"
      "Groups protocol (every image queries the rest of the database; positives = the other images of its\n"
      "group folder; image ids are <group>__<path inside the group without extension, '/' as __>, so groups\n"
      "may reuse file names; AP non-interpolated; also recall@1, top-4 score with its ceiling, AP per group):\n"
      "  oxbow eval --protocol groups --images ../shared/data/groups_hard \\\n"
      "             --distractors ../shared/data/distractors --out eval-report");
  cmd->add_option("--protocol", args->protocol,
                  "oxford (good/ok/junk folder), restricted (the same, limited to the images present), "
                  "revisited (JSON from scripts/revisited_gt_to_json.py), groups (a folder of sub-folders, one per "
                  "object or place)")
      ->capture_default_str()
      ->check(CLI::IsMember({"oxford", "restricted", "revisited", "groups"}));
  cmd->add_option("--images", args->images, "database images folder (groups: the folder of group folders)")->required();
  cmd->add_option("--distractors", args->distractors,
                  "groups: every image under this folder (recursively) joins the database as "
                  "distractor__<name>; never a query, never a positive");
  cmd->add_option("--gt", args->gt, "ground truth: folder of *_query.txt etc. (oxford, restricted) or JSON (revisited)");
  cmd->add_option("--setting", args->setting, "revisited difficulty: easy, medium, hard")
      ->capture_default_str()
      ->check(CLI::IsMember({"easy", "medium", "hard"}));
  cmd->add_option("--train-images", args->train_images,
                  "train the vocabulary on these images (recursively) instead of the database (with distractors)");
  cmd->add_option("--work", args->work, "folder caching vocabularies and indexes between runs (one database per folder)")
      ->check(FolderToWrite())
      ->capture_default_str();
  cmd->add_option("--out", args->out, "report folder (report.md, results.json, plots/)")
      ->check(FolderToWrite())
      ->capture_default_str();
  cmd->add_option("--features", args->features, "descriptor kinds to compare: sift, rootsift")
      ->delimiter(',')
      ->capture_default_str()
      ->check(CLI::IsMember({"sift", "rootsift"}));
  cmd->add_option("--words", args->words, "vocabulary sizes to compare, e.g. 10000,50000")
      ->delimiter(',')
      ->capture_default_str()
      ->check(Positive());
  cmd->add_option("--rerank", args->rerank, "re-ranking depths to compare (0 = tf-idf only)")
      ->delimiter(',')
      ->capture_default_str()
      ->check(NumberIn(0, 10000));
  cmd->add_option("--qe", args->qe, "query expansion settings to compare: off, on")
      ->delimiter(',')
      ->capture_default_str()
      ->check(CLI::IsMember({"off", "on"}));
  cmd->add_option("--transitive", args->transitive,
                  "transitive verification settings to compare: off (transitive_depth 0), on (transitive_depth " +
                      std::to_string(index::QueryOptions{}.transitive_depth) + ", the built-in depth)")
      ->delimiter(',')
      ->capture_default_str()
      ->check(CLI::IsMember({"off", "on"}));
  cmd->add_option("--hamming", args->hamming,
                  "Hamming-embedding re-scoring settings to compare: off, on (a vocabulary trained here gets the "
                  "parameters when on is listed; a cached one must have them: 'oxbow vocab hamming')")
      ->delimiter(',')
      ->capture_default_str()
      ->check(CLI::IsMember({"off", "on"}));
  cmd->add_option("--hamming-threshold", args->hamming_threshold,
                  "with --hamming on: largest matching distances (bits) to compare (other than the default: "
                  "--mode in-process)")
      ->delimiter(',')
      ->capture_default_str()
      ->check(CLI::Range(0, 64));
  cmd->add_option("--hamming-sigma", args->hamming_sigma,
                  "with --hamming on: weight widths (bits) of exp(-h^2/sigma^2) to compare (other than the default: "
                  "--mode in-process)")
      ->delimiter(',')
      ->capture_default_str()
      ->check(NumberIn(0, 64, /*lo_open=*/true));
  cmd->add_option("--top-k", args->top_k, "results per query (0 = the whole database, at most 10000)")
      ->check(NumberIn(0, 10000));
  cmd->add_option("--sample", args->sample, "descriptors sampled to train each vocabulary")->capture_default_str();
  cmd->add_option("--per-image", args->per_image, "cap of training descriptors per image (0 = vocab train's default)");
  cmd->add_option("--iterations", args->iterations, "k-means iterations (0 = vocab train's default)");
  cmd->add_option("--seed", args->seed, "random seed for sampling and k-means")->check(NonNegative())->capture_default_str();
  cmd->add_option("--threads", args->threads, "threads for training, indexing and serving (0 = all cores)");
  cmd->add_flag("--full-image", args->full_image, "query with the whole query image instead of its box");
  cmd->add_option("--mode", args->mode, "http (through oxbow serve), in-process, or both")->capture_default_str();
  cmd->add_option("--max-queries", args->max_queries, "evaluate only the first N queries (smoke runs; 0 = all)")->check(NonNegative());
  cmd->add_option("--server", args->server,
                  "evaluate a running server or cluster front (http://HOST:PORT) instead of building one: it must "
                  "hold exactly the database images under eval's ids (when it does not, eval writes the list to "
                  "index: WORK/database.list); --features, --words, --train-images and --mode do not apply; only "
                  "the search settings given here (--rerank, --qe, --transitive, --hamming) are sent, the others "
                  "are the server's own; a partial answer (a partition down) stops the evaluation");
  cmd->callback([args, command_line, &app] {
    std::string line = "oxbow eval";
    for (const auto* opt : app.get_subcommand("eval")->get_options()) {
      if (opt->count() == 0 || opt->get_name() == "--help") continue;
      line += " " + opt->get_name();
      for (const auto& r : opt->results()) line += " " + r;
      for (const char* setting : eval::kServerSearchSettings) {
        if (opt->get_name() == std::string("--") + setting) args->server_settings_given.insert(setting);
      }
    }
    if ((args->protocol == "oxford" || args->protocol == "restricted" || args->protocol == "revisited") && args->gt.empty()) {
      throw CommandError(2, "--gt is required for the " + args->protocol + " protocol");
    }
    if (args->mode != "http" && args->mode != "in-process" && args->mode != "both") {
      throw CommandError(2, "--mode must be http, in-process or both");
    }
    Run(*args, line);
  });
}

const bool registered_eval = RegisterCommand({"eval", 80, &SetUp});

}  // namespace
}  // namespace oxbow::cli
