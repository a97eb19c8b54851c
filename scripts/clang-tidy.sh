#!/usr/bin/env bash
# Runs clang-tidy (profile: .clang-tidy, warnings as errors) over every oxbow source file.
#   scripts/clang-tidy.sh [BUILD_DIR] [FILE_REGEX]
# BUILD_DIR holds compile_commands.json (configured here if missing; default build-tidy). FILE_REGEX
# narrows the files (default: every .cc of the modules and tests). Files run $OXBOW_JOBS (default nproc)
# at a time, each under a time limit of $OXBOW_TIDY_FILE_TIMEOUT seconds (default 600; a file that
# exceeds it is analysed once more, and a second timeout fails the run, so a pathological analysis
# cannot stall CI). Prints every finding, the
# slowest files and the total; exit 0 only when every file is clean. Per-file output: BUILD_DIR/clang-tidy/.
#
# Files analysed clean before with exactly the same input are not analysed again. A file's key is the
# SHA-256 of: clang-tidy's version, .clang-tidy, this script's check options, the file's compile command,
# and its whole translation unit as clang 16 preprocesses it with that command (every header it
# includes, comments kept so NOLINT markers count, line markers kept), with the checkout's path replaced
# by a placeholder so clones anywhere share keys. .ci/clang-tidy-clean.txt lists the keys of clean
# files ($OXBOW_TIDY_LEDGER overrides it; "none" disables the ledger). A file whose key is listed is
# reported as unchanged; any other file is analysed. Every run writes the keys of its clean files to
# BUILD_DIR/clang-tidy/clean-ledger.txt; OXBOW_TIDY_LEDGER_UPDATE=1 also copies it over the ledger
# (commit it with the change that was analysed). The ledger only saves time: without it, or with a
# stale one, every changed file is analysed as before. Its keys are those of build-asan's compile
# commands, the folder CI's tidy phase analyses (scripts/test-hardening.sh): an update from any other
# folder is refused, since none of its keys would match there (CI would analyse every file, about 20
# minutes on 2 cores).
#
# oxbow is C++23 built with GCC 12; clang-tidy 16 parses it as C++2b. libstdc++ 12 only declares
# std::expected when __cpp_concepts >= 202002L, which clang 16 implements (P0848, conditionally trivial
# special members) but still advertises as 201907L, so the macro is raised (-U then -D, which warns
# about nothing) for the analysis only.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${1:-$root/build-tidy}
files_regex=${2:-"^$root/(sift|vocab|index|api|server|eval|tests)/.*\\.cc\$"}
if [[ "${OXBOW_TIDY_LEDGER_UPDATE:-0}" == 1 && "$(realpath -m "$build_dir")" != "$(realpath -m "$root/build-asan")" ]]; then
  echo "clang-tidy.sh: OXBOW_TIDY_LEDGER_UPDATE=1 needs BUILD_DIR $root/build-asan (CI's tidy phase keys files by" \
       "its compile commands), not $build_dir: OXBOW_HARDENING_PHASES=tidy OXBOW_TIDY_LEDGER_UPDATE=1 scripts/test-hardening.sh" >&2
  exit 2
fi
tidy=$(command -v clang-tidy-16 || true)
if [[ -z "$tidy" ]]; then
  echo "clang-tidy.sh: clang-tidy-16 not found (scripts/install-deps.sh installs it)" >&2
  exit 1
fi
if [[ ! -f "$build_dir/compile_commands.json" ]]; then
  cmake -S "$root" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=Release -DOXBOW_UNITY_BUILD=OFF >/dev/null
fi
if grep -q '/Unity/unity_' "$build_dir/compile_commands.json"; then
  echo "clang-tidy.sh: $build_dir is a unity build: its compile database names unity files, not the sources;" \
       "configure it with -DOXBOW_UNITY_BUILD=OFF" >&2
  exit 2
fi
# Sources that include generated headers (server/cluster: shard.proto's) need them in the build tree.
cmake --build "$build_dir" --target oxbow_generated_sources >/dev/null
out=$build_dir/clang-tidy
rm -rf "$out" && mkdir -p "$out"
# Each selected file, and beside it (in $out/<path with / as _>.pp) the command that preprocesses it as
# the analysis sees it: its compile command run by clang++-16 with -E -C, without -c and -o.
mapfile -t files < <(python3 - "$build_dir/compile_commands.json" "$files_regex" "$out" <<'EOF'
import json, os, re, shlex, sys
entries = json.load(open(sys.argv[1]))
pattern = re.compile(sys.argv[2])
selected = {}
for e in entries:
    path = os.path.normpath(os.path.join(e["directory"], e["file"]))
    if pattern.search(path):
        selected[path] = e
for path in sorted(selected):
    e = selected[path]
    args = shlex.split(e["command"]) if "command" in e else list(e["arguments"])
    pp, skip = ["clang++-16"], False
    for a in args[1:]:
        if skip:
            skip = False
        elif a == "-o":
            skip = True
        elif a != "-c":
            pp.append(a)
    pp += ["-E", "-C", "-o", "-"]
    with open(os.path.join(sys.argv[3], path.replace("/", "_") + ".pp"), "w") as f:
        f.write("cd " + shlex.quote(e["directory"]) + " && " + shlex.join(pp) + "\n")
    print(path)
EOF
)
if [[ ${#files[@]} -eq 0 ]]; then
  echo "clang-tidy.sh: no file of $build_dir/compile_commands.json matches $files_regex" >&2
  exit 1
fi
ledger=${OXBOW_TIDY_LEDGER:-$root/.ci/clang-tidy-clean.txt}
[[ "$ledger" == none || -f "$ledger" ]] || ledger=none
# What every key starts with: the analyser, its profile, and this script's check options below.
tidy_context=$({ "$tidy" --version; cat "$root/.clang-tidy"; sed -n '/^check_one() {/,/^}/p' "$0"; } | sha256sum | cut -d' ' -f1)
export tidy build_dir out root ledger tidy_context
export limit=${OXBOW_TIDY_FILE_TIMEOUT:-600}
# One file: its findings go to $out/<n>.log, its line "seconds status path" to $out/<n>.time.
# GoogleTest files (*_test.cc) get every check but two:
#  - bugprone-unchecked-optional-access: its dataflow analysis does not see that ASSERT_TRUE(opt)
#    returns when opt is empty, so every access after such an assertion is reported
#    (llvm/llvm-project#181737, fixed only in releases much later than Debian 12's 16);
#  - clang-analyzer-* (the static analyser): two thirds of clang-tidy's time per file; what it looks
#    for (null dereferences, use after free, leaks) the asan phase checks while running every test.
# Both still check all non-test code (the modules, the server, the benchmarks, the fuzz targets).
check_one() {
  local n=$1 file=$2 start status=0 extra=() pp key
  if [[ $file == *_test.cc ]]; then extra=(--checks=-bugprone-unchecked-optional-access,-clang-analyzer-*); fi
  start=$(date +%s%N)
  pp=$(cat "$out/${file//\//_}.pp")
  # The key (see the top of this file); a failed preprocessing gives a key no ledger holds.
  key=$({ echo "$tidy_context ${extra[*]}"; echo "$pp";
          bash -c "$pp -std=c++2b -U__cpp_concepts -D__cpp_concepts=202002L -Wno-builtin-macro-redefined \
                   -Wno-unknown-warning-option -w" 2>&1 || echo "preprocessing failed $(date +%s%N)"; } |
        sed "s|$root|@ROOT@|g" | sha256sum | cut -d' ' -f1)
  if [[ "$ledger" != none ]] && grep -q "^$key " "$ledger"; then
    echo "$key ${file#"$root"/}" >"$out/$n.key"
    printf '%6.1f %3d %s (unchanged since a clean analysis)\n' "$(( ($(date +%s%N) - start) / 1000000 ))e-3" 0 "$file" >"$out/$n.time"
    : >"$out/$n.log"
    return
  fi
  timeout "$limit" "$tidy" -p "$build_dir" --quiet "${extra[@]}" --extra-arg=-std=c++2b --extra-arg=-U__cpp_concepts \
    --extra-arg=-D__cpp_concepts=202002L --extra-arg=-Wno-builtin-macro-redefined \
    --extra-arg=-Wno-unknown-warning-option "$file" >"$out/$n.log" 2>&1 || status=$?
  if [[ $status -eq 124 ]]; then echo "$file: error: clang-tidy took over $limit s (OXBOW_TIDY_FILE_TIMEOUT)" >>"$out/$n.log"; fi
  printf '%6.1f %3d %s\n' "$(( ($(date +%s%N) - start) / 1000000 ))e-3" "$status" "$file" >"$out/$n.time"
  if [[ $status -eq 0 ]]; then echo "$key ${file#"$root"/}" >"$out/$n.key"; fi
}
export -f check_one
# Stopping this script (Ctrl-C, or a TERM sent to it alone, as a caller's time limit does) stops the
# analyses it started: xargs does not pass a signal on to its workers. The workers run in the
# background so that the trap runs at once, not when they have all finished.
descendants() {  # the PIDs below $1, each parent before its children (from /proc: procps may be absent)
  local -A children=()
  local stat line rest pid ppid child queue=("$1")
  for stat in /proc/[0-9]*/stat; do
    read -r line 2>/dev/null <"$stat" || continue
    pid=${line%% *}
    rest=${line##*) }
    ppid=${rest#* }
    ppid=${ppid%% *}
    children[$ppid]+="$pid "
  done
  while ((${#queue[@]})); do
    pid=${queue[0]}
    queue=("${queue[@]:1}")
    for child in ${children[$pid]:-}; do
      echo "$child"
      queue+=("$child")
    done
  done
}
stop_workers() {
  trap - INT TERM
  local pids
  pids=$(descendants $$)
  # shellcheck disable=SC2086  # one PID per word
  if [[ -n $pids ]]; then kill -TERM $pids 2>/dev/null || true; fi
  echo "clang-tidy.sh: stopped; the analyses it had started were stopped too" >&2
  exit 130
}
trap stop_workers INT TERM
start=$(date +%s)
for i in "${!files[@]}"; do printf '%s\0%s\0' "$i" "${files[$i]}"; done |
  xargs -0 -n 2 -P "${OXBOW_JOBS:-$(nproc)}" bash -c 'check_one "$1" "$2"' _ &
wait $!
# clang-tidy 16's bugprone-unchecked-optional-access can spin in its SAT solver for far longer than the
# limit on a file that another run of the same command analyses in seconds: the order of the solver's
# work follows heap addresses, which differ from run to run (llvm/llvm-project#69298, fixed in 17). A
# file that ran out of time is analysed once more; a second timeout fails the run as before.
for t in "$out"/*.time; do
  read -r _ status file <"$t"
  if [[ $status -eq 124 ]]; then
    echo "clang-tidy.sh: $file took over $limit s; analysing it once more (llvm/llvm-project#69298)" >&2
    check_one "$(basename "$t" .time)" "$file"
  fi
done
cat "$out"/*.log | grep -E "(warning|error): " | sort -u || true
failed=$(cat "$out"/*.time | awk '$2 != 0' | wc -l)
unchanged=$(cat "$out"/*.time | grep -c "unchanged since a clean analysis" || true)
cat "$out"/*.key 2>/dev/null | sort >"$out/clean-ledger.txt" || true
if [[ "${OXBOW_TIDY_LEDGER_UPDATE:-0}" == 1 ]]; then
  # This run's files get this run's keys (none when not clean); the other files' lines stay while the
  # file is still in the tree.
  printf '%s\n' "${files[@]#"$root"/}" >"$out/run-files.txt"
  touch "$root/.ci/clang-tidy-clean.txt"
  { awk 'NR == FNR { run[$0] = 1; next } !($2 in run)' "$out/run-files.txt" "$root/.ci/clang-tidy-clean.txt" |
      while read -r key file; do
        if [[ -e "$root/$file" ]]; then printf '%s %s\n' "$key" "$file"; fi
      done
    cat "$out/clean-ledger.txt"; } | sort -k2 >"$out/ledger.new"
  mv "$out/ledger.new" "$root/.ci/clang-tidy-clean.txt"
  echo "clang-tidy.sh: .ci/clang-tidy-clean.txt now lists $(wc -l <"$root/.ci/clang-tidy-clean.txt") clean files ($(wc -l <"$out/clean-ledger.txt") of this run's ${#files[@]})"
fi
echo "clang-tidy.sh: slowest files analysed (s, exit status):"
cat "$out"/*.time | grep -v "unchanged since a clean analysis" | sort -rn | head -5 | sed 's/^/  /' || true
echo "clang-tidy.sh: ${#files[@]} files: $(( ${#files[@]} - unchanged )) analysed, $unchanged unchanged since a clean analysis ($([[ "$ledger" == none ]] && echo "no ledger" || echo "${ledger#"$root"/}")), $failed with findings, $(( $(date +%s) - start )) s wall (load average $(cut -d' ' -f1-3 /proc/loadavg)); per-file output in $out/"
[[ $failed -eq 0 ]]
