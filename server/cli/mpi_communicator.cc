// MPI implementation of vocab::Communicator (see mpi_communicator.h).
#include "server/cli/mpi_communicator.h"

#include <climits>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>
#include <vector>

#include "server/cli/cli.h"
#include "server/cli/modules/module_loader.h"
#include "server/cli/modules/mpi_api.h"
#include "sift/base/binary_io.h"
#include "sift/base/log.h"

namespace oxbow::cli {
namespace {

// MPI counts are int: large buffers go in pieces of at most kChunk elements.
constexpr size_t kChunk = size_t{1} << 30;

// The MPI module (modules/mpi_api.h), loaded on first use; CommandError when it cannot be.
const MpiApi& Mpi() {
  static const MpiApi* api = [] {
    const auto entry = LoadModuleEntry("oxbow_mpi", kMpiApiEntry);
    if (!entry) throw CommandError(entry.error());
    const MpiApi* table = reinterpret_cast<MpiApiEntry>(*entry)(kMpiApiVersion);
    if (table == nullptr) throw CommandError(ExitCodeFor(ErrorCode::kIncompatible), "the oxbow MPI module is of another oxbow version");
    return table;
  }();
  return *api;
}

class MpiWorld final : public vocab::Communicator {
 public:
  MpiWorld() {
    Mpi().rank(&rank_);
    Mpi().size(&size_);
  }
  int rank() const override { return rank_; }
  int size() const override { return size_; }

  void SumInPlace(std::span<int64_t> values) override {
    for (size_t at = 0; at < values.size(); at += kChunk) {
      const int count = static_cast<int>(std::min(kChunk, values.size() - at));
      Mpi().sum_int64(values.data() + at, count);
    }
  }
  double Max(double value) override {
    double out = value;
    Mpi().max_double(value, &out);
    return out;
  }
  void Broadcast(std::span<uint8_t> bytes) override {
    for (size_t at = 0; at < bytes.size(); at += kChunk) {
      const int count = static_cast<int>(std::min(kChunk, bytes.size() - at));
      Mpi().broadcast(bytes.data() + at, count);
    }
  }
  std::vector<uint8_t> Allgather(std::span<const uint8_t> bytes) override {
    if (bytes.size() > INT_MAX) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), "MPI message over 2 GiB");
    const int mine = static_cast<int>(bytes.size());
    std::vector<int> counts(size_), offsets(size_);
    Mpi().allgather_int(mine, counts.data());
    int64_t total = 0;
    for (int r = 0; r < size_; ++r) {
      if (total > INT_MAX) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), "MPI gather over 2 GiB");
      offsets[r] = static_cast<int>(total);
      total += counts[r];
    }
    if (total > INT_MAX) throw CommandError(ExitCodeFor(ErrorCode::kInvalidArgument), "MPI gather over 2 GiB");
    std::vector<uint8_t> out(static_cast<size_t>(total));
    Mpi().allgatherv_bytes(bytes.data(), mine, out.data(), counts.data(), offsets.data());
    return out;
  }

 private:
  int rank_ = 0;
  int size_ = 1;
};

// The refusal every rank agreed on (ThrowIfAnyRankRefuses).
class AgreedError final : public CommandError {
 public:
  using CommandError::CommandError;
};

[[noreturn]] void AbortJob(int rank, const std::string& message, int exit_code) {
  std::fprintf(stderr, "oxbow: error (rank %d): %s\n", rank, message.c_str());
  std::fflush(stderr);
  Mpi().abort(exit_code);
  std::_Exit(exit_code);  // MPI_Abort does not return; this keeps the compiler's view honest
}

}  // namespace

void RunWithMpi(const std::function<void(vocab::Communicator&)>& body) {
  Mpi().init();
  MpiWorld world;
  if (world.rank() != 0 && log::GetLevel() < log::Level::kWarning) log::SetLevel(log::Level::kWarning);
  try {
    body(world);
  } catch (const AgreedError& e) {
    // Every rank holds the same refusal: no abort; rank 0 reports it once, the others leave quietly.
    Mpi().finalize();
    if (world.rank() == 0) throw CommandError(e.exit_code(), e.what());
    std::exit(e.exit_code());
  } catch (const CommandError& e) {
    if (world.size() == 1) {
      Mpi().finalize();
      throw;
    }
    AbortJob(world.rank(), e.what(), e.exit_code());
  } catch (const std::exception& e) {
    if (world.size() == 1) {
      Mpi().finalize();
      throw;
    }
    AbortJob(world.rank(), std::string("internal error: ") + e.what(), 1);
  }
  Mpi().finalize();
}

void ThrowIfAnyRankRefuses(vocab::Communicator& comm, const std::optional<CommandError>& mine) {
  io::ByteWriter w;
  w.Put<uint32_t>(mine ? static_cast<uint32_t>(mine->exit_code()) : 0u);
  w.PutString(mine ? mine->what() : "");
  const std::vector<uint8_t> gathered = comm.size() == 1 ? w.bytes() : comm.Allgather(w.bytes());
  io::ByteReader r(gathered, "rank refusals");
  for (int rank = 0; rank < comm.size(); ++rank) {
    const uint32_t code = ValueOrExit(r.Get<uint32_t>());
    std::string message = ValueOrExit(r.GetString(1u << 20));
    if (code != 0) throw AgreedError(static_cast<int>(code), message);
  }
}

}  // namespace oxbow::cli
