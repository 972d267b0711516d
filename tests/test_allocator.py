"""The allocator keeps what a process frees: the trainer's heat maps of a batch (32 MB at 64 px and
256 samples, above glibc's adaptive ceiling), made again for the next batch, fault no page in once
freed memory is kept, and every page without it."""
from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest


# Eleven batches' heat maps, each freed before the next (as the trainer frees a step's batch);
# prints the page faults of the last five: kept, glibc settles within a few batches (measured: at
# most one of the first six faults its pages in again, none of the last five, but for the host's
# reclaim: this VM runs DAMON's, which once paged a kept buffer out between two batches, 8,320
# faults in one of them). Each mode in a child forked once torch is imported (before any torch
# thread exists): a fresh process's allocator, without a second torch import (~1.5 s).
BATCHES = """
import ctypes, os, resource
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: pages of 4 KB, whatever the host's huge-page policy
import torch
from cuboidtrain.allocator import keep_freed_memory
from cuboidtrain.train.startup import TRAINER_KEEPS
from cuboidtrain.models.codec import render_heatmaps
for mode in ("default", "kept"):
    child = os.fork()
    if child:
        assert os.waitpid(child, 0)[1] == 0, mode
        continue
    if mode == "kept":
        assert keep_freed_memory(TRAINER_KEEPS, TRAINER_KEEPS)
    keypoints, faults = torch.rand(256, 8, 2) * 64, []
    for _ in range(11):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        maps = render_heatmaps(keypoints, 64, 1.0)
        del maps
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    os.write(1, f"{mode} {' '.join(map(str, faults[-5:]))}\\n".encode())
    os._exit(0)
"""


def faults_of_later_batches() -> dict[str, int]:
    """Each mode's median of the last five batches' page faults (one batch's reclaim by the host moves it not)."""
    # glibc as it comes: no preloaded allocator, no tunables from the environment
    env = {k: v for k, v in os.environ.items() if k != "LD_PRELOAD" and not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    done = subprocess.run([sys.executable, "-c", BATCHES], capture_output=True, text=True, check=True, env=env)
    medians = {}
    for line in done.stdout.splitlines():
        mode, *faults = line.split()
        medians[mode] = sorted(map(int, faults))[2]
    return medians


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")
def test_the_next_batchs_heat_maps_reuse_the_freed_ones_without_faulting_pages_in():
    pages = 256 * 8 * 64 * 64 * 4 // 4096
    faults = faults_of_later_batches()
    assert faults["default"] >= pages // 2  # mapped afresh for every batch
    assert faults["kept"] < pages // 10
