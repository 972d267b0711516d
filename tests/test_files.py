"""The one atomic writer: its temporary names are what the sweep reads back, a failed write
leaves nothing, and every writer (spool, run folder, SPOOL.json) follows the same rule."""
from __future__ import annotations

import json
import os
import random
import string
import subprocess
from pathlib import Path

import pytest

from shared.files import (
    TMP_PREFIX, atomic_path, host_tag, process_alive, sweep_orphans, temporary_name, temporary_writer,
)

NAME_CHARS = string.ascii_letters + string.digits + "-._ é"


def random_names(count: int, seed: int = 0) -> list[str]:
    """File names of every shape a writer may hand over: dashes, dots, digits, leading `.tmp-`."""
    rng = random.Random(seed)
    names = ["a", "-", "--", "0-0-0", "last.pt", "SPOOL.json", f"{TMP_PREFIX}0-x-1-y"]
    names += ["".join(rng.choice(NAME_CHARS) for _ in range(rng.randint(1, 40))) for _ in range(count)]
    return names


def dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()  # reaped: the pid no longer exists
    return proc.pid


@pytest.mark.parametrize("name", random_names(300))
def test_every_temporary_name_reads_back_as_its_writer(name):
    rng = random.Random(name)
    host = "".join(rng.choice(string.ascii_letters + string.digits) for _ in range(rng.randint(1, 24)))
    pid = rng.randint(1, 2**22)
    tmp = temporary_name(name, host, pid)
    assert tmp.startswith(TMP_PREFIX) and tmp.endswith(name) and "/" not in tmp
    assert temporary_writer(tmp) == (host, pid)
    assert temporary_writer(temporary_name(name)) == (host_tag(), os.getpid())


@pytest.mark.parametrize("stray", ["notatemp", ".tmp-", ".tmp-x", ".tmp-meta-123", ".tmp-12-last.pt",
                                   ".tmp-0-host-notapid-x", ".tmp-0--12-x", ".tmp-0-host-12"])
def test_names_not_made_by_the_rule_are_strays(stray):
    assert temporary_writer(stray) is None


def test_atomic_path_replaces_the_file_through_a_temporary_the_sweep_reads(tmp_path):
    target = tmp_path / "sub" / "last.pt"
    with atomic_path(target) as tmp:
        assert temporary_writer(tmp.name) == (host_tag(), os.getpid()) and tmp.parent == target.parent
        tmp.write_text("new")
        assert not target.exists()  # readers see nothing new until the end
    assert target.read_text() == "new" and os.listdir(target.parent) == ["last.pt"]


def test_a_failed_write_leaves_the_old_file_and_nothing_else(tmp_path):
    target = tmp_path / "status.json"
    target.write_text("old")
    with pytest.raises(OSError, match="disk full"):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise OSError("disk full")
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["status.json"]


def test_the_sweep_keeps_live_writers_files_and_removes_dead_stale_and_stray_ones(tmp_path):
    live = temporary_name("last.pt")
    far_away = temporary_name("last.pt", host="otherhost", pid=dead_pid())  # its pid means nothing here
    dead = temporary_name("last.pt", pid=dead_pid())
    stale = temporary_name("old.pt", host="otherhost", pid=1)
    for name in (live, far_away, dead, stale, ".tmp-meta-1", "last.pt"):
        (tmp_path / name).write_text("x")
    os.utime(tmp_path / stale, (0, 0))
    assert sweep_orphans(tmp_path, max_age=60.0) == 3
    assert sorted(os.listdir(tmp_path)) == sorted([live, far_away, "last.pt"])


def test_a_gone_or_impossible_pid_is_not_alive():
    assert process_alive(os.getpid()) and not process_alive(dead_pid())
    assert not process_alive(0) and not process_alive(-1) and not process_alive(None)


def test_spool_metadata_is_written_atomically_and_a_failed_write_leaves_nothing(tmp_path, monkeypatch):
    import cuboidgen.daemon as daemon
    from cuboidgen.config import GenConfig

    daemon.write_metadata(GenConfig(spool=tmp_path))
    assert json.loads((tmp_path / "SPOOL.json").read_text())["generator"]["size"] == GenConfig().size
    written = (tmp_path / "SPOOL.json").read_text()

    real_write = Path.write_text

    def torn(path, text, *args, **kwargs):  # what a full disk leaves: part of the file, then an error
        real_write(path, text[:10])
        raise OSError("disk full")

    monkeypatch.setattr(Path, "write_text", torn)
    with pytest.raises(OSError):
        daemon.write_metadata(GenConfig(spool=tmp_path, size=32))
    assert os.listdir(tmp_path) == ["SPOOL.json"] and (tmp_path / "SPOOL.json").read_text() == written
