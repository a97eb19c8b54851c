#!/usr/bin/env bash
# Tests the Debian package (server/README.md, "Debian package"); scripts/test.sh runs it after ctest, on the build
# folder it has just built ($OXBOW_BUILD_DIR, default build/):
#   1. cpack -G DEB, and the package holds the files it must (the Python client's module among them, without
#      bytecode);
#   2. lintian: fails on any error or warning (intended tags are overridden, each with its reason, in
#      cmake/packaging/lintian-overrides);
#   3. systemd-analyze verify (no message at all) and security (exposure at most 2.0) on oxbow.service;
#   4. as root (CI) or with passwordless sudo: apt-get install of the .deb; the user, the unit and the
#      settings are there; the installed /usr/bin/oxbow, run as the user oxbow the way server/README.md says,
#      trains a tiny vocabulary, serves /var/lib/oxbow/index (created by the first start), takes images
#      over HTTP and finds box_in_scene for box.png (with curl, and with the installed Python client, which
#      Debian's python3 imports byte-compiled from /usr/lib/python3/dist-packages), and starts a shard's gRPC
#      port (the cluster module in /usr/lib/oxbow); under a running systemd, oxbow.service itself serves
#      it; then apt-get purge, and everything but the user and /var/lib/oxbow (kept on purge, as
#      documented) is gone, the client's bytecode included; the test deletes those two itself.
# Otherwise step 4 is SKIPPED, saying why. It is also skipped on a machine that already has an oxbow
# package, user or /var/lib/oxbow (it would replace and delete them). About 20 s.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${OXBOW_BUILD_DIR:-$root/build}
samples=/usr/share/doc/opencv-doc/examples/data
started=$SECONDS

say() { echo "package-test: $*" >&2; }
journal=0  # 1 while oxbow.service runs: a failure then prints its journal
fail() {
  echo "package-test: FAILED: $*" >&2
  if [[ $journal == 1 ]]; then as_root journalctl -u oxbow.service --no-pager -n 50 >&2 || true; fi
  exit 1
}
work=$(mktemp -d)
chmod 755 "$work"  # the user oxbow reads the image list, _apt the .deb
installed=0
server_pid=
sudo_cmd=()
as_root() { "${sudo_cmd[@]}" "$@"; }
cleanup() {
  if [[ -n $server_pid ]]; then kill "$server_pid" 2>/dev/null || true; fi
  if [[ $installed == 1 ]]; then
    as_root systemctl stop oxbow.service >/dev/null 2>&1 || true
    as_root env DEBIAN_FRONTEND=noninteractive apt-get purge -y -qq oxbow >/dev/null 2>&1 || true
    as_root rm -rf /var/lib/oxbow
    as_root deluser --system --quiet oxbow >/dev/null 2>&1 || true
    as_root delgroup --system --quiet oxbow >/dev/null 2>&1 || true
  fi
  rm -rf "$work"
}
trap cleanup EXIT

# ---- 1. build ----
cd "$build_dir"
rm -f oxbow_*.deb
cpack -G DEB >cpack.log 2>&1 || { cat cpack.log >&2; fail "cpack -G DEB (log above)"; }
debs=(oxbow_*.deb)
[[ ${#debs[@]} -eq 1 && -f ${debs[0]} ]] || fail "expected one oxbow_*.deb in $build_dir, found: ${debs[*]}"
deb=$build_dir/${debs[0]}
version=$(dpkg-deb -f "$deb" Version)
[[ ${debs[0]} == "oxbow_${version}_$(dpkg --print-architecture).deb" ]] || fail "file name ${debs[0]} for version $version"
contents=$(dpkg-deb -c "$deb" | awk '{ print $6 }')
for path in ./usr/bin/oxbow ./lib/systemd/system/oxbow.service ./etc/default/oxbow ./usr/share/doc/oxbow/copyright \
            ./usr/share/doc/oxbow/changelog.gz ./usr/share/man/man1/oxbow.1.gz ./usr/share/man/man1/oxbow-serve.1.gz \
            ./usr/share/man/man1/oxbow-index-build.1.gz ./usr/lib/oxbow/liboxbow_mpi.so ./usr/lib/oxbow/liboxbow_cluster.so \
            ./usr/lib/python3/dist-packages/oxbow_client/__init__.py ./usr/lib/python3/dist-packages/oxbow_client/py.typed \
            "./usr/lib/python3/dist-packages/oxbow_client-$version.dist-info/METADATA"; do
  grep -qx -- "$path" <<<"$contents" || fail "$path missing from $deb"
done
if grep -E '__pycache__|\.pyc$' <<<"$contents"; then fail "the package holds Python bytecode (above): postinst compiles it"; fi
[[ $(dpkg-deb -f "$deb" Suggests) == *python3* ]] || fail "Suggests does not name python3 (the client's module needs it)"
say "built $deb ($(du -k "$deb" | cut -f1) KiB; Depends: $(dpkg-deb -f "$deb" Depends))"

# ---- 2. lintian ----
if ! lintian --fail-on error,warning "$deb" >"$work/lintian.txt" 2>&1; then
  grep -v '^running with root privileges' "$work/lintian.txt" >&2
  fail "lintian reported errors or warnings (above)"
fi
say "lintian: no errors, no warnings"

# ---- 3. the unit, checked before installing: ExecStart pointed at the build's binary ----
dpkg-deb -x "$deb" "$work/root"
sed "s|/usr/bin/oxbow|$build_dir/server/oxbow|" "$work/root/lib/systemd/system/oxbow.service" >"$work/oxbow.service"
verify_unit() {  # verify_unit UNIT [--man=no]: any message (unknown key, bad value, missing binary) fails
  local messages
  messages=$(systemd-analyze verify "${@:2}" "$1" 2>&1) || fail "systemd-analyze verify $1: $messages"
  [[ -z $messages ]] || fail "systemd-analyze verify $1: $messages"
}
verify_unit "$work/oxbow.service" --man=no
systemd-analyze security --offline=yes --threshold=20 "$work/oxbow.service" >"$work/security.txt" 2>&1 \
  || { cat "$work/security.txt" >&2; fail "oxbow.service's exposure is above 2.0 (systemd-analyze security, above)"; }
say "oxbow.service: systemd-analyze verify clean; $(grep -o 'Overall exposure level.*' "$work/security.txt")"

# ---- 4. install, run, purge ----
if [[ $(id -u) -ne 0 ]]; then
  if sudo -n true 2>/dev/null; then
    sudo_cmd=(sudo -n)
  else
    say "SKIPPED install, run and purge: not root and no passwordless sudo (CI runs this as root). $((SECONDS - started)) s"
    exit 0
  fi
fi
if dpkg-query -W -f='${Status}' oxbow 2>/dev/null | grep -q . || getent passwd oxbow >/dev/null || [[ -e /var/lib/oxbow ]]; then
  say "SKIPPED install, run and purge: this machine already has an oxbow package, user or /var/lib/oxbow, which the test would replace and delete. $((SECONDS - started)) s"
  exit 0
fi
# Prefix running a command as the service runs: user and group oxbow, nothing of root's environment.
# (An array, not a function: `"${as_oxbow[@]}" cmd &` leaves $! the server's own pid when root.)
as_oxbow=("${sudo_cmd[@]}" setpriv --reuid=oxbow --regid=oxbow --init-groups env -i PATH=/usr/bin:/bin)

cp "$deb" "$work/"
installed=1
as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$work/${debs[0]}" >"$work/apt.log" 2>&1 \
  || { cat "$work/apt.log" >&2; fail "apt-get install ${debs[0]}"; }
[[ $(dpkg-query -W -f='${Status} ${Version}' oxbow) == "install ok installed $version" ]] || fail "dpkg does not list oxbow $version as installed"
[[ $(command -v oxbow) == /usr/bin/oxbow ]] || fail "oxbow is not /usr/bin/oxbow on PATH"
[[ $(/usr/bin/oxbow --version) == "oxbow $version" ]] || fail "/usr/bin/oxbow --version says '$(/usr/bin/oxbow --version)', the package $version"
IFS=: read -r _ _ uid _ _ home shell < <(getent passwd oxbow) || fail "no user oxbow after install"
[[ $uid -lt 1000 && $home == /var/lib/oxbow && $shell == */nologin ]] || fail "user oxbow: uid $uid, home $home, shell $shell"
[[ $(stat -c '%U:%G %a' /var/lib/oxbow) == "oxbow:oxbow 750" ]] || fail "/var/lib/oxbow is $(stat -c '%U:%G %a' /var/lib/oxbow)"
[[ $(stat -c '%U:%G %a' /var/lib/oxbow/collections) == "oxbow:oxbow 750" ]] ||
  fail "/var/lib/oxbow/collections (the service's --data folder) is $(stat -c '%U:%G %a' /var/lib/oxbow/collections 2>&1)"
[[ $(stat -c '%U %a' /etc/default/oxbow) == "root 600" ]] || fail "/etc/default/oxbow is $(stat -c '%U %a' /etc/default/oxbow)"
# The commented defaults in /etc/default/oxbow are those of the installed binary.
bash "$root/cmake/packaging/make-default.sh" /usr/bin/oxbow "$work/default"
as_root cat /etc/default/oxbow | diff - "$work/default" >&2 || fail "/etc/default/oxbow differs from the installed binary's serve --help"
[[ -f /lib/systemd/system/oxbow.service ]] || fail "oxbow.service not installed"
if command -v man >/dev/null; then verify_unit /lib/systemd/system/oxbow.service; else verify_unit /lib/systemd/system/oxbow.service --man=no; fi
# The Python client: postinst byte-compiled it (py3compile; checked before any import, which as root would
# write the bytecode itself), and Debian's python3 imports it from the package, at the package's version.
client=/usr/lib/python3/dist-packages/oxbow_client
compgen -G "$client/__pycache__/__init__.cpython-3*.pyc" >/dev/null || fail "postinst did not byte-compile $client (py3compile)"
imported=$(/usr/bin/python3 -I -c 'import importlib.metadata, oxbow_client; print(oxbow_client.__file__, importlib.metadata.version("oxbow-client"))') \
  || fail "/usr/bin/python3 cannot import oxbow_client"
[[ $imported == "$client/__init__.py $version" ]] || fail "python3 imports oxbow_client as '$imported', not $client at $version"
say "installed: /usr/bin/oxbow $version, user oxbow (uid $uid), /var/lib/oxbow, oxbow.service (verify clean), /etc/default/oxbow, python3 module oxbow_client (byte-compiled)"

# A tiny collection: 8 opencv-doc photos, box_in_scene.png among them; query box.png. 500 words is the
# smallest vocabulary here that verifies it (18 inliers; 200 words rank it 4th, unverified).
photos=(box_in_scene.png graf3.png leuvenB.jpg aero3.jpg building.jpg home.jpg fruits.jpg baboon.jpg)
[[ -f $samples/box.png ]] || fail "$samples/box.png missing (opencv-doc; scripts/install-deps.sh installs it)"
printf "$samples/%s\n" "${photos[@]}" >"$work/photos.txt"
"${as_oxbow[@]}" oxbow -q vocab train --list "$work/photos.txt" --words 500 --out /var/lib/oxbow/vocab.oxvoc >/dev/null \
  || fail "oxbow vocab train as the user oxbow"

# check_search PORT: adds the photos over HTTP, and box.png must find box_in_scene first, verified.
check_search() {
  local port=$1 ready=0 p
  for _ in $(seq 150); do
    if curl -fsS "http://127.0.0.1:$port/readyz" >/dev/null 2>&1; then ready=1 && break; fi
    sleep 0.2
  done
  [[ $ready == 1 ]] || fail "the server on port $port did not become ready in 30 s"
  for p in "${photos[@]}"; do
    curl -fsS --data-binary "@$samples/$p" "http://127.0.0.1:$port/v1/images?id=${p%.*}" >/dev/null || fail "adding $p over HTTP"
  done
  curl -fsS --data-binary "@$samples/box.png" "http://127.0.0.1:$port/v1/search?top_k=3" >"$work/search.json" \
    || fail "searching box.png over HTTP"
  python3 - "$work/search.json" <<'EOF' || fail "search result (above)"
import json, sys
first = json.load(open(sys.argv[1]))["results"][0]
print(f"package-test: search box.png -> {first['id']} (verified {first['verified']}, {first['inliers']} inliers)", file=sys.stderr)
sys.exit(0 if first["id"] == "box_in_scene" and first["verified"] else 1)
EOF
  # The same with the packaged Python client, as the user oxbow (-I: nothing but the system's modules).
  "${as_oxbow[@]}" /usr/bin/python3 -I - "$port" "$samples/box.png" "${#photos[@]}" <<'EOF' || fail "the installed Python client (above)"
import sys
from oxbow_client import Client
oxbow = Client(f"http://127.0.0.1:{sys.argv[1]}", timeout=60)
images, first = oxbow.stats()["images"], oxbow.search(sys.argv[2], top_k=3)["results"][0]
print(f"package-test: oxbow_client: {images} images, search box.png -> {first['id']}", file=sys.stderr)
sys.exit(0 if images == int(sys.argv[3]) and first["id"] == "box_in_scene" and first["verified"] else 1)
EOF
}

# The first start as server/README.md says: a vocabulary in /var/lib/oxbow and --vocab creates the index.
"${as_oxbow[@]}" oxbow serve --index /var/lib/oxbow/index --vocab /var/lib/oxbow/vocab.oxvoc --port 0 \
  >"$work/serve.out" 2>"$work/serve.err" &
server_pid=$!
for _ in $(seq 100); do
  grep -q '^listening on' "$work/serve.out" && break
  sleep 0.1
done
port=$(sed -n 's|^listening on http://127.0.0.1:\([0-9]*\)$|\1|p' "$work/serve.out")
[[ -n $port ]] || { cat "$work/serve.err" >&2; fail "oxbow serve did not start (log above)"; }
check_search "$port"
kill -TERM "$server_pid"
status=0
wait "$server_pid" || status=$?
server_pid=
[[ $status == 0 ]] || { cat "$work/serve.err" >&2; fail "oxbow serve exited with $status after SIGTERM (log above)"; }
# The CLI on the index the server wrote.
"${as_oxbow[@]}" oxbow query --index /var/lib/oxbow/index "$samples/box.png" >"$work/query.json" 2>/dev/null || fail "oxbow query"
python3 -c 'import json,sys; r = json.load(open(sys.argv[1]))["results"]; sys.exit(0 if len(r) == 8 and r[0]["id"] == "box_in_scene" else 1)' \
  "$work/query.json" || fail "oxbow query on the served index: $(head -c 400 "$work/query.json")"
# A shard's gRPC port: the binary loads its cluster module from /usr/lib/oxbow.
"${as_oxbow[@]}" oxbow serve --index /var/lib/oxbow/index --port 0 --grpc-port 0 >"$work/shard.out" 2>"$work/shard.err" &
server_pid=$!
for _ in $(seq 100); do
  grep -q '^listening on' "$work/shard.out" && break
  sleep 0.1
done
grep -q '^shard listening on grpc://' "$work/shard.out" || { cat "$work/shard.err" >&2; fail "oxbow serve --grpc-port did not start (log above)"; }
kill -TERM "$server_pid"
wait "$server_pid" || fail "oxbow serve --grpc-port exited with $? after SIGTERM"
server_pid=
say "installed binary as user oxbow: vocab train, serve (created the index), 8 adds over HTTP, search, query, a shard's gRPC port: ok"

if [[ -d /run/systemd/system ]]; then  # systemd runs: the unit itself, hardening included
  port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  as_root sed -i "s|^OXBOW_SERVE_ARGS=.*|OXBOW_SERVE_ARGS=\"--port $port --vocab /var/lib/oxbow/vocab.oxvoc\"|" /etc/default/oxbow
  journal=1
  as_root systemctl start oxbow.service || fail "systemctl start oxbow.service"
  check_search "$port"
  [[ -f /var/lib/oxbow/collections/default/catalogue.sqlite ]] || fail "the service did not create the collection default in /var/lib/oxbow/collections"
  as_root systemctl reload oxbow.service || fail "systemctl reload oxbow.service"
  [[ $(systemctl is-active oxbow.service) == active ]] || fail "oxbow.service is not active after the search and a reload"
  as_root systemctl stop oxbow.service
  journal=0
  say "oxbow.service (systemd): started on /var/lib/oxbow/collections (created default), 8 adds, search, reload, stopped: ok"
else
  say "oxbow.service not started: systemd is not running here (no /run/systemd/system); checked with systemd-analyze only"
fi

as_root env DEBIAN_FRONTEND=noninteractive apt-get purge -y -qq oxbow >"$work/apt.log" 2>&1 || { cat "$work/apt.log" >&2; fail "apt-get purge oxbow"; }
installed=0
if dpkg-query -W -f='${Status}' oxbow 2>/dev/null | grep -q .; then fail "dpkg still lists oxbow after purge"; fi
for path in /usr/bin/oxbow /usr/lib/oxbow /lib/systemd/system/oxbow.service /etc/default/oxbow /usr/share/doc/oxbow \
            /usr/share/man/man1/oxbow.1.gz /etc/systemd/system/oxbow.service "$client" "$client-$version.dist-info" \
            /var/lib/systemd/deb-systemd-helper-enabled/oxbow.service.dsh-also \
            /var/lib/systemd/deb-systemd-helper-masked/oxbow.service; do
  [[ ! -e $path && ! -L $path ]] || fail "$path is still there after apt-get purge"
done
# Kept on purge by design (server/README.md): the user and the index. Then removed by hand, as it says.
{ getent passwd oxbow >/dev/null && [[ -d /var/lib/oxbow/index ]]; } || fail "purge was to keep the user oxbow and /var/lib/oxbow"
as_root rm -rf /var/lib/oxbow
as_root deluser --system --quiet oxbow >/dev/null 2>&1  # (it mentions crontab without cron)
as_root delgroup --system --quiet oxbow >/dev/null 2>&1 || true
if getent passwd oxbow >/dev/null || getent group oxbow >/dev/null; then fail "user or group oxbow left after deluser"; fi
say "purged: no package, binary, unit, settings, Python module or systemd state left; user and /var/lib/oxbow removed after it"
say "ok ($((SECONDS - started)) s)"
