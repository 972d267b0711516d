"""`cuboidgen bench` (issue 38): it finishes, its on-the-fly DataLoader stage included."""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_generator_bench_finishes_with_tiny_settings_and_reports_the_on_the_fly_baseline(tmp_path):
    # the benchmarks before the on-the-fly stage run OpenCV's thread pool in this process; forked
    # DataLoader workers inherited its locks and hung on their first cv2 call, with no output
    out = tmp_path / "bench.json"
    code = ("import sys; from cuboidgen.cli import main; sys.argv = ['cuboidgen'] + sys.argv[1:]; main()")
    done = subprocess.run([sys.executable, "-c", code, "bench", "--size", "32", "--samples", "5", "--repeats", "1",
                           "--dir", str(tmp_path), "--json", str(out)], cwd=tmp_path, capture_output=True, text=True,
                          timeout=240, env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "120"})
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    fly = result["on_the_fly"]
    assert fly["workers"] == (os.cpu_count() or 1) and fly["on_the_fly_per_s"] > 0
    assert result["ratios"]["read_unpacked_over_on_the_fly"] > 0
    assert "on the fly in DataLoader" in done.stderr
    assert not list(tmp_path.glob(".bench-*"))  # its spools are gone


def test_an_on_the_fly_batch_that_never_comes_gives_the_stage_up_with_a_line(caplog):
    from cuboidgen.bench import bench_on_the_fly

    with caplog.at_level(logging.WARNING, logger="cuboidgen.bench"):
        fly = bench_on_the_fly(32, 4, 2, 1, 1, timeout=0.01)  # no spawned worker is up in 10 ms
    assert fly == {"workers": 1, "samples": 4, "on_the_fly_per_s": None, "timed_out_s": 0.01}
    assert [r.getMessage() for r in caplog.records] == [
        "on-the-fly stage given up: a DataLoader worker sent no batch within 0.01 s"]
