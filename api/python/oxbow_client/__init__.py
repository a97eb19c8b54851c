"""A Python client for the oxbow HTTP API (server/README.md), standard library only (Python 3.11+).

    from oxbow_client import Client, NotFoundError
    oxbow = Client("http://127.0.0.1:8080", api_key="secret", timeout=30)
    oxbow.add("eiffel-1", "photos/eiffel.jpg", metadata={"city": "Paris"})
    hits = oxbow.search("query.jpg", bbox=(10, 20, 300, 400), top_k=5)["results"]
    try:
        oxbow.get("nope")
    except NotFoundError as e:
        print(e.status, e.code, e.message, e.request_id)

Collections (a server started with `oxbow serve --data DIR`): each is an index of its own, with its own
vocabulary, keys and limits. The admin key (the server's --api-key) creates and deletes them and makes
their keys; `Client.collection(name)` has the image and search methods of Client, on that collection:

    oxbow.create_collection("paris", "/srv/vocab/paris.oxvoc", max_images=100_000)
    key = oxbow.create_key("paris", access="write")["key"]     # shown only here
    paris = Client("http://127.0.0.1:8080", api_key=key).collection("paris")
    paris.add("louvre-1", "photos/louvre.jpg")
    hits = paris.search("query.jpg", top_k=5)["results"]

Client's own image and search methods act on the collection named "default".

Every method returns the server's JSON answer as a dict (fields: server/README.md), or raises an
OxbowError subclass that carries the server's error code, message, HTTP status and request id: no answer
or a broken one (unreachable, connection broken, not HTTP) raises TransportError, and a 2xx answer whose
body is not JSON (a proxy's or captive portal's page) ServerError.
Images are given as bytes, a path (str or os.PathLike) or a binary file object. A Client holds no
connection between calls, so one may be shared by threads; so may a Collection.
"""

from __future__ import annotations

import dataclasses
import http.client
import json
import mimetypes
import os
import secrets
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterable, Iterator, Mapping
from email.message import Message
from typing import Any, BinaryIO, Literal, Union, overload

__version__ = "0.1.0"  # the oxbow version it belongs to (project(VERSION) in CMakeLists.txt)

__all__ = [
    "Client", "Collection", "AddResult", "Image", "JSONObject", "OxbowError", "TransportError",
    "ClientTimeoutError", "ClientError", "InvalidArgumentError", "UnauthorizedError", "UnauthenticatedError",
    "PermissionDeniedError", "NotFoundError", "ConflictError", "PayloadTooLargeError", "UnsupportedMediaTypeError",
    "ServerError", "UnavailableError", "CollectionFullError",
]

Image = Union[bytes, bytearray, memoryview, str, os.PathLike[str], BinaryIO]
"""An image: its encoded bytes, the path of its file, or a file object opened in binary mode."""

JSONObject = dict[str, Any]
"""A JSON object of the server's answer, as json.loads gives it."""


# ---- Errors ------------------------------------------------------------------------------------------

class OxbowError(Exception):
    """An oxbow request that failed.

    status: the HTTP status (None when no answer came: TransportError).
    code: the server's error code ("not_found", "invalid_argument", ...; server/README.md "Errors"), or None.
    message: the server's message (or what went wrong on the way).
    request_id: the X-Request-Id of the request, to find its line in the server's log, or None.
    """

    def __init__(self, message: str, *, status: int | None = None, code: str | None = None,
                 request_id: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.status = status
        self.code = code
        self.request_id = request_id

    def __str__(self) -> str:
        where = [f"HTTP {self.status}"] if self.status is not None else []
        if self.code:
            where.append(self.code)
        if self.request_id:
            where.append(f"request {self.request_id}")
        return f"{self.message} ({', '.join(where)})" if where else self.message


class TransportError(OxbowError):
    """No whole HTTP answer: the server could not be reached, the connection broke (before or in the middle
    of the answer), or what came back is not HTTP. The original exception is its __cause__."""


class ClientTimeoutError(TransportError):
    """The server did not answer within the client's timeout."""


class ClientError(OxbowError):
    """A 4xx answer: the request was refused."""


class InvalidArgumentError(ClientError):
    """400: a bad parameter, body, collection name or image (code invalid_argument, invalid_image or
    bad_request)."""


class UnauthorizedError(ClientError):
    """401 or 403: the API key is missing, wrong, or does not grant the request."""


class UnauthenticatedError(UnauthorizedError):
    """401: no API key where the request needs one (a write on a server started with --api-key, a read of
    a collection that is not public)."""


class PermissionDeniedError(UnauthorizedError):
    """403: a key that does not grant the request (a wrong key, another collection's key, a read key
    writing, a collection key on an admin route), or an admin route of a server without --api-key."""


class NotFoundError(ClientError):
    """404: unknown image id, collection, key id or vocabulary file (or route)."""


class ConflictError(ClientError):
    """409: the id or collection name is taken (already_exists), the index cannot take this image
    (incompatible), or the server serves one index folder (--index) and has no collections or keys to
    create or delete (incompatible)."""


class PayloadTooLargeError(ClientError):
    """413: the body is over the server's --max-upload-mb, or the image over its --max-megapixels."""


class UnsupportedMediaTypeError(ClientError):
    """415: not an image the server can decode."""


class ServerError(OxbowError):
    """A 5xx answer, or a 2xx answer whose body is not JSON (a proxy's or captive portal's page: code None,
    status the 2xx one)."""


class UnavailableError(ServerError):
    """503: the server is loading its index, overloaded or stopping; retry after `retry_after` seconds."""

    def __init__(self, message: str, *, retry_after: float | None = None, **kwargs: Any) -> None:
        super().__init__(message, **kwargs)
        self.retry_after = retry_after


class CollectionFullError(ServerError):
    """507: an add to a collection at its max_images or max_bytes (code collection_full); delete images,
    or recreate the collection with larger limits."""


_ERROR_BY_STATUS: dict[int, type[OxbowError]] = {
    400: InvalidArgumentError, 401: UnauthenticatedError, 403: PermissionDeniedError, 404: NotFoundError,
    409: ConflictError, 413: PayloadTooLargeError, 415: UnsupportedMediaTypeError, 503: UnavailableError,
    507: CollectionFullError,
}


def _error_from_response(status: int, headers: Mapping[str, str] | Message, body: bytes) -> OxbowError:
    request_id = headers.get("X-Request-Id")
    code = None
    message = body[:200].decode("utf-8", "replace").strip() or f"HTTP {status}"
    try:
        error = json.loads(body)["error"]
        code, message = error["code"], error["message"]
        request_id = error.get("request_id") or request_id
    except (ValueError, KeyError, TypeError):
        pass  # not oxbow's error shape (a proxy's page?): keep the text
    cls = _ERROR_BY_STATUS.get(status) or (ClientError if 400 <= status < 500 else
                                           ServerError if status >= 500 else OxbowError)
    kwargs: dict[str, Any] = {"status": status, "code": code, "request_id": request_id}
    if cls is UnavailableError:
        try:
            kwargs["retry_after"] = float(headers.get("Retry-After", ""))
        except ValueError:
            kwargs["retry_after"] = None
    return cls(message, **kwargs)


def _check_members(value: Any, names: tuple[str, ...], what: str) -> None:
    """ServerError unless `value` (a part of an answer that the client reads) is an object with `names`."""
    if not isinstance(value, dict) or any(name not in value for name in names):
        raise ServerError(f"{what} is not what oxbow answers: expected an object with "
                          + ", ".join(repr(name) for name in names) + f", got {json.dumps(value)[:200]}")


# ---- Request bodies ----------------------------------------------------------------------------------

def _image_bytes(image: Image) -> tuple[bytes, str]:
    """The bytes of an image given as bytes, a path or a binary file object, and a file name for it."""
    if isinstance(image, (bytes, bytearray, memoryview)):
        return bytes(image), "image"
    if isinstance(image, (str, os.PathLike)):
        with open(image, "rb") as f:
            return f.read(), os.path.basename(os.fspath(image))
    if hasattr(image, "read"):
        data = image.read()
        if not isinstance(data, (bytes, bytearray)):
            raise TypeError("the image file must be opened in binary mode ('rb')")
        name = getattr(image, "name", None)
        return bytes(data), os.path.basename(name) if isinstance(name, str) else "image"
    raise TypeError(f"an image is bytes, a path or a binary file object, not {type(image).__name__}")


def _field_value(value: Any) -> str:
    """A parameter as the server parses it: true/false, "x1,y1,x2,y2" for a box, JSON for mappings."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return ",".join(str(v) for v in value)
    if isinstance(value, Mapping):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def _quote_header_param(text: str) -> str:
    # As browsers write multipart names (WHATWG HTML form encoding): these three would end the value.
    return text.replace('"', "%22").replace("\r", "%0D").replace("\n", "%0A")


Fields = Union[Mapping[str, str], list[tuple[str, str]]]
Files = Union[Mapping[str, tuple[bytes, str]], list[tuple[str, tuple[bytes, str]]]]


def _multipart(fields: Fields, files: Files) -> tuple[bytes, str]:
    """A multipart/form-data body (RFC 7578) and its Content-Type; lists of pairs repeat names, in order."""
    parts: list[bytes] = []
    for name, value in (fields.items() if isinstance(fields, Mapping) else fields):
        parts.append(f'Content-Disposition: form-data; name="{_quote_header_param(name)}"\r\n\r\n'.encode()
                     + value.encode("utf-8"))
    for name, (data, filename) in (files.items() if isinstance(files, Mapping) else files):
        content_type = mimetypes.guess_type(filename)[0] or "application/octet-stream"
        head = (f'Content-Disposition: form-data; name="{_quote_header_param(name)}"; '
                f'filename="{_quote_header_param(filename)}"\r\nContent-Type: {content_type}\r\n\r\n')
        parts.append(head.encode("utf-8") + data)
    while True:  # a boundary must not occur in the parts; 128 random bits practically never do
        boundary = "oxbow-" + secrets.token_hex(16)
        if not any(boundary.encode() in part for part in parts):
            break
    delimiter = f"--{boundary}\r\n".encode()
    body = b"".join(delimiter + part + b"\r\n" for part in parts) + f"--{boundary}--\r\n".encode()
    return body, f"multipart/form-data; boundary={boundary}"


# ---- Images and search, of one collection ------------------------------------------------------------

@dataclasses.dataclass
class AddResult:
    """The outcome of one image of add_many: `response` (the add's answer) or `error`."""
    id: str
    response: JSONObject | None = None
    error: OxbowError | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class _ImageRoutes:
    """The image and search methods, over the routes under one prefix: Client's act on /v1/images,
    /v1/search, ... (the collection "default"), a Collection's on /v1/collections/{name}/images, ..."""

    _prefix: str       # "/v1" or "/v1/collections/NAME"
    _backup_path: str  # "/v1/admin/backup" or "/v1/collections/NAME/backup"

    @overload
    def _request(self, method: str, path: str, *, query: Mapping[str, Any] | None = None,
                 multipart: tuple[Fields, Files] | None = None, json_body: Any = None,
                 raw: Literal[False] = False, expect: tuple[str, ...] = ()) -> JSONObject: ...

    @overload
    def _request(self, method: str, path: str, *, query: Mapping[str, Any] | None = None,
                 multipart: tuple[Fields, Files] | None = None, json_body: Any = None,
                 raw: Literal[True], expect: tuple[str, ...] = ()) -> bytes: ...

    def _request(self, method: str, path: str, *, query: Mapping[str, Any] | None = None,
                 multipart: tuple[Fields, Files] | None = None, json_body: Any = None,
                 raw: bool = False, expect: tuple[str, ...] = ()) -> Any:
        """The answer to one request: its JSON object, or its body (raw=True); OxbowError if it failed.
        `expect`: members the object must have (the ones the caller reads), else ServerError."""
        status, headers, body = self._send(method, path, query, multipart, json_body)
        if raw:
            return body

        def not_oxbows(what: str) -> ServerError:  # a proxy's page, another service, another API version
            text = body[:200].decode("utf-8", "replace").strip()
            return ServerError(f"{method} {path}: the HTTP {status} answer {what} "
                               f"({headers.get('Content-Type') or 'no Content-Type'}): {text}",
                               status=status, request_id=headers.get("X-Request-Id"))

        try:
            answer = json.loads(body)
        except ValueError as e:  # JSONDecodeError, or UnicodeDecodeError
            raise not_oxbows("is not JSON") from e
        if not isinstance(answer, dict):
            raise not_oxbows("is JSON but not an object")
        missing = [name for name in expect if name not in answer]
        if missing:
            raise not_oxbows("has no " + ", ".join(repr(name) for name in missing))
        return answer

    def _send(self, method: str, path: str, query: Mapping[str, Any] | None, multipart: tuple[Fields, Files] | None,
              json_body: Any) -> tuple[int, Message, bytes]:
        """The status, headers and body of a 2xx answer; OxbowError for any other answer, or none."""
        raise NotImplementedError

    def stats(self) -> JSONObject:
        """GET /v1/stats: images, features, words, index_bytes, memory_rss_bytes, uptime_s, ..."""
        return self._request("GET", self._prefix + "/stats")

    # -- images

    def add(self, id: str, image: Image, *, metadata: Any = None, replace: bool = False) -> JSONObject:
        """POST /v1/images: indexes `image` under `id`, with optional `metadata`.

        metadata: any JSON value, given as the Python object that json.dumps writes (a dict, list, str,
          number or bool), e.g. {"city": "Paris"}. It is always sent as JSON, so a str is stored as a JSON
          string: metadata='{"city":"Paris"}' stores that text, not an object, and search filters on "city"
          never match it. For metadata held as JSON text, pass json.loads(text).
        An existing id raises ConflictError unless replace=True; a collection at its limits raises
        CollectionFullError. Returns the stored record with "replaced" and "timings_ms".
        """
        fields = {"id": id}
        if metadata is not None:
            fields["metadata"] = json.dumps(metadata, separators=(",", ":"))
        if replace:
            fields["replace"] = "true"
        return self._request("POST", self._prefix + "/images", multipart=(fields, {"file": _image_bytes(image)}))

    def add_many(self, items: Iterable[tuple[str, Image] | tuple[str, Image, Any] | Mapping[str, Any]], *,
                 replace: bool = False) -> list[AddResult]:
        """Adds several images; never raises for one image's failure.

        items: (id, image) or (id, image, metadata) tuples, or mappings with keys id, image and
          optionally metadata. metadata as add(): any JSON value as a Python object (a str is stored as a
          JSON string; for JSON text, pass json.loads(text)).
        Returns one AddResult per item, in order: the stored record (as get() returns it), or the
        OxbowError of that image. Every image whose AddResult is ok is acknowledged, hence durable.

        The images go in batches (POST /v1/images/batch), each at most the server's max_batch_images
        images and max_upload_bytes bytes (GET /v1), each batch one index transaction; a batch that fails
        as a whole (server unreachable or stopping, a storage failure) gives its error to each of its
        images, and the batches before it stay added. With replace=True the images are sent one by one
        (POST /v1/images?replace=true; the batch route adds new ids only) and the response is add()'s.
        """
        normalized = [_add_item(item) for item in items]
        if replace:
            return self._add_one_by_one(normalized)
        if not normalized:
            return []
        # The server's limits, the same for every collection.
        limits = self._request("GET", "/v1", expect=("limits",))["limits"]
        _check_members(limits, ("max_batch_images", "max_upload_bytes"), "GET /v1's limits")
        results: list[AddResult] = []
        # Read lazily: one batch of images in memory at a time.
        for batch in _batches(((id, _image_bytes(image), metadata) for id, image, metadata in normalized),
                              limits["max_batch_images"], limits["max_upload_bytes"]):
            results += self._add_batch(batch)
        return results

    def _add_one_by_one(self, items: list[tuple[str, Image, Any]]) -> list[AddResult]:
        results = []
        for id, image, metadata in items:
            try:
                results.append(AddResult(id, response=self.add(id, image, metadata=metadata, replace=True)))
            except OxbowError as e:
                results.append(AddResult(id, error=e))
        return results

    def _add_batch(self, batch: list[tuple[str, tuple[bytes, str], Any]]) -> list[AddResult]:
        fields = [("id", id) for id, _, _ in batch]
        if any(metadata is not None for _, _, metadata in batch):
            fields += [("metadata", "" if metadata is None else json.dumps(metadata, separators=(",", ":")))
                       for _, _, metadata in batch]
        files = [("image", image) for _, image, _ in batch]
        route = f"POST {self._prefix}/images/batch"
        try:
            answer = self._request("POST", self._prefix + "/images/batch", multipart=(fields, files),
                                   expect=("results",))
            if not isinstance(answer["results"], list) or len(answer["results"]) != len(batch):
                raise ServerError(f"{route}: the answer's results are not a list of one per image sent "
                                  f"({len(batch)})")
            for (id, _, _), result in zip(batch, answer["results"]):  # {"image"}, or {"status", "error"}
                if not (isinstance(result, dict) and "image" in result):
                    _check_members(result, ("status", "error"), f"{route}: the result for {id!r}")
        except OxbowError as e:  # nothing known of any image of the batch
            return [AddResult(id, error=e) for id, _, _ in batch]
        results = []
        for (id, _, _), result in zip(batch, answer["results"]):
            if "image" in result:
                results.append(AddResult(id, response=result["image"]))
            else:
                body = json.dumps({"error": result["error"]}).encode()
                results.append(AddResult(id, error=_error_from_response(result["status"], {}, body)))
        return results

    def get(self, id: str) -> JSONObject:
        """GET /v1/images/{id}: the image's record (NotFoundError if unknown)."""
        return self._request("GET", self._image_path(id))

    def delete(self, id: str) -> JSONObject:
        """DELETE /v1/images/{id}: {"id": id, "deleted": true} (NotFoundError if unknown)."""
        return self._request("DELETE", self._image_path(id))

    def list(self, offset: int = 0, limit: int = 100) -> JSONObject:
        """GET /v1/images: {"images": [...], "offset", "limit", "total"}, by id; limit 1..1000."""
        return self._request("GET", self._prefix + "/images", query={"offset": offset, "limit": limit},
                             expect=("images", "total"))

    def iter_images(self, page_size: int = 1000) -> Iterator[JSONObject]:
        """Every image record, by id, fetched `page_size` (1..1000) at a time with list(). Images added or
        deleted while it runs may be missed or seen twice (each page is read at its own offset)."""
        offset = 0
        while True:
            page = self.list(offset=offset, limit=page_size)
            images = page["images"]
            yield from images
            offset += len(images)
            if not images or offset >= page["total"]:
                return

    def thumbnail(self, id: str, size: int | None = None) -> bytes:
        """GET /v1/images/{id}/thumbnail: JPEG bytes, longest side <= size (16..2048, default 256)."""
        query = {"size": size} if size is not None else {}
        path = self._image_path(id) + "/thumbnail"
        body = self._request("GET", path, query=query, raw=True)
        if not body.startswith(b"\xff\xd8\xff"):  # a JPEG's start of image and first marker
            raise ServerError(f"GET {path}: the answer is not a JPEG image: {body[:200]!r}")
        return body

    def backup(self, out: str) -> JSONObject:
        """POST /v1/admin/backup (a Collection: /v1/collections/{name}/backup): copies the index into the
        new folder `out`, an absolute path on the server's machine, while the server keeps serving; restore
        by serving that folder. Needs the admin key (the server refuses the route without one). {"out",
        "images", "generation", "bytes", "attempts"}; ConflictError when `out` exists and is not empty (or
        a previous copy's OUT.tmp is left), NotFoundError when its parent folder does not exist."""
        return self._request("POST", self._backup_path, multipart=({"out": out}, {}))

    # -- search

    def search(self, image: Image, *, bbox: tuple[float, float, float, float] | None = None,
               filter: Mapping[str, Any] | str | None = None, **options: Any) -> JSONObject:
        """POST /v1/search with an image; bbox = (x1, y1, x2, y2) in the image's pixels.

        filter: only images whose metadata matches, a dict (or its JSON text) as server/README.md
        "Filtered search" describes, e.g. {"city": {"in": ["Paris", "Lyon"]}, "year": {"gte": 2000}}; a malformed
        one raises InvalidArgumentError.

        options: the server's search parameters (server/README.md "Search options"): top_k, rerank, qe, qe_images,
        min_inliers, max_pairs_per_word, transitive_depth, transitive_anchors, transitive_neighbours,
        transitive_attempts, query_assignments, quantizer_probes, hamming, asmk_weight, qe_asmk_weight,
        hamming_norm_exponent. Unknown names and out-of-range values raise InvalidArgumentError (the server
        refuses them).
        """
        fields = _search_fields(bbox, filter, options)
        return self._request("POST", self._prefix + "/search", multipart=(fields, {"file": _image_bytes(image)}))

    def similar(self, id: str, *, filter: Mapping[str, Any] | str | None = None, **options: Any) -> JSONObject:
        """GET /v1/images/{id}/similar: a search with an indexed image's stored features; filter and
        options as search."""
        return self._request("GET", self._image_path(id) + "/similar", query=_search_fields(None, filter, options))

    # -- duplicates

    def start_duplicates(self, **options: Any) -> JSONObject:
        """POST /v1/duplicates (a Collection: /v1/collections/{name}/duplicates): starts a duplicate search
        of the collection as a background job; {"job", "collection", "state"}. options: candidates,
        mirrored, min_coverage, near_copy_coverage, threads (server/README.md "Duplicates"). Needs write
        access; ConflictError while one runs on the collection."""
        return self._request("POST", self._prefix + "/duplicates", json_body=options if options else None,
                             expect=("job",))

    def find_duplicates(self, *, poll_s: float = 0.5, timeout_s: float | None = None, **options: Any) -> JSONObject:
        """Starts a duplicate search (start_duplicates) and waits for it: the job's report ("pairs",
        "groups", ...). OxbowError when the job failed; ClientTimeoutError after timeout_s (the job is
        cancelled)."""
        job = self.start_duplicates(**options)["job"]
        started = time.monotonic()
        while True:
            status = self.job(job)
            if status["state"] == "done":
                _check_members(status, ("result",), f"duplicate job {job}, done,")
                return status["result"]
            if status["state"] != "running":
                error = status.get("error", {})
                raise ServerError(f"duplicate job {job}: {status['state']}: {error.get('message', '')}",
                                  code=error.get("code"))
            if timeout_s is not None and time.monotonic() - started > timeout_s:
                self.cancel_job(job)
                raise ClientTimeoutError(f"duplicate job {job} still running after {timeout_s} s; cancelled")
            time.sleep(poll_s)

    def job(self, job: str) -> JSONObject:
        """GET /v1/jobs/{job}: {"job", "collection", "state", "done", "total", "elapsed_s"}, with
        "result" once done and "error" once failed."""
        return self._request("GET", "/v1/jobs/" + urllib.parse.quote(job, safe=""), expect=("state",))

    def cancel_job(self, job: str) -> JSONObject:
        """DELETE /v1/jobs/{job}: stops a running job (or forgets a finished one)."""
        return self._request("DELETE", "/v1/jobs/" + urllib.parse.quote(job, safe=""))

    def _image_path(self, id: str) -> str:
        return self._prefix + "/images/" + _quote_id(id)


# ---- The client --------------------------------------------------------------------------------------

class Client(_ImageRoutes):
    """oxbow's HTTP API.

    url: the server, e.g. "http://127.0.0.1:8080" (as printed by `oxbow serve`).
    api_key: sent as "Authorization: Bearer KEY": the server's --api-key (the admin key: everything), or a
      collection key ("oxk_...", from create_key: reads, or reads and writes, of its collection). Needed
      for writes on a server run with --api-key, and for reads of a collection that is not public.
    timeout: seconds to wait for the connection and for each read of the answer (a search of a large
      image takes a few seconds on a busy server); on expiry ClientTimeoutError.

    Its image and search methods (add, add_many, get, delete, list, iter_images, thumbnail, search,
    similar, stats, backup) act on the collection "default" (the only index of a server run with
    --index); collection(name) gives them for another collection.
    """

    _prefix = "/v1"
    _backup_path = "/v1/admin/backup"

    def __init__(self, url: str = "http://127.0.0.1:8080", *, api_key: str | None = None,
                 timeout: float = 60.0) -> None:
        self.url = url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout

    # -- status

    def health(self) -> JSONObject:
        """GET /healthz: {"status": "ok"} while the process is up."""
        return self._request("GET", "/healthz")

    def ready(self) -> bool:
        """GET /readyz: True once the index is loaded; False while loading or stopping."""
        try:
            self._request("GET", "/readyz")
        except UnavailableError:
            return False
        return True

    # -- two images

    def match(self, a: Image, b: Image, **options: Any) -> JSONObject:
        """POST /v1/match: matches and verifies two images (no index involved).

        options: model (hough-homography, hough-affine, similarity, affine, homography, fundamental), ratio, mutual,
        method (brute, kdtree), min_inliers, correspondences (True adds the inlier pairs).
        """
        fields = {name: _field_value(value) for name, value in options.items() if value is not None}
        return self._request("POST", "/v1/match", multipart=(fields, {"a": _image_bytes(a), "b": _image_bytes(b)}))

    # -- collections

    def collection(self, name: str) -> Collection:
        """The collection `name`, with Client's image and search methods (no request is made here: an
        unknown collection raises NotFoundError, or PermissionDeniedError for a key of another
        collection, at the first call)."""
        return Collection(self, name)

    def collections(self) -> list[JSONObject]:
        """GET /v1/collections: the collections this client's key may read (the admin key, or any key on a
        server without --api-key: all; a collection key: its own and the public ones; no key: the public
        ones), each a Collection object:
        {"name", "public", "images", "features", "disk_bytes", "vocabulary": {"words", "fingerprint",
        "descriptor", "hamming"}, "limits": {"max_images", "max_bytes"}}."""
        collections: list[JSONObject] = self._request("GET", "/v1/collections", expect=("collections",))["collections"]
        return collections

    def create_collection(self, name: str, vocabulary: str | None = None, *, like: str | None = None,
                          public: bool = False, max_images: int | None = None,
                          max_bytes: int | None = None) -> JSONObject:
        """POST /v1/collections (admin key): a new, empty collection; returns its Collection object.

        name: [a-z0-9][a-z0-9_-]{0,63}.
        vocabulary: the path of a vocabulary file on the server's machine; or
        like: the name of a collection whose vocabulary to use. Exactly one of the two (else ValueError).
        public: reads need no key.
        max_images, max_bytes: adds beyond them raise CollectionFullError (max_bytes: the bytes of the
          collection's folder on disk); None: no limit.
        Errors: ConflictError (the name is taken, or the server serves one --index folder),
        InvalidArgumentError (a bad name or limit), NotFoundError (no such vocabulary file or collection).
        """
        if (vocabulary is None) == (like is None):
            raise ValueError("give the new collection's vocabulary: a vocabulary file on the server, or like= "
                             "a collection whose vocabulary to use (one of the two)")
        body: dict[str, Any] = {"name": name, "vocabulary": vocabulary if like is None else {"like": like},
                                "public": public}
        if max_images is not None:
            body["max_images"] = max_images
        if max_bytes is not None:
            body["max_bytes"] = max_bytes
        return self._request("POST", "/v1/collections", json_body=body)

    def get_collection(self, name: str) -> JSONObject:
        """GET /v1/collections/{name}: its Collection object, with "stats" (as stats() answers)."""
        return self._request("GET", _collection_path(name))

    def delete_collection(self, name: str) -> JSONObject:
        """DELETE /v1/collections/{name} (admin key): deletes it, its images and its keys;
        {"name": name, "deleted": true}."""
        return self._request("DELETE", _collection_path(name))

    def create_key(self, name: str, access: Literal["read", "write"] = "read") -> JSONObject:
        """POST /v1/collections/{name}/keys (admin key): a new key of collection `name` that reads it
        ("read") or reads and writes it ("write"): {"key": "oxk_...", "id", "collection", "access",
        "created"}. The key is shown only in this answer (the server keeps a hash of it); use it as a
        Client's api_key."""
        return self._request("POST", _collection_path(name) + "/keys", json_body={"access": access})

    def list_keys(self, name: str) -> list[JSONObject]:
        """GET /v1/collections/{name}/keys (admin key): its keys as [{"id", "access", "created"}, ...]
        (never the keys themselves)."""
        keys: list[JSONObject] = self._request("GET", _collection_path(name) + "/keys", expect=("keys",))["keys"]
        return keys

    def delete_key(self, name: str, key_id: str) -> JSONObject:
        """DELETE /v1/collections/{name}/keys/{key_id} (admin key): revokes the key; {"id", "deleted": true}."""
        if not key_id:
            raise ValueError("a key id is not empty")
        return self._request("DELETE", _collection_path(name) + "/keys/" + urllib.parse.quote(key_id, safe=""))

    def backup_collection(self, name: str, out: str) -> JSONObject:
        """POST /v1/collections/{name}/backup (admin key): as backup(), of collection `name`."""
        return self.collection(name).backup(out)

    # -- transport

    def _send(self, method: str, path: str, query: Mapping[str, Any] | None, multipart: tuple[Fields, Files] | None,
              json_body: Any) -> tuple[int, Message, bytes]:
        url = self.url + path
        if query:
            url += "?" + urllib.parse.urlencode({k: _field_value(v) for k, v in query.items()})
        headers = {"Accept": "application/json", "User-Agent": "oxbow-client-python/" + __version__}
        if self.api_key is not None:
            headers["Authorization"] = "Bearer " + self.api_key
        data = None
        if multipart is not None:
            data, headers["Content-Type"] = _multipart(*multipart)
        elif json_body is not None:
            data, headers["Content-Type"] = json.dumps(json_body).encode(), "application/json"
        request = urllib.request.Request(url, data=data, headers=headers, method=method)
        try:
            try:
                with urllib.request.urlopen(request, timeout=self.timeout) as response:
                    return response.status, response.headers, response.read()
            except urllib.error.HTTPError as e:
                # A 4xx or 5xx answer. Its body is read here, inside the outer try: a body cut short or a
                # timeout while reading it is a TransportError or ClientTimeoutError like a 2xx answer's.
                with e:
                    error = _error_from_response(e.code, e.headers, e.read())
                raise error from None
        except (TimeoutError, socket.timeout) as e:
            raise ClientTimeoutError(f"{method} {path}: no answer within {self.timeout} s") from e
        except urllib.error.URLError as e:
            if isinstance(e.reason, (TimeoutError, socket.timeout)):
                raise ClientTimeoutError(f"{method} {path}: no answer within {self.timeout} s") from e
            raise TransportError(f"{method} {path}: cannot reach {self.url}: {e.reason}") from e
        except http.client.IncompleteRead as e:
            expected = f", {e.expected} more expected" if e.expected is not None else ""
            raise TransportError(f"{method} {path}: the connection to {self.url} broke mid-response "
                                 f"({len(e.partial)} bytes read{expected})") from e
        except OSError as e:  # http.client.RemoteDisconnected, ConnectionResetError, ...
            raise TransportError(f"{method} {path}: connection to {self.url} failed: {e}") from e
        except http.client.HTTPException as e:  # BadStatusLine, LineTooLong, ...: what came back is not HTTP
            raise TransportError(f"{method} {path}: the answer from {self.url} is not valid HTTP "
                                 f"({type(e).__name__}: {str(e).strip()[:200]})") from e


class Collection(_ImageRoutes):
    """One collection of the server: Client's image and search methods (add, add_many, get, delete, list,
    iter_images, thumbnail, search, similar, stats, backup) on /v1/collections/{name}/..., with the
    client's URL, key and timeout. Made by Client.collection(name).
    """

    def __init__(self, client: Client, name: str) -> None:
        self.client = client
        self.name = name
        self._prefix = _collection_path(name)
        self._backup_path = self._prefix + "/backup"

    def info(self) -> JSONObject:
        """GET /v1/collections/{name}: its Collection object, with "stats"."""
        return self.client.get_collection(self.name)

    def __repr__(self) -> str:
        return f"Collection({self.name!r} at {self.client.url})"

    def _send(self, method: str, path: str, query: Mapping[str, Any] | None, multipart: tuple[Fields, Files] | None,
              json_body: Any) -> tuple[int, Message, bytes]:
        return self.client._send(method, path, query, multipart, json_body)


# ---- Helpers -----------------------------------------------------------------------------------------

def _quote_id(id: str) -> str:
    # Every byte but unreserved ones encoded, "/" included: the server takes an encoded slash as part of
    # the id, never as a route separator (server/README.md "Routes").
    if not id:
        raise ValueError("an image id is not empty")
    return urllib.parse.quote(id, safe="")


def _collection_path(name: str) -> str:
    if not name:
        raise ValueError("a collection name is not empty")
    return "/v1/collections/" + urllib.parse.quote(name, safe="")


def _search_fields(bbox: Any, filter: Mapping[str, Any] | str | None,
                   options: Mapping[str, Any]) -> dict[str, str]:
    fields = {name: _field_value(value) for name, value in options.items() if value is not None}
    if filter is not None:
        fields["filter"] = _field_value(filter)
    if bbox is not None:
        if len(bbox) != 4:
            raise ValueError("bbox is (x1, y1, x2, y2)")
        fields["bbox"] = _field_value(bbox)
    return fields


def _batches(items: Iterable[tuple[str, tuple[bytes, str], Any]], max_images: int,
             max_bytes: int) -> Iterator[list[tuple[str, tuple[bytes, str], Any]]]:
    """Consecutive runs of items of at most max_images images and (roughly) max_bytes of request body;
    an image too large on its own goes alone (the server answers it 413)."""
    batch: list[tuple[str, tuple[bytes, str], Any]] = []
    size = 0
    for item in items:
        id, (data, filename), metadata = item
        # The multipart headers of its parts (~300 bytes) and its id, file name and metadata.
        cost = len(data) + 512 + 3 * (len(id) + len(filename)) + len(json.dumps(metadata))
        if batch and (len(batch) == max_images or size + cost > max_bytes):
            yield batch
            batch, size = [], 0
        batch.append(item)
        size += cost
    if batch:
        yield batch


def _add_item(item: Any) -> tuple[str, Image, Any]:
    if isinstance(item, Mapping):
        return item["id"], item["image"], item.get("metadata")
    if isinstance(item, tuple) and len(item) in (2, 3):
        return item[0], item[1], item[2] if len(item) == 3 else None
    raise TypeError("an add_many item is (id, image), (id, image, metadata) or a mapping with id and image")
