"""What `cuboidtrain infer` is asked to fit: files, folders and lists of paths, turned into one list.

A file is taken as given (one that cannot be read gets its error record later, and the run
goes on). A folder is walked recursively, in sorted order, for the files `--glob` matches
(default: the image extensions below); hidden names (`.tmp-...`, `.DS_Store`) are skipped.
A list file (`--from-list FILE`, `-` for stdin) holds one path a line, each taken as above;
blank lines and lines starting with `#` are skipped; relative paths are from the current
folder; every listed path must exist (a list naming missing files is refused whole). Nothing
to fit is a UsageError naming what was expected, before any model loads.

A PATH may also be a URL fsspec reads (`s3://bucket/masks/`, `file:///data/masks/`: `storage`):
a URL folder (a prefix) is walked as a folder is, by the same rules; a URL with glob characters
(`s3://bucket/masks/*_mask.png`) is expanded by the store, as a shell expands a local one.
"""
from __future__ import annotations

import json
import logging
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path, PurePath, PurePosixPath

from cuboidtrain.fit.storage import Lookup, has_glob, is_url
from cuboidtrain.geometry.intrinsics import KnownCamera
from shared.errors import UsageError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")  # what cv2.imread reads here
DEFAULT_GLOB_HELP = "*.png, *.jpg, *.jpeg, *.bmp, *.tif, *.tiff, *.webp"


def gather_inputs(paths: Sequence[str], from_list: str | None = None, glob: str | None = None) -> list[str]:
    """The inputs in order: the PATHs given, then the list file's. Folders expand to their
    matching files (sorted). A UsageError when there is nothing to fit."""
    given, lookup = list(paths), Lookup()
    if from_list is not None:
        listed = read_list(from_list)
        if not listed:
            raise UsageError(f"--from-list {from_list}: no paths in it; expected one mask path a line")
        check_listed(from_list, listed, lookup=lookup)
        given += listed
    if not given:
        raise UsageError("no inputs: expected mask PATHs (files or folders) or --from-list FILE")
    lookup.look_up(given)  # the URLs among them, many at a time
    inputs = []
    for path in given:
        inputs += expand(path, glob, lookup)
    missing = [p for p in inputs if not lookup.exists(p)]
    if missing and len(missing) == len(inputs):
        raise UsageError(f"{missing[0]}: no such file" + (f" (nor the {len(missing) - 1} other inputs)"
                                                          if len(missing) > 1 else "")
                         + "; expected mask images")
    if missing:  # the run goes on: each gets its error record
        log.warning("%d of %d inputs do not exist (the first: %s); their records say so",
                    len(missing), len(inputs), missing[0])
    return inputs


def check_listed(source: str, listed: list[str], named: int = 3, lookup: Lookup | None = None) -> None:
    """A list file whose paths do not all exist is refused whole, before any fit: a list is
    written by a program, and one stale or mistyped path usually means the whole list is off
    (made in another folder, or before the files were moved)."""
    lookup = lookup or Lookup()
    lookup.look_up(listed)  # the URLs among them, many at a time
    missing = [p for p in listed if not lookup.exists(p)]
    if missing:
        first = ", ".join(missing[:named]) + (", ..." if len(missing) > named else "")
        raise UsageError(f"--from-list {'stdin' if source == '-' else source}: {len(missing)} of {len(listed)} "
                         f"listed paths do not exist (first: {first}); expected existing mask files or folders")


def expand(path: str, glob: str | None, lookup: Lookup | None = None) -> list[str]:
    """A folder's matching files, sorted; a URL glob's matches; anything else as given."""
    lookup = lookup or Lookup()
    if is_url(path) and has_glob(path):
        return expand_url_glob(path, glob, lookup)
    if not lookup.is_folder(path):
        return [path]
    if is_url(path):
        found = sorted(url for url, relative in lookup.under(path) if wanted(PurePosixPath(relative), glob))
    else:
        found = sorted(str(p) for p in walk(Path(path), glob))
    if not found:
        raise UsageError(f"{path}: a folder with no files matching {glob or DEFAULT_GLOB_HELP}; "
                         f"expected mask images under it (or another --glob)")
    return found


def expand_url_glob(url: str, glob: str | None, lookup: Lookup) -> list[str]:
    """What a URL's glob matches, sorted, hidden names left out (as a shell's `*` leaves them);
    a matched folder expands as a folder does."""
    found = []
    for name, relative in lookup.matching(url):
        if not hidden(PurePosixPath(relative)):
            found += expand(name, glob, lookup) if lookup.is_folder(name) else [name]
    if not found:
        raise UsageError(f"{url}: nothing matches it; expected mask images (check the pattern, or give the folder)")
    return found


def walk(folder: Path, glob: str | None) -> Iterable[Path]:
    candidates = folder.rglob(glob) if glob else folder.rglob("*")
    for path in candidates:
        if hidden(path.relative_to(folder)) or not path.is_file():
            continue
        if glob or is_image(path):
            yield path


def wanted(relative: PurePath, glob: str | None) -> bool:
    """Whether a file at `relative` under a folder is an input: `walk`'s rule for a listing
    (a URL folder's) that `rglob` did not match for us."""
    return not hidden(relative) and (relative.match(glob) if glob else is_image(relative))


def hidden(relative: PurePath) -> bool:
    """A name starting with `.` (a writer's `.tmp-...`, `.DS_Store`), or anything under one."""
    return any(part.startswith(".") for part in relative.parts)


def is_image(path: PurePath) -> bool:
    return path.suffix.lower() in IMAGE_SUFFIXES


def read_list(source: str) -> list[str]:
    """The paths of a list file (or stdin for `-`): one a line, blanks and `#` comments skipped."""
    if source == "-":
        text = sys.stdin.read()
    else:
        try:
            text = Path(source).read_text()
        except FileNotFoundError:
            raise UsageError(f"--from-list {source}: no such file; expected a text file of mask paths") from None
        except (IsADirectoryError, UnicodeDecodeError) as exc:
            raise UsageError(f"--from-list {source}: not a text file of paths ({type(exc).__name__}); "
                             f"expected one mask path a line") from None
    lines = (line.strip() for line in text.splitlines())
    return [line for line in lines if line and not line.startswith("#")]


class OutputNames:
    """The file stem a per-input output (an `--explain` panel, a `--mesh` file) is named after:
    the input's own stem; a later input of the same stem (a/x.png, b/x.png) gets `-input<index>`.

    Given the run's inputs (in index order), the names are fixed up front, so every process of a
    `--workers` run, and a resumed run, names an input alike; without them, the first input to
    arrive with a stem takes it."""

    def __init__(self, inputs: Sequence[str] | None = None):
        self.stems: dict[str, int] = {}  # stem -> the input that took it
        self.fixed: list[str] | None = None
        if inputs is not None:
            self.fixed = [self(index, path) for index, path in enumerate(inputs)]

    def __call__(self, index: int, path: str) -> str:
        if self.fixed is not None and index < len(self.fixed):
            return self.fixed[index]
        stem = Path(path).stem
        if self.stems.setdefault(stem, index) != index:
            stem = f"{stem}-input{index}"
        return stem


def read_cameras(path: Path) -> tuple[tuple[str, KnownCamera], ...]:
    """`--camera FILE`: a JSON object mapping each input (its path as given, or its file name) to
    `{"focal_px": F, "principal_px": [X, Y]}` in that input's pixels (either key may be left out);
    a one-line UsageError naming the file and the entry that is not so."""
    try:
        given = json.loads(Path(path).read_text())
    except OSError as exc:
        raise UsageError(f"--camera {path}: cannot read it ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise UsageError(f"--camera {path}: not JSON ({exc})") from None
    if not isinstance(given, dict):
        raise UsageError(f"--camera {path}: expected a JSON object mapping each input to its camera")
    return tuple((str(name), _camera_entry(path, name, entry)) for name, entry in given.items())


def _camera_entry(path: Path, name: str, entry) -> KnownCamera:
    if not isinstance(entry, dict) or not set(entry) <= {"focal_px", "principal_px"}:
        raise UsageError(f"--camera {path}: {name!r}: {entry!r}: expected "
                         f'{{"focal_px": F, "principal_px": [X, Y]}} (px; either may be left out)')
    try:
        return KnownCamera.of(entry.get("focal_px"), entry.get("principal_px"))
    except ValueError as exc:
        raise UsageError(f"--camera {path}: {name!r}: {exc}") from None
