"""Tests of oxbow_client.py against a real `oxbow serve` (every method, success and error).

tests/python_client_test.cc runs it (ctest python_client_test) with a fresh server; by hand:
    OXBOW_URL=http://127.0.0.1:PORT OXBOW_API_KEY=KEY OXBOW_TEST_IMAGES=DIR python3 -m unittest -v oxbow_client_test
where the server was started with --api-key KEY --max-batch-images 2 over an empty index (add_many then
needs several batches), and DIR holds a.png, b.png and c.png:
three different textured pictures. The tests add, replace and delete images with ids starting "py-".
"""

import io
import os
import pathlib
import re
import socket
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import oxbow_client as ox  # noqa: E402

URL = os.environ.get("OXBOW_URL", "")
API_KEY = os.environ.get("OXBOW_API_KEY", "")
IMAGES = pathlib.Path(os.environ.get("OXBOW_TEST_IMAGES", "/nonexistent"))
GENERATED_ID = re.compile(r"^[0-9a-f]{16}$")  # the server's own request ids


def setUpModule():
    # Never skip: a run without a server must fail, not pass with nothing tested.
    if not URL or not API_KEY or not (IMAGES / "a.png").is_file():
        raise RuntimeError(__doc__)


class ClientTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.client = ox.Client(URL, api_key=API_KEY, timeout=60)
        cls.a = (IMAGES / "a.png").read_bytes()
        cls.b_path = IMAGES / "b.png"
        cls.c_path = str(IMAGES / "c.png")

    def assertServerError(self, context, cls, status, code):
        error = context.exception
        self.assertIsInstance(error, cls)
        self.assertIsInstance(error, ox.OxbowError)
        self.assertEqual(error.status, status)
        self.assertEqual(error.code, code)
        self.assertRegex(error.request_id or "", GENERATED_ID)
        self.assertTrue(error.message)

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


class ErrorMappingTest(unittest.TestCase):
    """Answers the test server cannot easily give on demand: the mapping alone."""

    def test_unavailable_carries_retry_after(self):
        body = b'{"error":{"code":"unavailable","message":"index loading","request_id":"r1"}}'
        error = ox._error_from_response(503, {"Retry-After": "1", "X-Request-Id": "r1"}, body)
        self.assertIsInstance(error, ox.UnavailableError)
        self.assertIsInstance(error, ox.ServerError)
        self.assertEqual((error.status, error.code, error.request_id, error.retry_after), (503, "unavailable", "r1", 1.0))

    def test_a_body_that_is_not_oxbows_keeps_its_text(self):
        error = ox._error_from_response(502, {"X-Request-Id": "r2"}, b"<html>Bad Gateway</html>")
        self.assertIsInstance(error, ox.ServerError)
        self.assertNotIsInstance(error, ox.UnavailableError)
        self.assertEqual((error.code, error.message, error.request_id), (None, "<html>Bad Gateway</html>", "r2"))
        self.assertIsInstance(ox._error_from_response(418, {}, b""), ox.ClientError)


if __name__ == "__main__":
    unittest.main()
