// Faults in memory-mapped files, answered instead of killing the process.
//
// Reading a page of a file mapping that lies past the end of the file (the file was truncated after it
// was mapped), or whose read from the disk fails, raises SIGBUS, whose default action ends the process.
// A checkpoint's geometry files are mapped (checkpoint.h, MappedFile) and can be truncated or damaged
// under the running index by anything that can write the folder. While a range is registered here, a
// SIGBUS whose faulting address lies in it is answered by mapping a page of zeros over the faulting page
// (mmap MAP_FIXED | MAP_PRIVATE | MAP_ANONYMOUS, read-only) and returning: the read is repeated and
// sees zeros, and so does every later read of that page. A reader must therefore check what it read
// (the geometry files' per-image XXH3-64, or the file's size after the read: MappedFile::Copy) and
// never use bytes it did not check. Any other SIGBUS (another address, one sent by kill, or a zero
// page that cannot be mapped) gets what was installed before the first registration: a handler is
// called, the default action ends the process as it would have.
//
// The handler is installed (sigaction, SA_SIGINFO) by the first registration and stays installed. The
// registry is lock-free: the handler reads it without waiting, registration and unregistration may run
// on any thread at any time, and the handler runs on the thread that faulted.
//
// Contract for owners of a range: register it after mapping it and unregister it (destroy the guard)
// before unmapping it, and never read a range after unregistering it: then the page the handler maps
// over is always within a mapping its owner still holds, and the owner's munmap removes the zero pages
// with the rest.
#pragma once

#include <cstddef>
#include <cstdint>

namespace oxbow::index {

class MappingFaultGuard {
 public:
  // Registers [begin, begin + size) (size > 0), installing the handler if it is not installed yet.
  MappingFaultGuard(const void* begin, size_t size);
  // Unregisters the range.
  ~MappingFaultGuard();
  MappingFaultGuard(const MappingFaultGuard&) = delete;
  MappingFaultGuard& operator=(const MappingFaultGuard&) = delete;

  // Faults answered with a zero page since the process started (all ranges).
  static uint64_t AnsweredFaults();

 private:
  void* slot_;  // the registry's slot of this range
};

}  // namespace oxbow::index
