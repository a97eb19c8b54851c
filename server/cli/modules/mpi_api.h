// The functions of liboxbow_mpi.so (mpi_module.cc), the only code of oxbow that calls MPI: the
// collectives that vocab::Communicator needs over MPI_COMM_WORLD, in C types, so that the binary does not
// link Open MPI (module_loader.h says why). Every function returns MPI's error code (0: MPI_SUCCESS).
#pragma once

#include <cstddef>
#include <cstdint>

namespace oxbow::cli {

// Bumped whenever a member changes: a module of another version is refused.
inline constexpr int kMpiApiVersion = 1;

struct MpiApi {
  int version;
  int (*init)();                      // MPI_Init unless already initialised
  int (*finalize)();
  int (*rank)(int* rank);             // in MPI_COMM_WORLD
  int (*size)(int* size);
  int (*sum_int64)(int64_t* values, int count);  // in place, every rank
  int (*max_double)(double value, double* max);
  int (*broadcast)(uint8_t* bytes, int count);   // from rank 0
  int (*allgather_int)(int mine, int* all);      // all[r] = rank r's value
  int (*allgatherv_bytes)(const uint8_t* mine, int count, uint8_t* all, const int* counts, const int* offsets);
  void (*abort)(int exit_code);       // MPI_Abort: ends every rank
};

// The module's exported function: its table, or nullptr when `version` is not its own.
using MpiApiEntry = const MpiApi* (*)(int version);
inline constexpr const char* kMpiApiEntry = "oxbow_mpi_api";

}  // namespace oxbow::cli
