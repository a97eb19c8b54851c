#include "eval/runner/experiment.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "eval/ground_truth.h"
#include "eval/runner/server_process.h"
#include "sift/base/log.h"
#include "sift/sift.h"
#include "vocab/vocabulary.h"

// After Eigen (via index/ and sift/ headers): httplib pulls in <resolv.h>, whose `_res` macro breaks
// Eigen's headers when they come later.
#include <httplib.h>

namespace oxbow::eval {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

// Returns the value or throws ExperimentError for the error (its exit code, "code: message").
template <typename T>
T Must(Result<T> result) {
  if (!result) throw ExperimentError(ExitCodeFor(result.error().code), result.error().ToString());
  return std::move(*result);
}

// The database image files by id: the protocol's own map (groups), else the files of --images by name
// without extension (listed as every command lists a folder).
std::map<std::string, std::string> DatabaseFiles(const ExperimentOptions& a, const eval::Protocol& protocol) {
  if (!protocol.files.empty()) return protocol.files;
  std::map<std::string, std::string> files;
  for (const std::string& path : Must(sift::ListImageFiles(a.images))) {
    files.emplace(fs::path(path).stem().string(), path);
  }
  return files;
}

// Writes `paths` to a list file for `oxbow vocab train --list` / `oxbow index build --list`.
std::string WriteList(const std::vector<std::string>& paths, const fs::path& path) {
  std::ofstream out(path);
  for (const std::string& file : paths) out << file << "\n";
  if (!out) throw ExperimentError(7, "cannot write '" + path.string() + "'");
  return path.string();
}

// Paths under which `oxbow index build` gives each file its id: `index build` names an image after its
// file, so a file whose name is not its id is listed through a symbolic link <id><extension> in
// `links_dir` (made once, kept with the work folder).
std::vector<std::string> PathsNamedById(const std::map<std::string, std::string>& files, const fs::path& links_dir) {
  std::vector<std::string> paths;
  paths.reserve(files.size());
  for (const auto& [id, file] : files) {
    if (fs::path(file).stem().string() == id) {
      paths.push_back(file);
      continue;
    }
    const fs::path link = links_dir / (id + fs::path(file).extension().string());
    std::error_code ec;
    fs::create_directories(links_dir, ec);
    const fs::path target = fs::absolute(file, ec);
    if (fs::is_symlink(link, ec) && fs::read_symlink(link, ec) != target) fs::remove(link, ec);
    if (!fs::is_symlink(link, ec)) fs::create_symlink(target, link, ec);
    if (ec) throw ExperimentError(7, "cannot link '" + link.string() + "' to '" + file + "': " + ec.message());
    paths.push_back(link.string());
  }
  return paths;
}

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

struct Config {
  std::string features;
  int words;
  std::string Dir(const std::string& work) const {
    return (fs::path(work) / (features + "-" + std::to_string(words))).string();
  }
};

// Trains the vocabulary and builds the index of one configuration unless the work folder has them.
void Prepare(const ExperimentOptions& a, const Config& c, const std::map<std::string, std::string>& database,
             const std::string& exe, eval::RunResult* base) {
  fs::create_directories(c.Dir(a.work));
  const std::string vocab = (fs::path(c.Dir(a.work)) / "vocabulary.oxvoc").string();
  const std::string index = (fs::path(c.Dir(a.work)) / "index").string();
  const std::vector<std::string> database_paths = PathsNamedById(database, fs::path(a.work) / "images-by-id");
  if (!fs::exists(vocab)) {
    const std::vector<std::string> training =
        a.train_images.empty() ? database_paths : Must(sift::ListImageFiles(a.train_images));
    const std::string list = WriteList(training, fs::path(c.Dir(a.work)) / "train_images.txt");
    std::vector<std::string> args = {exe, "vocab", "train", "--list", list,
                                     "--words", std::to_string(c.words), "--out", vocab, "--sample",
                                     std::to_string(a.sample), "--seed", std::to_string(a.seed)};
    args.insert(args.end(), {"--descriptor", c.features});
    if (a.per_image > 0) args.insert(args.end(), {"--per-image", std::to_string(a.per_image)});
    if (a.iterations > 0) args.insert(args.end(), {"--iterations", std::to_string(a.iterations)});
    if (a.threads > 0) args.insert(args.end(), {"--threads", std::to_string(a.threads)});
    const bool hamming = std::find(a.hamming.begin(), a.hamming.end(), "on") != a.hamming.end();
    args.emplace_back(hamming ? "--hamming" : "--no-hamming");
    const auto t0 = Clock::now();
    RunChild(args);
    base->build_vocab_s = std::chrono::duration<double>(Clock::now() - t0).count();
  }
  // A cached vocabulary without Hamming-embedding parameters would make the "+he" rows measure plain
  // tf-idf (an index without signatures ignores the switch).
  if (std::find(a.hamming.begin(), a.hamming.end(), "on") != a.hamming.end() &&
      !Must(vocab::Vocabulary::Read(vocab)).has_hamming()) {
    const fs::path list = fs::path(c.Dir(a.work)) / "train_images.txt";
    const std::string source = fs::exists(list) ? "--list " + list.string() : "--images <its training images>";
    throw ExperimentError(2, "--hamming on: " + vocab + " has no Hamming-embedding parameters; add them with 'oxbow vocab "
                          "hamming --vocab " + vocab + " " + source +
                          " --out V2', put V2 in its place and delete the index beside it, or pass --hamming off");
  }
  const fs::path list_path = fs::path(c.Dir(a.work)) / "database_images.txt";
  const fs::path complete = fs::path(c.Dir(a.work)) / "index.complete";
  if (index::ImageIndex::Exists(index) && fs::exists(complete)) {
    // A cached index of other images (another folder, distractors or not) would score the wrong database.
    // Compared file by file, each path resolved: the same files named from another folder, or through a
    // --work spelled another way (relative, absolute), are the same database.
    auto resolved = [](const std::vector<std::string>& paths) {
      std::vector<std::string> files;
      for (const std::string& p : paths) {
        std::error_code ec;
        const fs::path real = fs::weakly_canonical(p, ec);
        files.push_back(ec ? p : real.string());
      }
      return files;
    };
    std::vector<std::string> cached;
    {
      std::istringstream lines(ReadBytes(list_path.string()));
      for (std::string line; std::getline(lines, line);) cached.push_back(line);
    }
    if (resolved(cached) != resolved(database_paths)) {
      throw ExperimentError(2, "the work folder " + a.work + " holds an index of other images than " + list_path.string() +
                                " lists for this run; use another --work");
    }
  } else {
    const std::string list = WriteList(database_paths, list_path);
    std::vector<std::string> args = {exe, "index", "build", "--vocab", vocab, "--list", list, "--out", index};
    if (a.threads > 0) args.insert(args.end(), {"--threads", std::to_string(a.threads)});
    const auto t0 = Clock::now();
    RunChild(args);
    base->build_index_s = std::chrono::duration<double>(Clock::now() - t0).count();
    std::ofstream(complete) << "ok\n";
  }
}

std::string BoxParam(const std::array<float, 4>& b) {
  std::ostringstream s;
  s << b[0] << "," << b[1] << "," << b[2] << "," << b[3];
  return s.str();
}

// One Hamming-embedding setting of a run.
struct HammingSetting {
  bool on = false;
  int threshold = index::QueryOptions{}.hamming_threshold;
  double sigma = index::QueryOptions{}.hamming_sigma;
};

// Whether a search setting is sent with each search: always for a server eval starts itself, and for
// a running server (--server) only when it was given on eval's command line.
bool Sends(const ExperimentOptions& a, const std::string& setting) {
  return a.server.empty() || a.server_settings_given.count(setting) > 0;
}

}  // namespace

std::string SearchTarget(const ExperimentOptions& a, int rerank, bool qe, bool transitive, bool hamming, int top_k) {
  std::string target = "/v1/search?top_k=" + std::to_string(top_k);
  if (Sends(a, "rerank")) target += "&rerank=" + std::to_string(rerank);
  if (Sends(a, "qe")) target += std::string("&qe=") + (qe ? "true" : "false");
  if (Sends(a, "transitive")) {
    target += "&transitive_depth=" + std::to_string(transitive ? index::QueryOptions{}.transitive_depth : 0);
  }
  if (Sends(a, "hamming")) target += std::string("&hamming=") + (hamming ? "true" : "false");
  return target;
}

namespace {

void RunHttp(const ExperimentOptions& a, const eval::Protocol& protocol, const std::map<std::string, std::string>& files,
             const std::string& url, int rerank, bool qe, bool transitive, const HammingSetting& hamming, int top_k,
             eval::RunResult* run) {
  httplib::Client client(url);
  client.set_read_timeout(300, 0);
  client.set_write_timeout(60, 0);
  log::Progress progress("eval " + run->label, protocol.queries.size(), "queries");
  for (const eval::EvalQuery& q : protocol.queries) {
    const auto found = files.find(q.image);
    if (found == files.end()) throw ExperimentError(4, "query image '" + q.image + "' not found in " + a.images);
    const std::string& path = found->second;
    std::string target = SearchTarget(a, rerank, qe, transitive, hamming.on, top_k);
    if (q.bbox && !a.full_image) target += "&bbox=" + BoxParam(*q.bbox);
    const std::string body = ReadBytes(path);
    const auto t0 = Clock::now();
    auto response = client.Post(target, body, "application/octet-stream");
    const double ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    if (!response) throw ExperimentError(7, "search request failed: " + httplib::to_string(response.error()));
    if (response->status != 200) {
      throw ExperimentError(1, "search for " + q.name + " answered " + std::to_string(response->status) + ": " + response->body);
    }
    const auto json = nlohmann::json::parse(response->body);
    // A cluster front answers without a partition that failed ("partial"): such a ranking would score
    // as a worse mAP, not as an error. An evaluation needs every partition.
    if (json.value("partial", false)) {
      throw ExperimentError(1, "search for " + q.name + " through " + url + " is partial (partitions " +
                                json["shards"].value("failed", nlohmann::json::array()).dump() +
                                " did not answer): an evaluation needs every partition; bring them up and run it again");
    }
    std::vector<std::string> ranking;
    for (const auto& r : json.at("results")) {
      ranking.push_back(r.at("id").get<std::string>());
      if (!std::binary_search(protocol.database.begin(), protocol.database.end(), ranking.back()))
        throw ExperimentError(2, url + " answered image '" + ranking.back() +
                                  "', which is not in the protocol's database: the server must hold exactly the "
                                  "database images under eval's ids (server/README.md, `oxbow eval`)");
    }
    eval::QueryOutcome outcome = eval::ScoreRanking(q, ranking, protocol.ap);
    outcome.latency_ms = ms;
    for (const auto& [stage, value] : json.at("timings_ms").items()) {
      outcome.stage_ms[stage == "decode_extract" ? "extract" : stage] = value.get<double>();
    }
    run->queries.push_back(std::move(outcome));
    progress.Advance();
  }
}

void RunInProcess(const ExperimentOptions& a, const eval::Protocol& protocol, const std::map<std::string, std::string>& files,
                  const index::ImageIndex& idx, int rerank, bool qe, bool transitive, const HammingSetting& hamming,
                  int top_k,
                  eval::RunResult* run) {
  auto options = Must(sift::SiftOptions::FromDescription(idx.extractor_settings()));
  options.num_threads = a.threads;
  const auto extractor = Must(sift::SiftExtractor::Create(options));
  log::Progress progress("eval " + run->label, protocol.queries.size(), "queries");
  for (const eval::EvalQuery& q : protocol.queries) {
    const auto found = files.find(q.image);
    if (found == files.end()) throw ExperimentError(4, "query image '" + q.image + "' not found in " + a.images);
    const std::string& path = found->second;
    const auto t0 = Clock::now();
    auto features = Must(extractor.ExtractFromFile(path));
    const double extract_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    index::QueryOptions qo;
    qo.top_k = top_k;
    qo.rerank_depth = rerank;
    qo.query_expansion = qe;
    qo.hamming = hamming.on;
    qo.hamming_threshold = hamming.threshold;
    qo.hamming_sigma = hamming.sigma;
    if (!transitive) qo.transitive_depth = 0;
    if (q.bbox && !a.full_image) qo.region = *q.bbox;
    auto response = Must(idx.Query(features, qo));
    std::vector<std::string> ranking;
    ranking.reserve(response.results.size());
    for (const auto& r : response.results) ranking.push_back(r.id);
    eval::QueryOutcome outcome = eval::ScoreRanking(q, ranking, protocol.ap);
    outcome.latency_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    outcome.stage_ms = {{"extract", extract_ms},
                        {"quantize", response.timings.quantize_ms},
                        {"score", response.timings.score_ms},
                        {"verify", response.timings.verify_ms},
                        {"qe", response.timings.qe_ms}};
    run->queries.push_back(std::move(outcome));
    progress.Advance();
  }
}

eval::Protocol LoadProtocol(const ExperimentOptions& a) {
  if (a.protocol == "groups") return Must(eval::LoadGroupsProtocol(a.images, a.distractors));
  if (!a.distractors.empty()) throw ExperimentError(2, "--distractors is for the groups protocol");
  if (a.protocol == "revisited") {
    eval::RevisitedSetting setting = eval::RevisitedSetting::kMedium;
    if (a.setting == "easy") setting = eval::RevisitedSetting::kEasy;
    else if (a.setting == "hard") setting = eval::RevisitedSetting::kHard;
    else if (a.setting != "medium") throw ExperimentError(2, "--setting must be easy, medium or hard");
    auto protocol = Must(eval::LoadRevisitedProtocol(a.gt, setting, fs::path(a.gt).stem().string()));
    auto present = Must(eval::ListImageIds(a.images));
    if (present.size() < protocol.database.size()) {
      OXBOW_LOG(kWarning) << "eval: only " << present.size() << " of " << protocol.database.size()
                          << " database images are present; restricting the protocol to them";
      protocol = eval::RestrictToImages(protocol, present);
    }
    return protocol;
  }
  const std::string name = fs::path(a.gt).parent_path().filename().string().empty()
                                ? "oxford"
                                : fs::path(a.gt).lexically_normal().parent_path().filename().string();
  auto protocol = Must(eval::LoadOxfordProtocol(a.gt, name));
  if (a.protocol == "restricted") {
    protocol = eval::RestrictToImages(protocol, Must(eval::ListImageIds(a.images)));
    protocol.name += "-restricted";
  } else if (a.protocol != "oxford") {
    throw ExperimentError(2, "--protocol must be oxford, restricted, revisited or groups");
  }
  return protocol;
}

// Every (a, b) pair, a-major.
std::vector<std::pair<std::string, std::string>> Combinations(const std::vector<std::string>& as,
                                                              const std::vector<std::string>& bs) {
  std::vector<std::pair<std::string, std::string>> out;
  for (const auto& x : as) {
    for (const auto& y : bs) out.emplace_back(x, y);
  }
  return out;
}

std::string FormatSigma(double sigma) {
  std::ostringstream s;
  s << sigma;
  return s.str();
}

// off and/or on x every listed threshold x every listed width. Only in-process runs can set the two
// (the HTTP API takes hamming on/off and the server's settings).
std::vector<HammingSetting> HammingSettings(const ExperimentOptions& a) {
  const index::QueryOptions defaults;
  const bool tuned = a.hamming_threshold != std::vector<int>{defaults.hamming_threshold} ||
                     a.hamming_sigma != std::vector<double>{defaults.hamming_sigma};
  if (tuned && a.mode != "in-process") {
    throw ExperimentError(2, "--hamming-threshold and --hamming-sigma other than the server's defaults need "
                          "--mode in-process");
  }
  std::vector<HammingSetting> out;
  for (const std::string& text : a.hamming) {
    if (text == "off") {
      out.push_back({});
      continue;
    }
    for (const int threshold : a.hamming_threshold) {
      for (const double sigma : a.hamming_sigma) out.push_back({true, threshold, sigma});
    }
  }
  return out;
}

// " +he", with the threshold and width when they are not the server's defaults.
std::string HammingLabel(const HammingSetting& h) {
  if (!h.on) return "";
  const index::QueryOptions defaults;
  if (h.threshold == defaults.hamming_threshold && h.sigma == defaults.hamming_sigma) return " +he";
  return " +he" + std::to_string(h.threshold) + "/" + FormatSigma(h.sigma);
}

// --server: the running server's index figures (GET /v1/stats), after checking that it holds as many
// images as the protocol's database (else the list to index them is written and the run stops).
index::IndexStats ServerStats(const ExperimentOptions& a, const std::string& url, const std::map<std::string, std::string>& database) {
  httplib::Client client(url);
  client.set_read_timeout(60, 0);
  auto response = client.Get("/v1/stats");
  if (!response) throw ExperimentError(7, "cannot reach " + url + ": " + httplib::to_string(response.error()));
  if (response->status != 200)
    throw ExperimentError(7, url + "/v1/stats answered " + std::to_string(response->status) + ": " + response->body);
  const auto json = nlohmann::json::parse(response->body, nullptr, /*allow_exceptions=*/false);
  if (!json.is_object() || !json.contains("images") || !json.contains("words"))
    throw ExperimentError(7, url + "/v1/stats is not an oxbow server's answer");
  index::IndexStats stats;
  stats.num_images = json["images"].get<uint64_t>();
  stats.num_features = json.value("features", uint64_t{0});
  stats.bytes_per_feature = json.value("bytes_per_feature", 0.0);
  stats.vocabulary_size = json["words"].get<uint64_t>();
  if (stats.num_images != database.size()) {
    const fs::path list = fs::path(a.work) / "database.list";
    WriteList(PathsNamedById(database, fs::path(a.work) / "images-by-id"), list);
    throw ExperimentError(2, url + " holds " + std::to_string(stats.num_images) + " images; the protocol's database has " +
                              std::to_string(database.size()) + ". Index exactly these under eval's ids: `oxbow index build "
                              "--vocab V.oxvoc --list " + list.string() + " --out DIR` (add --mpi --partitions P for a "
                              "cluster), serve it, and run eval again");
  }
  return stats;
}

// The search settings every run shares (the server's defaults, index/image_index.h), for the report.
std::string SearchDefaults() {
  const index::QueryOptions o;
  std::ostringstream s;
  s << "transitive_depth " << o.transitive_depth << ", anchors " << o.transitive_anchors << ", neighbours "
    << o.transitive_neighbours << ", attempts " << o.transitive_attempts << ", qe_images " << o.qe_images
    << ", quantizer_probes " << o.quantizer_probes << ", max_pairs_per_word " << o.max_pairs_per_word
    << ", min_inliers " << o.verify.min_inliers << ", max_query_features " << o.max_query_features
    << ", max_tentative_matches " << o.max_tentative_matches << ", max_scored_postings " << o.max_scored_postings
    << ", hamming_shortlist " << o.hamming_shortlist << ", asmk_weight " << o.asmk_weight << ", qe_asmk_weight " << o.qe_asmk_weight
    << ", hamming_norm_exponent " << o.hamming_norm_exponent;
  return s.str();
}

}  // namespace

Experiments RunExperiments(const ExperimentOptions& a) {
  eval::Protocol protocol = LoadProtocol(a);
  if (a.max_queries > 0 && protocol.queries.size() > static_cast<size_t>(a.max_queries)) {
    protocol.queries.resize(static_cast<size_t>(a.max_queries));
  }
  if (protocol.queries.empty()) throw ExperimentError(2, "the protocol has no query with a positive image");
  OXBOW_LOG(kInfo) << "eval: protocol " << protocol.name << ": " << protocol.queries.size() << " queries, "
                   << protocol.database.size() << " database images (" << protocol.distractors << " distractors), AP "
                   << eval::ApDefinitionName(protocol.ap);
  const std::map<std::string, std::string> database = DatabaseFiles(a, protocol);
  const int top_k = a.top_k > 0 ? a.top_k : static_cast<int>(std::min<size_t>(10000, protocol.database.size()));
  const std::string& exe = a.oxbow_binary;
  const std::vector<HammingSetting> hamming_settings = HammingSettings(a);
  const std::array<std::string, 2> kModes = {"http", "in-process"};
  fs::create_directories(a.work);
  const bool external = !a.server.empty();
  const std::string server_url =
      !external || a.server.find("://") != std::string::npos ? a.server : "http://" + a.server;
  if (external && a.mode == "in-process") throw ExperimentError(2, "--server evaluates over HTTP: --mode in-process does not apply");
  // The end of every run's label: the settings left to a running server, e.g. " (the server's qe hamming)".
  std::string left_to_server;
  for (const char* setting : kServerSearchSettings) {
    if (!Sends(a, setting)) left_to_server += std::string(left_to_server.empty() ? " (the server's " : " ") + setting;
  }
  if (!left_to_server.empty()) left_to_server += ")";
  std::vector<eval::RunResult> runs;
  for (const std::string& features : external ? std::vector<std::string>{"server"} : a.features) {
    if (!external && features != "sift" && features != "rootsift")
      throw ExperimentError(2, "--features takes sift and/or rootsift");
    for (int words : external ? std::vector<int>{0} : a.words) {
      const Config config{features, words};
      eval::RunResult base;
      base.protocol = protocol.name;
      base.ap_definition = protocol.ap;
      base.distractors = protocol.distractors;
      index::IndexStats stats;
      std::unique_ptr<index::ImageIndex> idx;
      std::unique_ptr<ServerProcess> server;
      std::string index_dir;
      if (external) {
        stats = ServerStats(a, server_url, database);
        words = static_cast<int>(stats.vocabulary_size);
      } else {
        Prepare(a, config, database, exe, &base);
        index_dir = (fs::path(config.Dir(a.work)) / "index").string();
        idx = Must(index::ImageIndex::Open(index_dir));
        stats = idx->Stats();
      }
      base.index_images = stats.num_images;
      base.index_features = stats.num_features;
      base.index_bytes_per_feature = stats.bytes_per_feature;
      base.vocabulary_words = stats.vocabulary_size;
      // Every HTTP run, then every in-process run: one process at a time may open the index folder
      // (index/storage/folder_lock.h), so the server is stopped before this process opens it.
      for (const std::string& mode : kModes) {
        if (external ? mode != "http" : a.mode != "both" && a.mode != mode) continue;
        if (!external && mode == "http") {
          idx.reset();  // the server opens the index itself
          server = std::make_unique<ServerProcess>(exe, index_dir, (fs::path(config.Dir(a.work)) / "serve.log").string(),
                                                   a.threads);
        } else if (!external) {
          server.reset();  // waits for its exit, which releases the folder
          if (!idx) idx = Must(index::ImageIndex::Open(index_dir));
        }
        for (int rerank : a.rerank) {
          for (const auto& [qe_text, transitive_text] : Combinations(a.qe, a.transitive)) {
            const bool qe = qe_text == "on", transitive = transitive_text == "on";
            // QE and transitive verification build on verified results: both need re-ranking.
            if ((qe || !transitive) && rerank == 0) continue;
            for (const HammingSetting& hamming : hamming_settings) {
              eval::RunResult run = base;
              // A setting left to a running server is labelled as such, not with eval's default.
              const auto shown = [&](const std::string& setting, const std::string& value) {
                return Sends(a, setting) ? value : std::string("the server's");
              };
              run.label = (external ? server_url : features) + " " +
                          (words % 1000 == 0 ? std::to_string(words / 1000) + "k" : std::to_string(words)) +
                          (rerank > 0 && Sends(a, "rerank") ? " +rerank" + std::to_string(rerank) : "") +
                          (rerank > 0 && transitive && Sends(a, "transitive") ? " +tv" : "") +
                          (qe && Sends(a, "qe") ? " +qe" : "") + (Sends(a, "hamming") ? HammingLabel(hamming) : "") +
                          (a.mode == "both" && !external ? " (" + mode + ")" : "");
              run.label += left_to_server;
              run.settings = {{"features", external ? "the server's" : features},
                              {"words", std::to_string(words)},
                              {"vocabulary_trained_on", external ? "the server's"
                                                        : a.train_images.empty() ? "the database images"
                                                                                 : a.train_images},
                              {"training_sample", std::to_string(a.sample)},
                              {"seed", std::to_string(a.seed)},
                              {"rerank", shown("rerank", std::to_string(rerank))},
                              {"qe", shown("qe", qe ? "on" : "off")},
                              {"transitive", shown("transitive", rerank > 0 && transitive ? "on" : "off")},
                              {"hamming", shown("hamming", hamming.on ? "on" : "off")},
                              {"hamming_threshold", !hamming.on ? "-" : shown("hamming", std::to_string(hamming.threshold))},
                              {"hamming_sigma", !hamming.on ? "-" : shown("hamming", FormatSigma(hamming.sigma))},
                              {"search_defaults", external ? "the server's" : SearchDefaults()},
                              {"query_region", a.full_image ? "full image" : "ground-truth box"},
                              {"ap", eval::ApDefinitionName(protocol.ap)},
                              {"distractors", a.distractors.empty() ? "none"
                                                                    : std::to_string(protocol.distractors) +
                                                                          " images from " + a.distractors},
                              {"top_k", std::to_string(top_k)},
                              {"path", external ? "http, a running server: " + server_url : mode},
                              {"extractor", stats.vocabulary_size ? "oxbow SIFT (index settings)" : ""}};
              if (mode == "http") {
                RunHttp(a, protocol, database, external ? server_url : "http://127.0.0.1:" + std::to_string(server->port()),
                        rerank, qe, transitive, hamming, top_k, &run);
              } else {
                RunInProcess(a, protocol, database, *idx, rerank, qe, transitive, hamming, top_k, &run);
              }
              eval::Summarise(&run);
              OXBOW_LOG(kInfo) << "eval: " << protocol.name << " | " << run.label << " | mAP " << run.map
                               << " | recall@1 " << run.recall_at_1 << " | query p50 " << run.query_p50_ms << " ms";
              runs.push_back(std::move(run));
            }
          }
        }
      }
    }
  }
  return {protocol.name, protocol.ap, std::move(runs)};
}

}  // namespace oxbow::eval
