#!/usr/bin/env bash
# One extraction as a whole process, as a user runs it: `oxbow extract --threads 1 --format colmap` at
# cv::SIFT's contrast threshold (--contrast-threshold 0.04; oxbow's default is 0.034) on one image
# against cv_sift_extract (OpenCV's SIFT with its defaults on one thread, same output format), in turn,
# each from a fresh process; and `oxbow --version` alone, the cost of starting the binary.
#   eval/bench/extract_process.sh [--reps N] [--build DIR] IMAGE...
# For each image: the median CPU time (user + system) and wall time of each over N pairs (default 11),
# and the median of the pairs' CPU ratios oxbow / cv::SIFT (pair by pair, so that a drift of the
# machine's speed cancels). Times with the shell's own clock of the finished child (`times`).
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
reps=11
build=$root/build
images=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --reps) reps=$2; shift 2 ;;
    --build) build=$2; shift 2 ;;
    -h|--help) sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) images+=("$1"); shift ;;
  esac
done
[[ ${#images[@]} -gt 0 ]] || { echo "extract_process.sh: give one or more images (--help)" >&2; exit 2; }
oxbow=$build/server/oxbow
oxbow_extract=(extract --threads 1 --contrast-threshold 0.04 --format colmap)  # the same settings as the peer's
peer=$build/eval/bench/cv_sift_extract
for b in "$oxbow" "$peer"; do [[ -x $b ]] || { echo "extract_process.sh: $b is not built (cmake --build $build)" >&2; exit 2; }; done
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# Runs the command N times; prints "cpu_seconds wall_seconds" per run (children's user + system time).
measure() {
  python3 - "$@" <<'PY'
import os, subprocess, sys, time
cmd = sys.argv[1:]
t0 = time.perf_counter()
before = os.times()
subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
after = os.times()
wall = time.perf_counter() - t0
cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
print(f"{cpu:.4f} {wall:.4f}")
PY
}
median() { sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

printf '%-28s %10s %10s %10s %10s %12s\n' image "oxbow cpu" "wall" "cv cpu" "wall" "cpu ratio"
for image in "${images[@]}"; do
  name=$(basename "$image")
  "$oxbow" "${oxbow_extract[@]}" --out "$work/o" "$image" >/dev/null 2>&1  # warm the page cache
  "$peer" "$image" "$work/p.txt"
  : >"$work/rows"
  for ((i = 0; i < reps; ++i)); do
    o=$(measure "$oxbow" "${oxbow_extract[@]}" --out "$work/o" "$image")
    p=$(measure "$peer" "$image" "$work/p.txt")
    echo "$o $p" >>"$work/rows"
  done
  printf '%-28s %9.1fms %9.1fms %9.1fms %9.1fms %12.3f\n' "$name" \
    "$(awk '{ print $1 * 1000 }' "$work/rows" | median)" "$(awk '{ print $2 * 1000 }' "$work/rows" | median)" \
    "$(awk '{ print $3 * 1000 }' "$work/rows" | median)" "$(awk '{ print $4 * 1000 }' "$work/rows" | median)" \
    "$(awk '{ print $1 / $3 }' "$work/rows" | median)"
done
: >"$work/version"
for ((i = 0; i < reps; ++i)); do measure "$oxbow" --version >>"$work/version"; done
printf 'oxbow --version: cpu %.1f ms, wall %.1f ms (medians of %d)\n' "$(awk '{ print $1 * 1000 }' "$work/version" | median)" \
  "$(awk '{ print $2 * 1000 }' "$work/version" | median)" "$reps"
