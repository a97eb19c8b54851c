#!/usr/bin/env python3
"""Bounded load client for `oxbow serve` (used by scripts/load_test.sh; loopback only).

Runs two phases of equal length against one server:
  idle:   S search clients (POST /v1/search with an image) + G similar clients (GET /v1/images/{id}/similar)
  adds:   the same, plus A clients adding new images (POST /v1/images) as fast as they are acknowledged
and prints, per phase and kind, requests, errors, throughput and latency percentiles, then the ratio of
search p99 during adds to idle. Exit status 1 when any request failed (non-2xx or transport error).
Standard library only (http.client, threads): the server, not the client, is the bottleneck here.
"""
import argparse
import http.client
import json
import statistics
import sys
import threading
import time
import urllib.parse


def percentile(values, q):
    if not values:
        return float("nan")
    values = sorted(values)
    k = (len(values) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(values) - 1)
    return values[lo] + (values[hi] - values[lo]) * (k - lo)


class Recorder:
    def __init__(self):
        self.lock = threading.Lock()
        self.latencies = {}
        self.errors = {}
        self.samples = []

    def record(self, kind, seconds, ok, detail=""):
        with self.lock:
            self.latencies.setdefault(kind, [])
            self.errors.setdefault(kind, 0)
            if ok:
                self.latencies[kind].append(seconds * 1000)
            else:
                self.errors[kind] += 1
                if len(self.samples) < 5:
                    self.samples.append(f"{kind}: {detail}")


def worker(host, port, kind, deadline, recorder, make_request):
    conn = http.client.HTTPConnection(host, port, timeout=60)
    i = 0
    while time.monotonic() < deadline:
        method, path, body, headers = make_request(i)
        i += 1
        start = time.monotonic()
        try:
            conn.request(method, path, body=body, headers=headers)
            response = conn.getresponse()
            payload = response.read()
            elapsed = time.monotonic() - start
            ok = 200 <= response.status < 300
            recorder.record(kind, elapsed, ok, f"{response.status} {payload[:200]!r}")
            if response.getheader("Connection", "").lower() == "close":
                conn.close()
                conn = http.client.HTTPConnection(host, port, timeout=60)
        except Exception as e:  # transport error: count it and reconnect
            recorder.record(kind, time.monotonic() - start, False, repr(e))
            conn.close()
            conn = http.client.HTTPConnection(host, port, timeout=60)
    conn.close()


def run_phase(args, queries, add_images, similar_ids, with_adds, id_prefix):
    recorder = Recorder()
    deadline = time.monotonic() + args.seconds
    threads = []
    for c in range(args.search_clients):
        def search(i, c=c):
            name, data = queries[(i + c) % len(queries)]
            return "POST", f"/v1/search?top_k={args.top_k}", data, {"Content-Type": "application/octet-stream"}
        threads.append(threading.Thread(target=worker, args=(args.host, args.port, "search", deadline, recorder, search)))
    for c in range(args.similar_clients):
        def similar(i, c=c):
            image_id = urllib.parse.quote(similar_ids[(i + c) % len(similar_ids)], safe="")
            return "GET", f"/v1/images/{image_id}/similar?top_k={args.top_k}", None, {}
        threads.append(threading.Thread(target=worker, args=(args.host, args.port, "similar", deadline, recorder, similar)))
    if with_adds:
        for c in range(args.add_clients):
            def add(i, c=c):
                name, data = add_images[(i + c) % len(add_images)]
                image_id = urllib.parse.quote(f"{id_prefix}-{c}-{i}", safe="")
                return "POST", f"/v1/images?id={image_id}", data, {"Content-Type": "application/octet-stream"}
            threads.append(threading.Thread(target=worker, args=(args.host, args.port, "add", deadline, recorder, add)))
    start = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return recorder, time.monotonic() - start


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--seconds", type=float, default=20, help="length of each phase")
    p.add_argument("--search-clients", type=int, default=2)
    p.add_argument("--similar-clients", type=int, default=2)
    p.add_argument("--add-clients", type=int, default=1)
    p.add_argument("--top-k", type=int, default=10)
    p.add_argument("--query", action="append", required=True, help="query image file (repeatable)")
    p.add_argument("--add", action="append", required=True, help="image file to add during the add phase (repeatable)")
    p.add_argument("--json", help="also write the figures to this JSON file")
    args = p.parse_args()
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        sys.exit("load_client: loopback only")

    read = lambda path: (path, open(path, "rb").read())
    queries = [read(q) for q in args.query]
    add_images = [read(a) for a in args.add]
    conn = http.client.HTTPConnection(args.host, args.port, timeout=30)
    conn.request("GET", "/v1/images?limit=50")
    listing = json.loads(conn.getresponse().read())
    similar_ids = [image["id"] for image in listing["images"]]
    if not similar_ids and args.similar_clients:
        sys.exit("load_client: the index is empty; nothing to query with /similar")

    results = {}
    failed = 0
    samples = []
    prefix = f"load-{int(time.time())}"
    for phase, with_adds in (("idle", False), ("adds", True)):
        recorder, wall = run_phase(args, queries, add_images, similar_ids, with_adds, prefix)
        results[phase] = {}
        for kind in sorted(recorder.latencies):
            lat = recorder.latencies[kind]
            results[phase][kind] = {
                "requests": len(lat) + recorder.errors[kind],
                "errors": recorder.errors[kind],
                "per_s": len(lat) / wall,
                "p50_ms": percentile(lat, 0.50),
                "p95_ms": percentile(lat, 0.95),
                "p99_ms": percentile(lat, 0.99),
                "max_ms": max(lat) if lat else float("nan"),
                "mean_ms": statistics.fmean(lat) if lat else float("nan"),
            }
            failed += recorder.errors[kind]
        samples += recorder.samples

    print(f"\nload test: {args.seconds:.0f} s per phase; {args.search_clients} search + {args.similar_clients} similar "
          f"clients, {args.add_clients} add client(s) in the 'adds' phase; top_k={args.top_k}")
    print(f"| phase | route | requests | errors | req/s | p50 ms | p95 ms | p99 ms | max ms |")
    print(f"|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for phase, kinds in results.items():
        for kind, r in kinds.items():
            print(f"| {phase} | {kind} | {r['requests']} | {r['errors']} | {r['per_s']:.1f} | {r['p50_ms']:.1f} | "
                  f"{r['p95_ms']:.1f} | {r['p99_ms']:.1f} | {r['max_ms']:.1f} |")
    for kind in ("search", "similar"):
        if kind in results["idle"] and kind in results["adds"]:
            ratio = results["adds"][kind]["p99_ms"] / results["idle"][kind]["p99_ms"]
            results[f"{kind}_p99_ratio"] = ratio
            print(f"{kind} p99 during adds / idle: {ratio:.2f}x (target <= 2x)")
    print(f"errors: {failed}")
    for s in samples:
        print("  e.g.", s)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
