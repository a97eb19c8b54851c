#include "eval/ground_truth.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "sift/image.h"

namespace oxbow::eval {
namespace {

namespace fs = std::filesystem;

std::string StripOxfordPrefix(const std::string& name) {
  return name.starts_with("oxc1_") ? name.substr(5) : name;
}

// A folder opens as a stream on Linux, and fails only when read (an exception from the JSON parser).
Status CheckNotAFolder(const fs::path& path, const char* what) {
  std::error_code ec;
  if (fs::is_directory(path, ec)) {
    return Fail(ErrorCode::kInvalidArgument, "'" + path.string() + "' is a folder: give the " + what + " file");
  }
  return Ok();
}

// An nlohmann::json exception's text without its "[json.exception.type.403] " prefix.
std::string JsonErrorText(const std::exception& e) {
  const std::string text = e.what();
  const size_t end = text.rfind("[json.exception.", 0) == 0 ? text.find("] ") : std::string::npos;
  return end == std::string::npos ? text : text.substr(end + 2);
}

Result<std::vector<std::string>> ReadLines(const fs::path& path) {
  if (auto s = CheckNotAFolder(path, "ground-truth"); !s) return std::unexpected(s.error());
  std::ifstream in(path);
  if (!in) return Fail(ErrorCode::kNotFound, "cannot read ground-truth file '" + path.string() + "'");
  std::vector<std::string> lines;
  std::string line;
  while (std::getline(in, line)) {
    while (!line.empty() && (line.back() == '\r' || line.back() == ' ' || line.back() == '\t')) line.pop_back();
    if (!line.empty()) lines.push_back(line);
  }
  return lines;
}

}  // namespace

const char* RevisitedSettingName(RevisitedSetting setting) {
  switch (setting) {
    case RevisitedSetting::kEasy: return "easy";
    case RevisitedSetting::kMedium: return "medium";
    case RevisitedSetting::kHard: return "hard";
  }
  return "?";
}

Result<Protocol> LoadOxfordProtocol(const std::string& gt_dir, const std::string& name) {
  std::error_code ec;
  if (!fs::is_directory(gt_dir, ec)) {
    return Fail(ErrorCode::kNotFound, "ground-truth folder '" + gt_dir + "' does not exist");
  }
  Protocol protocol;
  protocol.name = name;
  std::set<std::string> database;
  for (const auto& entry : fs::directory_iterator(gt_dir)) {
    const std::string file = entry.path().filename().string();
    const std::string suffix = "_query.txt";
    if (!file.ends_with(suffix)) continue;
    const std::string query_name = file.substr(0, file.size() - suffix.size());
    auto query_lines = ReadLines(entry.path());
    if (!query_lines) return std::unexpected(query_lines.error());
    if (query_lines->size() != 1) {
      return Fail(ErrorCode::kCorruptData, "'" + entry.path().string() + "' should hold one line");
    }
    std::istringstream fields((*query_lines)[0]);
    EvalQuery query;
    query.name = query_name;
    std::string image;
    std::array<float, 4> box{};
    if (!(fields >> image >> box[0] >> box[1] >> box[2] >> box[3])) {
      return Fail(ErrorCode::kCorruptData,
                  "'" + entry.path().string() + "' is not '<image> x1 y1 x2 y2': '" + (*query_lines)[0] + "'");
    }
    query.image = StripOxfordPrefix(image);
    query.bbox = box;
    for (const char* list : {"good", "ok", "junk"}) {
      const fs::path list_path = fs::path(gt_dir) / (query_name + "_" + list + ".txt");
      auto ids = ReadLines(list_path);
      if (!ids) return std::unexpected(ids.error());
      for (const std::string& id : *ids) {
        database.insert(id);
        if (std::string(list) == "junk") {
          query.relevance.junk.insert(id);
        } else {
          query.relevance.positives.insert(id);
        }
      }
    }
    database.insert(query.image);
    protocol.queries.push_back(std::move(query));
  }
  if (protocol.queries.empty()) {
    return Fail(ErrorCode::kNotFound, "no '*_query.txt' files in '" + gt_dir + "'");
  }
  std::sort(protocol.queries.begin(), protocol.queries.end(),
            [](const EvalQuery& a, const EvalQuery& b) { return a.name < b.name; });
  protocol.database.assign(database.begin(), database.end());
  return protocol;
}

Protocol RestrictToImages(const Protocol& protocol, const std::vector<std::string>& present_ids) {
  const std::unordered_set<std::string> present(present_ids.begin(), present_ids.end());
  Protocol restricted;
  restricted.name = protocol.name;
  // Database = the images present (those no list names are negatives).
  const std::set<std::string> database(present_ids.begin(), present_ids.end());
  restricted.database.assign(database.begin(), database.end());
  // Query photos the protocol keeps out of its database (revisited Oxford/Paris) but that are among the
  // images present get indexed like the rest: they are junk for every query (neither help nor hurt),
  // otherwise a query's own photo would rank first as a negative.
  const std::unordered_set<std::string> official(protocol.database.begin(), protocol.database.end());
  std::vector<std::string> outside;
  for (const EvalQuery& query : protocol.queries) {
    if (present.contains(query.image) && !official.contains(query.image)) outside.push_back(query.image);
  }
  for (const EvalQuery& query : protocol.queries) {
    if (!present.contains(query.image)) continue;
    EvalQuery q = query;
    std::erase_if(q.relevance.positives, [&](const std::string& id) { return !present.contains(id); });
    std::erase_if(q.relevance.junk, [&](const std::string& id) { return !present.contains(id); });
    q.relevance.junk.insert(outside.begin(), outside.end());
    if (q.relevance.positives.empty()) continue;
    restricted.queries.push_back(std::move(q));
  }
  return restricted;
}

Result<Protocol> LoadRevisitedProtocol(const std::string& json_path, RevisitedSetting setting,
                                       const std::string& name) {
  if (auto s = CheckNotAFolder(json_path, "revisited ground-truth JSON (gnd_roxford5k.json, gnd_rparis6k.json)"); !s) {
    return std::unexpected(s.error());
  }
  std::ifstream in(json_path);
  if (!in) return Fail(ErrorCode::kNotFound, "cannot read '" + json_path + "'");
  nlohmann::json root;
  try {
    root = nlohmann::json::parse(in);
  } catch (const nlohmann::json::exception& e) {
    return Fail(ErrorCode::kCorruptData, "'" + json_path + "' is not valid JSON: " + JsonErrorText(e));
  }
  try {
    const auto imlist = root.at("imlist").get<std::vector<std::string>>();
    const auto qimlist = root.at("qimlist").get<std::vector<std::string>>();
    const auto& gnd = root.at("gnd");
    if (gnd.size() != qimlist.size()) {
      return Fail(ErrorCode::kCorruptData, "'" + json_path + "': gnd and qimlist differ in length");
    }
    Protocol protocol;
    protocol.name = name + "-" + RevisitedSettingName(setting);
    protocol.database = imlist;
    std::sort(protocol.database.begin(), protocol.database.end());
    auto names = [&](const nlohmann::json& indices) {
      std::vector<std::string> out;
      for (const auto& i : indices) {
        const size_t index = i.get<size_t>();
        if (index >= imlist.size()) throw std::out_of_range("image index " + std::to_string(index));
        out.push_back(imlist[index]);
      }
      return out;
    };
    for (size_t q = 0; q < qimlist.size(); ++q) {
      const auto easy = names(gnd[q].at("easy"));
      const auto hard = names(gnd[q].at("hard"));
      const auto junk = names(gnd[q].at("junk"));
      EvalQuery query;
      query.name = qimlist[q];
      query.image = qimlist[q];
      const auto bbx = gnd[q].at("bbx").get<std::vector<float>>();
      if (bbx.size() == 4) query.bbox = std::array<float, 4>{bbx[0], bbx[1], bbx[2], bbx[3]};
      auto add = [](std::unordered_set<std::string>& set, const std::vector<std::string>& ids) {
        set.insert(ids.begin(), ids.end());
      };
      switch (setting) {
        case RevisitedSetting::kEasy:
          add(query.relevance.positives, easy);
          add(query.relevance.junk, junk);
          add(query.relevance.junk, hard);
          break;
        case RevisitedSetting::kMedium:
          add(query.relevance.positives, easy);
          add(query.relevance.positives, hard);
          add(query.relevance.junk, junk);
          break;
        case RevisitedSetting::kHard:
          add(query.relevance.positives, hard);
          add(query.relevance.junk, junk);
          add(query.relevance.junk, easy);
          break;
      }
      if (query.relevance.positives.empty()) continue;  // as revisitop: no positives, no AP
      protocol.queries.push_back(std::move(query));
    }
    return protocol;
  } catch (const std::exception& e) {
    return Fail(ErrorCode::kCorruptData, "'" + json_path + "' is not revisited ground truth (revisitop's JSON: imlist, "
                                         "qimlist, gnd with easy, hard, junk and bbx per query): " + JsonErrorText(e));
  }
}

Result<std::vector<std::string>> ListImageIds(const std::string& dir) {
  auto files = sift::ListImageFiles(dir);  // the listing every command uses (recursive)
  if (!files) return std::unexpected(files.error());
  std::vector<std::string> ids;
  ids.reserve(files->size());
  for (const std::string& f : *files) ids.push_back(fs::path(f).stem().string());
  std::sort(ids.begin(), ids.end());
  return ids;
}

namespace {

// "<prefix>__<path of file inside root, without extension, '/' written "__">".
std::string GroupsId(const std::string& prefix, const fs::path& root, const fs::path& file) {
  std::string id = prefix;
  const fs::path relative = file.lexically_relative(root);
  for (auto part = relative.begin(); part != relative.end(); ++part) {
    id += "__";
    id += std::next(part) == relative.end() ? part->stem().string() : part->string();
  }
  return id;
}

// Adds every image under `root` to `protocol->files` as GroupsId(prefix, ...); returns the ids added.
Result<std::vector<std::string>> AddGroupsImages(const std::string& prefix, const fs::path& root,
                                                 Protocol* protocol) {
  auto files = sift::ListImageFiles(root.string());
  if (!files) return std::unexpected(files.error());
  std::vector<std::string> ids;
  ids.reserve(files->size());
  for (const std::string& file : *files) {
    const std::string id = GroupsId(prefix, root, file);
    if (const auto [it, added] = protocol->files.emplace(id, file); !added) {
      std::string message = "'" + file;
      message += "' and '";
      message += it->second;
      message += "' both get the image id '" + id + "'; rename one";
      return Fail(ErrorCode::kInvalidArgument, message);
    }
    protocol->database.push_back(id);
    ids.push_back(id);
  }
  return ids;
}

}  // namespace

Result<Protocol> LoadGroupsProtocol(const std::string& dir, const std::string& distractors_dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return Fail(ErrorCode::kNotFound, "folder '" + dir + "' does not exist");
  Protocol protocol;
  protocol.name = "groups";
  protocol.ap = ApDefinition::kNonInterpolated;
  std::vector<fs::path> group_dirs;
  for (const auto& entry : fs::directory_iterator(dir)) {
    if (entry.is_directory()) group_dirs.push_back(entry.path());
  }
  std::sort(group_dirs.begin(), group_dirs.end());
  for (const fs::path& group_dir : group_dirs) {
    const std::string group = group_dir.filename().string();
    auto members = AddGroupsImages(group, group_dir, &protocol);
    if (!members) return std::unexpected(members.error());
    for (const std::string& id : *members) {
      EvalQuery query;
      query.name = id;
      query.image = id;
      query.group = group;
      for (const std::string& other : *members) {
        if (other != id) query.relevance.positives.insert(other);
      }
      query.relevance.junk.insert(id);
      if (!query.relevance.positives.empty()) protocol.queries.push_back(std::move(query));
    }
  }
  if (protocol.database.empty()) return Fail(ErrorCode::kNotFound, "no sub-folders with images in '" + dir + "'");
  if (!distractors_dir.empty()) {
    auto distractors = AddGroupsImages("distractor", distractors_dir, &protocol);
    if (!distractors) return std::unexpected(distractors.error());
    if (distractors->empty()) return Fail(ErrorCode::kNotFound, "no images in '" + distractors_dir + "'");
    protocol.distractors = distractors->size();
    protocol.name += "+distractors";
  }
  std::sort(protocol.database.begin(), protocol.database.end());
  return protocol;
}

}  // namespace oxbow::eval
