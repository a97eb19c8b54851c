#!/bin/sh
# Container entry point. `docker run IMAGE [serve flags...]` serves on 0.0.0.0:8080 either the
# collections of /data/collections (when that folder exists: oxbow serve --data, each sub-folder an index
# folder, server/README.md "Collections") or the index /data/index;
# `docker run IMAGE <other oxbow command> ...` runs that command (e.g. vocab train, index build).
# When the index served as the collection "default" (/data/index, or /data/collections/default) does not
# exist yet, it is created with, in order of preference: $OXBOW_VOCAB, /data/vocab.oxvoc, or the small
# default vocabulary baked into the image (1000 words trained at image build time on the opencv-doc sample
# photos; fine to try the API, train your own for real collections).
set -eu
if [ "$#" -gt 0 ] && [ "${1#-}" = "$1" ] && [ "$1" != "serve" ]; then
  exec /usr/local/bin/oxbow "$@"
fi
[ "${1:-}" = "serve" ] && shift
if [ -d /data/collections ]; then
  served=/data/collections/default
  set -- serve --data /data/collections --host 0.0.0.0 --port 8080 "$@"
else
  served=/data/index
  set -- serve --index /data/index --host 0.0.0.0 --port 8080 "$@"
fi
if [ ! -f "$served/catalogue.sqlite" ]; then
  vocab=${OXBOW_VOCAB:-}
  if [ -z "$vocab" ]; then
    if [ -f /data/vocab.oxvoc ]; then vocab=/data/vocab.oxvoc; else vocab=/usr/local/share/oxbow/default.oxvoc; fi
  fi
  echo "entrypoint: no index in $served yet; creating one with vocabulary $vocab" >&2
  set -- "$@" --vocab "$vocab"
fi
exec /usr/local/bin/oxbow "$@"
