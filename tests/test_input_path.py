"""Feeding a GPU (issue 29): the input path's benchmark, the generator's pace per scene and shape,
the loader's workers on CUDA, and the warnings when the device waits for data or outruns the generator."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cuboidgen.bench import bench_scenes
from cuboidgen.config import SCENES
from cuboidtrain.data.sampler import EpochPosition
from cuboidtrain.train.monitor import stats
from cuboidtrain.train.monitor.dashboard import wait_cell
from cuboidtrain.train.monitor.progress import STARVED, Progress
from tests.conftest import small_library, train_config

ROOT = Path(__file__).resolve().parents[1]


def test_the_input_benchmark_prints_a_table_and_json_for_each_size_with_and_without_reframing(tmp_path):
    out = tmp_path / "input.json"
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "speed" / "bench_input.py"), "--sizes", "32", "64",
                           "--batch", "8", "--batches", "2", "--repeats", "1", "--json", str(out)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    assert [(r["size"], r["reframe"], r["spool_size"]) for r in result["rows"]] == [
        (32, False, 32), (32, True, 256), (64, False, 64), (64, True, 256)]
    for row in result["rows"]:
        assert row["loader_samples_per_s"] > 0 and row["whole_samples_per_s"] > 0 and row["samples_per_epoch"] >= 12
    assert result["device"] == "cpu" and result["torch_threads"] == 1 and len(result["core"]) == 1
    assert "reframe" in done.stdout and "whole path" in done.stdout
    assert not list(tmp_path.glob(".bench-input-*"))  # its spools are gone


def test_the_generator_bench_reports_every_scene_and_shape_on_one_core(tmp_path):
    rows = bench_scenes(32, 3, 1, small_library(), str(tmp_path))
    assert {(r["scene"], r["shape"]) for r in rows} == {(s, k) for s in SCENES for k in ("box", "twobox")}
    assert all(r["published_per_s_per_core"] > 0 and r["size"] == 32 for r in rows)


@pytest.mark.parametrize(("given", "device", "cores", "workers"), [
    (None, "cpu", 16, 2),  # as before issue 29 on the CPU
    (None, "cuda", 16, 4), (None, "cuda", 2, 2), (None, "cuda", 64, 6),  # a quarter of the cores, 2 to 6
    (0, "cuda", 16, 0), (3, "cpu", 16, 3),  # --loader-workers wins
])
def test_the_loaders_workers_default_to_a_quarter_of_the_cores_on_cuda(monkeypatch, given, device, cores, workers):
    from cuboidtrain.train import config as config_module

    monkeypatch.setattr(config_module.os, "cpu_count", lambda: cores)
    assert train_config(loader_workers=given).workers_on(device) == workers


class StandingSampler:
    def where(self) -> EpochPosition:
        return EpochPosition(0, 0, 1)


class QuietSpool:
    count = 100


def progress_after(tmp_path, monkeypatch, waited: float, reuse: float, steps: int = stats.WINDOW) -> Progress:
    """A Progress after `steps` steps of 1 s, each after `waited` s of data wait, on samples used `reuse` times before."""
    clock = [100.0]
    monkeypatch.setattr(stats.time, "perf_counter", lambda: clock[0])
    progress = Progress(train_config(out=str(tmp_path / "run")), torch.device("cpu"), watcher=QuietSpool())
    progress.sampler = StandingSampler()
    for _ in range(steps):
        clock[0] += 1.0
        progress.stats.stepped({"total": 1.0}, 8, waited, 1.0, reuse, {})
    return progress


def notes(progress: Progress) -> str:
    return " | ".join(progress.snapshot().notes)


def test_a_data_wait_that_stays_above_20_percent_is_a_warning_in_the_status(tmp_path, monkeypatch):
    assert STARVED == 0.20
    starved = notes(progress_after(tmp_path, monkeypatch, waited=0.3, reuse=0.0))
    assert "warning: data wait 30% of step time stays above 20%" in starved
    assert "the loader is starving" not in starved  # one note, the stronger
    assert "the loader is starving" in notes(progress_after(tmp_path, monkeypatch, waited=0.1, reuse=0.0))
    assert notes(progress_after(tmp_path, monkeypatch, waited=0.3, reuse=0.0, steps=stats.WINDOW - 1)) == ""  # not yet: it must stay
    assert notes(progress_after(tmp_path, monkeypatch, waited=0.01, reuse=0.0)) == ""


def test_a_trainer_that_outruns_the_generator_is_told_the_spools_reuse_feeds_it(tmp_path, monkeypatch):
    said = notes(progress_after(tmp_path, monkeypatch, waited=0.0, reuse=2.5))
    assert "samples reused 2.5 times on average: training outruns the generator" in said
    assert "not a faster generator" in said and "--limit" in said
    assert notes(progress_after(tmp_path, monkeypatch, waited=0.0, reuse=0.5)) == ""


def test_the_dashboard_warns_above_20_percent_data_wait():
    assert "warning" in wait_cell(0.25).plain and wait_cell(0.25).style == "bold red"
    assert "loader starving" in wait_cell(0.12).plain and "warning" not in wait_cell(0.12).plain
