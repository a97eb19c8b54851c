#!/usr/bin/env python3
"""Latency of GET /v1/images/{id}/thumbnail on a running `oxbow serve`, per case, over every image.

  python3 scripts/thumbnail_latency.py http://127.0.0.1:8080 [--limit 60]

Run it on an index whose thumbnails were never requested (e.g. fresh from `oxbow index build`, so the
first request makes each thumbnail from the source file). One keep-alive connection, sequential requests.
"""
import argparse, http.client, json, statistics, time, urllib.parse

parser = argparse.ArgumentParser()
parser.add_argument("url")
parser.add_argument("--limit", type=int, default=60)
args = parser.parse_args()
u = urllib.parse.urlparse(args.url)
conn = http.client.HTTPConnection(u.hostname, u.port)

def get(path, headers=None):
    start = time.perf_counter()
    conn.request("GET", path, headers=headers or {})
    response = conn.getresponse()
    body = response.read()
    return (time.perf_counter() - start) * 1000, response.status, body, response.getheader("ETag")

_, _, body, _ = get(f"/v1/images?limit={args.limit}")
ids = [urllib.parse.quote(i["id"], safe="") for i in json.loads(body)["images"]]
cases = {"first request, size=256 (made from the source file, stored)": ("256", None),
         "size=256 again (stored 512 px thumbnail, resized)": ("256", None),
         "size=512 (stored thumbnail as is)": ("512", None),
         "size=256 with If-None-Match (304)": ("256", "etag")}
times = {case: [] for case in cases}
sizes = {case: [] for case in cases}
for i in ids:
    etag = None
    for case, (size, conditional) in cases.items():
        ms, status, body, tag = get(f"/v1/images/{i}/thumbnail?size={size}",
                                    {"If-None-Match": etag} if conditional else None)
        assert status == (304 if conditional else 200), (case, status, body[:200])
        etag = etag or tag
        times[case].append(ms)
        sizes[case].append(len(body))
print(f"{len(ids)} images, one keep-alive connection, sequential")
print("| GET /v1/images/{id}/thumbnail | median ms | p90 ms | median bytes |\n|---|---:|---:|---:|")
for case in cases:
    t = sorted(times[case])
    print(f"| {case} | {statistics.median(t):.1f} | {t[int(len(t) * 0.9)]:.1f} | {int(statistics.median(sizes[case]))} |")
