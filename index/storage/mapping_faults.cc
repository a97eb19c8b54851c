#include "index/storage/mapping_faults.h"

#include <signal.h>
#include <sys/mman.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cerrno>
#include <mutex>

#include "sift/base/error.h"

namespace oxbow::index {
namespace {

// One registered range. `taken` gives the slot to one guard; its range is published as a sequence lock
// (odd `sequence` while begin and end are written), so that the handler, which cannot wait, reads a
// consistent pair or skips the slot. A slot being written is never the faulting thread's range: a
// range is registered before it is read and unregistered only when nothing reads it any more.
struct Slot {
  std::atomic<bool> taken{false};
  std::atomic<uint64_t> sequence{0};
  std::atomic<uintptr_t> begin{0};
  std::atomic<uintptr_t> end{0};  // one past the last byte; begin == end: no range
};

// Slots in blocks that are added as needed and never freed (the handler may be reading any of them).
constexpr size_t kSlotsPerBlock = 64;
struct Block {
  std::array<Slot, kSlotsPerBlock> slots;
  std::atomic<Block*> next{nullptr};
};
constinit Block first_block;

constinit std::atomic<uint64_t> answered{0};
// What SIGBUS did before the handler was installed; written once, before the handler can run.
struct sigaction previous_action;
uintptr_t page_bytes = 4096;
std::once_flag install_once;

void Publish(Slot& slot, uintptr_t begin, uintptr_t end) {
  const uint64_t sequence = slot.sequence.load(std::memory_order_relaxed);
  slot.sequence.store(sequence + 1, std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_release);
  slot.begin.store(begin, std::memory_order_relaxed);
  slot.end.store(end, std::memory_order_relaxed);
  slot.sequence.store(sequence + 2, std::memory_order_release);
}

// Whether `address` lies in a registered range. Async-signal-safe: loads only, no waiting.
bool Registered(uintptr_t address) {
  for (const Block* block = &first_block; block != nullptr; block = block->next.load(std::memory_order_acquire)) {
    for (const Slot& slot : block->slots) {
      const uint64_t before = slot.sequence.load(std::memory_order_acquire);
      if (before % 2 != 0) continue;
      const uintptr_t begin = slot.begin.load(std::memory_order_relaxed);
      const uintptr_t end = slot.end.load(std::memory_order_relaxed);
      std::atomic_thread_fence(std::memory_order_acquire);
      if (slot.sequence.load(std::memory_order_relaxed) != before) continue;
      if (address >= begin && address < end) return true;
    }
  }
  return false;
}

// A SIGBUS that is not ours: what was installed before, else the default action.
void PassOn(int signal, siginfo_t* info, void* context) {
  if ((previous_action.sa_flags & SA_SIGINFO) != 0) {
    if (previous_action.sa_sigaction != nullptr) {
      previous_action.sa_sigaction(signal, info, context);
      return;
    }
  } else if (previous_action.sa_handler == SIG_IGN) {
    // Ignored, as before, when another process sent it; a fault cannot be ignored (the kernel ends the
    // process whose fault signal is ignored), so it falls through to the default action.
    if (info == nullptr || info->si_code <= 0) return;
  } else if (previous_action.sa_handler != SIG_DFL) {
    previous_action.sa_handler(signal);
    return;
  }
  struct sigaction fallback {};
  fallback.sa_handler = SIG_DFL;
  sigemptyset(&fallback.sa_mask);
  ::sigaction(SIGBUS, &fallback, nullptr);
  // SIGBUS is blocked while this handler runs: it is delivered, with the default action (the process
  // ends with a core dump, as without this handler), as soon as the handler returns.
  ::raise(SIGBUS);
}

void OnBusError(int signal, siginfo_t* info, void* context) {
  const int saved_errno = errno;
  // si_code > 0: raised by the kernel for a fault at si_addr (not sent by kill or sigqueue).
  if (info != nullptr && info->si_code > 0) {
    const auto address = reinterpret_cast<uintptr_t>(info->si_addr);
    if (Registered(address)) {
      // mmap is a plain system call here (Linux), safe in a signal handler. The page lies in a mapping
      // its owner still holds (the contract in the header), so nothing else can be mapped there.
      // The page's start as a pointer into the faulting one (no integer-to-pointer cast).
      void* page = static_cast<char*>(info->si_addr) - (address & (page_bytes - 1));
      if (::mmap(page, page_bytes, PROT_READ, MAP_FIXED | MAP_PRIVATE | MAP_ANONYMOUS, -1, 0) != MAP_FAILED) {
        answered.fetch_add(1, std::memory_order_relaxed);
        errno = saved_errno;
        return;
      }
    }
  }
  PassOn(signal, info, context);
  errno = saved_errno;
}

void Install() {
  const long page = ::sysconf(_SC_PAGESIZE);
  if (page > 0) page_bytes = static_cast<uintptr_t>(page);
  // The previous action is read first, so that it is in place before the handler can run.
  OXBOW_CHECK(::sigaction(SIGBUS, nullptr, &previous_action) == 0, "cannot read the SIGBUS action");
  struct sigaction action {};
  action.sa_sigaction = OnBusError;
  action.sa_flags = SA_SIGINFO | SA_ONSTACK | SA_RESTART;
  sigemptyset(&action.sa_mask);
  OXBOW_CHECK(::sigaction(SIGBUS, &action, nullptr) == 0, "cannot install the SIGBUS handler");
}

}  // namespace

MappingFaultGuard::MappingFaultGuard(const void* begin, size_t size) : slot_(nullptr) {
  OXBOW_CHECK(begin != nullptr && size > 0);
  std::call_once(install_once, Install);
  const auto first = reinterpret_cast<uintptr_t>(begin);
  for (Block* block = &first_block;;) {
    for (Slot& slot : block->slots) {
      bool expected = false;
      if (!slot.taken.load(std::memory_order_relaxed) &&
          slot.taken.compare_exchange_strong(expected, true, std::memory_order_acquire)) {
        Publish(slot, first, first + size);
        slot_ = &slot;
        return;
      }
    }
    Block* next = block->next.load(std::memory_order_acquire);
    if (next == nullptr) {
      auto* fresh = new Block();
      // Another thread may have added one meanwhile: then that one is used and ours dropped.
      if (block->next.compare_exchange_strong(next, fresh, std::memory_order_acq_rel)) {
        next = fresh;
      } else {
        delete fresh;
      }
    }
    block = next;
  }
}

MappingFaultGuard::~MappingFaultGuard() {
  auto& slot = *static_cast<Slot*>(slot_);
  Publish(slot, 0, 0);
  slot.taken.store(false, std::memory_order_release);
}

uint64_t MappingFaultGuard::AnsweredFaults() { return answered.load(std::memory_order_relaxed); }

}  // namespace oxbow::index
