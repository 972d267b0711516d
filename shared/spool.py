"""The spool: a capped folder of samples, published atomically, evicted oldest first.

The spool folder is the only link between the generator and the trainer. Its rules (the
contract for outside readers and writers: docs/contract.md, "The spool"), as this code keeps them:

* A sample is one file `<time_ns>-<host>-<pid>-<token>-<seq>.cub`. The name sorts
  by age and never collides: pid and a random token tell apart writers on one
  host, the host name tells apart hosts, and the sequence number orders one
  writer's samples.
* Publishing writes `.tmp-0-<host>-<pid>-<name>` (shared.files.temporary_name; or
  rewrites a spare, below) and renames it in the same folder, so readers see a
  whole file or none. Nothing is fsynced unless
  asked: a killed process leaves at most three temporary files (one being written,
  two spares), which are swept when a writer next starts; only a power cut could
  lose data that was not synced.
* Every writer evicts. After each publish, a writer that believes the spool is
  at its limit deletes one file, the oldest it knows of; every `evict_every`
  publishes it lists the folder again and deletes down to the limit. So the
  spool never holds more than `limit + writers * evict_every` samples, however
  many writers on however many hosts share it.
* `limit == 0` retains the spool: nothing is ever evicted.
* On a local filesystem a writer recycles the files it evicts instead of creating
  new ones: creating a file is what publishing costs most, and on ext4 without a
  journal it grows with the files the spool itself has just deleted (the inode
  allocator passes over recently freed inodes one by one). Before a publish that
  will evict, the writer hard-links the sample to be evicted to a hidden spare
  `.tmp-0-<host>-<pid>-<token>-spare<k>.cub` (k = 0, 1, alternately: a temporary
  name of the same rule, which the sweep reads); eviction
  deletes its sample name as ever (readers and watchers see an ordinary
  deletion); the next publish rewrites that spare and renames it to its new
  sample name. It rewrites only while it holds a write lease (`F_SETLEASE`),
  which the kernel grants only while no other process has the file open, and
  only while the spare is the file's one name (not still a sample, not another
  writer's spare, not hard-linked by a copy): a reader that opened a sample
  before it was evicted keeps its bytes, and the spare is deleted and a new file
  written instead. Without `fsync`, a power cut may leave a just-published
  sample holding parts of the one its file held before (with `fsync` nothing
  changes). `SpoolWriter(recycle=False)` turns recycling off; network and FUSE
  filesystems, where a lease cannot see readers on other hosts, never recycle.
"""
from __future__ import annotations

import errno
import fcntl
import logging
import os
import secrets
import signal
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from shared.errors import UsageError
# TMP_PREFIX is the spool's too: inspect counts the temporary files by it.
from shared.files import TMP_PREFIX, host_tag, sweep_orphans, temporary_name  # noqa: F401

log = logging.getLogger(__name__)

SUFFIX = ".cub"
META_NAME = "SPOOL.json"
EVICT_EVERY = 64  # publishes between listings; the spool bound is limit + writers * EVICT_EVERY
ORPHAN_AGE = 60.0  # s: a temporary file this old belongs to no live writer on any host
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
_NO_LEASES = (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOLCK)
# Filesystems whose files only this kernel opens, so a lease sees every reader (not
# NFS, SMB or FUSE, where a reader on another host would go unseen).
LOCAL_FILESYSTEMS = frozenset({"ext2", "ext3", "ext4", "xfs", "btrfs", "tmpfs", "f2fs", "bcachefs"})
_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
_READ = os.O_RDONLY | getattr(os, "O_CLOEXEC", 0)
_REWRITE = os.O_WRONLY | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)


class SpoolError(UsageError):
    """The spool folder cannot be used (missing, not a folder, not writable)."""


class SpoolFull(OSError):
    """The disk under the spool is full; nothing was published."""


def check_spool(spool: Path, writable: bool = False, create: bool = False, readable: bool = False) -> Path:
    """The spool as a Path, or a one-line SpoolError saying what is wrong with it."""
    spool = Path(spool)
    if create and not spool.exists():
        try:
            # exist_ok: generators started together on a new spool race to make it; one makes it, all use it
            spool.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            pass  # a file of that name: "not a folder", below
        except OSError as exc:
            raise SpoolError(f"spool {spool}: cannot create it ({exc.strerror})") from None
    if not spool.exists():
        raise SpoolError(f"spool {spool}: no such folder")
    if not spool.is_dir():
        raise SpoolError(f"spool {spool}: not a folder")
    if writable and not os.access(spool, os.W_OK | os.X_OK):
        raise SpoolError(f"spool {spool}: not writable")
    if readable and not os.access(spool, os.R_OK | os.X_OK):
        raise SpoolError(f"spool {spool}: not readable")
    return spool


def is_sample_name(name: str) -> bool:
    return name.endswith(SUFFIX) and not name.startswith(".")


def foreign_names(spool: Path) -> list[str]:
    """Entries that are neither samples, nor hidden (temporary files, .gitkeep), nor SPOOL.json:
    files dropped in by someone else. Readers ignore them; censuses report them."""
    return sorted(n for n in os.listdir(spool) if not n.startswith(".") and not is_sample_name(n) and n != META_NAME)


def enumerate_spool(spool: Path) -> list[str]:
    """Sample file names in age order, oldest first."""
    return sorted(n for n in os.listdir(spool) if is_sample_name(n))


def name_time(name: str) -> float:
    """Publication time (unix seconds) encoded in a sample's name."""
    return int(name.split("-", 1)[0]) / 1e9


def read_sample_bytes(spool: Path, name: str) -> bytes | None:
    """The file's bytes, or None when it vanished (evicted) since it was enumerated."""
    try:
        fd = os.open(os.path.join(spool, name), _READ)
    except FileNotFoundError:
        return None
    try:  # a published sample never changes: read its size in one go (fewer calls than open())
        size = os.fstat(fd).st_size
        data = os.read(fd, size)
        if len(data) < size or not size:  # a short read, or a file without a size: read to the end
            chunks = [data]
            while chunk := os.read(fd, 1 << 16):
                chunks.append(chunk)
            data = b"".join(chunks)
        return data
    finally:
        os.close(fd)


def filesystem_type(path: Path) -> str | None:
    """The type (`ext4`, `nfs`, ...) of the filesystem holding `path`, from
    /proc/self/mountinfo; None where that cannot be told."""
    try:
        device = os.stat(path).st_dev
        wanted = f"{os.major(device)}:{os.minor(device)}"
        with open("/proc/self/mountinfo") as f:
            for line in f:
                fields = line.split()
                if len(fields) > 3 and fields[2] == wanted and "-" in fields:
                    return fields[fields.index("-", 6) + 1]
    except (OSError, ValueError, IndexError):
        pass
    return None


@dataclass
class WriterCounts:
    published: int = 0
    evicted: int = 0
    published_bytes: int = 0


class SpoolWriter:
    """Publishes sample bytes into a spool and keeps it within `limit` samples.

    Use as a context manager; `publish` is the only write path.
    """

    def __init__(
        self, spool: Path, limit: int, evict_every: int = EVICT_EVERY, fsync: bool = False,
        recycle: bool | None = None,
    ):
        """`recycle`: rewrite evicted files rather than create new ones (see the module's
        rules); None (the default) recycles on local filesystems that allow it."""
        if limit < 0:
            raise ValueError(f"limit {limit} is negative: expected 0 (retain everything) or a sample count")
        if evict_every < 1:
            raise ValueError(f"evict_every {evict_every}: expected at least 1")
        self.spool = Path(spool)
        self.limit, self.evict_every, self.fsync = limit, evict_every, fsync
        self.counts = WriterCounts()
        self._host, self._pid, token = host_tag(), os.getpid(), secrets.token_hex(3)
        self._prefix = f"{self._host}-{self._pid}-{token}"
        self._dir = os.fspath(self.spool)
        self._recycle = recycle
        # Two spare slots: the file to rewrite now, and the one this publish will evict.
        self._spare_paths = [
            os.path.join(self._dir, self._temporary(f"{token}-spare{k}{SUFFIX}")) for k in (0, 1)
        ]
        self._spare: str | None = None  # the slot holding an evicted sample's file to rewrite
        self._seq = 0
        self._known: deque[str] = deque()  # names believed present, oldest first
        self._believed = 0  # samples believed present
        self._since_listing = 0

    def __enter__(self) -> "SpoolWriter":
        check_spool(self.spool, writable=True, create=True)
        swept = sweep_orphans(self.spool, ORPHAN_AGE)
        if swept:
            log.info("swept %d orphaned temporary files from %s", swept, self.spool)
        if not hasattr(fcntl, "F_SETLEASE"):  # leases are Linux's
            self._recycle = False
        elif self._recycle is None:
            self._recycle = bool(self.limit) and filesystem_type(self.spool) in LOCAL_FILESYSTEMS
        if self.limit:
            self._list_and_evict()
        return self

    def __exit__(self, *exc) -> None:
        if self._spare is not None:
            _unlink_quietly(self._spare)
            self._spare = None

    def publish(self, data: bytes) -> str:
        """Atomically add one sample; returns its file name. Raises SpoolFull on a full disk."""
        self._seq += 1
        name = f"{time.time_ns():019d}-{self._prefix}-{self._seq:09d}{SUFFIX}"
        spare, self._spare = self._spare, None
        # The sample this publish is about to evict, kept under the other slot's name for
        # the next publish. Linked before publishing, deleted after as ever, so the spool
        # peaks by one for a moment (a kill -9 leaves one too many, never one too few).
        incoming = self._keep_as_spare(spare) if self._recycle and self._believed >= self.limit > 0 else None
        try:
            if not (spare is not None and self._rewrite_spare(spare, name, data)):
                self._write_atomically(name, data)
        except BaseException:
            if incoming is not None:
                _unlink_quietly(incoming)
            raise
        self._spare = incoming
        self.counts.published += 1
        self.counts.published_bytes += len(data)
        if self.limit:
            self._known.append(name)
            self._believed += 1
            self._since_listing += 1
            if self._since_listing >= self.evict_every:
                self._list_and_evict()
            else:
                self._evict_known()
        return name

    def _write_atomically(self, name: str, data: bytes) -> None:
        tmp = os.path.join(self._dir, self._temporary(name))
        try:
            fd = os.open(tmp, _CREATE, 0o666)  # open(..., 'xb')'s mode, less the umask
            try:
                _write_all(fd, data)
                if self.fsync:
                    os.fsync(fd)
            finally:
                os.close(fd)
            os.rename(tmp, os.path.join(self._dir, name))
        except BaseException as exc:
            _unlink_quietly(tmp)
            if isinstance(exc, OSError) and exc.errno in _NO_SPACE:
                raise SpoolFull(exc.errno, f"no space left under {self.spool}") from None
            raise

    def _temporary(self, name: str) -> str:
        return temporary_name(name, self._host, self._pid)  # host and pid looked up once, not per publish

    def _keep_as_spare(self, busy: str | None) -> str | None:
        """Hard-link the oldest known sample (the next to be evicted) to a free spare
        slot; returns the slot's path, or None."""
        slot = self._spare_paths[1] if busy == self._spare_paths[0] else self._spare_paths[0]
        try:
            os.link(os.path.join(self._dir, self._known[0]), slot)
            return slot
        except (FileNotFoundError, IndexError):  # another writer evicted it first; nothing known
            return None
        except FileExistsError:  # left over from an interrupted publish: it goes, this one is skipped
            _unlink_quietly(slot)
            return None
        except OSError as exc:  # no hard links here
            log.info("spool %s: not recycling evicted files (%s)", self.spool, exc.strerror)
            self._recycle = False
            return None

    def _rewrite_spare(self, spare: str, name: str, data: bytes) -> bool:
        """Publish `data` as `name` by rewriting a spare (an evicted sample's file);
        False, with the spare gone, when it cannot be rewritten safely."""
        try:
            fd = os.open(spare, _REWRITE)
        except OSError:  # swept by a starting writer, or replaced by something we must not touch
            _unlink_quietly(spare)
            return False
        try:
            # A lease break signals the holder (SIGIO, fatal by default): ask for SIGURG,
            # ignored by default, should anything open the spare in these microseconds.
            fcntl.fcntl(fd, fcntl.F_SETSIG, signal.SIGURG)
            fcntl.fcntl(fd, fcntl.F_SETLEASE, fcntl.F_WRLCK)  # refused while anyone else has it open
            status = os.fstat(fd)
            if status.st_nlink != 1:  # still a sample, or another writer's spare too, or hard-linked by a copy
                raise BlockingIOError(errno.EAGAIN, "spare has another name")
            _write_all(fd, data)
            if status.st_size > len(data):
                os.ftruncate(fd, len(data))
            if self.fsync:
                os.fsync(fd)
        except BaseException as exc:
            _unlink_quietly(spare)
            if isinstance(exc, OSError) and exc.errno in _NO_SPACE:
                raise SpoolFull(exc.errno, f"no space left under {self.spool}") from None
            if not isinstance(exc, OSError):
                raise
            if exc.errno in _NO_LEASES:  # this filesystem or kernel grants none: stop trying
                log.info("spool %s: not recycling evicted files (%s)", self.spool, exc.strerror)
                self._recycle = False
            return False
        finally:
            os.close(fd)  # also ends the lease
        try:
            os.rename(spare, os.path.join(self._dir, name))
        except FileNotFoundError:  # swept while we wrote it
            return False
        return True

    def _list_and_evict(self) -> None:
        names = enumerate_spool(self.spool)
        self._since_listing = 0
        self._known = deque(names)
        self._believed = len(names)
        self._evict_known()

    def _evict_known(self) -> None:
        """Delete the oldest known samples until the belief is back at the limit.

        Another writer may have deleted a file first: then try the next one, so each
        of our publishes at the limit is matched by exactly one deletion.
        """
        while self._believed > self.limit and self._known:
            try:
                os.unlink(os.path.join(self._dir, self._known.popleft()))
            except FileNotFoundError:
                continue
            self._believed -= 1
            self.counts.evicted += 1


def _write_all(fd: int, data: bytes) -> None:
    view, offset = memoryview(data), 0
    while offset < len(view):
        offset += os.pwrite(fd, view[offset:], offset)


def _unlink_quietly(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass
