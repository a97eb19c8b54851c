"""Tests of oxbow_client against a real `oxbow serve` (every method, success and error).

tests/python_client_test.cc runs it (ctest python_client_test) with a fresh server; by hand:
    OXBOW_URL=http://127.0.0.1:PORT OXBOW_API_KEY=KEY OXBOW_TEST_IMAGES=DIR OXBOW_VOCAB=VOCAB \
        python3 api/python/oxbow_client_test.py -v
where the server was started with `oxbow serve --data DATA --vocab VOCAB --api-key KEY --max-batch-images 2`
over an empty DATA folder (its collection "default" is then created empty, public, with VOCAB; add_many
needs several batches), VOCAB is a vocabulary file (the collection tests create collections with it, so it
is a path on the server's machine: the tests run beside the server), and DIR holds a.png, b.png and c.png:
three different textured pictures. The tests add, replace and delete images with ids starting "py-", and
create and delete collections named "py-<6 random hex digits>-...". Every test needs these four variables:
without one, the tests fail rather than skip.
"""

from __future__ import annotations

import http.client
import io
import os
import pathlib
import re
import secrets
import socket
import sys
import tempfile
import threading
import unittest
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import oxbow_client as ox  # noqa: E402

URL = os.environ.get("OXBOW_URL", "")
API_KEY = os.environ.get("OXBOW_API_KEY", "")
IMAGES = pathlib.Path(os.environ.get("OXBOW_TEST_IMAGES", "/nonexistent"))
VOCAB = os.environ.get("OXBOW_VOCAB", "")
GENERATED_ID = re.compile(r"^[0-9a-f]{16}$")  # the server's own request ids


def setUpModule() -> None:
    # Never skip: a run without a server must fail, not pass with nothing tested.
    if not URL or not API_KEY or not (IMAGES / "a.png").is_file():
        raise RuntimeError(__doc__)


class ServerTestCase(unittest.TestCase):
    def assertServerError(self, context: Any, cls: type[ox.OxbowError], status: int, code: str) -> None:
        error = context.exception
        self.assertIsInstance(error, cls)
        self.assertIsInstance(error, ox.OxbowError)
        self.assertEqual(error.status, status)
        self.assertEqual(error.code, code)
        self.assertRegex(error.request_id or "", GENERATED_ID)
        self.assertTrue(error.message)


class ClientTest(ServerTestCase):
    @classmethod
    def setUpClass(cls):
        cls.client = ox.Client(URL, api_key=API_KEY, timeout=60)
        cls.a = (IMAGES / "a.png").read_bytes()
        cls.b_path = IMAGES / "b.png"
        cls.c_path = str(IMAGES / "c.png")

    # -- status

    def test_health_ready_stats(self):
        self.assertEqual(self.client.health(), {"status": "ok"})
        self.assertTrue(self.client.ready())
        stats = self.client.stats()
        self.assertGreater(stats["words"], 0)
        self.assertIn("images", stats)

    # -- add, get, list, delete

    def test_add_from_bytes_path_and_file_object_then_get_list_delete(self):
        added = self.client.add("py-bytes", self.a, metadata={"city": "Paris", "n": 1})
        self.assertEqual(added["id"], "py-bytes")
        self.assertGreater(added["features"], 0)
        self.assertEqual(added["metadata"], {"city": "Paris", "n": 1})
        self.assertEqual(added["source"], "http:image")
        self.assertFalse(added["replaced"])
        self.assertEqual(self.client.add("py-path", self.b_path)["source"], "http:b.png")
        with open(self.c_path, "rb") as f:
            self.assertEqual(self.client.add("py-file/with slash", f)["source"], "http:c.png")

        record = self.client.get("py-bytes")
        self.assertEqual((record["id"], record["width"], record["height"]), ("py-bytes", added["width"], added["height"]))
        self.assertEqual(record["metadata"], {"city": "Paris", "n": 1})
        self.assertEqual(self.client.get("py-file/with slash")["id"], "py-file/with slash")

        listed = self.client.list(offset=0, limit=1000)
        ids = [image["id"] for image in listed["images"]]
        self.assertTrue({"py-bytes", "py-path", "py-file/with slash"} <= set(ids))
        self.assertEqual(listed["total"], len(ids))
        page = self.client.list(offset=1, limit=1)
        self.assertEqual((page["offset"], page["limit"], [i["id"] for i in page["images"]]), (1, 1, ids[1:2]))

        self.assertTrue(self.client.thumbnail("py-path", size=64).startswith(b"\xff\xd8"))

        for id in ("py-bytes", "py-path", "py-file/with slash"):
            self.assertEqual(self.client.delete(id), {"id": id, "deleted": True})
        with self.assertRaises(ox.NotFoundError) as e:
            self.client.get("py-bytes")
        self.assertServerError(e, ox.NotFoundError, 404, "not_found")

    def test_add_existing_id_conflicts_unless_replace(self):
        self.client.add("py-conflict", self.a)
        with self.assertRaises(ox.ConflictError) as e:
            self.client.add("py-conflict", self.b_path)
        self.assertServerError(e, ox.ConflictError, 409, "already_exists")
        replaced = self.client.add("py-conflict", self.b_path, replace=True, metadata=["x"])
        self.assertTrue(replaced["replaced"])
        self.assertEqual(self.client.get("py-conflict")["metadata"], ["x"])
        self.client.delete("py-conflict")

    def test_add_errors(self):
        nested: list = []
        for _ in range(100):  # deeper than the server's 64 levels
            nested = [nested]
        with self.assertRaises(ox.InvalidArgumentError) as e:
            self.client.add("py-garbage", b"this is not an image")
        self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_image")
        with self.assertRaises(ox.InvalidArgumentError) as e:
            self.client.add("py-bad-metadata", self.a, metadata=nested)
        self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")
        self.assertIn("metadata", e.exception.message)
        with self.assertRaises(ox.NotFoundError):
            self.client.get("py-bad-metadata")
        with self.assertRaises(TypeError):
            self.client.add("py-text-file", io.StringIO("text"))

    def test_add_many_reports_each_image(self):
        results = self.client.add_many([
            ("py-many-1", self.a),
            ("py-many-2", self.b_path, {"k": "v"}),
            {"id": "py-many-bad", "image": b"GIF89a not really"},
            {"id": "py-many-3", "image": self.c_path, "metadata": None},
        ])
        self.assertEqual([r.id for r in results], ["py-many-1", "py-many-2", "py-many-bad", "py-many-3"])
        self.assertEqual([r.ok for r in results], [True, True, False, True])
        self.assertEqual(results[1].response["metadata"], {"k": "v"})
        self.assertIsInstance(results[2].error, ox.ClientError)
        self.assertRegex(results[2].error.request_id, GENERATED_ID)
        self.assertIsNone(results[2].response)
        for id in ("py-many-1", "py-many-2", "py-many-3"):
            self.assertEqual(self.client.get(id)["id"], id)
        with self.assertRaises(ox.NotFoundError):
            self.client.get("py-many-bad")
        self.assertNotIn("replaced", results[0].response)  # the record, as get() returns it
        again = self.client.add_many([("py-many-1", self.a)])
        self.assertIsInstance(again[0].error, ox.ConflictError)
        self.assertTrue(self.client.add_many([("py-many-1", self.a)], replace=True)[0].response["replaced"])
        for id in ("py-many-1", "py-many-2", "py-many-3"):
            self.client.delete(id)

    def test_add_many_sends_batches_of_the_servers_size(self):
        limit = self.client._request("GET", "/v1")["limits"]["max_batch_images"]
        self.assertLess(limit, 5, "start the server with --max-batch-images 2 (see the module docstring)")
        posts = []
        request = self.client._request

        def counting(method, path, **kwargs):
            if path == "/v1/images/batch":
                posts.append(len([f for f in kwargs["multipart"][0] if f[0] == "id"]))
            return request(method, path, **kwargs)

        self.client._request = counting
        try:
            items = [("py-batch-1", self.a), ("py-batch-2", self.b_path), ("py-batch-1", self.c_path),
                     ("py-batch-3", self.c_path), ("py-batch-4", io.BytesIO(self.a))]
            results = self.client.add_many(items)
        finally:
            del self.client._request
        self.assertEqual(sum(posts), len(items))
        self.assertTrue(all(n <= limit for n in posts), posts)
        self.assertEqual(len(posts), -(-len(items) // limit))
        self.assertEqual([r.id for r in results], [id for id, _ in items])
        self.assertEqual([r.ok for r in results], [True, True, False, True, True])
        self.assertIsInstance(results[2].error, ox.ConflictError)  # taken by an earlier batch or this one
        for id in ("py-batch-1", "py-batch-2", "py-batch-3", "py-batch-4"):
            self.assertEqual(self.client.get(id)["id"], id)
            self.client.delete(id)

    def test_add_many_without_the_key_fails_each_image(self):
        results = ox.Client(URL, timeout=60).add_many([("py-nokey-1", self.a), ("py-nokey-2", self.b_path)])
        self.assertEqual([r.ok for r in results], [False, False])
        for r in results:
            self.assertIsInstance(r.error, ox.UnauthenticatedError)
        with self.assertRaises(ox.NotFoundError):
            self.client.get("py-nokey-1")
        self.assertEqual(ox.Client(URL, timeout=60).add_many([]), [])

    def test_unknown_ids(self):
        for call in (self.client.get, self.client.delete, self.client.similar, self.client.thumbnail):
            with self.subTest(call=call.__name__):
                with self.assertRaises(ox.NotFoundError) as e:
                    call("py-never-added")
                self.assertServerError(e, ox.NotFoundError, 404, "not_found")
                self.assertIn("py-never-added", e.exception.message)
                self.assertIn("py-never-added", str(e.exception))

    # -- search, similar, match

    def test_search_and_similar(self):
        self.client.add("py-search-a", self.a)
        self.client.add("py-search-b", self.b_path)
        try:
            for query in (self.a, str(IMAGES / "a.png"), io.BytesIO(self.a)):
                found = self.client.search(query, top_k=1, rerank=10, qe=False)
                self.assertEqual([r["id"] for r in found["results"]], ["py-search-a"])
                self.assertEqual(found["params"]["top_k"], 1)
            boxed = self.client.search(self.a, bbox=(0, 0, 200, 150), top_k=2)
            self.assertEqual(boxed["query"]["bbox"], [0, 0, 200, 150])
            self.assertLessEqual(boxed["query"]["features_used"], boxed["query"]["features"])
            similar = self.client.similar("py-search-b", top_k=1)
            self.assertEqual(similar["results"][0]["id"], "py-search-b")
        finally:
            self.client.delete("py-search-a")
            self.client.delete("py-search-b")

    def test_filtered_search_and_similar(self):
        self.client.add("py-filter-paris", self.a, metadata={"city": "Paris", "year": 2004})
        self.client.add("py-filter-lyon", self.a, metadata={"city": "Lyon", "year": 1999})
        self.client.add("py-filter-other", self.b_path)  # so that a's words have idf > 0
        try:
            found = self.client.search(self.a, filter={"city": "Lyon"}, top_k=5)
            self.assertEqual([r["id"] for r in found["results"]], ["py-filter-lyon"])
            text = self.client.search(self.a, filter='{"year": {"gte": 2000, "lt": 2010}}', top_k=5)
            self.assertEqual([r["id"] for r in text["results"]], ["py-filter-paris"])
            similar = self.client.similar("py-filter-paris", filter={"city": {"in": ["Lyon", "Nice"]}}, top_k=5)
            self.assertEqual([r["id"] for r in similar["results"]], ["py-filter-lyon"])
            with self.assertRaises(ox.InvalidArgumentError) as e:
                self.client.search(self.a, filter={"city": {"like": "P%"}})
            self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")
            self.assertIn("unknown operator 'like'", e.exception.message)
        finally:
            self.client.delete("py-filter-paris")
            self.client.delete("py-filter-lyon")
            self.client.delete("py-filter-other")

    def test_search_bad_parameters(self):
        cases = [({"top_k": 0}, "top_k"), ({"topk": 5}, "topk"), ({"bbox": (10, 10, 5, 5)}, "bbox"),
                 ({"qe_images": 101}, "qe_images")]
        for options, named in cases:
            with self.subTest(options=options):
                with self.assertRaises(ox.InvalidArgumentError) as e:
                    self.client.search(self.a, **options)
                self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")
                self.assertIn(named, e.exception.message)
        with self.assertRaises(ox.InvalidArgumentError) as e:
            self.client.similar("anything", rerank=-1)
        self.assertEqual(e.exception.code, "invalid_argument")

    def test_match(self):
        same = self.client.match(self.a, io.BytesIO(self.a), model="similarity", correspondences=True)
        self.assertTrue(same["verified"])
        self.assertEqual(same["model"], "similarity")
        self.assertEqual(len(same["correspondences"]), same["inliers"])
        self.assertEqual(same["a"]["width"], same["b"]["width"])
        with self.assertRaises(ox.InvalidArgumentError) as e:
            self.client.match(self.a, self.b_path, model="no-such-model")
        self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")
        self.assertIn("model", e.exception.message)

    # -- authentication and transport

    def test_api_key(self):
        anonymous = ox.Client(URL, timeout=60)
        self.assertTrue(anonymous.stats()["words"] > 0)  # reads stay open
        with self.assertRaises(ox.UnauthorizedError) as e:
            anonymous.add("py-anonymous", self.a)
        self.assertServerError(e, ox.UnauthenticatedError, 401, "unauthenticated")
        wrong = ox.Client(URL, api_key=API_KEY + "-wrong", timeout=60)
        for call in (lambda: wrong.add("py-wrong-key", self.a), lambda: wrong.delete("py-wrong-key")):
            with self.assertRaises(ox.UnauthorizedError) as e:
                call()
            self.assertServerError(e, ox.PermissionDeniedError, 403, "permission_denied")
        with self.assertRaises(ox.NotFoundError):
            self.client.get("py-anonymous")

    def test_backup(self):
        with tempfile.TemporaryDirectory() as folder:
            out = os.path.join(folder, "copy")
            with self.assertRaises(ox.UnauthorizedError) as e:
                ox.Client(URL, timeout=60).backup(out)
            self.assertServerError(e, ox.UnauthenticatedError, 401, "unauthenticated")
            answer = self.client.backup(out)
            self.assertEqual(answer["out"], out)
            self.assertGreaterEqual(answer["images"], 0)
            self.assertTrue(os.path.isfile(os.path.join(out, "catalogue.sqlite")))
            with self.assertRaises(ox.ConflictError):
                self.client.backup(out)

    def test_unreachable_server(self):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]  # closed when the block ends: nothing listens there
        with self.assertRaises(ox.TransportError) as e:
            ox.Client(f"http://127.0.0.1:{port}", timeout=5).stats()
        self.assertIsNone(e.exception.status)
        self.assertIsNone(e.exception.request_id)

    def test_timeout(self):
        with socket.socket() as s:  # accepts connections (the backlog) but never answers
            s.bind(("127.0.0.1", 0))
            s.listen(1)
            with self.assertRaises(ox.ClientTimeoutError):
                ox.Client(f"http://127.0.0.1:{s.getsockname()[1]}", timeout=0.2).stats()

    def test_iter_images_reads_every_page(self):
        ids = ["py-iter-1", "py-iter-2", "py-iter-3"]
        for id in ids:
            self.client.add(id, self.a)
        try:
            listed = [image["id"] for image in self.client.list(limit=1000)["images"]]
            for page_size in (1, 2, 1000):
                with self.subTest(page_size=page_size):
                    self.assertEqual([image["id"] for image in self.client.iter_images(page_size=page_size)], listed)
            self.assertTrue(set(ids) <= set(listed))
        finally:
            for id in ids:
                self.client.delete(id)


class CollectionTest(ServerTestCase):
    """Collections, their keys and limits, and the image and search methods of Client.collection(name)."""

    admin: ox.Client
    anonymous: ox.Client
    run_id: str
    a: bytes
    b_path: pathlib.Path
    c_path: str

    @classmethod
    def setUpClass(cls) -> None:
        if not VOCAB:
            raise RuntimeError("OXBOW_VOCAB is not set: the collection tests create collections with that vocabulary "
                               "file (a path on the server's machine); tests/python_client_test.cc sets it and starts "
                               "the server with --data DIR --vocab VOCAB. " + (__doc__ or ""))
        cls.admin = ox.Client(URL, api_key=API_KEY, timeout=60)
        cls.anonymous = ox.Client(URL, timeout=60)
        cls.run_id = secrets.token_hex(3)  # a second run against the same server makes other names
        cls.a = (IMAGES / "a.png").read_bytes()
        cls.b_path = IMAGES / "b.png"
        cls.c_path = str(IMAGES / "c.png")

    def make(self, suffix: str, vocabulary: str | None = None, **options: Any) -> tuple[str, dict[str, Any]]:
        """Creates the collection py-RUN-suffix (with OXBOW_VOCAB unless like= or vocabulary= is given),
        deleted after the test."""
        name = f"py-{self.run_id}-{suffix}"
        if vocabulary is None and "like" not in options:
            vocabulary = VOCAB
        created = self.admin.create_collection(name, vocabulary, **options)
        self.addCleanup(self.drop, name)
        return name, created

    def drop(self, name: str) -> None:
        try:
            self.admin.delete_collection(name)
        except ox.NotFoundError:
            pass  # the test deleted it

    def assertCollection(self, info: dict[str, Any], name: str, *, public: bool = False, images: int = 0,
                         limits: dict[str, Any] | None = None) -> None:
        self.assertEqual(info["name"], name)
        self.assertIs(info["public"], public)
        self.assertEqual(info["images"], images)
        self.assertEqual(info["features"] > 0, images > 0, info)
        self.assertIsInstance(info["disk_bytes"], int)
        self.assertGreater(info["disk_bytes"], 0)  # the vocabulary and the catalogue at least
        self.assertEqual(info["limits"], limits or {"max_images": None, "max_bytes": None})
        vocabulary = info["vocabulary"]
        self.assertGreater(vocabulary["words"], 0)
        self.assertRegex(vocabulary["fingerprint"], r"^[0-9a-f]{16}$")
        self.assertIn(vocabulary["descriptor"], ("sift", "rootsift"))
        self.assertIsInstance(vocabulary["hamming"], bool)

    # -- create, list, get, delete

    def test_create_list_get_delete(self):
        name, created = self.make("life")
        self.assertCollection(created, name)
        self.assertIn(name, [c["name"] for c in self.admin.collections()])
        self.assertIn("default", [c["name"] for c in self.admin.collections()])
        got = self.admin.get_collection(name)
        self.assertCollection(got, name)
        self.assertEqual(got["vocabulary"], created["vocabulary"])
        self.assertEqual((got["stats"]["images"], got["stats"]["words"]), (0, created["vocabulary"]["words"]))
        self.assertEqual(self.admin.collection(name).info()["name"], name)
        self.assertEqual(self.admin.collection(name).stats()["words"], created["vocabulary"]["words"])

        self.assertEqual(self.admin.delete_collection(name), {"name": name, "deleted": True})
        self.assertNotIn(name, [c["name"] for c in self.admin.collections()])
        for call in (lambda: self.admin.get_collection(name), lambda: self.admin.delete_collection(name),
                     lambda: self.admin.collection(name).list(), lambda: self.admin.collection(name).get("py-x")):
            with self.assertRaises(ox.NotFoundError) as e:
                call()
            self.assertServerError(e, ox.NotFoundError, 404, "not_found")

    def test_create_errors(self):
        name, _ = self.make("taken")
        for taken in (name, "default"):
            with self.assertRaises(ox.ConflictError) as e:
                self.admin.create_collection(taken, VOCAB)
            self.assertServerError(e, ox.ConflictError, 409, "already_exists")
        for bad in ("Upper", "-dash-first", "a" * 65, "dot.ted", "sl/ash", f"py-{self.run_id}-bad name"):
            with self.subTest(name=bad):
                with self.assertRaises(ox.InvalidArgumentError) as e:
                    self.admin.create_collection(bad, VOCAB)
                self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")
        with self.assertRaises(ox.InvalidArgumentError) as e:
            self.admin.create_collection(f"py-{self.run_id}-negative", VOCAB, max_images=-1)
        self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")
        with self.assertRaises(ox.NotFoundError) as e:
            self.admin.create_collection(f"py-{self.run_id}-novocab", os.path.join(VOCAB + ".d", "missing.oxvoc"))
        self.assertServerError(e, ox.NotFoundError, 404, "not_found")
        with self.assertRaises(ox.NotFoundError) as e:
            self.admin.create_collection(f"py-{self.run_id}-nolike", like=f"py-{self.run_id}-never-made")
        self.assertServerError(e, ox.NotFoundError, 404, "not_found")
        for failed in ("negative", "novocab", "nolike"):
            self.assertNotIn(f"py-{self.run_id}-{failed}", [c["name"] for c in self.admin.collections()])
        with self.assertRaises(ValueError):  # both, or neither: refused before any request
            self.admin.create_collection(f"py-{self.run_id}-both", VOCAB, like=name)
        with self.assertRaises(ValueError):
            self.admin.create_collection(f"py-{self.run_id}-neither")
        with self.assertRaises(ValueError):
            self.admin.collection("")

    def test_like_takes_the_vocabulary_of_another_collection(self):
        source, created = self.make("like-source")
        copy, copied = self.make("like-copy", like=source, public=True, max_images=10, max_bytes=10**9)
        self.assertCollection(copied, copy, public=True, limits={"max_images": 10, "max_bytes": 10**9})
        self.assertEqual(copied["vocabulary"], created["vocabulary"])

    # -- images and search in a collection

    def test_images_and_search_in_a_collection(self):
        name, _ = self.make("images")
        paris = self.admin.collection(name)
        self.assertEqual((paris.name, paris.client), (name, self.admin))
        added = paris.add("py-c-a", self.a, metadata={"city": "Paris"})
        self.assertEqual((added["id"], added["replaced"], added["metadata"]), ("py-c-a", False, {"city": "Paris"}))
        self.assertGreater(added["features"], 0)
        paris.add("py-c-b", self.b_path)
        with open(self.c_path, "rb") as f:
            paris.add("py-c-c/with slash", f)
        self.assertEqual(paris.get("py-c-c/with slash")["id"], "py-c-c/with slash")
        ids = ["py-c-a", "py-c-b", "py-c-c/with slash"]
        listed = paris.list(limit=1000)
        self.assertEqual(([i["id"] for i in listed["images"]], listed["total"]), (ids, 3))
        self.assertEqual([i["id"] for i in paris.iter_images(page_size=2)], ids)
        self.assertEqual(paris.stats()["images"], 3)
        self.assertCollection(paris.info(), name, images=3)
        self.assertTrue(paris.thumbnail("py-c-b", size=32).startswith(b"\xff\xd8"))

        # Separate from the collection "default" (Client's own methods), both ways.
        with self.assertRaises(ox.NotFoundError):
            self.admin.get("py-c-a")
        self.admin.add("py-default-only", self.a)
        try:
            with self.assertRaises(ox.NotFoundError):
                paris.get("py-default-only")
            self.assertNotIn("py-default-only", [i["id"] for i in paris.iter_images()])
        finally:
            self.admin.delete("py-default-only")

        found = paris.search(self.a, top_k=1)
        self.assertEqual([r["id"] for r in found["results"]], ["py-c-a"])
        self.assertEqual(paris.search(self.a, filter={"city": "Lyon"}, top_k=5)["results"], [])
        self.assertEqual(paris.similar("py-c-b", top_k=1)["results"][0]["id"], "py-c-b")
        with self.assertRaises(ox.InvalidArgumentError) as e:
            paris.search(self.a, top_k=0)
        self.assertServerError(e, ox.InvalidArgumentError, 400, "invalid_argument")

        with self.assertRaises(ox.ConflictError) as e:
            paris.add("py-c-a", self.b_path)
        self.assertServerError(e, ox.ConflictError, 409, "already_exists")
        self.assertTrue(paris.add("py-c-a", self.b_path, replace=True)["replaced"])
        self.assertEqual(paris.delete("py-c-b"), {"id": "py-c-b", "deleted": True})
        for call in (paris.get, paris.delete, paris.similar, paris.thumbnail):
            with self.subTest(call=call.__name__):
                with self.assertRaises(ox.NotFoundError) as e:
                    call("py-c-b")
                self.assertServerError(e, ox.NotFoundError, 404, "not_found")

    def test_find_duplicates_in_a_collection(self):
        name, _ = self.make("dups")
        photos = self.admin.collection(name)
        photos.add("py-d-a", self.a)
        photos.add("py-d-a-copy", self.a)
        photos.add("py-d-b", self.b_path)
        report = photos.find_duplicates(poll_s=0.05, timeout_s=60, candidates=10)
        self.assertEqual(report["images"], 3)
        self.assertEqual([(p["a"], p["b"], p["kind"]) for p in report["pairs"]], [("py-d-a", "py-d-a-copy", "exact")])
        self.assertEqual(report["settings"]["candidates"], 10)
        started = photos.start_duplicates(mirrored=False)
        self.assertEqual(started["collection"], name)
        self.assertIn(photos.job(started["job"])["state"], ("running", "done"))
        self.assertTrue(photos.cancel_job(started["job"])["deleted"])
        with self.assertRaises(ox.NotFoundError):
            photos.job(started["job"])
        with self.assertRaises(ox.InvalidArgumentError):
            photos.start_duplicates(candidates=0)
        with self.assertRaises(ox.UnauthenticatedError):
            self.anonymous.collection(name).start_duplicates()

    def test_add_many_in_a_collection(self):
        name, _ = self.make("many")
        lyon = self.admin.collection(name)
        posts = []
        request = lyon._request

        def counting(method: str, path: str, **kwargs: Any) -> Any:
            if method == "POST":
                posts.append(path)
            return request(method, path, **kwargs)

        lyon._request = counting
        items = [("py-m-1", self.a), ("py-m-2", self.b_path, {"k": "v"}), ("py-m-1", self.c_path),
                 ("py-m-bad", b"not an image"), ("py-m-3", self.c_path)]
        results = lyon.add_many(items)
        self.assertEqual([r.ok for r in results], [True, True, False, False, True])
        self.assertIsInstance(results[2].error, ox.ConflictError)
        self.assertIsInstance(results[3].error, ox.InvalidArgumentError)
        self.assertEqual(results[1].response["metadata"], {"k": "v"})
        self.assertGreater(len(posts), 1)  # the server's --max-batch-images 2
        self.assertEqual(set(posts), {f"/v1/collections/{name}/images/batch"})
        self.assertEqual([i["id"] for i in lyon.iter_images()], ["py-m-1", "py-m-2", "py-m-3"])
        replaced = lyon.add_many([("py-m-1", self.b_path)], replace=True)
        self.assertTrue(replaced[0].response["replaced"])
        self.assertEqual(posts[-1], f"/v1/collections/{name}/images")
        for id in ("py-m-1", "py-m-2", "py-m-3"):
            with self.assertRaises(ox.NotFoundError):
                self.admin.get(id)

    def test_default_is_the_collection_of_the_unprefixed_routes(self):
        default = self.admin.collection("default")
        self.admin.add("py-default-1", self.a, metadata={"n": 1})
        try:
            self.assertEqual(default.get("py-default-1")["metadata"], {"n": 1})
            self.assertIn("py-default-1", [i["id"] for i in default.iter_images()])
            self.assertEqual(default.stats()["images"], self.admin.stats()["images"])
            self.assertIs(default.info()["public"], True)  # --vocab made it public
        finally:
            self.assertEqual(default.delete("py-default-1"), {"id": "py-default-1", "deleted": True})
        with self.assertRaises(ox.NotFoundError):
            self.admin.get("py-default-1")

    # -- keys and access

    def test_keys_grant_read_or_write_of_one_collection(self):
        name, _ = self.make("keys")
        other, _ = self.make("keys-other")
        reader = self.admin.create_key(name)
        writer = self.admin.create_key(name, access="write")
        for key, access in ((reader, "read"), (writer, "write")):
            self.assertRegex(key["key"], r"^oxk_")
            self.assertEqual((key["collection"], key["access"]), (name, access))
            self.assertTrue(key["id"])
            self.assertTrue(key["created"])
        self.assertNotEqual(reader["key"], writer["key"])
        keys = self.admin.list_keys(name)
        self.assertEqual(sorted(k["id"] for k in keys), sorted([reader["id"], writer["id"]]))
        for listed in keys:
            self.assertNotIn("key", listed)
            self.assertEqual(listed["access"], "read" if listed["id"] == reader["id"] else "write")
            self.assertIn("created", listed)
        self.assertEqual(self.admin.list_keys(other), [])

        as_writer = ox.Client(URL, api_key=writer["key"], timeout=60)
        as_reader = ox.Client(URL, api_key=reader["key"], timeout=60)
        self.assertEqual(as_writer.collection(name).add("py-k-1", self.a)["id"], "py-k-1")
        self.assertEqual(as_writer.collection(name).add("py-k-2", self.b_path)["id"], "py-k-2")  # idf > 0 for a's words
        reading = as_reader.collection(name)
        self.assertEqual(reading.get("py-k-1")["id"], "py-k-1")
        self.assertEqual(reading.list()["total"], 2)
        self.assertEqual(reading.search(self.a, top_k=1)["results"][0]["id"], "py-k-1")
        self.assertEqual(as_reader.get_collection(name)["images"], 2)
        for call in (lambda: reading.add("py-k-3", self.a), lambda: reading.delete("py-k-1")):
            with self.assertRaises(ox.PermissionDeniedError) as e:
                call()
            self.assertServerError(e, ox.PermissionDeniedError, 403, "permission_denied")
        self.assertIsInstance(reading.add_many([("py-k-3", self.a)])[0].error, ox.PermissionDeniedError)
        self.assertEqual(reading.list()["total"], 2)

        # Without a key, the collection (not public) cannot be read; with another collection's key, nothing
        # tells whether a collection exists.
        for call in (lambda: self.anonymous.collection(name).get("py-k-1"), lambda: self.anonymous.get_collection(name),
                     lambda: self.anonymous.collection(name).add("py-k-3", self.a)):
            with self.assertRaises(ox.UnauthenticatedError) as e:
                call()
            self.assertServerError(e, ox.UnauthenticatedError, 401, "unauthenticated")
        never = f"py-{self.run_id}-never-made"
        messages = []
        for target in (other, never):
            with self.assertRaises(ox.PermissionDeniedError) as e:
                as_writer.collection(target).list()
            self.assertServerError(e, ox.PermissionDeniedError, 403, "permission_denied")
            messages.append(e.exception.message.replace(target, "NAME"))
        self.assertEqual(messages[0], messages[1])

        # What each key lists: its own collection and the public ones.
        for client in (as_reader, as_writer):
            names = [c["name"] for c in client.collections()]
            self.assertIn(name, names)
            self.assertIn("default", names)
            self.assertNotIn(other, names)
        names = [c["name"] for c in self.anonymous.collections()]
        self.assertIn("default", names)
        self.assertNotIn(name, names)

        # A collection key is not the admin key.
        for call in (lambda: as_writer.create_key(name), lambda: as_writer.list_keys(name),
                     lambda: as_writer.delete_key(name, reader["id"]), lambda: as_writer.delete_collection(name),
                     lambda: as_writer.create_collection(f"py-{self.run_id}-by-key", VOCAB),
                     lambda: as_writer.add("py-k-default", self.a)):  # the collection "default" is not its own
            with self.assertRaises(ox.PermissionDeniedError) as e:
                call()
            self.assertServerError(e, ox.PermissionDeniedError, 403, "permission_denied")

        # A deleted key grants nothing.
        self.assertEqual(self.admin.delete_key(name, reader["id"]), {"id": reader["id"], "deleted": True})
        self.assertEqual([k["id"] for k in self.admin.list_keys(name)], [writer["id"]])
        with self.assertRaises(ox.PermissionDeniedError) as e:
            reading.get("py-k-1")
        self.assertServerError(e, ox.PermissionDeniedError, 403, "permission_denied")
        with self.assertRaises(ox.NotFoundError) as e:
            self.admin.delete_key(name, reader["id"])
        self.assertServerError(e, ox.NotFoundError, 404, "not_found")
        # Deleting the collection deletes its keys.
        self.admin.delete_collection(name)
        with self.assertRaises(ox.PermissionDeniedError):
            as_writer.collection(name).list()

    def test_public_collection_is_read_without_a_key(self):
        name, created = self.make("public", public=True)
        self.assertCollection(created, name, public=True)
        self.admin.collection(name).add("py-p-1", self.a)
        self.admin.collection(name).add("py-p-2", self.b_path)
        public = self.anonymous.collection(name)
        self.assertEqual([i["id"] for i in public.iter_images()], ["py-p-1", "py-p-2"])
        self.assertEqual(public.search(self.a, top_k=1)["results"][0]["id"], "py-p-1")
        self.assertEqual(public.info()["images"], 2)
        self.assertIn(name, [c["name"] for c in self.anonymous.collections()])
        for call in (lambda: public.add("py-p-3", self.a), lambda: public.delete("py-p-1")):
            with self.assertRaises(ox.UnauthenticatedError) as e:
                call()
            self.assertServerError(e, ox.UnauthenticatedError, 401, "unauthenticated")

    # -- limits and backup

    def test_full_collection_refuses_adds(self):
        name, created = self.make("full", max_images=1)
        self.assertEqual(created["limits"], {"max_images": 1, "max_bytes": None})
        full = self.admin.collection(name)
        full.add("py-f-1", self.a)
        with self.assertRaises(ox.CollectionFullError) as e:
            full.add("py-f-2", self.b_path)
        self.assertServerError(e, ox.CollectionFullError, 507, "collection_full")
        self.assertIsInstance(e.exception, ox.ServerError)
        results = full.add_many([("py-f-2", self.b_path), ("py-f-3", self.c_path)])
        self.assertEqual([r.ok for r in results], [False, False])
        self.assertIsInstance(results[0].error, ox.CollectionFullError)
        full.delete("py-f-1")
        self.assertEqual(full.add("py-f-2", self.b_path)["id"], "py-f-2")

        name, _ = self.make("full-bytes", max_bytes=1)  # its folder already holds more
        with self.assertRaises(ox.CollectionFullError) as e:
            self.admin.collection(name).add("py-f-1", self.a)
        self.assertServerError(e, ox.CollectionFullError, 507, "collection_full")
        self.assertEqual(self.admin.get_collection(name)["images"], 0)

    def test_backup_collection(self):
        name, _ = self.make("backup")
        self.admin.collection(name).add("py-b-1", self.a)
        with tempfile.TemporaryDirectory() as folder:
            out = os.path.join(folder, "copy")
            with self.assertRaises(ox.UnauthenticatedError) as e:
                self.anonymous.backup_collection(name, out)
            self.assertServerError(e, ox.UnauthenticatedError, 401, "unauthenticated")
            writer = ox.Client(URL, api_key=self.admin.create_key(name, access="write")["key"], timeout=60)
            with self.assertRaises(ox.PermissionDeniedError) as e:
                writer.collection(name).backup(out)
            self.assertServerError(e, ox.PermissionDeniedError, 403, "permission_denied")
            answer = self.admin.backup_collection(name, out)
            self.assertEqual((answer["out"], answer["images"]), (out, 1))
            self.assertTrue(os.path.isfile(os.path.join(out, "catalogue.sqlite")))
            with self.assertRaises(ox.ConflictError):
                self.admin.collection(name).backup(out)
            with self.assertRaises(ox.NotFoundError):
                self.admin.backup_collection(f"py-{self.run_id}-never-made", os.path.join(folder, "other"))


class ErrorMappingTest(unittest.TestCase):
    """Answers the test server cannot easily give on demand: the mapping alone."""

    def test_unavailable_carries_retry_after(self):
        body = b'{"error":{"code":"unavailable","message":"index loading","request_id":"r1"}}'
        error = ox._error_from_response(503, {"Retry-After": "1", "X-Request-Id": "r1"}, body)
        self.assertIsInstance(error, ox.UnavailableError)
        self.assertIsInstance(error, ox.ServerError)
        self.assertEqual((error.status, error.code, error.request_id, error.retry_after), (503, "unavailable", "r1", 1.0))

    def test_collection_full_is_a_server_error(self):
        body = b'{"error":{"code":"collection_full","message":"at max_images 10","request_id":"r3"}}'
        error = ox._error_from_response(507, {}, body)
        self.assertIsInstance(error, ox.CollectionFullError)
        self.assertIsInstance(error, ox.ServerError)
        self.assertEqual((error.status, error.code, error.request_id), (507, "collection_full", "r3"))
        self.assertEqual(str(error), "at max_images 10 (HTTP 507, collection_full, request r3)")

    def test_a_body_that_is_not_oxbows_keeps_its_text(self):
        error = ox._error_from_response(502, {"X-Request-Id": "r2"}, b"<html>Bad Gateway</html>")
        self.assertIsInstance(error, ox.ServerError)
        self.assertNotIsInstance(error, ox.UnavailableError)
        self.assertEqual((error.code, error.message, error.request_id), (None, "<html>Bad Gateway</html>", "r2"))
        self.assertIsInstance(ox._error_from_response(418, {}, b""), ox.ClientError)


class StubServer:
    """A server on 127.0.0.1 that answers its first requests, one per connection, with `answers` (bytes as
    given, however malformed), closing each connection: the answers of a broken connection, a proxy, a
    captive portal or another service."""

    def __init__(self, *answers: bytes) -> None:
        self.answers = answers
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(10)  # never blocks the tests for longer when no request comes
        self.url = f"http://127.0.0.1:{self.listener.getsockname()[1]}"
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> StubServer:
        self.thread.start()
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.thread.join(10)
        self.listener.close()

    def _serve(self) -> None:
        for answer in self.answers:
            try:
                connection, _ = self.listener.accept()
            except OSError:
                return
            with connection:
                connection.settimeout(10)
                if not self._read_request(connection):
                    return
                connection.sendall(answer)
                connection.shutdown(socket.SHUT_WR)

    @staticmethod
    def _read_request(connection: socket.socket) -> bool:
        """Reads the request's head and its Content-Length bytes of body; False if the client left."""
        request = b""
        while b"\r\n\r\n" not in request:
            chunk = connection.recv(65536)
            if not chunk:
                return False
            request += chunk
        head, body = request.split(b"\r\n\r\n", 1)
        length = re.search(rb"(?im)^content-length:\s*(\d+)", head)
        remaining = (int(length.group(1)) if length else 0) - len(body)
        while remaining > 0:
            chunk = connection.recv(65536)
            if not chunk:
                return False
            remaining -= len(chunk)
        return True


def http_answer(status: str, content_type: str, body: bytes) -> bytes:
    return (f"HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {len(body)}\r\n\r\n").encode() + body


class BrokenAnswerTest(unittest.TestCase):
    """Answers that are not a whole HTTP answer, or not JSON: OxbowError like every failure."""

    def fetch_stats(self, answer: bytes) -> ox.OxbowError:
        with StubServer(answer) as server:
            with self.assertRaises(ox.OxbowError) as e:
                ox.Client(server.url, timeout=5).stats()
        self.assertIsInstance(e.exception, ox.OxbowError)
        return e.exception

    def test_a_body_cut_short_is_a_transport_error(self):
        for status in (b"200 OK", b"502 Bad Gateway"):  # the answer's body, or the body of an error answer
            with self.subTest(status=status):
                error = self.fetch_stats(b"HTTP/1.1 " + status + b"\r\nContent-Type: application/json\r\n"
                                         b"Content-Length: 100\r\n\r\n" + b'{"images":1')
                self.assertIsInstance(error, ox.TransportError)
                self.assertNotIsInstance(error, ox.ClientTimeoutError)
                self.assertIsNone(error.status)
                self.assertIn("mid-response", error.message)
                self.assertIsInstance(error.__cause__, http.client.IncompleteRead)

    def test_a_garbage_status_line_is_a_transport_error(self):
        error = self.fetch_stats(b"SSH-2.0-OpenSSH_9.2\r\n\r\n")
        self.assertIsInstance(error, ox.TransportError)
        self.assertIsNone(error.status)
        self.assertIsInstance(error.__cause__, http.client.BadStatusLine)

    def test_a_2xx_body_that_is_not_json_is_a_server_error(self):
        page = b"<html><body>Sign in to the network</body></html>"
        error = self.fetch_stats(b"HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nX-Request-Id: proxy-7\r\n"
                                 b"Content-Length: " + str(len(page)).encode() + b"\r\n\r\n" + page)
        self.assertIsInstance(error, ox.ServerError)
        self.assertEqual((error.status, error.code, error.request_id), (200, None, "proxy-7"))
        self.assertIn("not JSON", error.message)
        self.assertIn("Sign in to the network", error.message)

    def test_a_2xx_answer_that_is_json_but_not_an_object_is_a_server_error(self):
        error = self.fetch_stats(http_answer("200 OK", "application/json", b'["images", 3]'))
        self.assertIsInstance(error, ox.ServerError)
        self.assertEqual(error.status, 200)
        self.assertIn("not an object", error.message)

    def test_an_answer_without_what_the_client_reads_is_a_server_error(self):
        with StubServer(http_answer("200 OK", "application/json", b'{"items": []}')) as server:
            with self.assertRaises(ox.ServerError) as e:
                ox.Client(server.url, timeout=5).collections()
        self.assertIn("has no 'collections'", e.exception.message)
        with StubServer(http_answer("200 OK", "application/json", b'{"images": []}')) as server:
            with self.assertRaises(ox.ServerError) as e:
                list(ox.Client(server.url, timeout=5).iter_images())
        self.assertIn("has no 'total'", e.exception.message)

    def test_add_many_with_limits_or_results_not_oxbows(self):
        image = b"\x89PNG not read by the stub"
        limits_without_bytes = http_answer("200 OK", "application/json", b'{"limits": {"max_batch_images": 2}}')
        with StubServer(limits_without_bytes) as server:
            with self.assertRaises(ox.ServerError) as e:
                ox.Client(server.url, timeout=5).add_many([("a", image)])
        self.assertIn("'max_upload_bytes'", e.exception.message)
        limits = http_answer("200 OK", "application/json",
                             b'{"limits": {"max_batch_images": 4, "max_upload_bytes": 1000000}}')
        for results in (b'{"results": [{"image": {"id": "a"}}]}',  # one result for two images
                        b'{"results": [{"image": {"id": "a"}}, {"status": 400}]}'):  # no "error"
            with self.subTest(results=results):
                with StubServer(limits, http_answer("200 OK", "application/json", results)) as server:
                    added = ox.Client(server.url, timeout=5).add_many([("a", image), ("b", image)])
                self.assertEqual([r.id for r in added], ["a", "b"])
                for r in added:  # nothing is known of either image
                    self.assertFalse(r.ok)
                    self.assertIsInstance(r.error, ox.ServerError)

    def test_a_thumbnail_that_is_not_a_jpeg_is_a_server_error(self):
        with StubServer(http_answer("200 OK", "text/html", b"<html>Sign in</html>")) as server:
            with self.assertRaises(ox.ServerError) as e:
                ox.Client(server.url, timeout=5).thumbnail("a")
        self.assertIn("not a JPEG", e.exception.message)


if __name__ == "__main__":
    unittest.main()
