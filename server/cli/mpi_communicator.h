// vocab::Communicator over MPI (MPI_COMM_WORLD), for `--mpi` commands. MPI is initialised on first use
// only, so commands without --mpi never touch it; started without mpirun, MPI runs as a singleton
// (one rank). MPI itself is in the module liboxbow_mpi.so (modules/mpi_api.h), loaded on first use.
#pragma once

#include <functional>
#include <memory>
#include <optional>

#include "server/cli/cli.h"
#include "vocab/communicator.h"

namespace oxbow::cli {

// Initialises MPI (once per process), runs `body` with the world communicator, finalises MPI. A
// CommandError or any other exception on one rank is printed with the rank number and ends the whole
// job (MPI_Abort with the command's exit code): the other ranks would otherwise wait forever in a
// collective. Ranks other than 0 log warnings and errors only.
// An agreed refusal (ThrowIfAnyRankRefuses) is
// different: every rank knows it, rank 0 alone prints it, and every rank finalises MPI and exits with its
// code, so the message does not depend on which rank aborted first.
void RunWithMpi(const std::function<void(vocab::Communicator&)>& body);

// Collective: every rank passes its own refusal, or none. When any rank has one, every rank throws the
// refusal of the lowest such rank (as an agreed refusal, see RunWithMpi); otherwise returns. For checks
// made before any work, where different ranks can see different faults of one wrong command line.
void ThrowIfAnyRankRefuses(vocab::Communicator& comm, const std::optional<CommandError>& mine);

}  // namespace oxbow::cli
