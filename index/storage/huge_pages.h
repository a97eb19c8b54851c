// Transparent huge pages for large buffers about to be written (internal to index/).
//
// Thread safety: a pure function (one madvise call).
#pragma once

#include <sys/mman.h>

#include <cstddef>
#include <cstdint>

namespace oxbow::index {

// Asks for transparent huge pages over the whole 2 MiB pages within [data, data + size): a large
// buffer about to be written then takes one page fault per 2 MiB instead of one per 4 KiB. Advisory.
inline void AdviseHugePages(uint8_t* data, size_t size) {
  constexpr size_t kHuge = size_t{2} << 20;
  if (data == nullptr || size < 2 * kHuge) return;
  const size_t skip = (kHuge - reinterpret_cast<uintptr_t>(data) % kHuge) % kHuge;
  const size_t length = (size - skip) / kHuge * kHuge;
  if (length > 0) (void)::madvise(data + skip, length, MADV_HUGEPAGE);
}

}  // namespace oxbow::index
