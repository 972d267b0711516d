"""Shared builders for the tests: tiny configs, samples and spools."""
from __future__ import annotations

import contextlib
import functools
import importlib.abc
import importlib.util
import os
import resource
import signal
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cuboidgen.config import PAPER, GenConfig
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from shared.sample import encode
from shared.spool import SpoolWriter

# A suite started in the background of a non-interactive shell (`make test &`, nohup) inherits
# SIGINT ignored, and so would every command a test starts: Python installs its Ctrl-C handler
# only where SIGINT is not ignored, and the tests of Ctrl-C would see it do nothing. A handler
# here (not an ignore) lets the commands the tests start begin with SIGINT's default again.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

SIZE = 48  # px: tests stay tiny
# The registry's test architecture (cuboidtrain.models.networks): the compact design at a few
# channels, built and stepped in milliseconds. Tests of behaviour (training, resume,
# checkpoints, inference, export) use it; only tests of the real networks build others.
ARCH = "tiny"


@pytest.fixture(scope="session")
def library() -> OccluderLibrary:
    return OccluderLibrary.builtin(variants_per_kind=4, seed=0)


@functools.cache
def small_library() -> OccluderLibrary:
    return OccluderLibrary.builtin(variants_per_kind=2, seed=0)


def build_sample(seed: int = 0, shape: str = "box", size: int = SIZE, library=None, scene=PAPER):
    return make_sample(shape, scene, size, seed, library if library is not None else small_library())


def write_mask_pngs(folder: Path, count: int) -> list[str]:
    """`count` generated noisy masks of 64 to 128 px, box and twobox in turn, as PNGs: what a user
    points `cuboidtrain infer` at."""
    import cv2

    paths = []
    for seed in range(count):
        sample = build_sample(seed, ("box", "twobox")[seed % 2], size=64 + 16 * (seed % 5))
        paths.append(str(folder / f"m{seed:03d}.png"))
        cv2.imwrite(paths[-1], sample.noisy.astype("uint8") * 255)
    return paths


def fill_spool(spool: Path, count: int, limit: int = 0, shape: str = "box", library=None,
               size: int = SIZE) -> list[str]:
    """Publish `count` samples (seeds 0..count-1); returns their names, oldest first."""
    with SpoolWriter(spool, limit=limit) as writer:
        return [writer.publish(encode(build_sample(i, shape, size=size, library=library))) for i in range(count)]


def tiny_model(shape: str = "box", size: int = SIZE, seed: int = 0, sigma: float | None = None):
    """A freshly initialised model of the test architecture (`build_model(..., arch=ARCH)`)."""
    from cuboidtrain.models.networks import build_model  # torch: only for the tests that need it

    return build_model(shape, size, seed=seed, sigma=sigma, arch=ARCH)


def infer_paths(paths, models, explain=None, **options) -> list[dict]:
    """`cuboidtrain infer`'s records through the Fitter, on the CPU; `options` as FitOptions'."""
    from cuboidtrain.fit.fitter import Fitter
    from cuboidtrain.fit.options import FitOptions
    from cuboidtrain.infer.records import to_records

    fitter = Fitter(models, FitOptions(**({"device": "cpu"} | options)))
    return to_records(fitter.outcomes(paths, explain=explain), fitter.options)


def _built_once():
    """typer's runner builds the click command from the app at every invoke (~10 ms for
    `cuboidtrain`'s, some 450 times a suite): built once an app here. A click command holds no state
    between invocations (each has its own context), and typer registered the same callbacks either way."""
    import typer.testing

    if not hasattr(typer.testing._get_command, "cache_info"):
        typer.testing._get_command = functools.cache(typer.testing._get_command)


_built_once()


def command_here(args: list[str], env: dict[str, str] | None = None):
    """`cuboidtrain ARGS` in this process (click's runner, no terminal; `env` set meanwhile), read as a
    finished process is: exit status, stdout and stderr. For the runs whose process boundary is not
    what a test is about: a process of their own spends ~3 s of CPU starting Python and loading torch
    and the models."""
    import logging
    import subprocess

    from typer.testing import CliRunner

    from cuboidtrain.cli import app

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        result = CliRunner().invoke(app, args, env=env)
    finally:  # the command's log handler writes to the runner's stream, closed once it returns
        root.handlers[:] = handlers
        root.setLevel(level)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    return subprocess.CompletedProcess(args, result.exit_code, result.stdout, result.stderr)


@contextlib.contextmanager
def file_size_limit(size: int):
    """The kernel refuses (EFBIG) any write past `size` bytes into a file: a disk that fills,
    for every writer of this process (torch's C++ one too), with no privileges needed.
    Python ignores SIGXFSZ, so the write fails instead of the process."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def live_in_groups(groups: set[int]) -> list[int]:
    """The processes of these process groups still running (a zombie, exited but not reaped by
    whoever adopted it, is not), from /proc."""
    live = []
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            fields = Path(f"/proc/{entry}/stat").read_bytes().rsplit(b")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) in groups and fields[0] != b"Z":
            live.append(int(entry))
    return live


def groups_end(groups: set[int], within: float) -> bool:
    """True once no process of these groups runs (orphaned workers finish the sample in hand, or
    their start-up, and exit): waited on, not slept for."""
    deadline = time.monotonic() + within
    while live_in_groups(groups):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def with_generated_pdm(model):
    """`model` with the shape model a model file would carry, drawn from the generator."""
    from cuboidtrain.experiments.generated_pdm import generated_pdm

    model.pdm = generated_pdm(model.shape, model.size)
    return model


def train_config(**fields):
    """A TrainConfig of the test architecture; `fields` as TrainConfig's."""
    from cuboidtrain.train.config import TrainConfig

    return TrainConfig(arch=ARCH, **fields)


def tiny_config(spool: Path, **changes) -> GenConfig:
    base = GenConfig(spool=spool, limit=50, max_samples=20, workers=1, size=SIZE, seed=1, dashboard=False)
    return replace(base, **changes)


def centred(scene=PAPER, **changes):
    """A scene with fixed framing (margin 0.125, no jitter) so poses map to known pixels."""
    return replace(scene, margin=(0.125, 0.125), centre_jitter=0.0, **changes)


class _OneTorchThread(importlib.abc.MetaPathFinder):
    """Tiny 32-64 px models gain nothing from a second intra-op thread, and on a busy 2-core
    machine its barrier waits made a forward pass ~50x slower (4.8 s, not 0.1 s). So torch runs
    the tests at one thread, set the moment something imports it: the tests that never import
    torch (the generator's, the spool's, ...) never pay for loading it."""

    def __init__(self):
        self.before: int | None = None  # torch's own thread count, restored at the end

    def find_spec(self, fullname, path, target=None):
        if fullname != "torch":
            return None
        sys.meta_path.remove(self)  # once: the spec is found by the finders after this one
        spec = importlib.util.find_spec(fullname)
        if spec is not None and spec.loader is not None:
            spec.loader = _ThenOneThread(spec.loader, self)
        return spec

    def loaded(self, torch) -> None:
        self.before = torch.get_num_threads()
        torch.set_num_threads(1)


class _ThenOneThread(importlib.abc.Loader):
    """torch's own loader, then one intra-op thread; the module keeps its own loader."""

    def __init__(self, loader, hook: _OneTorchThread):
        self.loader, self.hook = loader, hook

    def __getattr__(self, name):
        return getattr(self.loader, name)

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module):
        module.__spec__.loader = module.__loader__ = self.loader  # torch as if loaded plainly
        self.loader.exec_module(module)
        self.hook.loaded(module)


ONE_TORCH_THREAD = _OneTorchThread()
if "torch" in sys.modules:  # loaded before the tests' conftest (by a plugin): set it now
    ONE_TORCH_THREAD.loaded(sys.modules["torch"])
else:
    sys.meta_path.insert(0, ONE_TORCH_THREAD)


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """torch's thread count restored after the session, where a test loaded torch (conftest's hook set it to 1)."""
    yield
    if ONE_TORCH_THREAD.before is not None:
        sys.modules["torch"].set_num_threads(ONE_TORCH_THREAD.before)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def start_page_server(*options: str):
    """`cuboidtrain serve --workers 1 OPTIONS` on a free 127.0.0.1 port, once it says its address:
    (the address `http://127.0.0.1:PORT/`, the process)."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    root = Path(__file__).resolve().parents[1]
    server = subprocess.Popen([sys.executable, "-m", "cuboidtrain", "serve", "--port", str(port), "--workers", "1",
                               *options], cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = server.stdout.readline()
    assert line.startswith(f"cuboid-fit page at http://127.0.0.1:{port}/"), (line, server.stderr.read()[-2000:])
    return f"http://127.0.0.1:{port}/", server


def pytest_configure(config):
    config.addinivalue_line("markers", "stops_page_server: stops the session's page server; run after every other test")


def pytest_collection_modifyitems(items):
    """The tests that stop the session's page server (`stops_page_server`) last: one server start (its
    worker importing torch and the models, ~5 s) serves every page test, the stop included."""
    last = [item for item in items if item.get_closest_marker("stops_page_server")]
    items[:] = [item for item in items if item not in last] + last


@pytest.fixture(scope="session")
def page_servers():
    """The page servers this pytest process started (`page_server`), stopped at its end where a test did not."""
    import signal

    servers = []
    yield servers
    for _, server in servers:
        if server.poll() is None:
            server.send_signal(signal.SIGINT)
            server.wait(30)


@pytest.fixture
def page_server(page_servers):
    """The page's server for its tests (tests/test_web.py, tests/test_web_browser.py), uploads up to 2 MB:
    one start serves every page test of this pytest process. tests/test_web.py's Ctrl-C test stops it
    and runs last (`stops_page_server`); a page test that still comes after it on the same worker
    (`make test` runs two, each given whole files) gets a new start rather than a closed port."""
    pytest.importorskip("starlette", reason="the web extra is not installed (pip install 'cuboid-fit[web]')")
    if not page_servers or page_servers[-1][1].poll() is not None:
        page_servers.append(start_page_server("--max-upload-mb", "2"))
    return page_servers[-1]
