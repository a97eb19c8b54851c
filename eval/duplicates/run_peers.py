#!/usr/bin/python3
"""Runs the peers of `oxbow index duplicates` on the benchmark's images; one result file each.

    run_peers.py --images DIR/images --out DIR/peers [--peers findimagedupes,dupeguru,dupeguru-default,phash]

Peers (all from Debian 12 packages, as shipped; settings in each result's "settings"):
  findimagedupes    Debian findimagedupes 2.20.1: 256-bit fingerprint (GraphicsMagick: 160x160, grey, blur,
                    normalise, equalise, 16x16, 1 bit), files match when at most 25 bits differ (its default
                    --threshold=90%). It prints sets of files, one per line: the connected components of the
                    matching pairs. Pairs = every pair inside a set, as a user reads that output.
                    The same run also gives findimagedupes-pairs.json: its matching pairs themselves, before
                    they are merged into sets (fingerprints printed with -v fp, compared as it compares them).
  dupeguru          dupeGuru 4.3.1 picture mode (Debian dupeguru), headless (dupeguru_scan.py): filter hardness
                    95 (its default), "Match pictures of different dimensions" on (needed for resized, cropped,
                    rotated and framed copies). Pairs = every pair inside one of its groups.
  dupeguru-default  the same with the GUI's default off: only pictures of equal dimensions are compared.
  phash             a perceptual hash written here (python3-imagehash is not in Debian 12): the pHash of the
                    imagehash library (grey, 32x32, 2-D DCT-II, 8x8 lowest frequencies against their median:
                    64 bits); a pair when the Hamming distance is at most 10 (--phash-threshold).
Writes OUT/<peer>.json in the common result format:
  {"method", "settings", "images", "pairs": [{"a", "b", ...}], "groups": [...], "timings_s": {"total"}}
with image ids = file names without extension, as `oxbow index duplicates` names them.
"""

import argparse
import base64
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
IMAGE_EXTS = (".jpg", ".jpeg", ".png")
PEERS = ["findimagedupes", "dupeguru", "dupeguru-default", "phash"]


def image_id(path):
    return os.path.splitext(os.path.basename(path))[0]


def write(out_dir, name, result):
    path = os.path.join(out_dir, name + ".json")
    with open(path, "w") as f:
        json.dump(result, f, indent=1)
    return path


def children_cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)  # finished, waited-for descendants
    return r.ru_utime + r.ru_stime


def pairs_of_groups(groups):
    pairs = []
    for gi, members in enumerate(groups):
        members = sorted(set(members))
        for i in range(len(members)):
            for j in range(i + 1, len(members)):
                pairs.append({"a": members[i], "b": members[j], "group": gi})
    return pairs


def threshold_bits(threshold):
    """findimagedupes' --threshold as the most bits that may differ: N% -> floor(2.56 (100 - N)); Nb -> N."""
    t = threshold.strip()
    if t.endswith("b"):
        return int(float(t[:-1]))
    return int(2.56 * (100 - float(t.rstrip("%"))))


def run_findimagedupes(images, out_dir, threshold):
    """Returns two results from one run: its printed sets (every pair inside a set) and its matching pairs
    themselves (fingerprints printed with -v fp, compared as its diffbits does: XOR, at most N bits)."""
    files = sorted(os.path.join(images, f) for f in os.listdir(images) if f.lower().endswith(IMAGE_EXTS))
    if any(any(c.isspace() for c in f) for f in files):
        sys.exit("run_peers: file names with white space cannot be read back from findimagedupes' output")
    t0, c0 = time.time(), children_cpu()
    # The list on stdin; -v fp prints "<base64 fingerprint>  <file>" per file; VIEW prints each set on one line.
    proc = subprocess.run(["findimagedupes", "-q", "-v", "fp", "-t", threshold, "-i", 'VIEW(){ echo "SET $*"; }',
                           "--", "-"], input="\n".join(files) + "\n", capture_output=True, text=True)
    elapsed, cpu = time.time() - t0, children_cpu() - c0
    if proc.returncode not in (0, 1):  # 1: warnings
        sys.exit("run_peers: findimagedupes exited %d: %s" % (proc.returncode, proc.stderr[-2000:]))
    groups, fps = [], {}
    for line in proc.stdout.splitlines():
        if line.startswith("SET "):
            groups.append([image_id(p) for p in line[4:].split()])
        elif line.strip():
            fp, path = line.split(None, 1)
            fps[image_id(path.strip())] = np.unpackbits(np.frombuffer(base64.b64decode(fp), dtype=np.uint8))
    settings = {"program": "findimagedupes 2.20.1 (Debian)", "threshold": threshold,
                "max_bits": threshold_bits(threshold)}
    sets = {"method": "findimagedupes",
            "settings": dict(settings, pairs="every pair inside a printed set (sets are connected components)"),
            "images": len(files), "pairs": pairs_of_groups(groups),
            "groups": [{"group": i, "images": sorted(g)} for i, g in enumerate(groups)],
            "timings_s": {"total": round(elapsed, 2), "cpu": round(cpu, 2)}}
    ids = sorted(fps)
    bits = np.array([fps[i] for i in ids])
    limit = threshold_bits(threshold)
    pairs = []
    for i in range(len(ids) - 1):
        d = np.count_nonzero(bits[i + 1:] != bits[i], axis=1)
        for j in np.nonzero(d <= limit)[0]:
            pairs.append({"a": ids[i], "b": ids[i + 1 + int(j)], "distance": int(d[j])})
    direct = {"method": "findimagedupes-pairs",
              "settings": dict(settings, pairs="its matching pairs before they are merged into sets "
                                               "(fingerprints from -v fp, at most max_bits differ)"),
              "images": len(files), "fingerprinted": len(ids),
              "not_fingerprinted": sorted(set(image_id(f) for f in files) - set(ids)), "pairs": pairs, "groups": [],
              "timings_s": {"total": round(elapsed, 2), "cpu": round(cpu, 2)}}
    return sets, direct


def run_dupeguru(images, out_dir, name, match_scaled, hardness):
    out = os.path.join(out_dir, name + ".json")
    cmd = [sys.executable, os.path.join(HERE, "dupeguru_scan.py"), "--images", images, "--out", out,
           "--work", os.path.join(out_dir, name + "-work"), "--hardness", str(hardness), "--name", name]
    if match_scaled:
        cmd.append("--match-scaled")
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    t0, c0 = time.time(), children_cpu()
    subprocess.run(cmd, check=True, env=env)
    elapsed, cpu = time.time() - t0, children_cpu() - c0
    with open(out) as f:
        result = json.load(f)
    result["timings_s"]["process"] = round(elapsed, 2)
    result["timings_s"]["cpu"] = round(cpu, 2)
    return result


def dct_matrix(n):
    k = np.arange(n)[:, None]
    x = np.arange(n)[None, :]
    return np.cos(np.pi * (2 * x + 1) * k / (2.0 * n))


def phash(path, dct=dct_matrix(32)):
    """imagehash.phash (hash_size 8, highfreq_factor 4): DCT-II (unnormalised; the scale does not change
    the comparison with the median) over rows and columns of the 32x32 grey image."""
    px = np.asarray(Image.open(path).convert("L").resize((32, 32), Image.LANCZOS), dtype=np.float64)
    coeffs = dct @ px @ dct.T
    low = coeffs[:8, :8]
    return (low > np.median(low)).flatten()


def run_phash(images, out_dir, threshold):
    files = sorted(os.path.join(images, f) for f in os.listdir(images) if f.lower().endswith(IMAGE_EXTS))
    t0, c0 = time.time(), time.process_time()
    bits = np.array([phash(f) for f in files], dtype=np.uint8)
    t_hash = time.time() - t0
    ids = [image_id(f) for f in files]
    pairs = []
    for i in range(len(files) - 1):
        d = np.count_nonzero(bits[i + 1:] != bits[i], axis=1)
        for j in np.nonzero(d <= threshold)[0]:
            pairs.append({"a": ids[i], "b": ids[i + 1 + int(j)], "distance": int(d[j])})
    elapsed = time.time() - t0
    return {"method": "phash",
            "settings": {"program": "pHash as imagehash.phash (64 bits), written with numpy/PIL",
                         "max_hamming": threshold},
            "images": len(files), "pairs": pairs, "groups": [],
            "timings_s": {"hashing": round(t_hash, 2), "total": round(elapsed, 2),
                          "cpu": round(time.process_time() - c0, 2)}}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", required=True)
    ap.add_argument("--out", required=True, help="folder for the result files")
    ap.add_argument("--peers", default=",".join(PEERS), help="comma-separated subset of " + ",".join(PEERS))
    ap.add_argument("--findimagedupes-threshold", default="90%", help="its --threshold (default 90%%, i.e. 25 bits)")
    ap.add_argument("--dupeguru-hardness", type=int, default=95)
    ap.add_argument("--phash-threshold", type=int, default=10)
    args = ap.parse_args()
    images = os.path.abspath(args.images)
    os.makedirs(args.out, exist_ok=True)
    for peer in [p for p in args.peers.split(",") if p]:
        if peer == "findimagedupes":
            result, direct = run_findimagedupes(images, args.out, args.findimagedupes_threshold)
            path = write(args.out, "findimagedupes-pairs", direct)
            print("run_peers: %-20s %6d pairs  (the same run)  -> %s" % ("findimagedupes-pairs", len(direct["pairs"]),
                                                                           path), flush=True)
        elif peer == "dupeguru":
            result = run_dupeguru(images, args.out, peer, True, args.dupeguru_hardness)
        elif peer == "dupeguru-default":
            result = run_dupeguru(images, args.out, peer, False, args.dupeguru_hardness)
        elif peer == "phash":
            result = run_phash(images, args.out, args.phash_threshold)
        else:
            sys.exit("run_peers: unknown peer %s" % peer)
        path = write(args.out, peer, result)
        print("run_peers: %-20s %6d pairs  %7.1f s (cpu %.1f s)  -> %s" % (
            peer, len(result["pairs"]), result["timings_s"]["total"], result["timings_s"]["cpu"], path), flush=True)


if __name__ == "__main__":
    main()
