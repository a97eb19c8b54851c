#!/usr/bin/env bash
# Writes /etc/default/oxbow, the settings of oxbow.service, to OUT. Its list of flags and defaults is this
# build's `oxbow serve --help`, so the commented defaults cannot disagree with the binary.
#   make-default.sh OXBOW_BINARY OUT
set -euo pipefail
binary=$1 out=$2
mkdir -p "$(dirname "$out")"
{
  cat <<'HEADER'
# Settings of oxbow.service (systemd reads this file as root: keep it root-only, it may hold the API key).
# After a change: systemctl restart oxbow
#
# The service runs, as the user oxbow:
#   /usr/bin/oxbow serve --index /var/lib/oxbow/index $OXBOW_SERVE_ARGS
# It needs an index there. Either build one as the oxbow user (images and vocabulary readable by it):
#   sudo -u oxbow oxbow index build --vocab VOCAB.oxvoc --images PHOTOS --out /var/lib/oxbow/index
# or copy a vocabulary (oxbow vocab train) to /var/lib/oxbow/vocab.oxvoc and add
# "--vocab /var/lib/oxbow/vocab.oxvoc" below: the first start then creates an empty index (images are
# added over HTTP); later starts check that the index was built with that vocabulary.
# The service cannot read /home, /root or /run/user (ProtectHome=yes) and writes only to /var/lib/oxbow.

# Flags added to `oxbow serve`, split at spaces (no quoting). Example:
#   OXBOW_SERVE_ARGS="--host 0.0.0.0 --port 8080 --http-workers 16 --vocab /var/lib/oxbow/vocab.oxvoc"
OXBOW_SERVE_ARGS=""

# Key needed by POST/DELETE /v1/images (Authorization: Bearer KEY or X-API-Key: KEY); set it before
# serving on another address than 127.0.0.1.
#OXBOW_API_KEY=

# Every flag of `oxbow serve` with its default (`oxbow serve --help`, `man oxbow-serve`):
#
HEADER
  (exec -a oxbow "$binary" serve --help) | sed -n '/^Usage:/,$p' | sed -e 's/^/# /' -e 's/ *$//'
} > "$out"
