// `oxbow query --index INDEX IMAGE`: rank the indexed images for a query photo, print JSON.
#include <chrono>
#include <cstdio>
#include <optional>
#include <sstream>
#include <string>

#include <nlohmann/json.hpp>

#include "api/filter.h"
#include "api/json.h"
#include "index/image_index.h"
#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "server/cli/search_flags.h"
#include "sift/sift.h"

namespace oxbow::cli {
namespace {

std::array<float, 4> ParseBox(const std::string& text) {
  std::array<float, 4> box{};
  std::stringstream in(text);
  std::string item;
  int n = 0;
  try {
    while (std::getline(in, item, ',')) {
      if (n == 4) throw std::invalid_argument("too many");
      box[n++] = std::stof(item);
    }
  } catch (const std::exception&) {
    n = -1;
  }
  if (n != 4) throw CommandError(2, "--bbox must be x1,y1,x2,y2 (pixels), got '" + text + "'");
  return box;
}

nlohmann::json ResultJson(const index::QueryResult& r) {
  // Stored by any version: too deep or invalid metadata comes back as its text, never parsed.
  const nlohmann::json metadata = api::MetadataToJson(r.record.metadata_json);
  nlohmann::json j = {{"id", r.id},
                      {"score", r.score},
                      {"verified", r.verified},
                      {"inliers", r.inliers},
                      {"source_path", r.record.source_path},
                      {"width", r.record.width},
                      {"height", r.record.height},
                      {"metadata", metadata}};
  if (!r.via.empty()) j["via"] = r.via;
  if (r.verified) {
    j["db_from_query"] = r.db_from_query.m;
    j["db_region"] = r.db_region;
  }
  return j;
}

void SetUpQuery(CLI::App& app) {
  struct Args {
    std::string index, image, bbox, filter;
    index::QueryOptions options;
    index::IndexOptions index_options;
    ImageFlags image_flags;
    int threads = 0;
  };
  auto args = std::make_shared<Args>();
  CLI::App* cmd = app.add_subcommand("query", "Rank the indexed images for a query image; prints JSON");
  cmd->add_option("--index", args->index, "index folder")->required();
  cmd->add_option("image", args->image, "query image file")->required();
  cmd->add_option("--bbox", args->bbox, "query region x1,y1,x2,y2 in pixels: only features inside are used");
  cmd->add_option("--filter", args->filter,
                  "only rank images whose metadata matches this JSON object, keys ANDed: "
                  "'{\"city\": \"Paris\"}', '{\"city\": {\"in\": [\"Paris\", \"Lyon\"]}}', "
                  "'{\"year\": {\"gte\": 2000, \"lt\": 2010}}' (server/README.md, Filtered search)");
  cmd->add_option("--top-k", args->options.top_k, "results returned")->capture_default_str()->check(NumberIn(1, 10000));
  cmd->add_option("--rerank", args->options.rerank_depth, "spatially verify the top R (0: tf-idf only)")
      ->capture_default_str()
      ->check(NumberIn(0, 10000));
  // Query expansion needs verified results: it does not apply to --rerank 0 unless asked for.
  auto* qe = cmd->add_flag("--qe,!--no-qe", args->options.query_expansion,
                           "average query expansion (Chum et al. 2007); on by default, --no-qe turns it off");
  AddSearchFlags(cmd, &args->options);
  AddIndexScoringFlags(cmd, &args->index_options);
  AddImageFlags(cmd, &args->image_flags);
  AddThreadsFlag(cmd, &args->threads);
  cmd->callback([args, qe] {
    const auto t0 = std::chrono::steady_clock::now();
    if (!args->bbox.empty()) args->options.region = ParseBox(args->bbox);
    if (args->options.rerank_depth == 0 && args->options.query_expansion) {
      // As the HTTP parameter: asked for, QE without re-ranking is an error; by default it does not apply.
      if (qe->count() > 0) throw CommandError(2, "--qe needs re-ranking: give --rerank above 0 (or leave --qe out)");
      args->options.query_expansion = false;
    }
    if (!args->filter.empty()) args->options.filter = ValueOrExit(api::ParseFilter(args->filter, "--filter"));
    if (auto e = args->options.Check()) throw CommandError(2, *e);
    if (auto e = args->index_options.Check()) throw CommandError(2, *e);
    const sift::DecodeOptions decode = args->image_flags.ToDecodeOptions();
    args->index_options.num_threads = args->threads;
    auto idx = ValueOrExit(index::ImageIndex::Open(args->index, args->index_options));
    const double open_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    sift::SiftOptions sift_options = ValueOrExit(sift::SiftOptions::FromDescription(idx->extractor_settings()));
    sift_options.num_threads = args->threads;
    const sift::SiftExtractor extractor = ValueOrExit(sift::SiftExtractor::Create(sift_options));
    const TimedFeatures f = ValueOrExit(ExtractTimed(extractor, args->image, decode));
    args->options.extractor_settings = idx->extractor_settings();
    const index::QueryResponse response = ValueOrExit(idx->Query(f.features, args->options));

    nlohmann::json out;
    out["query"] = {{"image", args->image}, {"width", f.features.image_width}, {"height", f.features.image_height},
                    {"features", f.features.size()}, {"features_used", response.query_features}};
    if (args->options.region) out["query"]["bbox"] = *args->options.region;
    out["candidates"] = response.candidates;
    out["results"] = nlohmann::json::array();
    for (const auto& r : response.results) out["results"].push_back(ResultJson(r));
    const auto& t = response.timings;
    out["timings_ms"] = {{"open_index", open_ms}, {"decode", f.decode_ms},   {"extract", f.extract_ms},
                         {"quantize", t.quantize_ms}, {"score", t.score_ms}, {"verify", t.verify_ms},
                         {"qe", t.qe_ms}, {"query_total", t.total_ms}};
    std::printf("%s\n", out.dump(2).c_str());
  });
}

const bool registered_query = RegisterCommand({"query", 40, &SetUpQuery});

}  // namespace
}  // namespace oxbow::cli
