#!/usr/bin/env python3
"""Docs that cannot drift: fails when the reference pages no longer describe the software.

Three checks, each printing what is missing:
  1. every flag that `oxbow [<command> [<subcommand>]] --help` shows is in the CLI reference
     (server/README.md), in the section of that command: the section whose heading names the command in
     backticks (`oxbow index build`), together with the sections of the same page it links to (shared
     tables such as the search options);
  2. every route and method of server/http/openapi.json is in the HTTP reference (server/README.md),
     written as `METHOD /path` (for example `GET /v1/images/{id}`);
  3. every relative link inside a tracked *.md file points at a file that exists and, for `#anchor`, at a
     heading (GitHub's anchor rules) or an `<a id>` of that file.

Usage: docs_check.py --oxbow BUILD/server/cli/oxbow --root SOURCE_DIR
The commands are read from the "Subcommands:" lists of the help output (CLI11's format), as
cmake/packaging/make-manpages.sh reads them for the man pages, so a new command is checked without a
change here. Standard library only.
"""

import argparse
import json
import os
import re
import subprocess
import sys

HELP_FLAG_RE = re.compile(r"(?<![\w-])(--[A-Za-z0-9][A-Za-z0-9-]*)")
IGNORED_FLAGS = {"--help", "--help-all"}  # CLI11 adds them to every command
HEADING_RE = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
LINK_RE = re.compile(r"(?<!!)\[((?:[^\[\]]|\[[^\]]*\])*)\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
IMAGE_RE = re.compile(r"!\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REF_DEF_RE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
EXPLICIT_ANCHOR_RE = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"")


# ---------------------------------------------------------------------------------------------- CLI help

def help_text(binary, words):
    run = subprocess.run([binary, *words, "--help"], capture_output=True, text=True, timeout=60)
    if run.returncode != 0:
        raise SystemExit(f"docs_check: `oxbow {' '.join(words)} --help` exited with {run.returncode}: "
                         f"{run.stderr.strip()[:500]}")
    return run.stdout


def subcommands(text):
    """Names in the 'Subcommands:' list of a CLI11 help text."""
    names, in_list = [], False
    for line in text.splitlines():
        if line.startswith("Subcommands:"):
            in_list = True
            continue
        if in_list and line and not line.startswith(" "):
            in_list = False
        if in_list:
            m = re.match(r"^  ([a-z][\w-]*)", line)
            if m:
                names.append(m.group(1))
    return names


def name_columns(text):
    """The name columns of the option lines of a CLI11 help text ("--top-k INT:INT in [1 - 10000]=20").

    An option line is indented by at most 8 spaces and starts with '-'; wrapped descriptions are indented
    further, so they are not read as options. The column ends where two spaces separate it from the
    description."""
    for line in text.splitlines():
        m = re.match(r"^\s{1,8}(-\S.*)$", line)
        if m:
            yield re.split(r"\s{2,}", m.group(1), maxsplit=1)[0]


def flags(text):
    """Long flags of the option lines of a CLI11 help text."""
    found = []
    for column in name_columns(text):
        for flag in HELP_FLAG_RE.findall(column):
            if flag not in IGNORED_FLAGS and flag not in found:
                found.append(flag)
    return found


def command_tree(binary, words=()):
    """[(words, flags, help text)] for the command and, depth first, every subcommand under it."""
    text = help_text(binary, list(words))
    out = [(tuple(words), flags(text), text)]
    for name in subcommands(text):
        out.extend(command_tree(binary, (*words, name)))
    return out


# ------------------------------------------------------------------------------------------- Markdown

def strip_code(text):
    """The text with fenced code blocks blanked (line count kept) and inline code spans removed."""
    lines, fence = [], None
    for line in text.splitlines():
        m = re.match(r"^\s{0,3}(`{3,}|~{3,})", line)
        if fence is None and m:
            fence = m.group(1)[0] * len(m.group(1))
            lines.append("")
            continue
        if fence is not None:
            if line.strip().startswith(fence):
                fence = None
            lines.append("")
            continue
        lines.append(re.sub(r"(`+)(?:(?!\1).)+?\1", "", line))
    return "\n".join(lines)


def heading_lines(text):
    """[(line index, level, heading text)] outside fenced code."""
    out, fence = [], None
    for i, line in enumerate(text.splitlines()):
        m = re.match(r"^\s{0,3}(`{3,}|~{3,})", line)
        if fence is None and m:
            fence = m.group(1)[0]
            continue
        if fence is not None:
            if line.strip().startswith(fence * 3):
                fence = None
            continue
        h = HEADING_RE.match(line)
        if h:
            out.append((i, len(h.group(1)), h.group(2)))
    return out


def github_slug(heading):
    """The anchor GitHub gives a heading: rendered text, lower case, punctuation dropped, spaces -> '-'."""
    text = re.sub(r"!\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"<[^>]+>", "", text)
    text = text.replace("`", "")
    text = re.sub(r"(\*\*|__|\*|_)(\S.*?\S|\S)\1", r"\2", text)
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text):
    seen, out = {}, set()
    for _, _, heading in heading_lines(text):
        slug = github_slug(heading)
        n = seen.get(slug, 0)
        out.add(slug if n == 0 else f"{slug}-{n}")
        seen[slug] = n + 1
    out.update(EXPLICIT_ANCHOR_RE.findall(text))
    return out


def sections(text):
    """{anchor: section text}: from a heading to the next heading of the same or a higher level."""
    lines = text.splitlines()
    heads = heading_lines(text)
    out, seen = {}, {}
    for k, (i, level, heading) in enumerate(heads):
        end = len(lines)
        for j, other_level, _ in heads[k + 1:]:
            if other_level <= level:
                end = j
                break
        slug = github_slug(heading)
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out[slug if n == 0 else f"{slug}-{n}"] = (heading, "\n".join(lines[i:end]))
    return out


def tracked_markdown(root):
    try:
        run = subprocess.run(["git", "-C", root, "ls-files", "-z", "--", "*.md"], capture_output=True,
                             timeout=60, check=True)
        files = [f for f in run.stdout.decode().split("\0") if f]
        # Files added but not committed yet are tracked too; deleted ones are not checked.
        return sorted(f for f in files if os.path.isfile(os.path.join(root, f)))
    except (OSError, subprocess.SubprocessError):
        skip = {".git", "node_modules", "demo-data", "Testing"}
        out = []
        for folder, dirs, names in os.walk(root):
            dirs[:] = [d for d in dirs if d not in skip and not d.startswith("build")]
            out += [os.path.relpath(os.path.join(folder, n), root) for n in names if n.endswith(".md")]
        return sorted(out)


def read(path):
    with open(path, encoding="utf-8") as f:
        return f.read()


# ----------------------------------------------------------------------------------------------- checks

def check_cli(binary, reference_path):
    """Every flag of every command's --help in that command's section of the reference."""
    text = read(reference_path)
    secs = sections(text)
    where = os.path.relpath(reference_path, os.path.dirname(os.path.dirname(reference_path)))
    problems = []
    for words, command_flags, help_output in command_tree(binary):
        name = " ".join(("oxbow", *words))
        # CLI11 writes a negated flag's value after its name ("--qe,--no-qe{false}"), which reads as a
        # default: the help formatter (server/cli/main.cc) leaves it out.
        for column in name_columns(help_output):
            if re.search(r"-[\w-]+\{", column):
                problems.append(f"`{name} --help` shows a flag's value in its name: {column}")
        if not command_flags:  # a group of subcommands only (`oxbow index`): its subcommands are checked
            continue
        # The sections whose heading names exactly this command in backticks (`oxbow index build`).
        mine = [body for heading, body in secs.values() if "`" + name + "`" in heading]
        if not mine:
            problems.append(f"{where}: no section for `{name}` "
                            f"(a heading naming it in backticks); its flags: {' '.join(command_flags) or '-'}")
            continue
        body = "\n".join(mine)
        # The sections this one links to on the same page (shared flag tables) count as its text.
        for target in re.findall(r"\]\(#([^)\s]+)\)", body):
            if target in secs:
                body += "\n" + secs[target][1]
        missing = [f for f in command_flags if not re.search(r"(?<![\w-])" + re.escape(f) + r"(?![\w-])", body)]
        if missing:
            problems.append(f"{where}: the section of `{name}` does not document {' '.join(missing)}")
    return problems


def check_http(openapi_path, reference_path):
    spec = json.loads(read(openapi_path))
    text = read(reference_path)
    problems = []
    for path, item in spec.get("paths", {}).items():
        for method in item:
            if method.lower() not in {"get", "put", "post", "delete", "patch", "head", "options"}:
                continue
            route = f"{method.upper()} {path}"
            if not re.search(re.escape(route) + r"(?![\w{}/.-])", text):
                problems.append(f"HTTP reference: `{route}` (in openapi.json) is not described")
    return problems


def check_links(root):
    problems = []
    cache = {}
    for md in tracked_markdown(root):
        full = os.path.join(root, md)
        raw = read(full)
        text = strip_code(raw)
        targets = [m.group(2) for m in LINK_RE.finditer(text)] + IMAGE_RE.findall(text)
        targets += [m.group(1) for line in text.splitlines() for m in [REF_DEF_RE.match(line)] if m]
        for target in targets:
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
                continue
            path_part, _, anchor = target.partition("#")
            if path_part:
                dest = os.path.normpath(os.path.join(os.path.dirname(full), path_part))
                if not os.path.exists(dest):
                    problems.append(f"{md}: dead link ({target}): {os.path.relpath(dest, root)} does not exist")
                    continue
            else:
                dest = full
            if anchor:
                if not dest.endswith(".md") or os.path.isdir(dest):
                    continue
                if dest not in cache:
                    cache[dest] = anchors(read(dest))
                if anchor not in cache[dest]:
                    problems.append(f"{md}: dead link ({target}): no heading or anchor #{anchor} in "
                                    f"{os.path.relpath(dest, root)}")
    return problems


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--oxbow", required=True, help="the oxbow binary")
    parser.add_argument("--root", required=True, help="the source tree")
    parser.add_argument("--cli-reference", default="server/README.md", help="relative to --root")
    parser.add_argument("--http-reference", default="server/README.md", help="relative to --root")
    parser.add_argument("--openapi", default="server/http/openapi.json", help="relative to --root")
    args = parser.parse_args()
    root = os.path.abspath(args.root)

    groups = [
        ("CLI flags", check_cli(args.oxbow, os.path.join(root, args.cli_reference))),
        ("HTTP routes", check_http(os.path.join(root, args.openapi), os.path.join(root, args.http_reference))),
        ("links", check_links(root)),
    ]
    failed = False
    for name, problems in groups:
        if problems:
            failed = True
            print(f"docs_check: {name}: {len(problems)} problem(s)")
            for p in problems:
                print(f"  {p}")
        else:
            print(f"docs_check: {name}: ok")
    if failed:
        print("docs_check: FAILED: document what is missing (server/README.md for flags and routes) or "
              "fix the links")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
