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
#   /usr/bin/oxbow serve --data /var/lib/oxbow/collections $OXBOW_SERVE_ARGS
# Every folder /var/lib/oxbow/collections/NAME holding an index is the collection NAME, served under
# /v1/collections/NAME/...; the routes without that prefix (/v1/images, /v1/search, ...) act on the
# collection "default". Make collections in one of three ways:
#  - build one as the oxbow user (images and vocabulary readable by it), before starting the service:
#      sudo -u oxbow oxbow index build --vocab VOCAB.oxvoc --images PHOTOS --out /var/lib/oxbow/collections/default
#  - copy a vocabulary (oxbow vocab train) to /var/lib/oxbow/vocab.oxvoc and add
#    "--vocab /var/lib/oxbow/vocab.oxvoc" below: the first start creates an empty collection "default"
#    (images are added over HTTP);
#  - with OXBOW_API_KEY set (the admin key), POST /v1/collections {"name": ..., "vocabulary": ...}, which
#    also makes read and write keys per collection (POST /v1/collections/NAME/keys).
# The keys are kept hashed in /var/lib/oxbow/collections/keys.json; `systemctl reload oxbow` re-reads it.
# The service cannot read /home, /root or /run/user (ProtectHome=yes) and writes only to /var/lib/oxbow.

# Flags added to `oxbow serve`, split at spaces (no quoting). Example:
#   OXBOW_SERVE_ARGS="--host 0.0.0.0 --port 8080 --http-workers 16 --vocab /var/lib/oxbow/vocab.oxvoc"
OXBOW_SERVE_ARGS=""

# The admin key (Authorization: Bearer KEY or X-API-Key: KEY): needed for writes unless a collection's
# write key is given, and for creating or deleting collections and keys; set it before serving on another
# address than 127.0.0.1.
#OXBOW_API_KEY=

# Every flag of `oxbow serve` with its default (`oxbow serve --help`, `man oxbow-serve`):
#
HEADER
  (exec -a oxbow "$binary" serve --help) | sed -n '/^Usage:/,$p' | sed -e 's/^/# /' -e 's/ *$//'
} > "$out"
