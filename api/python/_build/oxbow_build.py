"""The build backend of oxbow_client (PEP 517 and PEP 660), Python's standard library only.

pyproject.toml names it with `backend-path` and `requires = []`, so pip's isolated build installs nothing
and `pip install ./api/python` works without a network or setuptools. It builds:
  - a wheel, oxbow_client-VERSION-py3-none-any.whl: the package folder oxbow_client/ (its files, no
    bytecode) and oxbow_client-VERSION.dist-info/ with METADATA (core metadata 2.1 from pyproject.toml's
    [project] table), WHEEL and RECORD (sha256 and size of every file);
  - an sdist, oxbow_client-VERSION.tar.gz: pyproject.toml, the readme, this backend, the package and PKG-INFO,
    from which the same wheel builds;
  - an editable wheel (pip install -e): a .pth file that puts this source folder on sys.path.
Archives are reproducible: sorted entries, fixed permissions, and SOURCE_DATE_EPOCH (default 1980-01-01)
as every timestamp. The version is `__version__` in oxbow_client/__init__.py, read as text (not imported).

Hooks (as pip 23 calls them): get_requires_for_build_wheel/_sdist/_editable, prepare_metadata_for_build_wheel
/_editable, build_wheel, build_sdist, build_editable.

The same from a shell (OUT defaults to ./dist):
    python3 _build/oxbow_build.py wheel [OUT]
    python3 _build/oxbow_build.py sdist [OUT]
    python3 _build/oxbow_build.py install DEST [--installer NAME]
`install` writes what a wheel installs into DEST (a dist-packages folder, or a staging copy of one): the
package and its .dist-info with METADATA and INSTALLER but no RECORD, which marks it as managed by another
installer (the Debian package uses this; pip then refuses to uninstall it).
"""

from __future__ import annotations

import base64
import csv
import dataclasses
import gzip
import hashlib
import io
import os
import re
import shutil
import sys
import tarfile
import time
import tomllib
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent  # the folder of pyproject.toml
PACKAGE = "oxbow_client"
GENERATOR = "oxbow_build"
ZIP_EPOCH = 315532800  # 1980-01-01T00:00:00Z, the earliest time a zip entry can carry

# [project] keys this backend turns into metadata; any other key fails the build rather than being dropped.
SUPPORTED_PROJECT_KEYS = {"name", "version", "dynamic", "description", "readme", "requires-python", "authors",
                          "keywords", "classifiers", "dependencies", "urls"}
NAME_RE = re.compile(r"^([A-Z0-9]|[A-Z0-9][A-Z0-9._-]*[A-Z0-9])$", re.IGNORECASE)  # PEP 508 names
VERSION_RE = re.compile(r"^\d+(\.\d+)*((a|b|rc)\d+)?(\.post\d+)?(\.dev\d+)?$")  # PEP 440, public and normalised
VERSION_LINE_RE = re.compile(r"""^__version__\s*=\s*["']([^"']+)["']""", re.MULTILINE)
README_TYPES = {".md": "text/markdown", ".rst": "text/x-rst", ".txt": "text/plain"}


class BuildError(Exception):
    """pyproject.toml or the package cannot make a valid distribution; the message says why."""


@dataclasses.dataclass(frozen=True)
class Project:
    """What the archives are made of, read from a source folder."""
    root: Path
    name: str           # as written in pyproject.toml ("oxbow-client")
    version: str        # "0.1.0"
    metadata: str       # the METADATA / PKG-INFO text
    readme: Path | None

    @property
    def distribution(self) -> str:
        """The name in file names (wheel, sdist, .dist-info): normalised, with underscores."""
        return re.sub(r"[-_.]+", "_", self.name).lower()

    @property
    def dist_info(self) -> str:
        return f"{self.distribution}-{self.version}.dist-info"

    @property
    def wheel_name(self) -> str:
        return f"{self.distribution}-{self.version}-py3-none-any.whl"

    @property
    def sdist_name(self) -> str:
        return f"{self.distribution}-{self.version}.tar.gz"

    def package_files(self) -> list[Path]:
        """The package's files, relative to root, sorted; bytecode and caches left out."""
        package = self.root / PACKAGE
        if not (package / "__init__.py").is_file():
            raise BuildError(f"{package / '__init__.py'} is missing")
        return sorted(path.relative_to(self.root) for path in package.rglob("*")
                      if path.is_file() and "__pycache__" not in path.parts and path.suffix not in (".pyc", ".pyo"))


def read_project(root: Path = ROOT) -> Project:
    """Reads root/pyproject.toml's [project] and the package's __version__; BuildError on what it cannot use."""
    try:
        with open(root / "pyproject.toml", "rb") as f:
            pyproject = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise BuildError(f"{root / 'pyproject.toml'}: {e}") from e
    project = pyproject.get("project")
    if not isinstance(project, dict):
        raise BuildError("pyproject.toml has no [project] table")
    unknown = sorted(set(project) - SUPPORTED_PROJECT_KEYS)
    if unknown:
        raise BuildError(f"pyproject.toml [project]: {', '.join(unknown)} not supported by {GENERATOR} "
                         f"(it writes {', '.join(sorted(SUPPORTED_PROJECT_KEYS))})")
    name = project.get("name")
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise BuildError(f"pyproject.toml [project] name {name!r} is not a valid distribution name")
    version = _version(root, project)
    readme = project.get("readme")
    readme_path = None
    readme_type = None
    if isinstance(readme, str):
        readme_path = root / readme
        readme_type = README_TYPES.get(readme_path.suffix.lower())
        if readme_type is None:
            raise BuildError(f"readme {readme!r}: the type of a {readme_path.suffix!r} file is unknown")
    elif (isinstance(readme, dict) and isinstance(readme.get("file"), str)
          and isinstance(readme.get("content-type"), str)):
        readme_path, readme_type = root / readme["file"], readme["content-type"]
    elif readme is not None:
        raise BuildError("readme is a file name, or a table with file and content-type")
    if readme_path is not None and not readme_path.is_file():
        raise BuildError(f"the readme {readme_path} is missing")
    if readme_path is not None and not readme_path.resolve().is_relative_to(root.resolve()):
        raise BuildError(f"the readme {readme_path} is outside {root}: the sdist could not hold it")

    lines = ["Metadata-Version: 2.1", f"Name: {name}", f"Version: {version}"]
    if "description" in project:
        summary = _string(project, "description")
        if "\n" in summary:
            raise BuildError("description is one line")
        lines.append(f"Summary: {summary}")
    for author in _list(project, "authors"):
        if not isinstance(author, dict) or not set(author) <= {"name", "email"} or not author:
            raise BuildError("authors are tables with name and/or email")
        if "email" in author:
            who = f"{author['name']} <{author['email']}>" if "name" in author else author["email"]
            lines.append(f"Author-email: {who}")
        else:
            lines.append(f"Author: {author['name']}")
    if "keywords" in project:
        lines.append("Keywords: " + ",".join(_strings(project, "keywords")))
    lines += [f"Classifier: {c}" for c in _strings(project, "classifiers")]
    if "requires-python" in project:
        lines.append(f"Requires-Python: {_string(project, 'requires-python')}")
    urls = project.get("urls", {})
    if not isinstance(urls, dict) or not all(isinstance(v, str) for v in urls.values()):
        raise BuildError("urls is a table of strings")
    lines += [f"Project-URL: {label}, {url}" for label, url in urls.items()]
    lines += [f"Requires-Dist: {d}" for d in _strings(project, "dependencies")]
    if any("\n" in line or "\r" in line for line in lines):
        raise BuildError("a metadata value spans several lines")
    text = "\n".join(lines) + "\n"
    if readme_path is not None:
        text += f"Description-Content-Type: {readme_type}; charset=UTF-8\n\n" + readme_path.read_text("utf-8")
    return Project(root=root, name=name, version=version, metadata=text, readme=readme_path)


def _version(root: Path, project: Mapping[str, Any]) -> str:
    if "version" in project or project.get("dynamic") != ["version"]:
        raise BuildError('pyproject.toml [project]: the version is dynamic = ["version"], '
                         f"from __version__ in {PACKAGE}/__init__.py")
    try:
        found = VERSION_LINE_RE.search((root / PACKAGE / "__init__.py").read_text("utf-8"))
    except OSError as e:
        raise BuildError(str(e)) from e
    if not found:
        raise BuildError(f'{PACKAGE}/__init__.py has no line __version__ = "X.Y.Z"')
    if not VERSION_RE.match(found.group(1)):
        raise BuildError(f"__version__ {found.group(1)!r} is not a normalised PEP 440 version")
    return found.group(1)


def _string(table: Mapping[str, Any], key: str) -> str:
    value = table[key]
    if not isinstance(value, str):
        raise BuildError(f"{key} is a string")
    return value


def _list(table: Mapping[str, Any], key: str) -> list[Any]:
    value = table.get(key, [])
    if not isinstance(value, list):
        raise BuildError(f"{key} is an array")
    return value


def _strings(table: Mapping[str, Any], key: str) -> list[str]:
    values = _list(table, key)
    if not all(isinstance(v, str) for v in values):
        raise BuildError(f"{key} is an array of strings")
    return values


# ---- Archives ----------------------------------------------------------------------------------------

def _epoch() -> int:
    """The timestamp of every archive entry: SOURCE_DATE_EPOCH, not before 1980 (zip cannot say earlier)."""
    value = os.environ.get("SOURCE_DATE_EPOCH")
    return max(ZIP_EPOCH, int(value)) if value else ZIP_EPOCH


def _wheel_file() -> str:
    return f"Wheel-Version: 1.0\nGenerator: {GENERATOR}\nRoot-Is-Purelib: true\nTag: py3-none-any\n"


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def _write_wheel(project: Project, directory: str | os.PathLike[str], name: str,
                 files: Iterable[tuple[str, bytes]]) -> str:
    """Writes a wheel of `files` (archive path, bytes) plus the .dist-info; returns its file name."""
    entries = list(files)
    dist_info = project.dist_info
    entries += [(f"{dist_info}/METADATA", project.metadata.encode("utf-8")),
                (f"{dist_info}/WHEEL", _wheel_file().encode())]
    record = io.StringIO()
    writer = csv.writer(record, lineterminator="\n")
    for path, data in entries:
        writer.writerow([path, _record_hash(data), len(data)])
    writer.writerow([f"{dist_info}/RECORD", "", ""])
    entries.append((f"{dist_info}/RECORD", record.getvalue().encode()))

    date_time = _zip_time(_epoch())
    target = Path(directory) / name
    temporary = target.with_name(target.name + ".part")
    with zipfile.ZipFile(temporary, "w", compression=zipfile.ZIP_DEFLATED) as wheel:
        for path, data in entries:
            info = zipfile.ZipInfo(path, date_time=date_time)
            info.external_attr = 0o100644 << 16  # a regular file, rw-r--r--
            info.compress_type = zipfile.ZIP_DEFLATED
            wheel.writestr(info, data)
    os.replace(temporary, target)
    return name


def _zip_time(epoch: int) -> tuple[int, int, int, int, int, int]:
    t = time.gmtime(epoch)
    return (t.tm_year, t.tm_mon, t.tm_mday, t.tm_hour, t.tm_min, t.tm_sec)


def _package_entries(project: Project) -> list[tuple[str, bytes]]:
    return [(path.as_posix(), (project.root / path).read_bytes()) for path in project.package_files()]


def _sdist_files(project: Project) -> list[Path]:
    """What the sdist holds besides PKG-INFO, relative to root, sorted."""
    files = {Path("pyproject.toml"), Path("_build") / Path(__file__).name, *project.package_files()}
    if project.readme is not None:
        files.add(project.readme.relative_to(project.root))
    return sorted(files)


def _write_metadata_dir(project: Project, metadata_directory: str | os.PathLike[str]) -> str:
    target = Path(metadata_directory) / project.dist_info
    target.mkdir(parents=True, exist_ok=True)
    (target / "METADATA").write_text(project.metadata, "utf-8")
    (target / "WHEEL").write_text(_wheel_file())
    return project.dist_info


# ---- PEP 517 / PEP 660 hooks -------------------------------------------------------------------------

def get_requires_for_build_wheel(config_settings: Mapping[str, Any] | None = None) -> list[str]:
    return []


def get_requires_for_build_sdist(config_settings: Mapping[str, Any] | None = None) -> list[str]:
    return []


def get_requires_for_build_editable(config_settings: Mapping[str, Any] | None = None) -> list[str]:
    return []


def prepare_metadata_for_build_wheel(metadata_directory: str, config_settings: Mapping[str, Any] | None = None) -> str:
    return _write_metadata_dir(read_project(), metadata_directory)


def prepare_metadata_for_build_editable(metadata_directory: str,
                                        config_settings: Mapping[str, Any] | None = None) -> str:
    return _write_metadata_dir(read_project(), metadata_directory)


def build_wheel(wheel_directory: str, config_settings: Mapping[str, Any] | None = None,
                metadata_directory: str | None = None) -> str:
    project = read_project()
    return _write_wheel(project, wheel_directory, project.wheel_name, _package_entries(project))


def build_editable(wheel_directory: str, config_settings: Mapping[str, Any] | None = None,
                   metadata_directory: str | None = None) -> str:
    project = read_project()
    pth = (f"__editable__.{project.distribution}-{project.version}.pth", (str(project.root) + "\n").encode())
    return _write_wheel(project, wheel_directory, project.wheel_name, [pth])


def build_sdist(sdist_directory: str, config_settings: Mapping[str, Any] | None = None) -> str:
    project = read_project()
    top = f"{project.distribution}-{project.version}"
    epoch = _epoch()
    members = [(f"{top}/{path.as_posix()}", (project.root / path).read_bytes()) for path in _sdist_files(project)]
    members.append((f"{top}/PKG-INFO", project.metadata.encode("utf-8")))
    archive = io.BytesIO()  # a few tens of kB
    with tarfile.open(fileobj=archive, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for path, data in sorted(members):
            info = tarfile.TarInfo(path)
            info.size, info.mtime, info.mode = len(data), epoch, 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            tar.addfile(info, io.BytesIO(data))
    target = Path(sdist_directory) / project.sdist_name
    temporary = target.with_name(target.name + ".part")
    temporary.write_bytes(gzip.compress(archive.getvalue(), mtime=epoch))  # no file name in the gzip header
    os.replace(temporary, target)
    return project.sdist_name


# ---- Command line ------------------------------------------------------------------------------------

def install(destination: Path, installer: str = GENERATOR, root: Path = ROOT) -> list[Path]:
    """Writes the package and its .dist-info (METADATA, INSTALLER; no RECORD) into `destination`, replacing
    what an earlier install of this distribution left there; returns the files written."""
    project = read_project(root)
    destination.mkdir(parents=True, exist_ok=True)
    for old in [destination / PACKAGE, *destination.glob(f"{project.distribution}-*.dist-info")]:
        if old.is_dir():
            shutil.rmtree(old)
    written = []
    for path in project.package_files():
        target = destination / path
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(root / path, target)
        written.append(target)
    dist_info = destination / project.dist_info
    dist_info.mkdir()
    (dist_info / "METADATA").write_text(project.metadata, "utf-8")
    (dist_info / "INSTALLER").write_text(installer + "\n")
    written += [dist_info / "METADATA", dist_info / "INSTALLER"]
    return written


def main(argv: list[str]) -> int:
    usage = __doc__.split("The same from a shell (OUT defaults to ./dist):\n", 1)[1].split("\n`install`", 1)[0]
    try:
        if len(argv) in (1, 2) and argv[0] in ("wheel", "sdist"):
            out = Path(argv[1] if len(argv) == 2 else "dist")
            out.mkdir(parents=True, exist_ok=True)
            name = build_wheel(str(out)) if argv[0] == "wheel" else build_sdist(str(out))
            print(out / name)
            return 0
        if argv[:1] == ["install"] and (len(argv) == 2 or (len(argv) == 4 and argv[2] == "--installer")):
            written = install(Path(argv[1]), argv[3] if len(argv) == 4 else GENERATOR)
            print(f"{GENERATOR}: installed {len(written)} files into {argv[1]}")
            return 0
    except BuildError as e:
        print(f"{GENERATOR}: {e}", file=sys.stderr)
        return 1
    print("usage:\n" + usage, file=sys.stderr, end="")
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
