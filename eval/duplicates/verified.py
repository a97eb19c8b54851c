#!/usr/bin/python3
"""Precision of verified search results on the duplicate benchmark: every image queries the index through
the HTTP API with the server's defaults; each verified result (the query itself left out) is a pair
labelled by truth.json.

    verified.py --truth DIR/truth.json --images DIR/images (--url http://127.0.0.1:PORT |
                --oxbow build/server/oxbow --index DIR/index) [--params "top_k=50"] [--json out.json]
                [--false N]

With --oxbow the script serves --index itself on a loopback port (`oxbow serve --port 0`) and stops it at
the end. A verified pair is true when truth.json calls it positive (a copy of one photo, two copies that
overlap, or another photo of one groups_dev scene), false when it is an overlay negative (two photos
sharing a logo, caption or frame) or unrelated; ignored pairs (README.md "Protocol") are counted apart.
Prints precision over all verified results, over direct and transitive ones (`via`), and over those
with at least 30 inliers, then the --false N false ones with most inliers. The protocol is in README.md.
"""

import argparse
import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from score import Truth, norm_id  # noqa: E402


def start_server(oxbow, index):
    proc = subprocess.Popen([oxbow, "serve", "--index", index, "--port", "0", "--host", "127.0.0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in proc.stdout:
        if line.startswith("listening on "):
            return proc, line.split("listening on ", 1)[1].strip()
    proc.wait()
    sys.exit("verified.py: `oxbow serve` exited before listening (status %s)" % proc.returncode)


def search(url, path, params):
    with open(path, "rb") as f:
        body = f.read()
    request = urllib.request.Request(url + "/v1/search" + ("?" + params if params else ""), data=body,
                                     headers={"Content-Type": "application/octet-stream"}, method="POST")
    for attempt in range(300):
        try:
            with urllib.request.urlopen(request, timeout=300) as r:
                return json.load(r)
        except urllib.error.HTTPError as e:
            text = e.read().decode(errors="replace")
            if e.code != 503 or attempt == 299:  # 503: the index is still loading
                sys.exit("verified.py: %s: HTTP %d: %s" % (path, e.code, text))
        except OSError:
            if attempt >= 2:
                raise
        time.sleep(1)
    return None


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--images", required=True)
    ap.add_argument("--url")
    ap.add_argument("--oxbow")
    ap.add_argument("--index")
    ap.add_argument("--params", default="", help="query string added to every search (default: none)")
    ap.add_argument("--json", help="writes every verified pair with its label here")
    ap.add_argument("--false", type=int, default=20, help="false pairs listed (most inliers first)")
    args = ap.parse_args()
    if not args.url and not (args.oxbow and args.index):
        ap.error("give --url, or --oxbow and --index")
    truth = Truth(args.truth)
    files = {norm_id(name): os.path.join(args.images, name) for name in os.listdir(args.images)}
    ids = sorted(i for i in truth.images if i in files)
    if len(ids) != len(truth.images):
        sys.exit("verified.py: %d images of truth.json are not in %s" % (len(truth.images) - len(ids), args.images))
    server = None
    url = args.url
    if not url:
        server, url = start_server(args.oxbow, args.index)
    rows = []
    start = time.time()
    try:
        for n, qid in enumerate(ids):
            answer = search(url, files[qid], args.params)
            for r in answer["results"]:
                rid = norm_id(r["id"])
                if rid == qid or not r.get("verified"):
                    continue
                key = (qid, rid) if qid < rid else (rid, qid)
                label = truth.label(key)[0]
                rows.append({"query": qid, "result": rid, "rank": r["rank"], "inliers": r["inliers"],
                             "via": r.get("via"), "label": label})
            if (n + 1) % 50 == 0 or n + 1 == len(ids):
                print("  %d / %d queries, %.0f s" % (n + 1, len(ids), time.time() - start), file=sys.stderr)
    finally:
        if server:
            server.terminate()
            server.wait()

    def precision(subset):
        counted = [r for r in subset if r["label"] != "ignore"]
        good = sum(r["label"] == "positive" for r in counted)
        return good, len(counted), (good / len(counted) if counted else None)

    print("| verified results | true | counted | precision | overlay negatives | unrelated | ignored |")
    print("|---|---|---|---|---|---|---|")
    for name, subset in [("all", rows), ("direct", [r for r in rows if not r["via"]]),
                         ("transitive (`via`)", [r for r in rows if r["via"]]),
                         (">= 30 inliers", [r for r in rows if r["inliers"] >= 30])]:
        good, counted, p = precision(subset)
        print("| %s | %d | %d | %s | %d | %d | %d |" % (
            name, good, counted, "-" if p is None else "%.4f" % p, sum(r["label"] == "overlay" for r in subset),
            sum(r["label"] == "unrelated" for r in subset), sum(r["label"] == "ignore" for r in subset)))
    false = sorted((r for r in rows if r["label"] in ("overlay", "unrelated")), key=lambda r: -r["inliers"])
    if false and args.false > 0:
        print("\nfalse verified results, most inliers first:")
        for r in false[:args.false]:
            print("  %s -> %s: %d inliers, %s%s" % (r["query"], r["result"], r["inliers"], r["label"],
                                                   ", via " + r["via"] if r["via"] else ""))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"params": args.params, "queries": len(ids), "verified": rows}, f, indent=1)


if __name__ == "__main__":
    main()
