// The collective operations distributed training and indexing need, as an interface, so that vocab/
// and the libraries above it stay free of MPI: the `oxbow` CLI implements it over MPI
// (server/cli/mpi_communicator.h), SingleProcess below is the one-rank case.
//
// Contract (as MPI collectives): every rank calls the same operations in the same order with the
// arguments described; a call returns when its result is complete on this rank. A failure inside
// an implementation ends the whole job (MPI is fail-stop), so the methods return no errors.
// Not thread-safe: one thread per rank talks to the communicator.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

namespace oxbow::vocab {

class Communicator {
 public:
  virtual ~Communicator() = default;
  virtual int rank() const = 0;  // 0 .. size() - 1
  virtual int size() const = 0;  // number of ranks, >= 1
  // Element-wise sum over all ranks, in place (every rank passes the same length). Integer sums are
  // exact and independent of the reduction order, which is what makes the results rank-count free.
  virtual void SumInPlace(std::span<int64_t> values) = 0;
  // The largest of the ranks' values.
  virtual double Max(double value) = 0;
  // Rank 0's bytes into every rank's `bytes` (every rank passes the same length).
  virtual void Broadcast(std::span<uint8_t> bytes) = 0;
  // Every rank's bytes (any length, up to 2 GiB in all), concatenated in rank order, on every rank.
  virtual std::vector<uint8_t> Allgather(std::span<const uint8_t> bytes) = 0;
};

// One rank: every collective is the identity.
class SingleProcess final : public Communicator {
 public:
  int rank() const override { return 0; }
  int size() const override { return 1; }
  void SumInPlace(std::span<int64_t>) override {}
  double Max(double value) override { return value; }
  void Broadcast(std::span<uint8_t>) override {}
  std::vector<uint8_t> Allgather(std::span<const uint8_t> bytes) override { return {bytes.begin(), bytes.end()}; }
};

}  // namespace oxbow::vocab
