#include "server/cli/modules/cluster_api.h"

#include "server/cli/cli.h"
#include "server/cli/modules/module_loader.h"

namespace oxbow::cli {

const ClusterApi& Cluster() {
  static const ClusterApi* api = [] {
    const auto entry = LoadModuleEntry("oxbow_cluster", kClusterApiEntry);
    if (!entry) throw CommandError(entry.error());
    const ClusterApi* table = reinterpret_cast<ClusterApiEntry>(*entry)(kClusterApiVersion);
    if (table == nullptr) {
      throw CommandError(ExitCodeFor(ErrorCode::kIncompatible), "the oxbow cluster module is of another oxbow version");
    }
    return table;
  }();
  return *api;
}

}  // namespace oxbow::cli
