#!/usr/bin/env bash
# The duplicate benchmark end to end: generate it, index it with oxbow, run `oxbow index duplicates`,
# run the peers (findimagedupes, dupeGuru's picture mode, a perceptual hash) and score them side by side.
#
#   eval/duplicates/run.sh --oxbow build/server/oxbow --vocab V.oxvoc --work DIR
#   options: --data DIR (default ../shared/data)  --seed N (1)  --threads N (0 = all cores)
#            --storage-index DIR   also time `oxbow index duplicates` on that index folder (the 100k-image
#                                  storage benchmark folder: build/eval/bench/index_benchmark storage ...)
#            --duplicates-args "..."  extra arguments for `oxbow index duplicates`
#            --skip-oxbow (scores DIR/oxbow.json when present)  --skip-peers (scores DIR/peers/ when present)
#            --fresh (delete DIR's benchmark, index and results first)
# DIR must be outside the repository. A second run reuses DIR's images, truth.json and index (the index
# build is resumable). Writes DIR/report.md, DIR/scores.json and DIR/timings.tsv (wall and CPU seconds,
# peak memory per step). Exit status 3 when an oxbow step failed (the peers are still run and scored).
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
root=$(realpath "$here/../..")
py=${PYTHON:-/usr/bin/python3}   # Debian's python3, which has python3-pil and python3-numpy
oxbow="" vocab="" work="" data="$root/../shared/data" seed=1 threads=0 storage="" dup_args=""
skip_oxbow=0 skip_peers=0 fresh=0
while [[ $# -gt 0 ]]; do
  case "$1" in
    --oxbow) oxbow="$2"; shift 2 ;;
    --vocab) vocab="$2"; shift 2 ;;
    --work) work="$2"; shift 2 ;;
    --data) data="$2"; shift 2 ;;
    --seed) seed="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --storage-index) storage="$2"; shift 2 ;;
    --duplicates-args) dup_args="$2"; shift 2 ;;
    --skip-oxbow) skip_oxbow=1; shift ;;
    --skip-peers) skip_peers=1; shift ;;
    --fresh) fresh=1; shift ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    *) echo "run.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
  esac
done
[[ -n "$work" ]] || { echo "run.sh: --work DIR is required" >&2; exit 2; }
if [[ $skip_oxbow -eq 0 ]]; then
  [[ -x "$oxbow" ]] || { echo "run.sh: --oxbow BINARY is required (or --skip-oxbow)" >&2; exit 2; }
  [[ -f "$vocab" ]] || { echo "run.sh: --vocab FILE is required (or --skip-oxbow)" >&2; exit 2; }
  oxbow=$(cd "$(dirname "$oxbow")" && pwd)/$(basename "$oxbow")
fi
work=$(realpath -m "$work")
case "$work/" in "$root"/*) echo "run.sh: --work must be outside the repository" >&2; exit 2 ;; esac
mkdir -p "$work"

say() { printf '\n==> %s\n' "$*" >&2; }
timings="$work/timings.tsv"
# timed STEP COMMAND...: runs the command under GNU time; appends wall s, CPU s (user + system) and peak
# resident MB to timings.tsv. Returns the command's status.
timed() {
  local step=$1; shift
  local tf="$work/.time-$step" rc=0
  /usr/bin/time -o "$tf" -f '%e %U %S %M' "$@" || rc=$?
  if [[ $rc -eq 0 ]]; then
    tail -n 1 "$tf" | awk -v s="$step" '{ printf "%s\t%.1f\t%.1f\t%.0f\n", s, $1, $2 + $3, $4 / 1024 }' >> "$timings"
    tail -n 1 "$timings" | awk -F '\t' '{ printf "    %s: %s s wall, %s s CPU, %s MB peak\n", $1, $2, $3, $4 }' >&2
  fi
  rm -f "$tf"
  return $rc
}
oxbow_failed=0

if [[ $fresh -eq 1 ]]; then
  rm -rf "$work/images" "$work/truth.json" "$work/index" "$work/peers" "$work/oxbow.json" \
         "$work/report.md" "$work/scores.json" "$work/storage-duplicates.json"
fi
printf 'step\twall_s\tcpu_s\tpeak_rss_mb\n' > "$timings"

if [[ -f "$work/truth.json" ]]; then
  say "benchmark: reusing $work/truth.json ($(find "$work/images" -type f | wc -l) images)"
else
  say "benchmark: generating into $work (seed $seed)"
  timed generate "$py" "$here/make_benchmark.py" --data "$data" --out "$work" --seed "$seed" > "$work/generate.log"
  tail -n 1 "$work/generate.log" >&2
fi
n_images=$(find "$work/images" -type f | wc -l)

results=()
if [[ $skip_oxbow -eq 0 ]]; then
  say "oxbow index build ($n_images images)"
  if timed index_build "$oxbow" index build --vocab "$vocab" --images "$work/images" --out "$work/index" \
       --threads "$threads" > "$work/index-build.json"; then
    "$py" -c 'import json, sys; r = json.load(open(sys.argv[1]))
print("    added %d images (%d already indexed), %.1f images/s" % (r["added"], r["already_indexed"], r["images_per_second"]))' \
      "$work/index-build.json" >&2 2>/dev/null || true
    say "oxbow index duplicates"
    # shellcheck disable=SC2086
    if timed duplicates "$oxbow" index duplicates --index "$work/index" --format json --out "$work/oxbow.json" $dup_args; then
      results+=("oxbow=$work/oxbow.json")
    else
      echo "run.sh: oxbow index duplicates failed; scoring the peers only" >&2; oxbow_failed=1
    fi
  else
    echo "run.sh: oxbow index build failed" >&2; oxbow_failed=1
  fi
fi

if [[ $skip_oxbow -eq 1 && -f "$work/oxbow.json" ]]; then
  echo "run.sh: scoring the existing $work/oxbow.json" >&2
  results+=("oxbow=$work/oxbow.json")
fi
if [[ $skip_peers -eq 0 ]]; then
  say "peers"
  timed peers "$py" "$here/run_peers.py" --images "$work/images" --out "$work/peers"
fi
for p in findimagedupes findimagedupes-pairs dupeguru dupeguru-default phash; do
  if [[ -f "$work/peers/$p.json" ]]; then results+=("$p=$work/peers/$p.json"); fi
done

if [[ ${#results[@]} -gt 0 ]]; then
  say "score"
  timed score "$py" "$here/score.py" --truth "$work/truth.json" --out "$work/report.md" --json "$work/scores.json" \
    "${results[@]}"
fi

if [[ -n "$storage" && $skip_oxbow -eq 0 ]]; then
  say "oxbow index duplicates on $storage"
  # shellcheck disable=SC2086
  if ! timed storage_duplicates "$oxbow" index duplicates --index "$storage" --format json \
       --out "$work/storage-duplicates.json" $dup_args; then
    echo "run.sh: oxbow index duplicates failed on $storage" >&2; oxbow_failed=1
  fi
fi

say "timings ($timings)"
column -t -s $'\t' "$timings" >&2
if [[ ${#results[@]} -gt 0 ]]; then echo "report: $work/report.md" >&2; fi
if [[ $oxbow_failed -eq 1 ]]; then exit 3; fi
