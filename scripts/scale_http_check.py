#!/usr/bin/env python3
"""Measures a large index through the real server, over HTTP, as a user would (eval/results/index-scale.md).

  python3 scripts/scale_http_check.py --index DIR [--photos DIR] [--oxbow build/server/oxbow]
                                      [--queries 40] [--adds 40] [--port 18765] [--serve-arg=ARG ...]
                                      [--no-read-postings]

DIR: an index folder, e.g. the one `build/eval/bench/index_benchmark storage --images 1000000 --out DIR` leaves.
Its postings and segment files are first read into the page cache (--no-read-postings: not). It is then
served as it is by `oxbow serve --index DIR` (server defaults) and measured:
  1. start to /readyz 200 (a new server process) and resident memory when ready;
  2. searches with real photos (default: the Paris subset, else OpenCV's samples), one at a time:
     server time excluding decoding and extraction (timings_ms.total - timings_ms.decode_extract),
     p50/p95/p99, the client's wall time, and the p50 of each of the server's timings_ms stages; first
     right after /readyz, while the server's background check of the geometry files runs, then, once the
     server has logged that check's end, with other photos (so that the second round finds none of its
     postings read by the first);
  3. adds of real photos (ids scalecheck-N) while another client searches without pause: the server's
     add time excluding extraction (timings_ms.add), p50/p95/p99;
  4. kill -9 right after the last add was acknowledged, restart: time to /readyz again, and every
     acknowledged add is there (then they are deleted, leaving DIR's images as they were).
Prints one line per figure. Needs nothing beyond Python's standard library and the client in api/python (oxbow_client).
"""
import argparse
import os
import signal
import statistics
import subprocess
import sys
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "api", "python"))
import oxbow_client  # noqa: E402


def percentile(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def summary(values):
    return "p50 %.1f ms, p95 %.1f ms, p99 %.1f ms (%d)" % (percentile(values, .5), percentile(values, .95),
                                                           percentile(values, .99), len(values))


def read_postings(index):
    """Reads the index's postings and segment files once (as `cat DIR/postings* DIR/segment* >/dev/null`), so
    that the searches find them in the page cache; returns (seconds, bytes)."""
    t0 = time.monotonic()
    total = 0
    for name in sorted(os.listdir(index)):
        if not name.startswith(("postings", "segment")):
            continue
        with open(os.path.join(index, name), "rb", buffering=0) as f:
            while True:
                chunk = f.read(8 << 20)
                if not chunk:
                    break
                total += len(chunk)
    return time.monotonic() - t0, total


def start_server(args):
    """Starts `oxbow serve`; returns (process, seconds until /readyz answered 200)."""
    t0 = time.monotonic()
    proc = subprocess.Popen([args.oxbow, "serve", "--index", args.index, "--port", str(args.port)] + args.serve_arg,
                            stdout=subprocess.DEVNULL, stderr=open(args.log, "a"))
    client = oxbow_client.Client("http://127.0.0.1:%d" % args.port, timeout=120)
    while True:
        if proc.poll() is not None:
            sys.exit("oxbow serve exited with status %d (log: %s)" % (proc.returncode, args.log))
        try:
            if client.ready():
                return proc, time.monotonic() - t0
        except oxbow_client.TransportError:
            pass
        time.sleep(0.05)


def wait_for_log(path, offset, text, timeout_s):
    """Waits until `text` appears in the file at `path` after byte `offset`; returns the seconds waited,
    or None after timeout_s."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        with open(path, "rb") as f:
            f.seek(offset)
            if text.encode() in f.read():
                return time.monotonic() - t0
        time.sleep(0.5)
    return None


def search_round(client, queries, label):
    """Searches each photo in turn; prints the server's time after extraction and the client's wall time."""
    server_ms, wall_ms, stages = [], [], {}
    for path in queries:
        t0 = time.monotonic()
        found = client.search(path)
        wall_ms.append((time.monotonic() - t0) * 1000)
        t = found["timings_ms"]
        server_ms.append(t["total"] - t["decode_extract"])
        for stage, ms in t.items():
            stages.setdefault(stage, []).append(ms)
    print("search %s, server time after extraction: %s" % (label, summary(server_ms)))
    print("search %s, client wall time (upload, decode, extraction included): %s" % (label, summary(wall_ms)))
    print("search %s, the server's stages, p50: %s" % (
        label, ", ".join("%s %.1f ms" % (stage, percentile(ms, .5)) for stage, ms in stages.items())))


def rss_bytes(pid):
    with open("/proc/%d/status" % pid) as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--index", required=True)
    parser.add_argument("--photos", default=None, help="folder of real photos (default: Paris subset, else OpenCV's)")
    parser.add_argument("--oxbow", default=os.path.join(ROOT, "build", "server", "oxbow"))
    parser.add_argument("--queries", type=int, default=40)
    parser.add_argument("--adds", type=int, default=40)
    parser.add_argument("--port", type=int, default=18765)
    parser.add_argument("--check-timeout", type=int, default=600,
                        help="seconds to wait for the server's background check of the geometry files (logged)")
    parser.add_argument("--log", default="/tmp/scale_http_check.log", help="the server's stderr")
    parser.add_argument("--serve-arg", action="append", default=[],
                        help="one more argument for `oxbow serve` (repeat it), e.g. --serve-arg=--max-scored-postings=0")
    parser.add_argument("--no-read-postings", dest="read_postings", action="store_false",
                        help="do not read the postings files into the page cache before the server starts (the "
                             "method of eval/results/index-scale.md reads them: memory idle for a few seconds may be "
                             "reclaimed on a VM, and searches then measure the disk)")
    args = parser.parse_args()

    photo_dirs = [args.photos] if args.photos else [os.path.join(ROOT, "..", "shared", "data", "paris6k", "images"),
                                                    "/usr/share/doc/opencv-doc/examples/data"]
    photos = []
    for folder in photo_dirs:
        if os.path.isdir(folder):
            photos = sorted(os.path.join(folder, n) for n in os.listdir(folder) if n.lower().endswith((".jpg", ".png")))
            if photos:
                break
    if not photos:
        sys.exit("no real photos found in %s" % photo_dirs)
    step = max(1, len(photos) // args.queries)
    queries = photos[::step][:args.queries]
    chosen = set(queries)
    rest = [p for p in photos if p not in chosen] or photos
    later = rest[::max(1, len(rest) // args.queries)][:args.queries]
    print("photos: %d from %s; server log: %s" % (len(photos), os.path.dirname(photos[0]), args.log))

    if args.read_postings:
        read_s, read_bytes = read_postings(args.index)
        print("postings read into the page cache: %.2f GB in %.1f s" % (read_bytes / 1e9, read_s))
    log_offset = os.path.getsize(args.log) if os.path.exists(args.log) else 0
    proc, ready_s = start_server(args)
    client = oxbow_client.Client("http://127.0.0.1:%d" % args.port, timeout=120)
    stats = client.stats()
    features = stats.get("features", 0)
    rss = rss_bytes(proc.pid)
    print("start to /readyz: %.1f s; %s images, %s features; RSS when ready %.2f GB = %.2f bytes per feature"
          % (ready_s, stats.get("images"), features, rss / 1e9, rss / max(1, features)))

    search_round(client, queries, "right after /readyz")
    waited = wait_for_log(args.log, log_offset, "geometry files of the checkpoint verified", args.check_timeout)
    if waited is None:
        print("the background check of the geometry files did not end within %d s: no second round" % args.check_timeout)
    else:
        print("background check of the geometry files ended %.1f s after the first round" % waited)
        search_round(client, later, "after the background check")

    stop = threading.Event()
    searched = [0]

    def search_loop():
        searcher = oxbow_client.Client("http://127.0.0.1:%d" % args.port, timeout=120)
        i = 0
        while not stop.is_set():
            searcher.search(queries[i % len(queries)])
            searched[0] += 1
            i += 1

    thread = threading.Thread(target=search_loop)
    thread.start()
    add_ms = []
    ids = []
    try:
        for i in range(args.adds):
            added = client.add("scalecheck-%d" % i, photos[(i * 7) % len(photos)], replace=True)
            add_ms.append(added["timings_ms"]["add"])
            ids.append("scalecheck-%d" % i)
    finally:
        stop.set()
        thread.join()
    print("add while searching, server time excluding extraction: %s; %d searches ran alongside"
          % (summary(add_ms), searched[0]))
    print("RSS after searches and adds: %.2f bytes per feature" % (rss_bytes(proc.pid) / max(1, features)))

    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc, ready_s = start_server(args)
    missing = []
    for i in ids:
        try:
            client.get(i)
        except oxbow_client.NotFoundError:
            missing.append(i)
    print("restart after kill -9 (right after the last acknowledged add): /readyz in %.1f s; %d of %d acknowledged "
          "adds present" % (ready_s, len(ids) - len(missing), len(ids)))
    remove_ms = []
    for i in ids:
        if i not in missing:
            t0 = time.monotonic()
            client.delete(i)
            remove_ms.append((time.monotonic() - t0) * 1000)
    print("delete, client wall time: %s" % summary(remove_ms))
    proc.send_signal(signal.SIGTERM)
    proc.wait()
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
