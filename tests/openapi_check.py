#!/usr/bin/env python3
"""Checks running `oxbow serve` processes against the OpenAPI description they serve (GET /v1/openapi.json).

Sends requests that cover every route with success and error answers, and validates every response
(status listed for that route and method, content type, body against the schema of that status, required
headers) against the document; derives out-of-range requests from the parameter ranges the document
states; checks that the document's paths and methods are exactly the server's route table (GET /v1).
Run by tests/openapi_test.cc, which starts the servers:

  openapi_check.py --url URL --keyed-url URL --data-url URL --api-key KEY --image PNG --other-image PNG

--url: a server without API key and with --max-upload-mb 1; --keyed-url: one with --api-key KEY,
--request-timeout-s 1 and --max-connections-per-client 4. Both start on an empty index over the same
vocabulary. --data-url: `oxbow serve --data DIR --vocab V --api-key KEY` on an empty data folder (its
collection `default` made with that vocabulary), for the collection routes and the duplicate jobs. Exit 0:
every check passed; 1: failures (listed); 77: python3-jsonschema is missing.
"""

import argparse
import json
import os
import re
import shutil
import socket
import struct
import sys
import tempfile
import time
import urllib.parse
import zlib

try:
    import jsonschema
except ImportError:
    print("openapi_check: python3-jsonschema is missing (scripts/install-deps.sh installs it)")
    sys.exit(77)


class Response:
    def __init__(self, raw):
        head, _, body = raw.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        self.status = int(lines[0].split(" ")[1]) if lines[0].startswith("HTTP/") else 0
        self.headers = {}
        for line in lines[1:]:
            name, _, value = line.partition(":")
            self.headers[name.strip().lower()] = value.strip()
        length = int(self.headers.get("content-length", len(body)))
        self.body = body[:length]

    def json(self):
        return json.loads(self.body)


def exchange(base, raw, partial_wait=0.0):
    """Sends `raw` bytes (a whole request) on a new connection to `base`; reads the response until close.
    With partial_wait, waits that long after sending (a body that never completes)."""
    host, port = urllib.parse.urlsplit(base).netloc.split(":")
    with socket.create_connection((host, int(port)), timeout=60) as s:
        s.sendall(raw)
        if partial_wait:
            time.sleep(partial_wait)
        return Response(receive(s, one_response=True))


def receive(s, one_response):
    """The bytes `s` receives until the server closes (or resets) it, or, with one_response, until one
    whole response with a Content-Length has arrived."""
    data = b""
    while True:
        try:
            chunk = s.recv(65536)
        except ConnectionResetError:
            break
        if not chunk:
            break
        data += chunk
        if one_response and b"\r\n\r\n" in data:
            r = Response(data)
            if "content-length" in r.headers and len(r.body) >= int(r.headers["content-length"]):
                break
    return data


def exchange_pipelined(base, raws):
    """Sends several whole requests at once on one connection (HTTP/1.1 pipelining: the server reads the
    next as soon as it has answered the previous; all but the last should say Connection: keep-alive);
    the responses, in order."""
    host, port = urllib.parse.urlsplit(base).netloc.split(":")
    with socket.create_connection((host, int(port)), timeout=60) as s:
        s.sendall(b"".join(raws))
        data = receive(s, one_response=False)
    responses = []
    while b"\r\n\r\n" in data:
        r = Response(data)
        responses.append(r)
        data = data.partition(b"\r\n\r\n")[2][len(r.body):]
    return responses


def build(method, target, headers=None, body=b"", version="HTTP/1.1", connection="close"):
    lines = [f"{method} {target} {version}", "Host: 127.0.0.1", f"Connection: {connection}"]
    headers = dict(headers or {})
    if (body or method in ("POST", "PUT")) and "Content-Length" not in headers and "Transfer-Encoding" not in headers:
        headers["Content-Length"] = str(len(body))
    lines += [f"{k}: {v}" for k, v in headers.items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body


def multipart(parts):
    """parts: [(name, bytes, filename or None)] -> (content type, body)."""
    boundary = "oxbowopenapicheck"
    out = b""
    for name, value, filename in parts:
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out += f"--{boundary}\r\nContent-Disposition: {disposition}\r\n".encode()
        if filename:
            out += b"Content-Type: application/octet-stream\r\n"
        out += b"\r\n" + value + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return f"multipart/form-data; boundary={boundary}", out


def png(width, height, rows=None):
    """A grey 8-bit PNG; `rows` (bytes per row) default flat. A header may declare more than the data holds."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    raw = b"".join(b"\0" + (rows[y] if rows else bytes([128]) * width) for y in range(min(height, 64)))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)) +
            chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def pointer(ref):
    """The keys of a local JSON pointer reference ("#/components/schemas/Error")."""
    if not ref.startswith("#/"):
        raise KeyError(ref)
    return [urllib.parse.unquote(p).replace("~1", "/").replace("~0", "~") for p in ref[2:].split("/")]


def resolve(doc, node):
    """`node`, or what its $ref (a chain of them) points to in `doc`."""
    while isinstance(node, dict) and "$ref" in node:
        target = doc
        for part in pointer(node["$ref"]):
            target = target[part]
        node = target
    return node


class Checker:
    def __init__(self, doc):
        self.doc = doc
        self.failures = []
        self.seen = {}  # (template, method) -> set of statuses
        self.templates = []
        literal_first = sorted(doc["paths"], key=lambda p: "{" in p)
        for template in literal_first:
            pattern = "^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(template)) + "$"
            self.templates.append((template, re.compile(pattern)))

    def fail(self, what):
        self.failures.append(what)
        print("FAIL", what)

    def resolve(self, node):
        return resolve(self.doc, node)

    def validate(self, instance, schema, what):
        # The schema's $refs point into the document's components: validate it with those beside it.
        wrapper = dict(schema)
        wrapper["components"] = self.doc["components"]
        errors = sorted(jsonschema.Draft202012Validator(wrapper).iter_errors(instance), key=lambda e: list(e.path))
        for e in errors[:3]:
            self.fail(f"{what}: {'/'.join(map(str, e.absolute_path)) or '(root)'}: {e.message[:300]}")
        return not errors

    def route(self, path):
        for template, pattern in self.templates:
            if pattern.match(path):
                return template
        return None

    def check(self, name, base, method, target, expect, code=None, headers=None, body=b"", raw=None, partial_wait=0.0):
        """Sends the request, checks it got `expect` (and error `code`), validates it against the
        document; returns the Response."""
        r = exchange(base, raw or build(method, target, headers, body), partial_wait)
        what = f"{name}: {method} {target[:80]} -> {r.status}"
        if r.status != expect:
            self.fail(f"{what}: expected {expect}; body {r.body[:300]!r}")
        self.conform(what, method, target, r)
        if code is not None and r.status >= 400:
            got = r.json().get("error", {}).get("code") if r.headers.get("content-type", "").startswith("application/json") else None
            if got != code:
                self.fail(f"{what}: expected error code {code}, got {got}")
        return r

    def conform(self, what, method, target, r):
        path = urllib.parse.urlsplit(target).path if target.startswith("/") else "?"
        template = self.route(path)
        if template is None:
            response = self.resolve(self.doc["components"]["responses"]["NotFound"])
            if r.status != 404:
                self.fail(f"{what}: a path that is no route must get 404")
        elif method.lower() not in self.doc["paths"][template]:
            response = self.resolve(self.doc["components"]["responses"]["MethodNotAllowed"])
            documented = {m.upper() for m in self.doc["paths"][template] if m != "parameters"}
            if "GET" in documented:
                documented.add("HEAD")  # answered as GET without a body (the document's description)
            allowed = {m.strip() for m in r.headers.get("allow", "").split(",") if m.strip()}
            if r.status != 405 or allowed != documented:
                self.fail(f"{what}: an undescribed method must get 405 with Allow {sorted(documented)}, got Allow {sorted(allowed)}")
        else:
            responses = self.doc["paths"][template][method.lower()]["responses"]
            self.seen.setdefault((template, method.lower()), set()).add(str(r.status))
            if str(r.status) not in responses:
                self.fail(f"{what}: status {r.status} is not described for {method} {template}")
                return
            response = self.resolve(responses[str(r.status)])
        for name, header in response.get("headers", {}).items():
            header = self.resolve(header)
            value = r.headers.get(name.lower())
            if value is None:
                if header.get("required"):
                    self.fail(f"{what}: required header {name} missing")
            elif "schema" in header:
                self.validate(value, header["schema"], f"{what}: header {name}")
        content = response.get("content")
        if not content:
            if r.body:
                self.fail(f"{what}: the description has no body for this status, got {len(r.body)} bytes")
            return
        media = self.media_type(r.headers.get("content-type", ""), content)
        if media is None:
            self.fail(f"{what}: Content-Type {r.headers.get('content-type')!r} not among {sorted(content)}")
            return
        schema = content[media].get("schema")
        if media.startswith("application/json"):
            try:
                body = r.json()
            except ValueError as e:
                self.fail(f"{what}: body is not JSON: {e}")
                return
            if schema is not None:
                self.validate(body, schema, what)
            if r.status >= 400 and body.get("error", {}).get("request_id") != r.headers.get("x-request-id"):
                self.fail(f"{what}: error request_id differs from the X-Request-Id header")
        elif schema is not None and schema.get("type") == "string":
            self.validate(r.body.decode("utf-8"), schema, what)

    @staticmethod
    def media_type(given, content):
        if given in content:
            return given
        base = given.split(";")[0].strip()
        for key in content:
            k = key.split(";")[0].strip()
            if k == base or k == "*/*" or (k.endswith("/*") and base.startswith(k[:-1])):
                return key
        return None


def walk(node, path=""):
    if isinstance(node, dict):
        yield path, node
        for k, v in node.items():
            yield from walk(v, f"{path}/{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from walk(v, f"{path}/{i}")


def check_document(c, doc, routes):
    """The document on its own (no Debian package validates OpenAPI 3.1 itself): version, $refs, every
    schema valid JSON Schema 2020-12, operations complete; and its paths = the server's route table."""
    if not str(doc.get("openapi", "")).startswith("3.1."):
        c.fail(f"openapi version {doc.get('openapi')!r} is not 3.1.x")
    for key in ("info", "paths", "components"):
        if key not in doc:
            c.fail(f"document has no {key}")
    for where, node in walk(doc):
        if "$ref" in node and isinstance(node["$ref"], str):
            try:
                resolve(doc, node)
            except (KeyError, IndexError, TypeError):
                c.fail(f"{where}: $ref {node['$ref']} does not resolve")
        if "schema" in node and isinstance(node["schema"], dict) and not where.endswith("/properties"):
            try:
                jsonschema.Draft202012Validator.check_schema(node["schema"])
            except jsonschema.SchemaError as e:
                c.fail(f"{where}/schema: not a valid JSON Schema 2020-12: {e.message[:200]}")
    for name, schema in doc["components"]["schemas"].items():
        try:
            jsonschema.Draft202012Validator.check_schema(schema)
        except jsonschema.SchemaError as e:
            c.fail(f"components/schemas/{name}: not a valid JSON Schema 2020-12: {e.message[:200]}")
    operation_ids = set()
    for template, item in doc["paths"].items():
        for method, operation in item.items():
            if method == "parameters":
                continue
            if method not in ("get", "put", "post", "delete", "options", "head", "patch", "trace"):
                c.fail(f"{template}: unknown method {method}")
                continue
            if operation.get("operationId") in operation_ids or not operation.get("responses"):
                c.fail(f"{method} {template}: duplicate operationId or no responses")
            operation_ids.add(operation.get("operationId"))
            params = [resolve(doc, p) for p in item.get("parameters", []) + operation.get("parameters", [])]
            declared = {p["name"] for p in params if p["in"] == "path"}
            if declared != set(re.findall(r"\{([^}]+)\}", template)):
                c.fail(f"{method} {template}: path parameters {sorted(declared)} do not match the template")
            for status, response in operation["responses"].items():
                if not re.fullmatch(r"[1-5][0-9][0-9]", status) or "description" not in resolve(doc, response):
                    c.fail(f"{method} {template}: response {status} is not a status with a description")
    served = {r["route"]: {m.strip().lower() for m in r["methods"].split(",")} for r in routes}
    described = {t: {m for m in item if m != "parameters"} for t, item in doc["paths"].items()}
    if served != described:
        c.fail(f"paths and methods differ from the route table (GET /v1): served {sorted(served.items())}, "
               f"described {sorted(described.items())}")


def probes(doc, parameter):
    """(valid values, invalid values) for a parameter, from the range its schema states; None when the
    schema states no range to probe (free strings)."""
    schema = resolve(doc, parameter["schema"])
    valid, invalid = [], []
    for s in schema.get("anyOf", [schema]):
        kind = s.get("type")
        if "enum" in s:
            valid += s["enum"]
            invalid.append("bogus")
        elif kind == "integer":
            valid += [str(s["minimum"]), str(s["maximum"])]
            invalid += [str(s["minimum"] - 1), str(s["maximum"] + 1), "1.5"]
        elif kind == "number" and "exclusiveMinimum" in s:
            valid.append(str(s["maximum"]))
            invalid += [str(s["exclusiveMinimum"]), str(s["maximum"] + 0.5), "x"]
        elif kind == "number":
            valid += [str(s["minimum"]), str(s["maximum"])]
            invalid += [str(s["minimum"] - 0.5), str(s["maximum"] + 0.5), "x"]
        elif kind == "boolean":
            valid += ["true", "false"]
            invalid.append("maybe")
        elif kind == "array" and s.get("minItems") == 4:
            valid.append("10,10,300,200")
            invalid += ["10,10,300", "300,10,10,200", "10,10,300,200,5"]
        else:
            return None
    return valid, invalid


def probe_ranges(c, base, template, method, send):
    """Every query parameter of the operation at the ends of its range (2xx) and just outside (400
    invalid_argument), plus an unknown and a repeated one; send(query) sends the request."""
    item = c.doc["paths"][template]
    for parameter in [resolve(c.doc, p) for p in item.get("parameters", []) + item[method].get("parameters", [])]:
        if parameter["in"] != "query":
            continue
        found = probes(c.doc, parameter)
        if found is None:
            continue
        name = parameter["name"]
        for value in found[0]:
            r = send(f"{name}={urllib.parse.quote(str(value))}", 200, None, f"{name}={value}")
            if r.status >= 300:
                c.fail(f"{method} {template}: {name}={value} is inside the described range but got {r.status}")
        for value in found[1]:
            send(f"{name}={urllib.parse.quote(str(value))}", 400, "invalid_argument", f"{name}={value}")
    send("no_such_parameter=1", 400, "invalid_argument", "unknown parameter")
    first = next(resolve(c.doc, p)["name"] for p in item[method]["parameters"] if resolve(c.doc, p)["in"] == "query")
    send(f"{first}=1&{first}=2", 400, "invalid_argument", "repeated parameter")


def check_collections(c, url, data, key, image, other):
    """The collection routes on `data` (oxbow serve --data, admin key `key`) and the refusals of `url`
    (a server of one index folder, without a key)."""
    json_type = {"Content-Type": "application/json"}
    admin = {"X-API-Key": key}
    png_type = {"Content-Type": "image/png"}

    def post_json(name, base, target, body, expect, code=None, headers=None):
        return c.check(name, base, "POST", target, expect, code, headers={**json_type, **(headers or {})},
                       body=json.dumps(body).encode())

    # Listing, creating.
    c.check("collections", data, "GET", "/v1/collections", 200)
    r = c.check("collections unknown key", data, "GET", "/v1/collections", 200, headers={"X-API-Key": "wrong"})
    create = {"name": "alpha", "vocabulary": {"like": "default"}}
    post_json("create without key", data, "/v1/collections", create, 401, "unauthenticated")
    post_json("create wrong key", data, "/v1/collections", create, 403, "permission_denied", {"X-API-Key": "wrong"})
    post_json("create on a server without key", url, "/v1/collections", create, 403, "permission_denied")
    post_json("create bad name", data, "/v1/collections", {**create, "name": "Alpha"}, 400, "invalid_argument", admin)
    post_json("create unknown like", data, "/v1/collections", {**create, "vocabulary": {"like": "nope"}}, 404, "not_found", admin)
    r = post_json("create", data, "/v1/collections", create, 201, headers=admin)
    if r.status == 201 and (r.json().get("name") != "alpha" or r.json().get("public") is not False):
        c.fail(f"create: {r.body[:300]!r}")
    post_json("create taken", data, "/v1/collections", create, 409, "already_exists", admin)
    post_json("create full", data, "/v1/collections", {"name": "full", "vocabulary": {"like": "default"}, "public": True,
                                                       "max_images": 0}, 201, headers=admin)
    r = c.check("collections admin", data, "GET", "/v1/collections", 200, headers=admin)
    if r.status == 200 and [x["name"] for x in r.json()["collections"]] != ["alpha", "default", "full"]:
        c.fail(f"collections with the admin key: {r.body[:300]!r}")
    r = c.check("collections without key", data, "GET", "/v1/collections", 200)
    if r.status == 200 and "alpha" in [x["name"] for x in r.json()["collections"]]:
        c.fail("collections without key: lists the private collection alpha")
    c.check("collection", data, "GET", "/v1/collections/alpha", 200, headers=admin)
    c.check("collection without key", data, "GET", "/v1/collections/alpha", 401, "unauthenticated")
    c.check("collection unknown", data, "GET", "/v1/collections/nope", 404, "not_found", headers=admin)

    # Keys.
    keys = "/v1/collections/alpha/keys"
    r = post_json("key write", data, keys, {"access": "write"}, 201, headers=admin)
    write = {"X-API-Key": r.json().get("key", "")} if r.status == 201 else {}
    r = post_json("key read", data, keys, {"access": "read"}, 201, headers=admin)
    read = {"X-API-Key": r.json().get("key", "")} if r.status == 201 else {}
    read_id = r.json().get("id", "x") if r.status == 201 else "x"
    post_json("key bad access", data, keys, {"access": "admin"}, 400, "invalid_argument", admin)
    post_json("key by a collection key", data, keys, {"access": "read"}, 403, "permission_denied", write)
    c.check("keys", data, "GET", keys, 200, headers=admin)
    c.check("keys without key", data, "GET", keys, 401, "unauthenticated")
    r = post_json("key of full", data, "/v1/collections/full/keys", {"access": "write"}, 201, headers=admin)
    other_key = {"X-API-Key": r.json().get("key", "")} if r.status == 201 else {}

    # The image and search routes of a collection, with its keys.
    base = "/v1/collections/alpha"
    r = c.check("collection add", data, "POST", f"{base}/images?id=a", 201, headers={**png_type, **write}, body=image)
    if r.headers.get("location") != f"{base}/images/a":
        c.fail(f"collection add: Location {r.headers.get('location')!r}")
    c.check("collection add b", data, "POST", f"{base}/images?id=b", 201, headers={**png_type, **write}, body=other)
    c.check("collection add without key", data, "POST", f"{base}/images?id=k", 401, "unauthenticated", headers=png_type, body=image)
    c.check("collection add read key", data, "POST", f"{base}/images?id=k", 403, "permission_denied", headers={**png_type, **read}, body=image)
    c.check("collection add other key", data, "POST", f"{base}/images?id=k", 403, "permission_denied", headers={**png_type, **other_key}, body=image)
    c.check("collection add unknown (other key)", data, "POST", "/v1/collections/nope/images?id=k", 403, "permission_denied",
            headers={**png_type, **other_key}, body=image)
    ctype, body = multipart([("image", image, "c.png"), ("id", b"c", None)])
    c.check("collection batch", data, "POST", f"{base}/images/batch", 200, headers={"Content-Type": ctype, **write}, body=body)
    c.check("collection batch read key", data, "POST", f"{base}/images/batch", 403, "permission_denied",
            headers={"Content-Type": ctype, **read}, body=body)
    c.check("collection full", data, "POST", "/v1/collections/full/images?id=f", 507, "collection_full", headers={**png_type, **admin}, body=image)
    c.check("collection full batch", data, "POST", "/v1/collections/full/images/batch", 507, "collection_full",
            headers={"Content-Type": ctype, **admin}, body=body)
    c.check("collection list", data, "GET", f"{base}/images", 200, headers=read)
    c.check("collection list without key", data, "GET", f"{base}/images", 401, "unauthenticated")
    c.check("collection get", data, "GET", f"{base}/images/a", 200, headers=read)
    c.check("collection get unknown", data, "GET", f"{base}/images/nope", 404, "not_found", headers=read)
    c.check("collection thumbnail", data, "GET", f"{base}/images/a/thumbnail", 200, headers=read)
    c.check("collection thumbnail unknown", data, "GET", f"{base}/images/nope/thumbnail", 404, "not_found", headers=read)
    c.check("collection similar", data, "GET", f"{base}/images/a/similar", 200, headers=read)
    c.check("collection similar unknown", data, "GET", f"{base}/images/nope/similar", 404, "not_found", headers=read)
    c.check("collection search", data, "POST", f"{base}/search", 200, headers={**png_type, **read}, body=image)
    c.check("collection search without key", data, "POST", f"{base}/search", 401, "unauthenticated", headers=png_type, body=image)
    c.check("collection stats", data, "GET", f"{base}/stats", 200, headers=read)
    c.check("collection stats without key", data, "GET", f"{base}/stats", 401, "unauthenticated")
    check_duplicate_jobs(c, data, key, write, read, other_key)

    c.check("collection delete read key", data, "DELETE", f"{base}/images/b", 403, "permission_denied", headers=read)
    c.check("collection delete", data, "DELETE", f"{base}/images/b", 200, headers=write)

    # Backup, revoking, deleting.
    backups = tempfile.mkdtemp(prefix="oxbow-openapi-collection-backup-")
    try:
        post_json("collection backup", data, f"{base}/backup", {"out": os.path.join(backups, "alpha")}, 200, headers=admin)
        post_json("collection backup relative", data, f"{base}/backup", {"out": "alpha"}, 400, "invalid_argument", admin)
        post_json("collection backup write key", data, f"{base}/backup", {"out": os.path.join(backups, "b")}, 403,
                  "permission_denied", write)
    finally:
        shutil.rmtree(backups, ignore_errors=True)
    c.check("key delete", data, "DELETE", f"{keys}/{read_id}", 200, headers=admin)
    c.check("key delete again", data, "DELETE", f"{keys}/{read_id}", 404, "not_found", headers=admin)
    c.check("revoked key", data, "GET", f"{base}/images", 403, "permission_denied", headers=read)
    c.check("collection delete without key", data, "DELETE", base, 401, "unauthenticated")
    c.check("collection delete", data, "DELETE", base, 200, headers=admin)
    c.check("collection delete again", data, "DELETE", base, 404, "not_found", headers=admin)
    c.check("collection delete on a server without key", url, "DELETE", "/v1/collections/default", 403, "permission_denied")


def check_duplicate_jobs(c, data, key, write, read, other_key):
    """The duplicate searches of `data` as jobs: POST .../duplicates, GET and DELETE /v1/jobs/{job}. The
    collection alpha holds the images a and c (the same picture) and b (another) when this runs; `write`
    and `read` are its keys, `other_key` a write key of the public, empty collection full."""
    json_type = {"Content-Type": "application/json"}
    admin = {"X-API-Key": key}
    dup = "/v1/collections/alpha/duplicates"

    def start(name, target, body, expect, code=None, headers=None):
        return c.check(name, data, "POST", target, expect, code, headers={**json_type, **(headers or {})},
                       body=body if isinstance(body, bytes) else json.dumps(body).encode())

    def follow(job, headers, name="job"):
        """GET /v1/jobs/{job} until the job no longer runs (at most 60 s); the last answer."""
        deadline = time.monotonic() + 60
        while True:
            r = c.check(name, data, "GET", f"/v1/jobs/{job}", 200, headers=headers)
            if r.status != 200 or r.json().get("state") != "running" or time.monotonic() > deadline:
                return r
            time.sleep(0.02)

    def started(r, collection):
        """The job id of a 202 answer (None otherwise), its Location and collection checked."""
        if r.status != 202:
            return None
        job = r.json().get("job", "")
        if r.headers.get("location") != f"/v1/jobs/{job}" or r.json().get("collection") != collection:
            c.fail(f"duplicates on {collection}: Location {r.headers.get('location')!r}, body {r.body[:200]!r}")
        return job

    # Refusals before any job starts: keys, unknown collection, bodies.
    start("duplicates without key", dup, {}, 401, "unauthenticated")
    start("duplicates read key", dup, {}, 403, "permission_denied", read)
    start("duplicates other key", dup, {}, 403, "permission_denied", other_key)
    start("duplicates unknown (other key)", "/v1/collections/nope/duplicates", {}, 403, "permission_denied", other_key)
    start("duplicates unknown collection", "/v1/collections/nope/duplicates", {}, 404, "not_found", admin)
    for body in ({"candidates": 0}, {"candidates": 1001}, {"candidates": 1.5}, {"mirrored": "yes"},
                 {"min_coverage": -0.1}, {"min_coverage": 1.5}, {"near_copy_coverage": 2}, {"threads": -1},
                 {"threads": 257}, {"max_anisotropy": 2}, {"nope": 1}, [], "text", b"{", b"candidates=5"):
        start(f"duplicates body {body!r}", dup, body, 400, "invalid_argument", write)

    # A job with every option at one end of its range, then at the other; the report echoes them.
    for options in ({"candidates": 1, "mirrored": False, "min_coverage": 0, "near_copy_coverage": 1, "threads": 0},
                    {"candidates": 1000, "mirrored": True, "min_coverage": 1, "near_copy_coverage": 0, "threads": 2}):
        job = started(start(f"duplicates {options}", dup, options, 202, headers=write), "alpha")
        if job:
            r = follow(job, write)
            settings = r.json().get("result", {}).get("settings", {}) if r.status == 200 else {}
            if any(settings.get(k) != v for k, v in options.items() if k != "threads"):
                c.fail(f"duplicates {options}: settings {settings}")
            c.check("job delete (done)", data, "DELETE", f"/v1/jobs/{job}", 200, headers=write)

    # One job per collection: a second start while the first runs is 409. Both requests go pipelined on one
    # connection, so the second is answered microseconds after the first, while the job (milliseconds) still
    # runs; should the job end first all the same (a loaded machine), both start, and the pair is sent again.
    job, conflict = None, False
    for attempt in range(5):
        raws = [build("POST", dup, {**json_type, **write}, b"{}", connection="keep-alive"),
                build("POST", dup, {**json_type, **write}, b"{}")]
        answers = exchange_pipelined(data, raws)
        for r in answers:
            c.conform(f"duplicates pipelined ({attempt}): POST {dup} -> {r.status}", "POST", dup, r)
        statuses = [r.status for r in answers]
        jobs = [started(r, "alpha") for r in answers if r.status == 202]
        for j in jobs:
            last = follow(j, read, "job read key")
        if statuses == [202, 409]:
            conflict = True
            if answers[1].json().get("error", {}).get("code") != "already_exists":
                c.fail(f"duplicates while one runs: {answers[1].body[:300]!r}")
            job = jobs[0]
            break
        if statuses != [202, 202]:
            c.fail(f"duplicates pipelined: statuses {statuses}")
            break
        for j in jobs:
            c.check("job delete (done)", data, "DELETE", f"/v1/jobs/{j}", 200, headers=write)
    if not conflict:
        c.fail("duplicates: no 409 for a second job while one runs (5 pipelined attempts)")
    if job:
        # The report of alpha: a and c are one picture (an exact pair, a group), b another.
        report = last.json().get("result", {}) if last.status == 200 else {}
        if (last.json().get("state") != "done" or last.json().get("done") != 3 or last.json().get("total") != 3 or
                [(p["a"], p["b"], p["kind"]) for p in report.get("pairs", [])] != [("a", "c", "exact")] or
                report.get("groups") != [{"group": 0, "images": ["a", "c"]}]):
            c.fail(f"duplicates of alpha: {last.body[:600]!r}")
        c.check("job without key", data, "GET", f"/v1/jobs/{job}", 401, "unauthenticated")
        c.check("job other key", data, "GET", f"/v1/jobs/{job}", 403, "permission_denied", headers=other_key)
        c.check("job wrong key", data, "GET", f"/v1/jobs/{job}", 403, "permission_denied", headers={"X-API-Key": "wrong"})
        c.check("job admin", data, "GET", f"/v1/jobs/{job}", 200, headers=admin)
        c.check("job delete without key", data, "DELETE", f"/v1/jobs/{job}", 401, "unauthenticated")
        c.check("job delete read key", data, "DELETE", f"/v1/jobs/{job}", 403, "permission_denied", headers=read)
        r = c.check("job delete", data, "DELETE", f"/v1/jobs/{job}", 200, headers=write)
        if r.status == 200 and r.json() != {"job": job, "cancelled": False, "deleted": True}:
            c.fail(f"job delete of a finished job: {r.body[:300]!r}")
        c.check("job deleted", data, "GET", f"/v1/jobs/{job}", 404, "not_found", headers=admin)
        c.check("job delete again", data, "DELETE", f"/v1/jobs/{job}", 404, "not_found", headers=admin)
    c.check("job unknown", data, "GET", "/v1/jobs/0123456789abcdef", 404, "not_found", headers=admin)
    # Job ids are 64 random bits: an unknown one is 404 whatever the key.
    c.check("job unknown without key", data, "GET", "/v1/jobs/0123456789abcdef", 404, "not_found")
    c.check("job unknown collection key", data, "GET", "/v1/jobs/0123456789abcdef", 404, "not_found", headers=read)
    c.check("duplicates unknown parameter", data, "POST", "/v1/collections/alpha/duplicates?bogus=1", 400,
            "invalid_argument", headers=write)
    c.check("job delete unknown", data, "DELETE", "/v1/jobs/0123456789abcdef", 404, "not_found", headers=admin)

    # Deleting a job as soon as it started: cancelled when it still ran (a 3-image job may have ended).
    job = started(start("duplicates to cancel", dup, {}, 202, headers=write), "alpha")
    if job:
        c.check("job cancel", data, "DELETE", f"/v1/jobs/{job}", 200, headers=write)
        c.check("job cancelled", data, "GET", f"/v1/jobs/{job}", 404, "not_found", headers=admin)

    # A public collection's job is read without a key; the routes without a prefix act on `default`.
    job = started(start("duplicates of full", "/v1/collections/full/duplicates", b"", 202, headers=other_key), "full")
    if job:
        r = follow(job, {}, "job of a public collection")
        if r.status == 200 and (r.json().get("state") != "done" or r.json()["result"]["images"] != 0):
            c.fail(f"duplicates of the empty collection full: {r.body[:300]!r}")
    start("duplicates default without key", "/v1/duplicates", {}, 401, "unauthenticated")
    start("duplicates default alpha's key", "/v1/duplicates", {}, 403, "permission_denied", write)
    start("duplicates default bad body", "/v1/duplicates", {"candidates": "all"}, 400, "invalid_argument", admin)
    job = started(start("duplicates default", "/v1/duplicates", {"mirrored": False}, 202, headers=admin), "default")
    if job:
        follow(job, admin)
        c.check("job delete admin", data, "DELETE", f"/v1/jobs/{job}", 200, headers=admin)


def run(args):
    image = open(args.image, "rb").read()
    other = open(args.other_image, "rb").read()  # shares few visual words with `image`: idf > 0
    url, keyed, key = args.url, args.keyed_url, args.api_key
    doc_response = exchange(url, build("GET", "/v1/openapi.json"))
    if doc_response.status != 200:
        print(f"FAIL GET /v1/openapi.json -> {doc_response.status}")
        return 1
    doc = doc_response.json()
    c = Checker(doc)
    routes = exchange(url, build("GET", "/v1")).json()["routes"]
    check_document(c, doc, routes)
    png_type = {"Content-Type": "image/png"}

    # Status routes and this description.
    r = c.check("description", url, "GET", "/v1/openapi.json", 200)
    if r.json() != doc:
        c.fail("GET /v1/openapi.json differs between two requests")
    c.check("description cached", url, "GET", "/v1/openapi.json", 304, headers={"If-None-Match": r.headers.get("etag", "")})
    for target in ("/healthz", "/readyz", "/metrics", "/v1", "/v1/stats"):
        c.check("status", url, "GET", target, 200)
    r = c.check("own request id", url, "GET", "/v1/images/nope", 404, "not_found", headers={"X-Request-Id": "abc.DEF_1-2"})
    if r.headers.get("x-request-id") != "abc.DEF_1-2":
        c.fail("X-Request-Id not echoed")
    r = c.check("page", url, "GET", "/", 200)
    c.check("page cached", url, "GET", "/", 304, headers={"If-None-Match": r.headers.get("etag", "")})
    r = c.check("page file", url, "GET", "/static/app.js", 200)
    c.check("page file cached", url, "GET", "/static/app.js", 304, headers={"If-None-Match": r.headers.get("etag", "")})
    c.check("page file unknown", url, "GET", "/static/nope.js", 404, "not_found")

    # Adding images: raw, multipart, form-encoded label; every refusal.
    r = c.check("add raw", url, "POST", "/v1/images?id=a", 201, headers=png_type, body=image)
    if r.headers.get("location") != "/v1/images/a":
        c.fail(f"add: Location {r.headers.get('location')!r}")
    ctype, body = multipart([("id", b"b", None), ("metadata", b'{"city":"Paris","year":2001}', None), ("file", other, "b.png")])
    c.check("add multipart", url, "POST", "/v1/images", 201, headers={"Content-Type": ctype}, body=body)
    c.check("add form-encoded label", url, "POST", "/v1/images?id=c", 201,
            headers={"Content-Type": "application/x-www-form-urlencoded"}, body=image)
    c.check("add taken id", url, "POST", "/v1/images?id=a", 409, "already_exists", headers=png_type, body=image)
    r = c.check("replace", url, "POST", "/v1/images?id=a&replace=true", 200, headers=png_type, body=image)
    if r.status == 200 and r.json().get("replaced") is not True:
        c.fail("replace: replaced is not true")
    c.check("add without id", url, "POST", "/v1/images", 400, "invalid_argument", headers=png_type, body=image)
    c.check("add sub-route id", url, "POST", "/v1/images?id=x%2Fsimilar", 400, "invalid_argument", headers=png_type, body=image)
    c.check("add id batch", url, "POST", "/v1/images?id=batch", 400, "invalid_argument", headers=png_type, body=image)
    c.check("add metadata not JSON", url, "POST", "/v1/images?id=m&metadata=nope", 400, "invalid_argument", headers=png_type, body=image)
    deep = urllib.parse.quote("[" * 65 + "]" * 65)
    c.check("add metadata too deep", url, "POST", f"/v1/images?id=m&metadata={deep}", 400, "invalid_argument", headers=png_type, body=image)
    ctype, body = multipart([("id", b"m", None), ("file", image, "m.png")])
    c.check("add id twice", url, "POST", "/v1/images?id=m", 400, "invalid_argument", headers={"Content-Type": ctype}, body=body)
    ctype, body = multipart([("id", b"m", None), ("file", b"", "m.png")])
    c.check("add empty part", url, "POST", "/v1/images", 400, "invalid_image", headers={"Content-Type": ctype}, body=body)
    c.check("add not an image", url, "POST", "/v1/images?id=m", 400, "invalid_image", headers=png_type, body=b"not an image at all")
    c.check("add empty body", url, "POST", "/v1/images?id=m", 400, "invalid_image", headers=png_type)
    c.check("add JSON", url, "POST", "/v1/images?id=m", 415, "unsupported_format", headers={"Content-Type": "application/json"}, body=b"{}")
    c.check("add compressed", url, "POST", "/v1/images?id=m", 415, "unsupported_encoding",
            headers={**png_type, "Content-Encoding": "gzip"}, body=image)
    c.check("add pixel bomb", url, "POST", "/v1/images?id=m", 413, "image_too_large", headers=png_type, body=png(60000, 60000))
    c.check("add over upload limit", url, "POST", "/v1/images?id=m", 413, "payload_too_large",
            raw=build("POST", "/v1/images?id=m", {**png_type, "Content-Length": str(2 << 20)}))

    # Adding several images in one request: each answered on its own; refusals of the whole request.
    def batch(parts, expect, code=None, base=url, name="batch", headers=None):
        ctype, body = multipart(parts)
        return c.check(name, base, "POST", "/v1/images/batch", expect, code, headers={"Content-Type": ctype, **(headers or {})}, body=body)
    r = batch([("image", image, "ba.png"), ("id", b"ba", None), ("metadata", b'{"k": 1}', None),
               ("image", other, "bb.png"), ("id", b"bb", None), ("metadata", b"", None)], 200)
    if r.status == 200 and ([x["status"] for x in r.json()["results"]] != [201, 201] or r.json()["added"] != 2):
        c.fail(f"batch of two new images: not both added: {r.body[:300]!r}")
    r = batch([("image", b"not an image", "bc.png"), ("id", b"bc", None), ("image", image, "ba.png"), ("id", b"ba", None),
               ("image", image, "bd.png"), ("id", b"bd", None)], 200)
    if r.status == 200 and [x["status"] for x in r.json()["results"]] != [400, 409, 201]:
        c.fail(f"batch with an undecodable image and a taken id: {r.body[:300]!r}")
    tiny = png(32, 32)
    batch([p for i in range(65) for p in (("image", tiny, f"t{i}.png"), ("id", f"t{i}".encode(), None))], 413, "payload_too_large")
    batch([("image", image, "be.png")], 400, "invalid_argument", name="batch without id")
    batch([("image", image, "be.png"), ("id", b"be", None), ("replace", b"true", None)], 400, "invalid_argument", name="batch unknown part")
    c.check("batch not multipart", url, "POST", "/v1/images/batch", 415, "unsupported_format", headers=png_type, body=image)
    if exchange(url, build("GET", "/v1/images/be")).status != 404:
        c.fail("a refused batch stored an image")

    # Records, list, thumbnails.
    c.check("get", url, "GET", "/v1/images/b", 200)
    c.check("get unknown", url, "GET", "/v1/images/nope", 404, "not_found")
    c.check("list", url, "GET", "/v1/images", 200)
    probe_ranges(c, url, "/v1/images", "get",
                 lambda q, e, code, n: c.check(f"list {n}", url, "GET", f"/v1/images?{q}", e, code))
    r = c.check("thumbnail", url, "GET", "/v1/images/a/thumbnail", 200)
    c.check("thumbnail cached", url, "GET", "/v1/images/a/thumbnail", 304, headers={"If-None-Match": r.headers.get("etag", "")})
    c.check("thumbnail unknown", url, "GET", "/v1/images/nope/thumbnail", 404, "not_found")
    probe_ranges(c, url, "/v1/images/{id}/thumbnail", "get",
                 lambda q, e, code, n: c.check(f"thumbnail {n}", url, "GET", f"/v1/images/a/thumbnail?{q}", e, code))

    # Searches: by id, by upload; verified and unverified results.
    r = c.check("similar", url, "GET", "/v1/images/a/similar", 200)
    if r.status == 200 and not any(x["verified"] for x in r.json()["results"]):
        c.fail("similar: no verified result (the schema's verified branch went unchecked)")
    r = c.check("similar tf-idf only", url, "GET", "/v1/images/a/similar?rerank=0", 200)
    if r.status == 200 and (not r.json()["results"] or any(x["verified"] for x in r.json()["results"])):
        c.fail("similar rerank=0: expected unverified results")
    c.check("similar unknown", url, "GET", "/v1/images/nope/similar", 404, "not_found")
    probe_ranges(c, url, "/v1/images/{id}/similar", "get",
                 lambda q, e, code, n: c.check(f"similar {n}", url, "GET", f"/v1/images/a/similar?{q}", e, code))
    c.check("qe without rerank", url, "GET", "/v1/images/a/similar?rerank=0&qe=true", 400, "invalid_argument")
    r = c.check("search raw", url, "POST", "/v1/search?bbox=0,0,200,150", 200, headers=png_type, body=image)
    if r.status == 200 and not r.json()["results"]:
        c.fail("search: no results (the result schema went unchecked)")
    ctype, body = multipart([("top_k", b"5", None), ("file", image, "q.png")])
    c.check("search multipart", url, "POST", "/v1/search", 200, headers={"Content-Type": ctype}, body=body)
    ctype, body = multipart([("top_k", b"5", None)])
    c.check("search multipart without image", url, "POST", "/v1/search", 400, "invalid_argument", headers={"Content-Type": ctype}, body=body)
    c.check("search JSON", url, "POST", "/v1/search", 415, "unsupported_format", headers={"Content-Type": "application/json"}, body=b"{}")
    c.check("search not an image", url, "POST", "/v1/search", 400, "invalid_image", headers=png_type, body=b"not an image")
    probe_ranges(c, url, "/v1/search", "post",
                 lambda q, e, code, n: c.check(f"search {n}", url, "POST", f"/v1/search?{q}", e, code, headers=png_type, body=image))

    # Matching two images.
    flat = png(64, 64)
    def match(q, e, code, n, a=image, b=image):
        ctype, body = multipart([("a", a, "a.png"), ("b", b, "b.png")])
        return c.check(f"match {n}", url, "POST", f"/v1/match?{q}", e, code, headers={"Content-Type": ctype}, body=body)
    r = match("correspondences=true", 200, None, "verified")
    if r.status == 200 and not (r.json()["verified"] and r.json().get("correspondences")):
        c.fail("match of an image with itself: not verified or no correspondences")
    r = match("", 200, None, "unverified", b=flat)
    if r.status == 200 and r.json()["verified"]:
        c.fail("match with a flat image: verified")
    probe_ranges(c, url, "/v1/match", "post", match)
    ctype, body = multipart([("a", image, "a.png")])
    c.check("match without b", url, "POST", "/v1/match", 400, "invalid_argument", headers={"Content-Type": ctype}, body=body)
    c.check("match not multipart", url, "POST", "/v1/match", 415, "unsupported_format", headers=png_type, body=image)

    # Deleting.
    c.check("delete", url, "DELETE", "/v1/images/c", 200)
    c.check("delete unknown", url, "DELETE", "/v1/images/c", 404, "not_found")

    # Every route with a method it does not take; paths that are no route.
    for template in doc["paths"]:
        target = (template.replace("{name}", "default").replace("{id}", "a").replace("{file}", "app.js")
                  .replace("{job}", "0123456789abcdef"))
        c.check(f"wrong method {template}", url, "PUT", target, 405, "method_not_allowed")
    c.check("unknown route", url, "GET", "/v1/nope", 404, "not_found")
    c.check("unknown route", url, "POST", "/v2/search", 404, "not_found", headers=png_type, body=image)

    # Requests refused before any route runs, on every operation.
    many = {f"X-Filler-{i}": "1" for i in range(150)}
    for template, item in doc["paths"].items():
        target = (template.replace("{name}", "default").replace("{id}", "a").replace("{file}", "app.js")
                  .replace("{job}", "0123456789abcdef"))
        for method in (m.upper() for m in item if m != "parameters"):
            c.check("target too long", url, method, target + "?" + "x" * 9000, 414, "uri_too_long")
            c.check("too many headers", url, method, target, 431, "headers_too_large", headers=many)
            c.check("HTTP/1.2", url, method, target, 505, "http_version_not_supported", raw=build(method, target, version="HTTP/1.2"))
            c.check("transfer encoding", url, method, target, 501, "not_implemented", headers={"Transfer-Encoding": "gzip"})
            c.check("content encoding", url, method, target, 415, "unsupported_encoding", headers={"Content-Encoding": "gzip"})
            if method == "POST":
                c.check("over upload limit", url, method, target, 413, "payload_too_large",
                        raw=build(method, target, {**png_type, "Content-Length": str(2 << 20)}))
            else:
                c.check("body without POST", url, method, target, 400, "bad_request", headers={"Content-Length": "5"}, body=b"hello")

    # With an API key: writes need it, reads do not.
    c.check("add without key", keyed, "POST", "/v1/images?id=k", 401, "unauthenticated", headers=png_type, body=image)
    c.check("add wrong key", keyed, "POST", "/v1/images?id=k", 403, "permission_denied",
            headers={**png_type, "Authorization": "Bearer wrong"}, body=image)
    c.check("add with key", keyed, "POST", "/v1/images?id=k", 201, headers={**png_type, "Authorization": f"Bearer {key}"}, body=image)
    batch([("image", image, "k.png"), ("id", b"kb", None)], 401, "unauthenticated", base=keyed, name="batch without key")
    batch([("image", image, "k.png"), ("id", b"kb", None)], 403, "permission_denied", base=keyed, name="batch wrong key",
          headers={"X-API-Key": "wrong"})
    batch([("image", image, "k.png"), ("id", b"kb", None)], 200, base=keyed, name="batch with key",
          headers={"Authorization": f"Bearer {key}"})
    c.check("search without key", keyed, "POST", "/v1/search", 200, headers=png_type, body=image)
    c.check("delete without key", keyed, "DELETE", "/v1/images/k", 401, "unauthenticated")
    c.check("delete wrong key", keyed, "DELETE", "/v1/images/k", 403, "permission_denied", headers={"X-API-Key": "wrong"})
    c.check("delete with key", keyed, "DELETE", "/v1/images/k", 200, headers={"X-API-Key": key})
    # Backups: a new folder on the server's machine, which is this one.
    backups = tempfile.mkdtemp(prefix="oxbow-openapi-backup-")
    try:
        json_type = {"Content-Type": "application/json"}
        target = json.dumps({"out": os.path.join(backups, "copy")}).encode()
        c.check("backup on a server without key", url, "POST", "/v1/admin/backup", 403, "permission_denied",
                headers=json_type, body=target)
        c.check("backup without key", keyed, "POST", "/v1/admin/backup", 401, "unauthenticated", headers=json_type, body=target)
        c.check("backup wrong key", keyed, "POST", "/v1/admin/backup", 403, "permission_denied",
                headers={**json_type, "X-API-Key": "wrong"}, body=target)
        c.check("backup relative", keyed, "POST", "/v1/admin/backup", 400, "invalid_argument",
                headers={**json_type, "X-API-Key": key}, body=b'{"out": "copy"}')
        r = c.check("backup", keyed, "POST", "/v1/admin/backup", 200, headers={**json_type, "X-API-Key": key}, body=target)
        if r.status == 200 and not os.path.isfile(os.path.join(backups, "copy", "catalogue.sqlite")):
            c.fail("backup: no catalogue in the copy")
        c.check("backup form, existing folder", keyed, "POST", "/v1/admin/backup", 409, "already_exists",
                headers={"Content-Type": "application/x-www-form-urlencoded", "X-API-Key": key},
                body=b"out=" + urllib.parse.quote(os.path.join(backups, "copy")).encode())
        c.check("backup without parent", keyed, "POST", "/v1/admin/backup", 404, "not_found",
                headers={**json_type, "X-API-Key": key}, body=json.dumps({"out": os.path.join(backups, "no", "copy")}).encode())
    finally:
        shutil.rmtree(backups, ignore_errors=True)
    # A body that never completes (the keyed server's request timeout is 1 s).
    c.check("late body", keyed, "POST", "/v1/search", 408, "request_timeout",
            raw=build("POST", "/v1/search", {**png_type, "Content-Length": "1000"}) + b"12345", partial_wait=2.5)
    # More connections from one address than --max-connections-per-client 4 (last: it fills the server).
    idle = [socket.create_connection(urllib.parse.urlsplit(keyed).netloc.split(":")) for _ in range(4)]
    try:
        c.check("too many connections", keyed, "GET", "/healthz", 503, "unavailable")
    finally:
        for s in idle:
            s.close()

    check_collections(c, url, args.data_url, key, image, other)

    # Coverage: every described operation answered at least once with success and once with an error.
    for template, item in doc["paths"].items():
        for method in (m for m in item if m != "parameters"):
            statuses = c.seen.get((template, method), set())
            untested = sorted(set(item[method]["responses"]) - statuses)
            print(f"{method.upper():6} {template:28} checked {' '.join(sorted(statuses)):44} not sent: {' '.join(untested)}")
            if not any(s < "400" for s in statuses) or not any(s >= "400" for s in statuses):
                c.fail(f"{method} {template}: not checked with both a success and an error")
    checked = sum(len(s) for s in c.seen.values())
    print(f"openapi_check: {checked} route/method/status combinations checked, {len(c.failures)} failures")
    return 1 if c.failures else 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", required=True)
    parser.add_argument("--keyed-url", required=True)
    parser.add_argument("--data-url", required=True, help="oxbow serve --data DIR --vocab V --api-key KEY")
    parser.add_argument("--api-key", required=True)
    parser.add_argument("--image", required=True, help="a textured PNG (features to find)")
    parser.add_argument("--other-image", required=True, help="another textured PNG, unlike --image")
    sys.exit(run(parser.parse_args()))


if __name__ == "__main__":
    main()
