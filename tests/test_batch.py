"""`infer` over many masks (cuboidtrain/infer/batch.py, pool.py, progress.py): a run killed with SIGKILL
and resumed ends with the records of an uninterrupted run, none twice; a pool of workers gives
the records of one process; without a terminal, progress is plain log lines and a summary."""
from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from rich.console import Console

from cuboidtrain.infer.batch import Batch, run_batch
from cuboidtrain.infer.pool import CHUNK, warm_up
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.records import read_records, to_records
from cuboidtrain.models.zoo import default_checkpoints
from tests.conftest import command_here, file_size_limit, write_mask_pngs

ROOT = Path(__file__).resolve().parents[1]
SLOW = FitOptions(refine_steps=6, device="cpu")  # the shipped models, six Refiner passes: ~0.1 s a mask
COUNT, BAD = 24, 12  # masks, and the one that is no image


@pytest.fixture(scope="module")
def masks(tmp_path_factory) -> list[str]:
    """24 generated masks of 64 to 128 px, box and twobox, and one file that is no image."""
    folder = tmp_path_factory.mktemp("masks")
    paths = write_mask_pngs(folder, COUNT)
    Path(paths[BAD]).write_text("not a picture")  # an unreadable input among them
    return paths


@functools.cache
def reference(paths: tuple[str, ...], options, workers=1) -> list[dict]:
    """An uninterrupted run's records, in this process (one torch thread, as the workers have);
    computed once for the tests that compare with the same run."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        checkpoints = default_checkpoints(None, options.shapes)
        batch = Batch(tuple(paths), tuple(checkpoints), options, workers)
        outcomes = run_batch(batch, Fitter.from_files(checkpoints, options), Console(file=open(os.devnull, "w")))[0]
        return to_records(outcomes, options)
    finally:
        torch.set_num_threads(threads)


def infer_command(folder: str, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "cuboidtrain", "infer", folder, "--jsonl", str(out), "--refine-steps", "6",
            "--device", "cpu", "--networks-only", *extra]  # the references are the networks' records


def resume_here(command: list[str]) -> subprocess.CompletedProcess:
    """A resumed run of `command` (`[python, -m, cuboidtrain, infer, ...]`) in this process: the kill or
    the full disk came to the first run's process; the rerun only reads its store and fits the rest."""
    return command_here(command[3:])


def test_a_run_killed_mid_way_resumes_to_the_records_of_an_uninterrupted_run(tmp_path, masks):
    out, folder = tmp_path / "out.jsonl", str(Path(masks[0]).parent)
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    run = subprocess.Popen(infer_command(folder, out), cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and (not out.exists() or out.read_bytes().count(b"\n") < 8):
        time.sleep(0.01)
    run.send_signal(signal.SIGKILL)
    run.wait()
    kept = read_records(out)
    assert 8 <= len(kept) < COUNT, "killed mid-way"
    with out.open("a") as torn:  # as if the kill had come mid-write
        torn.write(f'{{"index": {COUNT - 1}, "input": "')
    resumed = resume_here(infer_command(folder, out))
    assert resumed.returncode == 1, resumed.stderr  # one is no image
    assert f"holds {len(kept)} of the {COUNT} inputs" in resumed.stderr
    records = read_records(out)
    assert [r["index"] for r in records] == list(range(COUNT))  # each input once, the torn line gone
    assert out.read_text().count("\n") == COUNT
    expected = reference(tuple(masks), SLOW)
    assert [{k: v for k, v in r.items() if k != "index"} for r in records] == expected
    assert records[BAD]["error"] and sum(r["error"] is not None for r in records) == 1


def descendants(pid: int) -> list[int]:
    """The processes under `pid` (its children, theirs, ...), from /proc."""
    children = {}
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{entry}/stat").read_bytes()
        except OSError:
            continue
        children.setdefault(int(stat.rsplit(b")", 1)[1].split()[1]), []).append(int(entry))
    found, todo = [], [pid]
    while todo:
        below = children.get(todo.pop(), [])
        found += below
        todo += below
    return sorted(found)


def running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_bytes().rsplit(b")", 1)[1].split()[0] != b"Z"
    except OSError:
        return False


def test_two_workers_killed_leave_no_process_behind_and_resume_to_one_process_s_records(tmp_path, masks):
    out, folder = tmp_path / "out.jsonl", str(Path(masks[0]).parent)
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    run = subprocess.Popen(infer_command(folder, out, "--workers", "2"), cwd=ROOT, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and (not out.exists() or out.read_bytes().count(b"\n") < 8):
        time.sleep(0.01)
    under = descendants(run.pid)  # the fork server and the two workers it forked
    run.send_signal(signal.SIGKILL)
    run.wait()
    kept = len(read_records(out))
    assert 8 <= kept < COUNT, "killed mid-way"
    assert len(under) >= 3
    deadline = time.monotonic() + 10  # a worker looks for its parent every PARENT_LOOK_S
    while time.monotonic() < deadline and any(map(running, under)):
        time.sleep(0.1)
    assert not [pid for pid in under if running(pid)], "workers outlived a killed infer"
    resumed = resume_here(infer_command(folder, out, "--workers", "2"))
    assert resumed.returncode == 1 and f"holds {kept} of the {COUNT} inputs" in resumed.stderr  # one is no image
    records = read_records(out)
    assert [r["index"] for r in records] == list(range(COUNT))
    assert [{k: v for k, v in r.items() if k != "index"} for r in records] == reference(tuple(masks), SLOW)


def test_two_workers_give_the_records_of_one_process(masks):
    options = FitOptions(device="cpu")
    assert reference(tuple(masks[:16]), options, workers=2) == reference(tuple(masks[:16]), options)


def test_without_a_terminal_progress_is_log_lines_and_a_summary(tmp_path, masks, monkeypatch, caplog):
    monkeypatch.setattr("cuboidtrain.infer.reporting.LOG_SECONDS", 0.0)
    console = Console(file=(tmp_path / "console.txt").open("w"), width=300)
    checkpoints = default_checkpoints(None)
    batch = Batch(tuple(masks[BAD - 5:BAD + 5]), tuple(checkpoints), FitOptions(device="cpu"), jsonl=tmp_path / "o.jsonl",
                  keep=False)
    with caplog.at_level("INFO", logger="cuboidtrain.infer.reporting"):
        records, tally = run_batch(batch, Fitter.from_files(checkpoints, FitOptions(device="cpu")), console)
    console.file.close()
    assert records == [] and tally.done == 10 and tally.failed == 1
    assert "10/10 masks" in caplog.records[-1].getMessage() and "1 failure" in caplog.records[-1].getMessage()
    summary = (tmp_path / "console.txt").read_text()
    shapes = {r["shape"] for r in read_records(tmp_path / "o.jsonl")} - {None}
    assert "10 masks; fitted 9 in" in summary and "1 failed" in summary  # 9 + 1 = 10
    assert all(f"{shape} " in summary for shape in shapes)


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_full_disk_stops_the_run_in_one_line_keeping_whole_records_and_a_rerun_resumes(tmp_path, masks, workers):
    """In this process (the disk fills under the run's writer, not at a process boundary), its pool's
    fork server started first: a server started under the limit would hand it to every later worker."""
    out, folder = tmp_path / "out.jsonl", str(Path(masks[0]).parent)
    command = ["infer", folder, "--jsonl", str(out), "--device", "cpu", "--networks-only"]
    warm_up(int(workers))
    with file_size_limit(8 * 1024):  # room for about ten records
        full = command_here(command + ["--workers", workers])
    lines = [line for line in full.stderr.splitlines() if line.startswith("error:")]
    assert full.returncode == 2 and "Traceback" not in full.stderr, full.stderr
    kept = read_records(out)
    assert 4 <= len(kept) < COUNT and out.stat().st_size <= 8 * 1024
    assert lines == [f"error: --jsonl {out}: file size limit reached after {len(kept)} records (all kept); "
                     f"expected free space: make some and rerun to resume"]
    assert out.read_bytes().endswith(b"\n") and out.read_bytes().count(b"\n") == len(kept)  # whole records only
    resumed = command_here(command)
    assert resumed.returncode == 1 and f"holds {len(kept)} of the {COUNT} inputs" in resumed.stderr  # one is no image
    records = read_records(out)
    assert [r["index"] for r in records] == list(range(COUNT))
    assert [{k: v for k, v in r.items() if k != "index"} for r in records] == reference(tuple(masks), FitOptions(device="cpu"))


def test_a_pipe_from_two_workers_ends_when_infer_does(masks):
    """`infer --workers 2 --json - | jq`: the workers' fork server outlives infer by a moment as it
    shuts down, and must not hold the pipe's write end (its stdout is /dev/null): once infer has
    exited, its stdout is at end of file at once."""
    import select

    few = masks[:2 * CHUNK]  # a chunk for each worker: what it shows needs no more
    command = [sys.executable, "-m", "cuboidtrain", "infer", *few, "--workers", "2", "--json", "-",
               "--networks-only", "--device", "cpu"]
    proc = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            env=os.environ | {"OMP_NUM_THREADS": "1"})
    assert proc.wait(timeout=180) in (0, 1)  # its records fit the pipe's buffer: it need not wait for a reader
    fd, text = proc.stdout.fileno(), b""
    while True:
        ready, _, _ = select.select([fd], [], [], 0.1)
        assert ready, "infer has exited, but its stdout is still held open"
        chunk = os.read(fd, 1 << 16)
        if not chunk:
            break
        text += chunk
    proc.stdout.close()
    assert len(json.loads(text)) == len(few)
