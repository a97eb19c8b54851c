#!/usr/bin/env bash
# oxbow in one command: install, build, train a small vocabulary, index a bundled photo collection,
# start the HTTP server and answer a real query. The vocabulary and index are cached in a work folder
# (demo-data/, git-ignored), so a second run starts serving in seconds.
#
#   bash scripts/demo.sh                 # opencv-doc sample photos; server stays up (Ctrl-C stops it)
#   bash scripts/demo.sh --no-serve      # stop after showing the query
#   bash scripts/demo.sh --data paris    # the 250-photo Paris subset (../shared/data/paris6k) if present
#   options: --port P (default 8080; 0 = any free port)  --work DIR (default demo-data)  --words K
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
data=opencv
serve=1
port=8080
work="$root/demo-data"
words=""
while [[ $# -gt 0 ]]; do
  case "$1" in
    --data) data="$2"; shift 2 ;;
    --no-serve) serve=0; shift ;;
    --port) port="$2"; shift 2 ;;
    --work) work="$2"; shift 2 ;;
    --words) words="$2"; shift 2 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "demo: unknown option '$1' (see --help)" >&2; exit 2 ;;
  esac
done

say() { printf '\n\033[1m==> %s\033[0m\n' "$*" >&2; }

say "1/5 dependencies (scripts/install-deps.sh)"
"$root/scripts/install-deps.sh"

say "2/5 build (scripts/build.sh)"
build_dir=${OXBOW_BUILD_DIR:-$root/build}
OXBOW_BUILD_DIR="$build_dir" "$root/scripts/build.sh"
oxbow="$build_dir/server/oxbow"
[[ -x "$oxbow" ]] || { echo "demo: $oxbow was not built" >&2; exit 1; }

samples=/usr/share/doc/opencv-doc/examples/data
paris="$root/../shared/data/paris6k"
case "$data" in
  opencv)
    # The photos of Debian's opencv-doc package. box.png, graf1.png and leuvenA.jpg are kept out of
    # the index: they are the queries whose other views (box_in_scene, graf3, leuvenB) are indexed.
    photos=(box_in_scene.png graf3.png leuvenB.jpg aero1.jpg aero3.jpg aloeL.jpg apple.jpg baboon.jpg
            basketball1.png blox.jpg board.jpg building.jpg butterfly.jpg cards.png fruits.jpg home.jpg
            left01.jpg left07.jpg messi5.jpg orange.jpg pic1.png pic3.png rubberwhale1.png smarties.png
            starry_night.jpg stuff.jpg sudoku.png Blender_Suzanne1.jpg HappyFish.jpg
            ela_original.jpg licenseplate_motion.jpg notes.png)
    default_words=1000
    query="$samples/box.png"
    query_params="top_k=5"
    expect="box_in_scene"
    ;;
  paris)
    [[ -d "$paris/images" ]] || { echo "demo: no Paris subset at $paris (use --data opencv)" >&2; exit 2; }
    default_words=8000
    query="$paris/images/paris_defense_000056.jpg"
    query_params="top_k=5&bbox=8,104,707,913"   # official query box of Paris6k query defense_4
    expect=""
    ;;
  *) echo "demo: --data must be opencv or paris" >&2; exit 2 ;;
esac
words=${words:-$default_words}
dir="$work/$data-$words"
mkdir -p "$dir"
list="$dir/images.txt"
if [[ "$data" == opencv ]]; then
  : > "$list"
  for p in "${photos[@]}"; do [[ -f "$samples/$p" ]] && echo "$samples/$p" >> "$list"; done
else
  find "$paris/images" -name '*.jpg' | sort > "$list"
fi
echo "demo: $(wc -l < "$list") photos ($data), vocabulary of $words words, work folder $dir" >&2

say "3/5 vocabulary (oxbow vocab train; cached)"
if [[ ! -f "$dir/vocab.oxvoc" ]]; then
  "$oxbow" vocab train --list "$list" --words "$words" --out "$dir/vocab.oxvoc"
else
  echo "demo: using cached $dir/vocab.oxvoc" >&2
fi

say "4/5 index (oxbow index build; resumable)"
"$oxbow" index build --vocab "$dir/vocab.oxvoc" --list "$list" --out "$dir/index"

say "5/5 server (oxbow serve) and a query"
log="$dir/serve.log"
fifo="$dir/serve.stdout"
rm -f "$fifo"
mkfifo "$fifo"
"$oxbow" serve --index "$dir/index" --port "$port" > "$fifo" 2> >(tee -a "$log" >&2) &
server_pid=$!
stop_server() { kill -TERM "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; rm -f "$fifo"; }
trap stop_server EXIT
trap 'echo; echo "demo: stopping the server" >&2; exit 0' INT TERM
exec 3< "$fifo"
url=""
while IFS= read -r -t 60 line <&3; do
  echo "$line"
  if [[ "$line" =~ listening\ on\ (http://[^[:space:]]+) ]]; then url="${BASH_REMATCH[1]}"; break; fi
done
[[ -n "$url" ]] || { echo "demo: the server did not start (port $port in use? try --port 0); see $log" >&2; exit 1; }
cat <&3 >/dev/null &   # keep draining the server's stdout
for _ in $(seq 1 600); do
  curl -fsS "$url/readyz" >/dev/null 2>&1 && break
  sleep 0.1
done
curl -fsS "$url/readyz" >/dev/null || { echo "demo: the server did not become ready; see $log" >&2; exit 1; }

command=(curl -sS --data-binary "@$query" -H 'Content-Type: application/octet-stream' "$url/v1/search?$query_params")
shown="curl -sS --data-binary @$query -H 'Content-Type: application/octet-stream' '$url/v1/search?$query_params'"
echo >&2
echo "demo: query: $shown" >&2
response=$("${command[@]}")
python3 - "$response" "$expect" "$(basename "$query")" <<'PY'
import json, sys
body = json.loads(sys.argv[1]); expect = sys.argv[2]; query = sys.argv[3]
if "error" in body:
    print("error:", body["error"]); sys.exit(1)
t = body["timings_ms"]
print(f"\nquery {query}: {body['query']['features']} features, {body['candidates']} candidate images, "
      f"{t['total']:.0f} ms (decode+extract {t['decode_extract']:.0f}, quantise {t['quantize']:.1f}, "
      f"score {t['score']:.1f}, verify {t['verify']:.1f}, qe {t['qe']:.1f})")
print(f"{'rank':>4}  {'id':<28} {'score':>7} {'inliers':>7}  verified  region in the result image")
for r in body["results"]:
    region = ",".join(f"{v:.0f}" for v in r["region"]) if r["region"] else "-"
    print(f"{r['rank']:>4}  {r['id']:<28} {r['score']:7.3f} {r['inliers']:7d}  {'yes' if r['verified'] else 'no':<8}  {region}")
if expect:
    first = body["results"][0]["id"] if body["results"] else None
    print(f"\n{'OK' if first == expect else 'UNEXPECTED'}: first result is {first!r} (expected {expect!r})")
    sys.exit(0 if first == expect else 1)
PY

cat >&2 <<HINTS

Try it yourself: open $url/ in a browser (the search page), or
  $shown
  curl -s '$url/v1/images?limit=5'
  curl -s '$url/v1/images/$( [[ $data == opencv ]] && echo graf3 || echo paris_eiffel_000266 )/similar?top_k=3'
  curl -s $url/v1/stats
HINTS
if [[ "$serve" == 0 ]]; then
  echo "demo: --no-serve: stopping the server" >&2
  exit 0
fi
echo "demo: the server runs at $url (search page: $url/; log: $log); Ctrl-C stops it" >&2
wait "$server_pid"
