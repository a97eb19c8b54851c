#!/usr/bin/python3
"""Scores duplicate finders on the benchmark: pair precision and recall per transformation, side by side.

    score.py --truth DIR/truth.json [--main oxbow] [--out report.md] [--json scores.json] \\
             oxbow=DIR/oxbow.json findimagedupes=DIR/peers/findimagedupes.json ...

Each result is NAME=FILE (or FILE; the name is then its "method" or the file name): the JSON of
`oxbow index duplicates --format json` or of run_peers.py (a "pairs" list of {"a", "b", ...}), or the CSV
of `--format csv` (header a,b,kind,mirrored,...). Pairs are unordered; ids are file names without
extension (paths and extensions are stripped). A result that only has groups is scored on every pair
inside each group. Prints markdown. The protocol is in README.md.
"""

import argparse
import csv
import json
import os
import sys

KINDS = ["exact", "near_copy", "same_scene"]


def norm_id(x):
    x = str(x)
    base = os.path.basename(x)
    stem, ext = os.path.splitext(base)
    return stem if ext.lower() in (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".tif", ".tiff", ".bmp", ".webp") else base


def parse_bool(v):
    if isinstance(v, bool):
        return v
    if v is None or v == "":
        return None
    return str(v).strip().lower() in ("1", "true", "yes")


def load_result(spec):
    name, path = (spec.split("=", 1) if "=" in spec and not os.path.exists(spec) else (None, spec))
    info = {"settings": None, "timings_s": None}
    pairs = []
    if path.lower().endswith(".csv"):
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                pairs.append({"a": row["a"], "b": row["b"], "kind": row.get("kind") or None,
                              "mirrored": parse_bool(row.get("mirrored"))})
    else:
        with open(path) as f:
            doc = json.load(f)
        info["settings"] = doc.get("settings")
        info["timings_s"] = doc.get("timings_s")
        name = name or doc.get("method")
        raw = doc.get("pairs")
        if raw is None:  # groups only
            raw = []
            for g in doc.get("groups", []):
                members = g["images"] if isinstance(g, dict) else g
                for i in range(len(members)):
                    for j in range(i + 1, len(members)):
                        raw.append({"a": members[i], "b": members[j]})
        for p in raw:
            pairs.append({"a": p["a"], "b": p["b"], "kind": p.get("kind"), "mirrored": parse_bool(p.get("mirrored"))})
    name = name or os.path.splitext(os.path.basename(path))[0]
    found = {}
    for p in pairs:
        a, b = norm_id(p["a"]), norm_id(p["b"])
        if a == b:
            continue
        key = (a, b) if a < b else (b, a)
        found.setdefault(key, p)  # the first answer for a pair counts
    return name, path, found, info


class Truth:
    def __init__(self, path):
        with open(path) as f:
            t = json.load(f)
        self.doc = t
        self.images = {r["id"]: r for r in t["images"]}
        self.transformations = [x["name"] for x in t["transformations"]]
        self.kind_of_transformation = {x["name"]: x["kind"] for x in t["transformations"]}
        self.pairs = {}
        for p in t["positives"]:
            self.pairs[self.key(p)] = ("positive", p)
        for p in t["ignore"]:
            self.pairs[self.key(p)] = ("ignore", p)
        for p in t["overlay_negatives"]:
            self.pairs[self.key(p)] = ("overlay", p)
        self.positives = t["positives"]
        n = len(self.images)
        self.n_overlay = len(t["overlay_negatives"])
        self.n_unrelated = n * (n - 1) // 2 - len(t["positives"]) - len(t["ignore"]) - self.n_overlay

    @staticmethod
    def key(p):
        a, b = p["a"], p["b"]
        return (a, b) if a < b else (b, a)

    def label(self, key):
        return self.pairs.get(key, ("unrelated", None))


def ratio(num, den):
    return num / den if den else None


def fmt(x, digits=3):
    return "-" if x is None else ("%.*f" % (digits, x))


def score(truth, found):
    imgs = truth.images
    unknown = sorted({i for k in found for i in k if i not in imgs})
    rows = {}
    row_names = truth.transformations + ["copy_pair", "same_scene"]
    for r in row_names:
        rows[r] = {"positives": 0, "found_pos": 0, "scope_pos": 0, "scope_neg": 0, "kind_ok": 0, "kind_n": 0}
    for p in truth.positives:
        r = rows[p["transformation"]]
        r["positives"] += 1
        k = Truth.key(p)
        if k in found:
            r["found_pos"] += 1
            kind = found[k].get("kind")
            if kind:
                r["kind_n"] += 1
                r["kind_ok"] += kind in p["accept_kinds"]
    s = {"found": len(found), "unknown_ids": len(unknown), "ignored_found": 0, "positive_found": 0,
         "same_scene_found": 0, "overlay_fp": 0, "unrelated_fp": 0, "kind_n": 0, "kind_ok": 0,
         "mirror_n": 0, "mirror_ok": 0, "confusion": {}, "fp_examples": []}
    for key, fp in found.items():
        if key[0] not in imgs or key[1] not in imgs:
            continue
        label, rec = truth.label(key)
        if label == "ignore":
            s["ignored_found"] += 1
            continue
        ta, tb = imgs[key[0]]["transform"], imgs[key[1]]["transform"]
        positive = label == "positive"
        # precision scopes: a transformation's row = pairs with a copy of that transformation;
        # copy_pair = pairs of two copies; same_scene = pairs of two untransformed photos
        scopes = {t for t in (ta, tb) if t != "original" and t in rows}
        if ta != "original" and tb != "original":
            scopes.add("copy_pair")
        if ta == "original" and tb == "original":
            scopes.add("same_scene")
        for sc in scopes:
            rows[sc]["scope_pos" if positive else "scope_neg"] += 1
        if positive:
            s["positive_found"] += 1
            if rec["kind"] == "same_scene":
                s["same_scene_found"] += 1
            kind = fp.get("kind")
            if kind:
                s["kind_n"] += 1
                s["kind_ok"] += kind in rec["accept_kinds"]
                c = s["confusion"].setdefault(rec["kind"], {})
                c[kind] = c.get(kind, 0) + 1
            if fp.get("mirrored") is not None:
                s["mirror_n"] += 1
                s["mirror_ok"] += bool(fp["mirrored"]) == bool(rec["mirrored"])
        elif label == "overlay":
            s["overlay_fp"] += 1
            if len(s["fp_examples"]) < 5:
                s["fp_examples"].append("%s ~ %s (same %s)" % (key[0], key[1], rec["overlay"]))
        else:
            s["unrelated_fp"] += 1
            if len(s["fp_examples"]) < 10:
                s["fp_examples"].append("%s ~ %s" % key)
    near = [p for p in truth.positives if p["transformation"] not in ("copy_pair", "same_scene")]
    s["near_recall"] = ratio(sum(Truth.key(p) in found for p in near), len(near))
    cp = rows["copy_pair"]
    s["copy_pair_recall"] = ratio(cp["found_pos"], cp["positives"])
    ss = rows["same_scene"]
    s["same_scene_recall"] = ratio(ss["found_pos"], ss["positives"])
    judged = s["positive_found"] + s["overlay_fp"] + s["unrelated_fp"]
    s["precision"] = ratio(s["positive_found"], judged)
    s["near_precision"] = ratio(s["positive_found"] - s["same_scene_found"], judged - s["same_scene_found"])
    s["kind_accuracy"] = ratio(s["kind_ok"], s["kind_n"])
    s["mirrored_accuracy"] = ratio(s["mirror_ok"], s["mirror_n"])
    for r in rows.values():
        r["recall"] = ratio(r["found_pos"], r["positives"])
        r["precision"] = ratio(r["scope_pos"], r["scope_pos"] + r["scope_neg"])
        r["kind_accuracy"] = ratio(r["kind_ok"], r["kind_n"])
    s["rows"] = rows
    s["unknown"] = unknown[:10]
    return s


def markdown(truth, results, main_name):
    names = [r["name"] for r in results]
    c = truth.doc["counts"]
    out = []
    out.append("Benchmark: %d images (%d originals x %d transformations, groups_dev, overlay-only and unrelated "
               "photos), %d positive pairs, %d overlay negatives, %d unrelated negatives, %d ignored pairs."
               % (c["images"], c["originals"], c["copies_per_original"], c["positives"],
                  truth.n_overlay, truth.n_unrelated, c["ignored"]))
    out.append("")
    out.append("| | " + " | ".join(names) + " |")
    out.append("|---|" + "---|" * len(names))

    def line(label, f):
        out.append("| %s | %s |" % (label, " | ".join(f(r["score"]) for r in results)))
    line("near-copy recall (original ~ copy)", lambda s: fmt(s["near_recall"]))
    line("near-copy recall (copy ~ copy)", lambda s: fmt(s["copy_pair_recall"]))
    line("same-scene recall (groups_dev other views)", lambda s: fmt(s["same_scene_recall"]))
    line("near-copy precision (same-scene pairs not counted)", lambda s: fmt(s["near_precision"]))
    line("precision (all found pairs)", lambda s: fmt(s["precision"]))
    line("overlay-only pairs found (false)", lambda s: "%d / %d" % (s["overlay_fp"], truth.n_overlay))
    line("unrelated pairs found (false)", lambda s: "%d / %d" % (s["unrelated_fp"], truth.n_unrelated))
    line("pairs found (of them ignored)", lambda s: "%d (%d)" % (s["found"], s["ignored_found"]))
    line("kind right (exact / near copy / same scene)",
         lambda s: "-" if s["kind_accuracy"] is None else "%s (%d)" % (fmt(s["kind_accuracy"]), s["kind_n"]))
    line("mirrored flag right", lambda s: "-" if s["mirrored_accuracy"] is None
         else "%s (%d)" % (fmt(s["mirrored_accuracy"]), s["mirror_n"]))
    line("unknown ids", lambda s: str(s["unknown_ids"]))
    def seconds(t):
        if not t:
            return "-"
        wall = t["total"] if "total" in t else sum(  # else the sum of its stages
            v for k, v in t.items() if k != "cpu" and isinstance(v, (int, float)))
        return fmt(wall, 1) + (" (cpu %s)" % fmt(t["cpu"], 1) if "cpu" in t else "")
    out.append("| time, s (as the result reports it) | %s |" % " | ".join(
        seconds(r["info"]["timings_s"]) for r in results))
    out.append("")
    out.append("Recall / precision per transformation. Recall: the (original, copy) pairs found; precision: of the "
               "found pairs that hold a copy of that transformation, the share that are positives (ignored pairs "
               "left out). `copy_pair`: two copies of one original whose visible parts overlap by at least half "
               "(precision over pairs of two copies); `same_scene`: two different photos of one groups_dev group "
               "(precision over pairs of two untransformed photos).")
    out.append("")
    out.append("| transformation | pairs | " + " | ".join(names) + " |")
    out.append("|---|---|" + "---|" * len(names))
    for t in truth.transformations + ["copy_pair", "same_scene"]:
        cells = []
        for r in results:
            row = r["score"]["rows"][t]
            cells.append("%s / %s" % (fmt(row["recall"], 2), fmt(row["precision"], 2)))
        out.append("| %s | %d | %s |" % (t, results[0]["score"]["rows"][t]["positives"] if results else 0,
                                         " | ".join(cells)))
    with_kinds = [r for r in results if r["score"]["kind_n"]]
    for r in with_kinds:
        s = r["score"]
        out.append("")
        out.append("Kinds given by %s to the positives it found (rows: truth; the cereal-shelf pairs of groups_dev "
                   "accept near_copy too):" % r["name"])
        out.append("")
        found_kinds = sorted({k for row in s["confusion"].values() for k in row}, key=lambda k: (k not in KINDS, k))
        out.append("| truth \\ given | " + " | ".join(found_kinds) + " |")
        out.append("|---|" + "---|" * len(found_kinds))
        for tk in KINDS:
            row = s["confusion"].get(tk, {})
            out.append("| %s | %s |" % (tk, " | ".join(str(row.get(k, 0)) for k in found_kinds)))
        out.append("")
        out.append("Kind right per transformation (%s): " % r["name"] + ", ".join(
            "%s %s" % (t, fmt(s["rows"][t]["kind_accuracy"], 2)) for t in truth.transformations + ["copy_pair", "same_scene"]
            if s["rows"][t]["kind_accuracy"] is not None))
    main = [r for r in results if r["name"] == main_name]
    if main:
        m = main[0]["score"]
        peers = [r for r in results if r["name"] != main_name]
        out.append("")
        out.append("Targets for %s:" % main_name)
        out.append("")
        checks = [
            ("near-copy precision >= 0.99", m["near_precision"] is not None and m["near_precision"] >= 0.99,
             fmt(m["near_precision"])),
            ("near-copy recall (original ~ copy) >= 0.98", m["near_recall"] is not None and m["near_recall"] >= 0.98,
             fmt(m["near_recall"])),
            ("kind right >= 0.95", m["kind_accuracy"] is not None and m["kind_accuracy"] >= 0.95,
             fmt(m["kind_accuracy"])),
            ("same-scene recall >= 0.80", m["same_scene_recall"] is not None and m["same_scene_recall"] >= 0.80,
             fmt(m["same_scene_recall"])),
        ]
        behind = []
        for t in truth.transformations + ["same_scene"]:
            mr = m["rows"][t]["recall"] or 0.0
            ahead = ["%s %s" % (p["name"], fmt(p["score"]["rows"][t]["recall"] or 0.0, 2)) for p in peers
                     if mr < (p["score"]["rows"][t]["recall"] or 0.0)
                     or (mr == (p["score"]["rows"][t]["recall"] or 0.0) and mr < 1.0)]
            if ahead:
                behind.append("%s %s (%s)" % (t, fmt(mr, 2), ", ".join(ahead)))
        checks.append(("recall above every peer (%s) on every transformation, or 1.00 where a peer has 1.00"
                       % ", ".join(p["name"] for p in peers), not behind,
                       ("not above on: " + "; ".join(behind)) if behind else "yes"))
        for label, ok, value in checks:
            out.append("- [%s] %s: %s" % ("x" if ok else " ", label, value))
    for r in results:
        s = r["score"]
        if s["fp_examples"]:
            out.append("")
            out.append("%s, first false pairs: %s" % (r["name"], "; ".join(s["fp_examples"])))
        if s["unknown"]:
            out.append("")
            out.append("%s, ids not in the benchmark: %s" % (r["name"], ", ".join(s["unknown"])))
    out.append("")
    out.append("Settings: " + "; ".join("%s: %s" % (r["name"], json.dumps(r["info"]["settings"], sort_keys=True))
                                        for r in results if r["info"]["settings"]))
    return "\n".join(out) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--main", default="oxbow", help="the method checked against the targets and the peers")
    ap.add_argument("--out", help="also write the markdown here")
    ap.add_argument("--json", help="write every number here")
    ap.add_argument("results", nargs="+", help="NAME=FILE or FILE")
    args = ap.parse_args()
    truth = Truth(args.truth)
    results = []
    for spec in args.results:
        name, path, found, info = load_result(spec)
        results.append({"name": name, "path": path, "info": info, "score": score(truth, found)})
    text = markdown(truth, results, args.main)
    sys.stdout.write(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    if args.json:
        with open(args.json, "w") as f:
            json.dump([{"name": r["name"], "path": r["path"], "settings": r["info"]["settings"],
                        "timings_s": r["info"]["timings_s"],
                        "score": {k: v for k, v in r["score"].items() if k != "fp_examples"}} for r in results],
                      f, indent=1)


if __name__ == "__main__":
    main()
