#include "sift/types.h"

namespace oxbow::sift {

const char* DescriptorKindName(DescriptorKind kind) {
  switch (kind) {
    case DescriptorKind::kSift: return "sift";
    case DescriptorKind::kRootSift: return "rootsift";
  }
  return "unknown";
}

}  // namespace oxbow::sift
