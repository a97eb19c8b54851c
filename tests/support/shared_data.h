// Where tests find the shared test data (boat sequence, Paris subset; see its README.md): the folder
// named by $OXBOW_SHARED_DATA when set, else ../shared/data beside the source tree (where CI has it).
// Tests that need it live in a test suite whose name contains "SharedData" and skip with the path
// they looked at when it is absent; ctest lists them as <binary>_shared_data (cmake/OxbowHelpers.cmake),
// reported "Skipped" in that case. Header-only; tests only.
#pragma once

#include <cstdlib>
#include <filesystem>

namespace oxbow::testing {

inline std::filesystem::path SharedDataDir() {
  const char* dir = std::getenv("OXBOW_SHARED_DATA");
  if (dir != nullptr && *dir != '\0') return dir;
  return std::filesystem::path(OXBOW_SOURCE_DIR) / ".." / "shared" / "data";
}

}  // namespace oxbow::testing
