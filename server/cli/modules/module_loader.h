// The run-time modules of the `oxbow` binary: code whose libraries are loaded only by the commands that
// use them, so that every other command starts without them.
//
//   liboxbow_mpi.so      `--mpi` (vocab train, index build): Open MPI (mpi_module.cc, behind mpi_api.h)
//   liboxbow_cluster.so  `serve --cluster` and `serve --grpc-port`: gRPC, protobuf and the cluster code
//                        (cluster_module.cc, behind cluster_api.h)
//
// Linked into the binary, Open MPI and gRPC with abseil and protobuf are about 55 shared libraries that
// every process loads and relocates before main. A module is found in OXBOW_MODULE_DIR when that is set,
// else in <folder of the running binary>/../lib/oxbow/: build/lib/oxbow/ for build/server/oxbow,
// /usr/lib/oxbow/ for the Debian package's /usr/bin/oxbow.
#pragma once

#include <string>

#include "sift/base/error.h"

namespace oxbow::cli {

// dlopen()s module `name` (the file lib<name>.so) once per process and returns the address of its
// exported C function `entry`. kNotFound (naming the path and OXBOW_MODULE_DIR) when the file is missing;
// kIncompatible when it cannot be loaded or lacks the function.
[[nodiscard]] Result<void*> LoadModuleEntry(const std::string& name, const char* entry);

}  // namespace oxbow::cli
