// vocab::Communicator over MPI (MPI_COMM_WORLD), for `--mpi` commands. MPI is initialised on first use
// only, so commands without --mpi never touch it; started without mpirun, MPI runs as a singleton
// (one rank). The only file of the CLI that includes <mpi.h>.
#pragma once

#include <functional>
#include <memory>

#include "vocab/communicator.h"

namespace oxbow::cli {

// Initialises MPI (once per process), runs `body` with the world communicator, finalises MPI. A
// CommandError or any other exception on one rank is printed with the rank number and ends the whole
// job (MPI_Abort with the command's exit code): the other ranks would otherwise wait forever in a
// collective. Ranks other than 0 log warnings and errors only.
void RunWithMpi(const std::function<void(vocab::Communicator&)>& body);

}  // namespace oxbow::cli
