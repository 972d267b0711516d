"""Torch-free tests import no torch: conftest sets torch's one test thread only when something
loads torch, so the generator's, the spool's and the geometry's tests run without paying for it."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Test modules of code that needs no torch: the generator's drawing, occluders and noise, the sample format.
TORCH_FREE = ["tests/test_augment.py", "tests/test_scene.py", "tests/test_occluders.py", "tests/test_raster.py",
              "tests/test_sample.py"]
# Runs them in a fresh interpreter (no cache written), then says whether torch was loaded and whether
# conftest's hook still waits for it.
RUN = """import sys, pytest
rc = pytest.main(["-q", "-p", "no:cacheprovider", *sys.argv[1:]])
print("torch loaded:", "torch" in sys.modules)
print("hook waiting:", sys.modules["tests.conftest"].ONE_TORCH_THREAD in sys.meta_path)
sys.exit(rc)
"""


def test_the_torch_free_tests_run_without_loading_torch():
    result = subprocess.run([sys.executable, "-c", RUN, *TORCH_FREE], cwd=ROOT, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert " passed" in result.stdout and " failed" not in result.stdout
    assert "torch loaded: False" in result.stdout, result.stdout
    assert "hook waiting: True" in result.stdout  # a test that loads torch would get one thread all the same


def test_a_test_that_loads_torch_runs_it_at_one_thread():
    import torch

    assert torch.get_num_threads() == 1
