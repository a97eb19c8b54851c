#!/usr/bin/env bash
# Bounded load test of `oxbow serve` on loopback: concurrent searches, then the same searches while
# images are being added, for a fixed time each; prints requests, errors, p50/p95/p99 latency per
# route and the ratio of search p99 during adds to idle (target: at most 2x, zero errors).
# Runs on a throw-away copy of the demo index (scripts/demo.sh builds it on first use).
#
#   bash scripts/load_test.sh [--seconds 20] [--search-clients 2] [--similar-clients 2] [--add-clients 1]
#                             [--http-workers 8] [--json out.json] [--serve-arg FLAG]...
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${OXBOW_BUILD_DIR:-$root/build}
oxbow="$build_dir/server/oxbow"
work="$root/demo-data"
threads=8
client_args=()
serve_args=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --http-workers) threads="$2"; shift 2 ;;   # oxbow serve --http-workers
    --serve-arg) serve_args+=("$2"); shift 2 ;;   # extra `oxbow serve` flag, e.g. --serve-arg=--add-nice --serve-arg=0
    --work) work="$2"; shift 2 ;;
    --seconds|--search-clients|--similar-clients|--add-clients|--json|--top-k) client_args+=("$1" "$2"); shift 2 ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) echo "load_test: unknown option '$1'" >&2; exit 2 ;;
  esac
done

index_src="$work/opencv-1000/index"
if [[ ! -x "$oxbow" || ! -d "$index_src" ]]; then
  echo "load_test: building the demo index first (scripts/demo.sh --no-serve)" >&2
  OXBOW_BUILD_DIR="$build_dir" bash "$root/scripts/demo.sh" --no-serve --port 0 --work "$work"
fi

tmp=$(mktemp -d /tmp/oxbow-load-XXXXXX)
cp -r "$index_src" "$tmp/index"
samples=/usr/share/doc/opencv-doc/examples/data
"$oxbow" serve --index "$tmp/index" --host 127.0.0.1 --port 0 --http-workers "$threads" "${serve_args[@]}" > "$tmp/stdout" 2> "$tmp/serve.log" &
pid=$!
cleanup() { kill -TERM "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true; rm -rf "$tmp"; }
trap cleanup EXIT
port=""
for _ in $(seq 1 300); do
  port=$(sed -n 's|^listening on http://127.0.0.1:\([0-9]*\).*|\1|p' "$tmp/stdout")
  [[ -n "$port" ]] && curl -fsS "http://127.0.0.1:$port/readyz" >/dev/null 2>&1 && break
  sleep 0.1
done
[[ -n "$port" ]] || { echo "load_test: server did not start"; cat "$tmp/serve.log"; exit 1; }
echo "load_test: server on 127.0.0.1:$port ($threads workers ${serve_args[*]}), index copy $tmp/index, $(nproc) CPU cores" >&2

python3 "$root/scripts/load_client.py" --port "$port" "${client_args[@]}" \
  --query "$samples/box.png" --query "$samples/graf1.png" --query "$samples/leuvenA.jpg" \
  --add "$samples/box_in_scene.png" --add "$samples/graf3.png" --add "$samples/leuvenB.jpg" --add "$samples/home.jpg"
status=$?
echo "load_test: server log lines: $(wc -l < "$tmp/serve.log"); 503s: $(grep -c 'status=503' "$tmp/serve.log" || true)" >&2
exit $status
