// Ground truth for the retrieval protocols: which images form the database, which are the queries (with
// their box), and per query which database images are positives and which are junk.
//
// Protocols (eval/README.md):
//  - Oxford/Paris (Philbin et al. 2007): a folder of `<name>_query.txt` ("<image> x1 y1 x2 y2"; Oxford
//    prefixes images with "oxc1_"), `<name>_good.txt`, `<name>_ok.txt`, `<name>_junk.txt`. Positives are
//    good + ok; junk is skipped. The query image stays in the database (it is on its own good list).
//  - Restricted (a partial image set, e.g. the 250-image Paris subset): database = the images present;
//    only queries whose query image is present; good/ok/junk intersected with the database.
//  - Revisited Oxford/Paris (Radenovic et al. 2018): `gnd_*.pkl` converted to JSON once by
//    scripts/revisited_gt_to_json.py (python3's own pickle); Easy: positives easy, junk junk+hard;
//    Medium: positives easy+hard, junk junk; Hard: positives hard, junk junk+easy. Queries are not in the
//    database.
//  - Groups (UKBench/Holidays style; ../shared/data/groups_dev/README.md): a folder of sub-folders, one
//    per object; every image queries the rest; the query itself is junk for its own ranking (it is in the
//    database); optionally a folder of distractors added to the database (never queries, never
//    positives). Non-interpolated AP.
#pragma once

#include <array>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "eval/average_precision.h"
#include "sift/base/error.h"

namespace oxbow::eval {

struct EvalQuery {
  std::string name;                            // e.g. "defense_4"
  std::string image;                           // database image id of the query photo (no extension)
  std::optional<std::array<float, 4>> bbox;    // x1,y1,x2,y2 pixels of the query region
  Relevance relevance;
  std::string group;                           // groups protocol: the query's group folder
};

struct Protocol {
  std::string name;                   // e.g. "paris6k-restricted", "roxford5k-medium", "groups"
  std::vector<std::string> database;  // image ids (file name without extension), sorted
  std::vector<EvalQuery> queries;     // sorted by name
  ApDefinition ap = ApDefinition::kOxfordTrapezoid;
  // Image file of every database id when ids are not the files' names (groups); empty otherwise: the
  // id is then the file name without extension in the images folder.
  std::map<std::string, std::string> files;
  size_t distractors = 0;             // database images that no query may count as positive
};

// Reads an Oxford/Paris ground-truth folder. The database is every image named in any list.
[[nodiscard]] Result<Protocol> LoadOxfordProtocol(const std::string& gt_dir, const std::string& name);

// Restricts a protocol to the images present (ids): drops queries whose image is absent and intersects
// the lists; queries left with no positive are dropped too (their AP is undefined). Query images
// present but outside the protocol's database (revisited: queries are not database images) become
// junk for every query.
Protocol RestrictToImages(const Protocol& protocol, const std::vector<std::string>& present_ids);

enum class RevisitedSetting { kEasy, kMedium, kHard };
const char* RevisitedSettingName(RevisitedSetting setting);  // "easy" | "medium" | "hard"

// Reads the JSON written by scripts/revisited_gt_to_json.py ({"imlist": [...], "qimlist": [...],
// "gnd": [{"bbx": [..], "easy": [idx..], "hard": [..], "junk": [..]}, ...]}).
[[nodiscard]] Result<Protocol> LoadRevisitedProtocol(const std::string& json_path, RevisitedSetting setting,
                                                     const std::string& name);

// A folder of sub-folders, one per object or place; images with extensions jpg/jpeg/png/ppm/pgm/bmp/
// tif/tiff/webp (recursively within a group). Every image is a query; positives = the other images of
// its group. Photos of different groups may share a file name, so ids are "<group>__<name>" (the path
// inside the group without extension, each '/' written "__"), mapped to their files in `files`.
// `distractors_dir` (optional): every image under it, recursively, joins the database as
// "distractor__<name>". Ids that still collide are refused (kInvalidArgument).
[[nodiscard]] Result<Protocol> LoadGroupsProtocol(const std::string& dir, const std::string& distractors_dir = "");

// Image ids (file names without extension) of the image files directly inside `dir`, sorted.
[[nodiscard]] Result<std::vector<std::string>> ListImageIds(const std::string& dir);

}  // namespace oxbow::eval
