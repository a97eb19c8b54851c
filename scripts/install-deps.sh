#!/usr/bin/env bash
# Installs every Debian 12 package oxbow needs to build, test, benchmark and run.
# Used by the README's commands, .ci/run (through scripts/test.sh) and docker/Dockerfile.
# Idempotent: does nothing (and needs no network) when everything is already installed.
#   scripts/install-deps.sh            build + test + benchmark dependencies
#   scripts/install-deps.sh --runtime  only what the `oxbow` binary needs at run time
set -euo pipefail

build_packages=(
  build-essential cmake ninja-build pkg-config git
  lld                    # the linker (CMakeLists.txt, OXBOW_USE_LLD): links every executable about 4x faster than BFD ld
  libopencv-dev          # decode/resize/draw; cv::SIFT only as a reference peer in tests and benchmarks
  libeigen3-dev          # least squares in verification, exact k-means path
  libflann-dev           # randomised kd-forests (matching, approximate k-means)
  libopenmpi-dev openmpi-bin  # `--mpi` in vocab train / index build (mpirun; tests/mpi_test.cc)
  libsqlite3-dev         # the index catalogue
  libssl-dev             # collection keys (api/access_keys.cc): salted SHA-256, random bytes (OpenSSL's libcrypto)
  zlib1g-dev             # CRC-32 of stored files and feature BLOBs (sift/base/binary_io.cc)
  libxxhash-dev          # XXH3 checksums of the index checkpoint files (verified at every open)
  nlohmann-json3-dev     # JSON in the CLI and the HTTP API
  libcli11-dev           # the oxbow CLI
  libcpp-httplib-dev     # the HTTP server
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler  # a cluster's front <-> shard calls
                         # (server/cluster/shard.proto): deadlines, status codes, health checking
  libgtest-dev libgmock-dev
  libjpeg-dev            # sift/image_decoders.cc decodes JPEG with libjpeg (damage, scan limit); tests: a CMYK JPEG fixture
  libpng-dev             # sift/image_decoders.cc decodes PNG with libpng
  libtiff-dev            # sift/image.cc checks TIFF data with libtiff (damage, the dimensions libtiff decodes)
  opencv-doc             # sample photos (graf, box, ...) used as test and demo data
  libvlfeat-dev          # VLFeat SIFT: benchmark peer only
  libfaiss-dev           # faiss: benchmark peer only
  curl python3           # demo and evaluation scripts
  openssl                # tests/cluster_security_test.cc makes the TLS certificates of its shards
  python3-jsonschema     # tests/openapi_check.py validates every response against server/http/openapi.json
  python3-venv           # api/python/packaging_test.py installs the Python client into a fresh `python3 -m venv`
                         # (pip comes from python3-pip-whl, offline)
  python3-pil python3-numpy  # eval/duplicates: the duplicate benchmark's generator, scorer and perceptual-hash peer
  findimagedupes         # eval/duplicates: peer of `oxbow index duplicates` (GraphicsMagick fingerprints, Hamming threshold)
  dupeguru               # eval/duplicates: peer of `oxbow index duplicates` (its picture mode's engine, run headless)
  fonts-dejavu-core      # eval/duplicates: the fonts of the benchmark's captions, logo and screenshot frames
  chromium nodejs        # the web page's end-to-end test (tests/browser: playwright-core drives /usr/bin/chromium)
  libclang-rt-14-dev     # libFuzzer runtime for the fuzz targets (scripts/fuzz.sh; GCC-instrumented, cmake/OxbowFuzz.cmake)
  clang-tidy-16          # static checks (scripts/clang-tidy.sh): the first Debian 12 clang-tidy that parses libstdc++ 12's <expected>
  clang-16               # clang++-16 -E: the preprocessed input that keys scripts/clang-tidy.sh's ledger (clang-tidy-16 pulls it in too)
  libomp-16-dev          # <omp.h> for clang-tidy 16 (faiss's headers include it; GCC's copy does not parse with clang)
  help2man               # the Debian package's man pages, from `oxbow ... --help` (cmake/packaging/make-manpages.sh)
  lintian                # checks the Debian package (scripts/package-test.sh); dpkg-shlibdeps, which computes its
                         # Depends, is in dpkg-dev (from build-essential)
  systemd                # systemd-analyze verify/security on oxbow.service (scripts/package-test.sh)
)
runtime_packages=(
  libopencv-core406 libopencv-imgproc406 libopencv-imgcodecs406 libopencv-features2d406 libopencv-calib3d406
  libopencv-flann406 libflann1.9 libopenmpi3 libsqlite3-0 libcpp-httplib0.11 libgrpc++1.51 libprotobuf32 libjpeg62-turbo libpng16-16 libtiff6 libssl3 curl ca-certificates
)

packages=("${build_packages[@]}")
if [[ "${1:-}" == "--runtime" ]]; then packages=("${runtime_packages[@]}"); fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
# npm (tests/browser): Debian's nodejs leaves it to the npm package; NodeSource's nodejs carries its own.
if [[ "${1:-}" != "--runtime" ]] && ! command -v npm >/dev/null 2>&1; then missing+=(npm); fi
if [[ ${#missing[@]} -eq 0 ]]; then
  echo "install-deps: all ${#packages[@]} packages present" >&2
  exit 0
fi

sudo_cmd=()
if [[ $(id -u) -ne 0 ]]; then sudo_cmd=(sudo); fi
echo "install-deps: installing ${missing[*]}" >&2
"${sudo_cmd[@]}" apt-get update -qq
DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"
