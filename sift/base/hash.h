// FNV-1a 64 (Fowler, Noll, Vo): a tiny, stable, non-cryptographic hash of bytes. Stable across runs,
// machines and builds, so its values may be stored on disk or decide where data lives (partitions).
#pragma once

#include <cstdint>
#include <string_view>

namespace oxbow {

inline constexpr uint64_t kFnv1a64Basis = 0xcbf29ce484222325ull;

// FNV-1a 64 of `bytes`; pass a previous result as `hash` to chain pieces.
constexpr uint64_t Fnv1a64(std::string_view bytes, uint64_t hash = kFnv1a64Basis) {
  for (const char c : bytes) {
    hash ^= static_cast<uint8_t>(c);
    hash *= 0x100000001b3ull;
  }
  return hash;
}

}  // namespace oxbow
