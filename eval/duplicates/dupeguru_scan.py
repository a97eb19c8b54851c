#!/usr/bin/python3
"""dupeGuru's picture mode without its window: the scanner the GUI runs, on one folder.

    dupeguru_scan.py --images DIR --out FILE.json --work DIR [--hardness 95] [--match-scaled]

Drives Debian's dupeguru package (/usr/share/dupeguru): core.pe.scanner.ScannerPE with the "Contents"
scan type (fuzzy block matching: 15 x 15 average colours per picture, compared as a percentage) and
qt.pe.photo.File (Qt's image loader, EXIF orientation applied), as the GUI does after "Scan". The GUI's
defaults: filter hardness 95, "Match pictures of different dimensions" off. The result is dupeGuru's
groups (every member matches every other, as the result window shows them); pairs are all the pairs
inside a group. Writes the common result format of run_peers.py.
"""

import argparse
import json
import os
import sys
import time

DUPEGURU = "/usr/share/dupeguru"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--work", required=True, help="folder for dupeGuru's picture cache and file database")
    ap.add_argument("--hardness", type=int, default=95, help="filter hardness (minimum match percentage)")
    ap.add_argument("--match-scaled", action="store_true", help="match pictures of different dimensions")
    ap.add_argument("--name", default="dupeguru")
    args = ap.parse_args()

    if not os.path.isdir(DUPEGURU):
        sys.exit("dupeguru_scan: %s missing (Debian package dupeguru; scripts/install-deps.sh)" % DUPEGURU)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    sys.path.insert(0, DUPEGURU)
    from pathlib import Path
    from core import fs
    from core.scanner import ScanType
    from core.pe.scanner import ScannerPE
    from core.pe.photo import Photo
    from qt.pe.photo import File

    os.makedirs(args.work, exist_ok=True)
    for f in ("files.db", "pictures.db"):
        p = os.path.join(args.work, f)
        if os.path.exists(p):
            os.remove(p)
    fs.filesdb.connect(os.path.join(args.work, "files.db"))
    scanner = ScannerPE()
    scanner.scan_type = ScanType.FUZZYBLOCK
    scanner.min_match_percentage = args.hardness
    scanner.match_scaled = args.match_scaled
    scanner.mix_file_kind = True
    scanner.cache_path = os.path.join(args.work, "pictures.db")

    t0 = time.time()
    names = sorted(n for n in os.listdir(args.images)
                   if os.path.splitext(n)[1].lower().lstrip(".") in Photo.HANDLED_EXTS)
    files = [File(Path(os.path.abspath(os.path.join(args.images, n)))) for n in names]
    groups = scanner.get_dupe_groups(files)
    elapsed = time.time() - t0
    fs.filesdb.close()

    def image_id(f):
        return os.path.splitext(f.path.name)[0]

    out_groups, pairs = [], []
    for gi, g in enumerate(groups):
        members = sorted(image_id(f) for f in g)
        out_groups.append({"group": gi, "images": members})
        for i in range(len(members)):
            for j in range(i + 1, len(members)):
                pairs.append({"a": members[i], "b": members[j], "group": gi})
    result = {"method": args.name,
              "settings": {"program": "dupeGuru 4.3.1 picture mode (Debian dupeguru), scan type Contents",
                           "filter_hardness": args.hardness, "match_scaled": args.match_scaled},
              "images": len(files), "pairs": pairs, "groups": out_groups,
              "timings_s": {"total": round(elapsed, 2)}}
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print("%s: %d images, %d groups, %d pairs, %.1f s" % (args.name, len(files), len(groups), len(pairs), elapsed))


if __name__ == "__main__":
    main()
