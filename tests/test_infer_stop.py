"""What was fitted is kept (issue 30, Must have 2): Ctrl-C or SIGTERM during `infer --json FILE` writes
the records fitted so far, atomically, says how many of how many, and exits 130 or 143; the
`--explain` and `--mesh` files written stay, none half-written. Through the command, as a user runs it.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.conftest import groups_end, write_mask_pngs
from cuboidtrain.infer.stopping import held_during_import

ROOT = Path(__file__).resolve().parents[1]
MASKS = 150


@pytest.fixture(scope="module")
def masks(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("masks")
    write_mask_pngs(folder, MASKS)
    return folder


def stopped_run(tmp_path: Path, masks: Path, sig: int, written: str, *extra: str, group: bool = False):
    """`infer MASKS --json OUT *extra`, sent `sig` once `written` (a folder) holds 3 files; its exit
    status, stderr, the JSON list it wrote and the files of `written`."""
    out = tmp_path / "out.json"
    proc = subprocess.Popen([sys.executable, "-c", "from cuboidtrain.cli import main; main()", "infer", str(masks),
                             "--device", "cpu", "--json", str(out), *extra],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    deadline = time.monotonic() + 300
    while not (Path(written).is_dir() and len(list(Path(written).iterdir())) >= 3):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
        time.sleep(0.05)
    if group:  # Ctrl-C in a terminal: the whole foreground process group (the workers too)
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=300)
    files = sorted(p.name for p in Path(written).iterdir())
    return proc.returncode, stderr, json.loads(out.read_text()), files, proc.pid


def check_kept(tmp_path: Path, code: int, stderr: str, records: list[dict], files: list[str], suffix: str,
               name: str) -> None:
    assert 3 <= len(records) < MASKS, stderr[-2000:]
    assert all(r["error"] is None for r in records)
    assert [Path(r["input"]).stem for r in records] == sorted(Path(r["input"]).stem for r in records)  # input order
    assert files == sorted(Path(r["input"]).stem + suffix for r in records)  # a file a record, none half-written
    assert not [p for p in tmp_path.rglob(".tmp-*")]
    last = stderr.strip().splitlines()[-1]
    assert last == f"stopped by {name}: {len(records)} of {MASKS} inputs fitted; {len(records)} records in {tmp_path}/out.json"


def test_ctrl_c_writes_the_records_and_meshes_fitted_so_far(tmp_path, masks):
    meshes = tmp_path / "meshes"
    code, stderr, records, files, _ = stopped_run(tmp_path, masks, signal.SIGINT, meshes, "--mesh", str(meshes))
    assert code == 130
    check_kept(tmp_path, code, stderr, records, files, ".obj", "Ctrl-C")
    assert f"stopped by Ctrl-C: {len(records)} of {MASKS} masks; fitted {len(records)}" in stderr


def test_sigterm_writes_the_records_and_pictures_fitted_so_far(tmp_path, masks):
    pictures = tmp_path / "explain"
    code, stderr, records, files, _ = stopped_run(tmp_path, masks, signal.SIGTERM, pictures, "--explain", str(pictures))
    assert code == 143
    check_kept(tmp_path, code, stderr, records, files, ".png", "SIGTERM")


def test_ctrl_c_to_a_pool_finishes_the_inputs_in_hand_and_leaves_no_process(tmp_path, masks):
    meshes = tmp_path / "meshes"
    code, stderr, records, files, group = stopped_run(tmp_path, masks, signal.SIGINT, meshes, "--mesh", str(meshes),
                                                      "--workers", "2", group=True)
    assert code == 130
    check_kept(tmp_path, code, stderr, sorted(records, key=lambda r: r["input"]), files, ".obj", "Ctrl-C")
    # the workers and their fork server end with the run (exited: a zombie left to the container's init to reap is gone)
    assert groups_end({group}, within=20.0), "processes of the stopped run are left"


@pytest.mark.parametrize("delay", [1.0, 2.5])
def test_ctrl_c_while_a_pool_starts_ends_quietly(tmp_path, masks, delay):
    """Before any fit (torch importing here and in the workers' fork server): exit 130, no traceback
    from any process of the group."""
    proc = subprocess.Popen([sys.executable, "-c", "from cuboidtrain.cli import main; main()", "infer", str(masks),
                             "--device", "cpu", "--workers", "2", "--json", str(tmp_path / "out.json")],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    time.sleep(delay)
    os.killpg(proc.pid, signal.SIGINT)
    _, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-3000:]


def test_a_signal_during_a_held_import_is_delivered_when_it_ends():
    """`held_during_import`: the signal waits for the block's end (a KeyboardInterrupt raised inside torch's native
    initialisation aborts the interpreter), then comes as it would have."""
    class Delivered(Exception):
        pass

    def handler(signum, frame):
        raise Delivered

    order = []
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        with pytest.raises(Delivered):
            with held_during_import():
                signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)  # to this thread: held here
                order.append("inside")  # not interrupted here
            order.append("after")  # never: it comes as the block ends
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert order == ["inside"]
    assert signal.pthread_sigmask(signal.SIG_BLOCK, set()) == set()  # nothing left held
