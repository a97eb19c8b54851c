// What a filter costs a search: the allow-bitmap of a filtered query calls ImageFilter::Matches once per
// live image (index/image_index.h), so this times Matches over N synthetic metadata documents of about
// the size real ones have (six members, ~100 bytes), on one thread, for a selective filter (about 1% of
// the images) and a broad one. A search spreads the calls over the index's threads. Reports the
// thread's CPU time (less disturbed than wall time on a shared machine) per pass over the images.
//
//   filter_benchmark [--images N] [--repeats R]
#include <algorithm>
#include <ctime>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "api/filter.h"

namespace {

double ThreadCpuMs() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) * 1e3 + static_cast<double>(t.tv_nsec) * 1e-6;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace oxbow;
  size_t images = 1000000;
  int repeats = 3;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i];
    if (flag == "--images") {
      images = std::stoul(argv[i + 1]);
    } else if (flag == "--repeats") {
      repeats = std::stoi(argv[i + 1]);
    } else {
      std::fprintf(stderr, "usage: filter_benchmark [--images N] [--repeats R]\n");
      return 2;
    }
  }
  std::mt19937_64 rng(1);
  std::vector<index::ImageRecord> records(images);
  size_t bytes = 0;
  for (size_t i = 0; i < images; ++i) {
    records[i].metadata_json = R"({"city":"city-)" + std::to_string(rng() % 100) + R"(","year":)" +
                               std::to_string(1950 + rng() % 75) + R"(,"camera":"model-)" + std::to_string(rng() % 40) +
                               R"(","public":)" + (rng() % 2 ? "true" : "false") + R"(,"tags":["a","b"],"source":"img-)" +
                               std::to_string(i) + R"("})";
    bytes += records[i].metadata_json.size();
  }
  std::printf("%zu images, metadata %.0f bytes on average\n", images, static_cast<double>(bytes) / images);
  // An "in" list of the longest length accepted, one of whose values is present (about 1% of the images).
  std::string long_in = R"({"city": {"in": ["city-7")";
  for (size_t i = 1; i < api::kMaxFilterValues; ++i) long_in += ",\"town-" + std::to_string(i) + "\"";
  long_in += "]}}";
  for (const std::string& text : {std::string(R"({"city": "city-7"})"),
                                  std::string(R"({"city": {"in": ["city-7", "city-8"]}, "year": {"gte": 2000}})"),
                                  std::string(R"({"year": {"gte": 1950}})"), long_in}) {
    const auto filter = api::ParseFilter(text, "filter");
    if (!filter || *filter == nullptr) return 1;
    std::vector<double> ms;
    size_t matched = 0;
    for (int r = 0; r < repeats; ++r) {
      const double t0 = ThreadCpuMs();
      matched = 0;
      for (const index::ImageRecord& record : records) matched += (*filter)->Matches(record) ? 1 : 0;
      ms.push_back(ThreadCpuMs() - t0);
    }
    std::sort(ms.begin(), ms.end());
    const std::string shown = text.size() <= 70 ? text : "{\"city\": {\"in\": [" + std::to_string(api::kMaxFilterValues) + " strings]}}";
    std::printf("%-70s matched %6.2f%%  %8.1f ms CPU (median of %d)  %6.0f ns/image\n", shown.c_str(),
                100.0 * static_cast<double>(matched) / static_cast<double>(images), ms[ms.size() / 2], repeats,
                1e6 * ms[ms.size() / 2] / static_cast<double>(images));
  }
  return 0;
}
