"""Where masks are read from: local paths, or fsspec URLs (`s3://bucket/masks/`, `gs://...`,
`file:///data/masks/`, `memory://...`: any protocol fsspec knows, chained ones too).

A URL is told by its leading `scheme://`; anything else is a local path, read as it always was,
and never imports fsspec. fsspec is no dependency of its own here: torch and Dask (the `cluster`
extra) bring it, and a store's own package (s3fs, gcsfs, adlfs) is the user's to install.
Without either, a URL is a one-line UsageError naming what to install.

This module answers three questions for `inputs` (what a PATH names) and `masks` (its bytes):
what a path is (a folder, a file, nothing), which objects lie under a URL folder or match a
URL's glob, and the bytes of one mask. URLs found by listing keep the spelling they were given
in (`memory://masks/` lists `memory://masks/a.png`), since a record's `input` is that string
and resuming a `--jsonl` store matches it.
"""
from __future__ import annotations

import errno
import os
import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from shared.errors import UsageError

_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]+(::[A-Za-z][A-Za-z0-9+.-]+)*://")  # two letters at least: not C:/
_MAGIC = re.compile(r"[*?[]")  # fsspec's glob characters
LOOKUPS = 16  # URLs looked up at once: a store answers each in tens of ms, and a list may name thousands

FOLDER, FILE = "folder", "file"


def is_url(path: str | Path) -> bool:
    return isinstance(path, str) and _URL.match(path) is not None


def has_glob(url: str) -> bool:
    return _MAGIC.search(url.partition("://")[2]) is not None


def read_bytes(path: str | Path) -> np.ndarray:
    """The bytes of one mask file or URL as a uint8 array; an OSError when they cannot be read
    (a missing fsspec or store package is a UsageError instead)."""
    if not is_url(path):
        return np.fromfile(str(path), dtype=np.uint8)
    fs, where = filesystem(path)
    try:
        with fs.open(where, "rb") as file:
            return np.frombuffer(file.read(), dtype=np.uint8)
    except FileNotFoundError:  # fsspec's names only the path: say what a local file's says
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path) from None
    except OSError:
        raise
    except Exception as error:  # a store's own errors (botocore's, aiohttp's): this input's, not the run's
        raise OSError(f"{type(error).__name__}: {error}") from error


def filesystem(url: str):
    """fsspec's (filesystem, path on it) for `url`; a one-line UsageError when fsspec or the
    protocol's package is not installed, or fsspec knows no such protocol."""
    try:
        from fsspec.core import url_to_fs
    except ImportError:
        raise UsageError(f"{url}: reading a URL needs fsspec, which is not installed; expected "
                         f"pip install 'cuboid-fit[cluster]' (it brings fsspec), or a local path") from None
    protocol = url.partition("://")[0].rpartition("::")[2]
    try:
        return url_to_fs(url)
    except ImportError as error:  # fsspec's message names the package: "Install s3fs to access S3"
        package = _package(protocol)
        raise UsageError(f"{url}: reading {protocol}:// needs {package or 'a package'}, which is not installed "
                         f"({error}); expected: pip install {package or '<that package>'}") from None
    except ValueError as error:  # "Protocol not known: ..."
        raise UsageError(f"{url}: {error}; expected a local path or a URL of a protocol fsspec knows "
                         f"(s3://, gs://, file://, ...)") from None


def _package(protocol: str) -> str | None:
    """The package that implements `protocol` (s3fs for s3), None for fsspec's own ones."""
    from fsspec.registry import known_implementations

    module = known_implementations.get(protocol, {}).get("class", "").partition(".")[0]
    return module if module and module != "fsspec" else None


class Lookup:
    """What each input path is: a folder, a file, or nothing (None), for one gathering of inputs.

    A local path is asked of the file system each time, as ever. A store answers in tens of ms, not
    microseconds: a URL is asked once, however many questions it meets (listed? a folder? there?),
    many at a time (`look_up`), and the objects a folder's listing or a glob found are not asked at all."""

    def __init__(self):
        self.urls: dict[str, str | None] = {}  # URL -> FOLDER, FILE or None
        self.globs: dict[str, list[tuple[str, str]]] = {}  # glob URL -> what `matching` found

    def look_up(self, paths: Iterable[str]) -> None:
        todo = [p for p in dict.fromkeys(paths) if is_url(p) and not has_glob(p) and p not in self.urls]
        if len(todo) > 1:
            from concurrent.futures import ThreadPoolExecutor  # only for URLs: a local run's start-up unchanged

            with ThreadPoolExecutor(min(LOOKUPS, len(todo))) as pool:
                self.urls.update(zip(todo, pool.map(url_kind, todo)))
        elif todo:
            self.urls[todo[0]] = url_kind(todo[0])

    def exists(self, path: str) -> bool:
        """Whether `path` names something; a URL's glob whether it matches anything."""
        if not is_url(path):
            return Path(path).exists()
        if has_glob(path):
            return bool(self.matching(path))
        self.look_up([path])
        return self.urls[path] is not None

    def is_folder(self, path: str) -> bool:
        if not is_url(path):
            return Path(path).is_dir()
        if has_glob(path):  # a pattern: `matching` expands it
            return False
        self.look_up([path])
        return self.urls[path] == FOLDER

    def under(self, url: str) -> list[tuple[str, str]]:
        """Every object below the URL folder `url`, recursively: (its URL, its path relative to `url`)."""
        fs, root = filesystem(url)
        found = [_relative(path, root) for path in _store_call(url, "list it", fs.find, root)]
        objects = [(_join(url, relative), relative) for relative in found]
        self.urls.update((name, FILE) for name, _ in objects)
        return objects

    def matching(self, url: str) -> list[tuple[str, str]]:
        """The objects and folders `url`'s glob matches: (its URL, its path from the glob's first
        folder), sorted. Each is known as what it is; the store is asked once."""
        if url in self.globs:
            return self.globs[url]
        fs, pattern = filesystem(url)
        url_head, path_head = _head(url), _head(pattern)
        found = {}
        for path, info in _store_call(url, "glob it", fs.glob, pattern, detail=True).items():
            inside = path.startswith(path_head)  # always, but for a store that answers otherwise
            relative = path[len(path_head):] if inside else path
            name = url_head + relative if inside else fs.unstrip_protocol(path)
            found[name] = (relative, FOLDER if info.get("type") == "directory" else FILE)
        self.urls.update((name, kind) for name, (_, kind) in found.items())
        self.globs[url] = sorted((name, relative) for name, (relative, _) in found.items())
        return self.globs[url]


def url_kind(url: str) -> str | None:
    """FOLDER, FILE, or None when there is no such object (nor any object below it)."""
    fs, path = filesystem(url)
    try:
        info = _store_call(url, "look it up", fs.info, path)
    except FileNotFoundError:
        return None
    return FOLDER if info.get("type") == "directory" else FILE


def _store_call(url: str, what: str, call, *args, **kwargs):
    """`call` on a store; its failures (no credentials, no permission, no network) are a one-line
    UsageError naming the URL. FileNotFoundError passes: a missing input is not an error here."""
    try:
        return call(*args, **kwargs)
    except (FileNotFoundError, UsageError):
        raise
    except Exception as error:  # botocore's, aiohttp's, gcsfs's own errors as well as OSErrors
        raise UsageError(f"{url}: cannot {what} ({type(error).__name__}: {' '.join(str(error).split())}); "
                         f"expected a readable URL (credentials, permissions, network)") from None


def _relative(path: str, root: str) -> str:
    root = root.rstrip("/")
    return path[len(root):].lstrip("/") if path.startswith(root) else path


def _head(text: str) -> str:
    """A glob URL's or path's part before the folder its first glob character is in."""
    return text[: text.rfind("/", 0, _MAGIC.search(text).start()) + 1]


def _join(url: str, relative: str) -> str:
    return (url if url.endswith("/") else url + "/") + relative
