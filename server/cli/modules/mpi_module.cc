// liboxbow_mpi.so: mpi_api.h over Open MPI (MPI_COMM_WORLD). Loaded by mpi_communicator.cc for `--mpi`.
#include <mpi.h>

#include <cstdio>

#include "server/cli/modules/mpi_api.h"

namespace oxbow::cli {
namespace {

int Init() {
  int initialized = 0;
  MPI_Initialized(&initialized);
  return initialized ? MPI_SUCCESS : MPI_Init(nullptr, nullptr);
}
int Finalize() { return MPI_Finalize(); }
int Rank(int* rank) { return MPI_Comm_rank(MPI_COMM_WORLD, rank); }
int Size(int* size) { return MPI_Comm_size(MPI_COMM_WORLD, size); }
int SumInt64(int64_t* values, int count) {
  return MPI_Allreduce(MPI_IN_PLACE, values, count, MPI_INT64_T, MPI_SUM, MPI_COMM_WORLD);
}
int MaxDouble(double value, double* max) { return MPI_Allreduce(&value, max, 1, MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD); }
int Broadcast(uint8_t* bytes, int count) { return MPI_Bcast(bytes, count, MPI_BYTE, 0, MPI_COMM_WORLD); }
int AllgatherInt(int mine, int* all) { return MPI_Allgather(&mine, 1, MPI_INT, all, 1, MPI_INT, MPI_COMM_WORLD); }
int AllgathervBytes(const uint8_t* mine, int count, uint8_t* all, const int* counts, const int* offsets) {
  return MPI_Allgatherv(mine, count, MPI_BYTE, all, counts, offsets, MPI_BYTE, MPI_COMM_WORLD);
}
void Abort(int exit_code) {
  std::fflush(nullptr);  // what this rank has printed, before MPI ends the process
  MPI_Abort(MPI_COMM_WORLD, exit_code);
}

constexpr MpiApi kApi{kMpiApiVersion, Init,      Finalize,     Rank,          Size, SumInt64,
                      MaxDouble,      Broadcast, AllgatherInt, AllgathervBytes, Abort};

}  // namespace
}  // namespace oxbow::cli

extern "C" __attribute__((visibility("default"))) const oxbow::cli::MpiApi* oxbow_mpi_api(int version) {
  return version == oxbow::cli::kMpiApiVersion ? &oxbow::cli::kApi : nullptr;
}
