#!/usr/bin/env bash
# Writes gzipped man pages for `oxbow` and every subcommand (oxbow.1.gz, oxbow-serve.1.gz,
# oxbow-index-build.1.gz, ...) into OUTDIR, with help2man, from the binary's own --help output, so that they
# cannot disagree with it. The subcommands are read from the "Subcommands:" lists of that output (CLI11's
# help format), so a new command gets its page without a change here.
#   make-manpages.sh OXBOW_BINARY VERSION OUTDIR
set -euo pipefail
binary=$1 version=$2 out=$3
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rm -rf "$out" && mkdir -p "$out"

# Help text of `oxbow WORDS...`, with "oxbow" (not the build path) as the program name in its usage line.
help_of() { (exec -a oxbow "$binary" "$@" --help); }
# "name<TAB>first line of its summary" for each entry of the Subcommands: list of `oxbow WORDS... --help`.
subcommands_of() {
  help_of "$@" | awk '/^Subcommands:/ { in_list = 1; next }
                      in_list && /^[^ ]/ { in_list = 0 }
                      in_list && /^  [a-z]/ { name = $1; sub(/^  [^ ]+ +/, ""); print name "\t" $0 }'
}

pages=()
page() {  # page SUMMARY WORDS...
  local summary=$1; shift
  local name; name=$(IFS=-; echo "oxbow${*:+-$*}")
  # help2man names the page after the program it runs: a wrapper named like the page.
  printf '#!/bin/bash\nexec -a oxbow "%s" %s "$@"\n' "$binary" "$*" > "$work/$name"
  chmod +x "$work/$name"
  local see_also
  if [[ $# -eq 0 ]]; then see_also=""; else see_also="oxbow(1)"; fi
  printf '[SEE ALSO]\n%s\n' "${see_also:-@SUBPAGES@}" > "$work/$name.h2m"
  help2man --no-info --section=1 --source="oxbow $version" --manual="oxbow manual" \
    --version-string="$version" --name="$summary" --include="$work/$name.h2m" \
    --output="$out/$name.1" "$work/$name"
  pages+=("$name")
  local sub description
  while IFS=$'\t' read -r sub description; do
    page "${description%%.*}" "$@" "$sub"
  done < <(subcommands_of "$@")
}
page "instance-level image retrieval: SIFT features, visual words, an HTTP search server"

# The top page's SEE ALSO lists every other page.
refs=$(printf '.BR %s (1),\n' "${pages[@]:1}")
refs=${refs%,}
awk -v refs="$refs" '/^@SUBPAGES@$/ { print refs; next } { print }' "$out/oxbow.1" > "$work/oxbow.1" && mv "$work/oxbow.1" "$out/oxbow.1"
gzip -9n "$out"/*.1
