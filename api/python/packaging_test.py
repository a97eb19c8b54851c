"""Tests of the oxbow_client distribution: the build backend (_build/oxbow_build.py) and installs with pip.

    python3 api/python/packaging_test.py -v      (ctest python_client_package; no server needed)

BackendTest builds the archives and reads them back: the wheel's files, METADATA, WHEEL and RECORD (every
hash and size checked), the sdist and a wheel rebuilt from it, the editable wheel, the install tree of the
Debian package, reproducibility, and the refusal of pyproject.toml keys the backend would drop.
InstallTest makes a virtual environment with the running interpreter (`python3 -m venv`: Debian's
python3-venv), then installs the source folder, the wheel, the sdist and the folder in editable mode with
`pip install --no-index` (nothing downloaded: the backend needs no build dependency) and imports each
from outside the source tree. Nothing is skipped: without venv or pip the test fails, saying what to install.
"""

from __future__ import annotations

import base64
import contextlib
import csv
import email.parser
import hashlib
import io
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
import unittest
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_build"))
import oxbow_build  # noqa: E402

REPO = HERE.parent.parent  # the oxbow checkout


def found(pattern: str, text: str) -> str:
    match = re.search(pattern, text, re.MULTILINE)
    if match is None:
        raise AssertionError(f"no {pattern!r} in {text[:200]!r}...")
    return match.group(1)


VERSION = found(r"""^__version__ = "([^"]+)""", (HERE / "oxbow_client" / "__init__.py").read_text())
WHEEL = f"oxbow_client-{VERSION}-py3-none-any.whl"
DIST_INFO = f"oxbow_client-{VERSION}.dist-info"


def record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def run(*command: str | os.PathLike[str], cwd: Path | None = None,
        env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([os.fspath(c) for c in command], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


@contextlib.contextmanager
def source_copy() -> Iterator[Path]:
    """A copy of this folder's distribution sources (what the sdist holds), to change without touching it."""
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "src"
        for path in ["pyproject.toml", "README.md", "_build/oxbow_build.py", "oxbow_client"]:
            source, target = HERE / path, root / path
            target.parent.mkdir(parents=True, exist_ok=True)
            if source.is_dir():
                shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copyfile(source, target)
        yield root


class BackendTest(unittest.TestCase):
    def setUp(self) -> None:
        self.out = Path(self.enterContext(tempfile.TemporaryDirectory()))

    def package_files(self) -> dict[str, bytes]:
        return {path.relative_to(HERE).as_posix(): path.read_bytes()
                for path in sorted((HERE / "oxbow_client").rglob("*"))
                if path.is_file() and "__pycache__" not in path.parts}

    def test_the_hooks_need_nothing(self) -> None:
        self.assertEqual(oxbow_build.get_requires_for_build_wheel(), [])
        self.assertEqual(oxbow_build.get_requires_for_build_sdist(), [])
        self.assertEqual(oxbow_build.get_requires_for_build_editable(), [])

    def test_wheel_files_metadata_and_record(self) -> None:
        self.assertEqual(oxbow_build.build_wheel(str(self.out)), WHEEL)
        self.assertEqual(sorted(os.listdir(self.out)), [WHEEL])  # no temporary file left
        with zipfile.ZipFile(self.out / WHEEL) as wheel:
            self.assertIsNone(wheel.testzip())
            names = wheel.namelist()
            contents = {name: wheel.read(name) for name in names}
            infos = wheel.infolist()
        files = self.package_files()
        self.assertIn("oxbow_client/__init__.py", files)
        self.assertIn("oxbow_client/py.typed", files)
        self.assertEqual(names, [*files, f"{DIST_INFO}/METADATA", f"{DIST_INFO}/WHEEL", f"{DIST_INFO}/RECORD"])
        for name, data in files.items():
            self.assertEqual(contents[name], data, name)
        for info in infos:
            self.assertEqual(info.external_attr >> 16, 0o100644, info.filename)

        wheel_fields = email.parser.Parser().parsestr(contents[f"{DIST_INFO}/WHEEL"].decode())
        self.assertEqual((wheel_fields["Wheel-Version"], wheel_fields["Root-Is-Purelib"], wheel_fields.get_all("Tag")),
                         ("1.0", "true", ["py3-none-any"]))

        metadata = email.parser.Parser().parsestr(contents[f"{DIST_INFO}/METADATA"].decode())
        self.assertEqual((metadata["Metadata-Version"], metadata["Name"], metadata["Version"]),
                         ("2.1", "oxbow-client", VERSION))
        self.assertEqual(metadata["Requires-Python"], ">=3.11")
        self.assertIn("Typing :: Typed", metadata.get_all("Classifier"))
        self.assertIsNone(metadata["Requires-Dist"])  # standard library only
        self.assertEqual(metadata["Description-Content-Type"], "text/markdown; charset=UTF-8")
        self.assertEqual(metadata.get_payload(), (HERE / "README.md").read_text())

        rows = list(csv.reader(io.StringIO(contents[f"{DIST_INFO}/RECORD"].decode())))
        self.assertEqual([row[0] for row in rows], names)  # every file, RECORD last
        self.assertEqual(rows[-1], [f"{DIST_INFO}/RECORD", "", ""])
        for path, digest, size in rows[:-1]:
            self.assertEqual(digest, record_hash(contents[path]), path)
            self.assertEqual(int(size), len(contents[path]), path)

    def test_prepared_metadata_is_the_wheels(self) -> None:
        self.assertEqual(oxbow_build.prepare_metadata_for_build_wheel(str(self.out)), DIST_INFO)
        self.assertEqual(oxbow_build.prepare_metadata_for_build_editable(str(self.out / "e")), DIST_INFO)
        oxbow_build.build_wheel(str(self.out), metadata_directory=str(self.out / DIST_INFO))
        with zipfile.ZipFile(self.out / WHEEL) as wheel:
            for name in ("METADATA", "WHEEL"):
                self.assertEqual((self.out / DIST_INFO / name).read_bytes(), wheel.read(f"{DIST_INFO}/{name}"))
                self.assertEqual((self.out / "e" / DIST_INFO / name).read_bytes(), wheel.read(f"{DIST_INFO}/{name}"))

    def test_archives_are_reproducible(self) -> None:
        first, second, dated = self.out / "1", self.out / "2", self.out / "3"
        for folder in (first, second, dated):
            folder.mkdir()
        builds: list[Callable[[str], str]] = [oxbow_build.build_wheel, oxbow_build.build_sdist]
        for build in builds:
            name = build(str(first))
            self.assertEqual(build(str(second)), name)
            self.assertEqual((first / name).read_bytes(), (second / name).read_bytes(), name)
        with zipfile.ZipFile(first / WHEEL) as wheel:  # not the clock's time
            self.assertEqual({info.date_time for info in wheel.infolist()}, {(1980, 1, 1, 0, 0, 0)})
        with tarfile.open(first / f"oxbow_client-{VERSION}.tar.gz") as tar:
            self.assertEqual({member.mtime for member in tar.getmembers()}, {315532800})
        with modified_environment(SOURCE_DATE_EPOCH="1764633600"):  # 2025-12-02
            oxbow_build.build_wheel(str(dated))
            oxbow_build.build_sdist(str(dated))
        with zipfile.ZipFile(dated / WHEEL) as wheel:
            self.assertEqual({info.date_time for info in wheel.infolist()}, {(2025, 12, 2, 0, 0, 0)})
        with tarfile.open(dated / f"oxbow_client-{VERSION}.tar.gz") as tar:
            self.assertEqual({member.mtime for member in tar.getmembers()}, {1764633600})

    def test_sdist_holds_what_rebuilds_the_same_wheel(self) -> None:
        name = oxbow_build.build_sdist(str(self.out))
        self.assertEqual(name, f"oxbow_client-{VERSION}.tar.gz")
        top = f"oxbow_client-{VERSION}"
        with tarfile.open(self.out / name) as tar:
            members = tar.getmembers()
            self.assertEqual(sorted(m.name for m in members), sorted(
                [f"{top}/{path}" for path in ["PKG-INFO", "README.md", "_build/oxbow_build.py", "pyproject.toml",
                                              *self.package_files()]]))
            for member in members:
                self.assertTrue(member.isfile(), member.name)
                self.assertEqual((member.mode, member.uid, member.gid), (0o644, 0, 0), member.name)
            for member in members:  # files only (checked above), written out one by one
                target = self.out / "unpacked" / member.name
                target.parent.mkdir(parents=True, exist_ok=True)
                source = tar.extractfile(member)
                assert source is not None
                target.write_bytes(source.read())
        unpacked = self.out / "unpacked" / top
        oxbow_build.build_wheel(str(self.out))
        metadata = read_zip(self.out / WHEEL, f"{DIST_INFO}/METADATA")
        self.assertEqual((unpacked / "PKG-INFO").read_bytes(), metadata)
        rebuilt = run(sys.executable, unpacked / "_build" / "oxbow_build.py", "wheel", self.out / "rebuilt",
                      env=dict(os.environ, PYTHONDONTWRITEBYTECODE="1"))
        self.assertEqual(rebuilt.returncode, 0, rebuilt.stderr)
        self.assertEqual((self.out / "rebuilt" / WHEEL).read_bytes(), (self.out / WHEEL).read_bytes())

    def test_editable_wheel_points_at_the_source_folder(self) -> None:
        self.assertEqual(oxbow_build.build_editable(str(self.out)), WHEEL)
        with zipfile.ZipFile(self.out / WHEEL) as wheel:
            pth = f"__editable__.oxbow_client-{VERSION}.pth"
            self.assertEqual(wheel.namelist(),
                             [pth, f"{DIST_INFO}/METADATA", f"{DIST_INFO}/WHEEL", f"{DIST_INFO}/RECORD"])
            self.assertEqual(wheel.read(pth).decode(), f"{HERE}\n")

    def test_install_tree_of_the_debian_package(self) -> None:
        destination = self.out / "dist-packages"
        (destination / "oxbow_client").mkdir(parents=True)
        (destination / "oxbow_client" / "removed.py").write_text("")  # from an earlier version
        (destination / "oxbow_client-0.0.1.dist-info").mkdir()
        (destination / "other.py").write_text("")                    # not ours: kept
        written = oxbow_build.install(destination, installer="dpkg")
        found = sorted(p.relative_to(destination).as_posix() for p in destination.rglob("*") if p.is_file())
        self.assertEqual(found, sorted([*self.package_files(), f"{DIST_INFO}/INSTALLER", f"{DIST_INFO}/METADATA",
                                        "other.py"]))
        self.assertEqual(len(written), len(found) - 1)
        self.assertEqual((destination / DIST_INFO / "INSTALLER").read_text(), "dpkg\n")
        oxbow_build.build_wheel(str(self.out))
        self.assertEqual((destination / DIST_INFO / "METADATA").read_bytes(),
                         read_zip(self.out / WHEEL, f"{DIST_INFO}/METADATA"))
        for path, data in self.package_files().items():
            self.assertEqual((destination / path).read_bytes(), data)

    def test_command_line(self) -> None:
        env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
        wheel = run(sys.executable, HERE / "_build" / "oxbow_build.py", "wheel", self.out, env=env)
        self.assertEqual((wheel.returncode, wheel.stdout.strip()), (0, str(self.out / WHEEL)), wheel.stderr)
        install = run(sys.executable, HERE / "_build" / "oxbow_build.py", "install", self.out / "tree",
                      "--installer", "dpkg", env=env)
        self.assertEqual(install.returncode, 0, install.stderr)
        self.assertTrue((self.out / "tree" / "oxbow_client" / "py.typed").is_file())
        usage = run(sys.executable, HERE / "_build" / "oxbow_build.py", "bogus", env=env)
        self.assertEqual(usage.returncode, 2)
        self.assertIn("python3 _build/oxbow_build.py wheel [OUT]", usage.stderr)

    def test_bytecode_is_left_out(self) -> None:
        with source_copy() as root:
            (root / "oxbow_client" / "__pycache__").mkdir()
            (root / "oxbow_client" / "__pycache__" / "__init__.cpython-311.pyc").write_bytes(b"\0")
            (root / "oxbow_client" / "stale.pyc").write_bytes(b"\0")
            built = run(sys.executable, root / "_build" / "oxbow_build.py", "wheel", self.out,
                        env=dict(os.environ, PYTHONDONTWRITEBYTECODE="1"))
            self.assertEqual(built.returncode, 0, built.stderr)
        with zipfile.ZipFile(self.out / WHEEL) as wheel:
            self.assertEqual([n for n in wheel.namelist() if "pyc" in n or "__pycache__" in n], [])

    def test_what_the_backend_cannot_write_fails_the_build(self) -> None:
        cases = [
            ('dependencies = []', 'dependencies = []\nlicense = {text = "MIT"}', "license not supported"),
            ('dynamic = ["version"]', 'version = "1.0"', "dynamic"),
            ('name = "oxbow-client"', 'name = "-oxbow"', "not a valid distribution name"),
            ('readme = "README.md"', 'readme = "README.pdf"', "type of a '.pdf' file is unknown"),
            ('readme = "README.md"', 'readme = "../outside.md"', "outside"),
        ]
        for old, new, message in cases:
            with self.subTest(new=new), source_copy() as root:
                (root.parent / "outside.md").write_text("# a readme the sdist would not hold\n")
                pyproject = root / "pyproject.toml"
                text = pyproject.read_text()
                self.assertIn(old, text)
                pyproject.write_text(text.replace(old, new))
                with self.assertRaises(oxbow_build.BuildError) as e:
                    oxbow_build.read_project(root)
                self.assertIn(message, str(e.exception))
        with source_copy() as root:
            init = root / "oxbow_client" / "__init__.py"
            init.write_text(init.read_text().replace(f'__version__ = "{VERSION}"', '__version__ = "1.0-beta"'))
            with self.assertRaisesRegex(oxbow_build.BuildError, "not a normalised PEP 440 version"):
                oxbow_build.read_project(root)

    def test_version_is_the_projects(self) -> None:
        cmake = (REPO / "CMakeLists.txt").read_text()
        self.assertEqual(found(r"project\(oxbow VERSION (\S+)", cmake), VERSION,
                         "oxbow_client/__init__.py's __version__ follows project(VERSION) in CMakeLists.txt")


class InstallTest(unittest.TestCase):
    """pip installs, offline, into a fresh virtual environment, and imports from outside the source tree."""

    work: Path          # the venv and the archives
    env: dict[str, str]  # of pip and the venv's python: no PIP_* or PYTHON* of the caller's
    python: Path        # the venv's

    @classmethod
    def setUpClass(cls) -> None:
        cls.work = Path(tempfile.mkdtemp(prefix="oxbow-client-install-"))
        cls.addClassCleanup(shutil.rmtree, cls.work)
        cls.env = {key: value for key, value in os.environ.items() if not key.startswith(("PIP_", "PYTHON"))}
        cls.env.update(PIP_CONFIG_FILE=os.devnull, PIP_DISABLE_PIP_VERSION_CHECK="1", PIP_NO_CACHE_DIR="1",
                       PYTHONDONTWRITEBYTECODE="1", PYTHONNOUSERSITE="1")
        started = time.monotonic()
        made = run(sys.executable, "-m", "venv", cls.work / "venv", env=cls.env)
        if made.returncode != 0:
            raise RuntimeError(f"{sys.executable} -m venv failed (on Debian, install python3-venv: "
                               f"scripts/install-deps.sh):\n{made.stdout}{made.stderr}")
        cls.python = cls.work / "venv" / "bin" / "python"
        print(f"\n  venv with pip: {time.monotonic() - started:.1f} s", file=sys.stderr)

    def pip(self, *arguments: str | os.PathLike[str]) -> str:
        started = time.monotonic()
        done = run(self.python, "-m", "pip", *arguments, cwd=self.work, env=self.env)
        command = "pip " + " ".join(map(str, arguments))
        self.assertEqual(done.returncode, 0, f"{command}:\n{done.stdout}{done.stderr}")
        print(f"  {command}: {time.monotonic() - started:.1f} s", file=sys.stderr)
        return done.stdout

    def imported(self) -> list[str]:
        """Where the venv's python imports oxbow_client from, its version, its metadata's, py.typed."""
        script = ("import importlib.metadata, pathlib, oxbow_client\n"
                  "from oxbow_client import Client, Collection, CollectionFullError, NotFoundError\n"
                  "assert issubclass(CollectionFullError, oxbow_client.ServerError)\n"
                  "assert Client('http://127.0.0.1:1').collection('paris').name == 'paris'\n"
                  "folder = pathlib.Path(oxbow_client.__file__).parent\n"
                  "print(folder, oxbow_client.__version__, importlib.metadata.version('oxbow-client'),\n"
                  "      (folder / 'py.typed').is_file())\n")
        # From the work folder: HERE, which holds oxbow_client/, is not on sys.path.
        done = run(self.python, "-c", script, cwd=self.work, env=self.env)
        self.assertEqual(done.returncode, 0, done.stderr)
        return done.stdout.split()

    def site_packages(self) -> str:
        done = run(self.python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))", env=self.env)
        return done.stdout.strip()

    def test_installs_offline(self) -> None:
        installed = [str(Path(self.site_packages()) / "oxbow_client"), VERSION, VERSION, "True"]

        self.pip("install", "--no-index", HERE)  # the source folder: pip runs the PEP 517 hooks
        self.assertEqual(self.imported(), installed)
        self.assertRegex(self.pip("list"), rf"(?m)^oxbow-client +{re.escape(VERSION)}$")
        self.pip("uninstall", "--yes", "oxbow-client")
        self.assertFalse((Path(self.site_packages()) / "oxbow_client").exists())

        wheel = oxbow_build.build_wheel(str(self.work))
        self.pip("install", "--no-index", self.work / wheel)
        self.assertEqual(self.imported(), installed)
        self.pip("uninstall", "--yes", "oxbow-client")

        sdist = oxbow_build.build_sdist(str(self.work))
        self.pip("install", "--no-index", self.work / sdist)
        self.assertEqual(self.imported(), installed)
        self.pip("uninstall", "--yes", "oxbow-client")

        self.pip("install", "--no-index", "--editable", HERE)  # PEP 660
        self.assertEqual(self.imported(), [str(HERE / "oxbow_client"), VERSION, VERSION, "True"])
        self.pip("uninstall", "--yes", "oxbow-client")
        self.pip("check")


@contextlib.contextmanager
def modified_environment(**values: str) -> Iterator[None]:
    saved = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def read_zip(path: Path, name: str) -> bytes:
    with zipfile.ZipFile(path) as archive:
        return archive.read(name)


if __name__ == "__main__":
    unittest.main()
