"""The infer records, made from the typed outcomes where JSON is written, and the JSONL store of `--jsonl OUT`.

`to_record` turns a Fit or a FitFailure into its JSON record (docs/contract.md, "The infer
record"): for the `--json` list, and for each line of OUT, which is written as fits complete
and resumed after a kill. The byte format lives here, writer and reader (docs/contract.md,
"The JSONL form"): one infer record a line, UTF-8, each line ending in a newline, every record
led by `"index"` (the input's position in the run's inputs) then `"input"`. An input's records
(one, or one per component) go out in one `os.write`, in the order fits complete, not input order.

Resuming: `RecordStore` reads OUT first. A last line without its newline is a torn write
(a kill or a full disk mid-write): it is cut off, with the lines of the same input before
it, so an input is either wholly in OUT or not at all. The inputs OUT holds are skipped.
A kill -9 loses only the masks in flight; the kernel keeps every completed write. An fsync
every `FSYNC_SECONDS` bounds what a power cut could take.
"""
from __future__ import annotations

import errno
import json
import os
import re
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from cuboidtrain.fit.fitter import Fit, FitFailure, Outcome
from cuboidtrain.fit.options import FitOptions
from shared.errors import UsageError
from shared.files import json_text, write_json

FSYNC_SECONDS = 2.0  # at most this much work is only in the page cache
_TORN_INDEX = re.compile(rb'^\{"index": (\d+)')  # a torn line still names its input, if it got that far


def to_record(outcome: Outcome | dict, with_component: bool = False, cuboid: bool = False) -> dict:
    """The infer record of an outcome: a Fit's fields, or a FitFailure's `error` with the fit fields
    null (`cuboid` null with the cuboid fit, `component` null with `all_components`). A record read
    back from OUT (a resumed input's) is one already: as read."""
    if isinstance(outcome, Fit):
        return outcome.record(with_component)
    if isinstance(outcome, FitFailure):
        record = {"input": outcome.input, "shape": None, "confidence": None, "keypoints": None, "ratios": None,
                  **({"ratios_sd": None} if cuboid else {}), "refine_steps": None, "refine_converged": None, "error": outcome.reason, "warnings": [],
                  "candidates": {}}
        return record | ({"trust": None, "cuboid": None, "shape_call": None} if cuboid else {}) | ({"component": None} if with_component else {})
    return outcome


def to_records(outcomes: Iterable[Outcome | dict], options: FitOptions) -> list[dict]:
    """The infer records of outcomes fitted with `options`."""
    return [to_record(o, options.all_components, options.cuboid) for o in outcomes]


def encode_group(index: int, records: Iterable[dict]) -> bytes:
    """One input's records as JSONL bytes, `index` first in each."""
    return b"".join(json_text({"index": index} | r, what=f"record of input {index}").encode() + b"\n" for r in records)


def scan(path: str | Path) -> tuple[list[dict], int]:
    """The complete records of OUT and how many of its bytes hold them (the rest is a torn
    tail, and the records of its input). A line in the middle that is not a record is a
    UsageError: OUT is not an infer JSONL file."""
    data = Path(path).read_bytes()
    body, _, tail = data.rpartition(b"\n")
    lines = body.split(b"\n") if body or data.startswith(b"\n") else []
    records, ends, end = [], [], 0
    for number, line in enumerate(lines, 1):
        end += len(line) + 1
        try:
            record = json.loads(line)
        except ValueError:
            record = None
        if not isinstance(record, dict) or not {"index", "input"} <= record.keys():
            raise UsageError(f"--jsonl {path}: line {number} is not an infer record; expected one JSON record "
                             f"a line with \"index\" and \"input\" (a file cuboidtrain infer --jsonl wrote)")
        records.append(record)
        ends.append(end)
    if tail and (torn := _TORN_INDEX.match(tail)):  # drop its input's earlier components too
        while records and records[-1]["index"] == int(torn.group(1)):
            records.pop()
            ends.pop()
    return records, (ends[-1] if ends else 0)


def read_records(path: str | Path) -> list[dict]:
    """The records of an infer JSONL file, a torn last line ignored, sorted by input index."""
    return sorted(scan(path)[0], key=lambda r: r["index"])


class RecordStore:
    """Appends input groups to OUT, flushed at once (unbuffered writes), fsync'd every few seconds.

        with RecordStore(out) as store:
            todo = [(i, p) for i, p in enumerate(inputs) if p not in store.done]
            store.write(index, outcomes)

    `options`, the run's, give the records' form (`to_records`).
    """

    def __init__(self, path: str | Path, options: FitOptions = FitOptions()):
        self.path = Path(path)
        self.options = options
        self.records: list[dict] = []  # what OUT held when opened
        self.done: set[str] = set()  # the inputs OUT holds
        self.written = 0  # records this run
        self.fd = -1
        self.synced = time.monotonic()

    def __enter__(self) -> "RecordStore":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:  # a read-only file or file system, a folder we may not write in
            raise UsageError(f"--jsonl {self.path}: cannot open it to write ({exc.strerror}); "
                             f"expected a file this user can read and write") from None
        self.records, keep = scan(self.path)
        if os.fstat(self.fd).st_size != keep:  # a torn tail: cut it off for good
            os.ftruncate(self.fd, keep)
        os.lseek(self.fd, keep, os.SEEK_SET)
        self.done = {r["input"] for r in self.records}
        return self

    def write(self, index: int, outcomes: Sequence[Outcome]) -> None:
        """One input's records; a full disk truncates back to the last whole input and is a
        one-line UsageError that says the records written are kept."""
        data, start = encode_group(index, to_records(outcomes, self.options)), os.lseek(self.fd, 0, os.SEEK_CUR)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self.fd, view):]
        except OSError as exc:
            try:  # a part of this input's lines may be in: cut back to the last whole input
                os.ftruncate(self.fd, start)
                os.lseek(self.fd, start, os.SEEK_SET)
            except OSError:
                pass  # then the next open cuts the torn tail
            raise self.failed(exc) from None
        self.written += len(outcomes)
        if time.monotonic() - self.synced > FSYNC_SECONDS:
            self.sync()

    def sync(self) -> None:
        try:
            os.fsync(self.fd)
        except OSError as exc:  # a delayed write failed (a network or thin-provisioned disk full)
            raise self.failed(exc, kept="the whole ones on disk kept") from None
        self.synced = time.monotonic()

    def failed(self, exc: OSError, kept: str = "all kept") -> UsageError:
        """A write that failed, as one line saying the records before it are kept."""
        count = len(self.records) + self.written
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):  # EFBIG: a file size limit, full all the same
            what = "disk full" if exc.errno != errno.EFBIG else "file size limit reached"
            return UsageError(f"--jsonl {self.path}: {what} after {count} records ({kept}); "
                              f"expected free space: make some and rerun to resume")
        return UsageError(f"--jsonl {self.path}: cannot write after {count} records ({exc.strerror}; {kept}); "
                          f"expected a writable file: rerun to resume")

    def __exit__(self, *exc) -> None:
        if self.fd >= 0:
            try:
                self.sync()
            except UsageError:
                if exc[0] is None:  # else the error in flight is the one to report
                    raise
            finally:
                os.close(self.fd)
                self.fd = -1


def write_records(path: Path, records: list[dict]) -> None:
    """The JSON list, replaced atomically: a reader never sees half of it."""
    write_json(path, records, indent=2)
