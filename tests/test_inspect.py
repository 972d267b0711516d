"""Spool freshness (shared.inspect.freshness) and `cuboidgen health`, the generator's container healthcheck."""
import os
import time

import pytest
from typer.testing import CliRunner

from cuboidgen.cli import app
from shared.inspect import freshness
from shared.spool import host_tag
from tests.conftest import fill_spool

runner = CliRunner()


def rename_as(spool, name: str, host: str, age_s: float) -> str:
    """Give a published sample another host and publication time (its name says both)."""
    stamp = time.time_ns() - int(age_s * 1e9)
    new = f"{stamp:019d}-{host}-" + name.split("-", 2)[2]
    os.rename(spool / name, spool / new)
    return new


def health(spool, *options) -> tuple[int, list[str]]:
    result = runner.invoke(app, ["health", str(spool), *options])
    return result.exit_code, [line for line in result.output.splitlines() if line.strip()]


def test_freshness_reports_the_newest_sample_of_a_host(tmp_path, library):
    names = fill_spool(tmp_path, 3, library=library)
    other = rename_as(tmp_path, names[2], "otherhost", age_s=0.0)  # the newest, but not ours
    rename_as(tmp_path, names[0], host_tag(), age_s=90.0)
    mine = rename_as(tmp_path, names[1], host_tag(), age_s=30.0)
    everyone = freshness(tmp_path)
    assert everyone["newest"] == other and everyone["samples"] == 3 and everyone["age_s"] < 5
    ours = freshness(tmp_path, host_tag())
    assert ours["newest"] == mine and ours["samples"] == 2 and 29 < ours["age_s"] < 35
    assert ours["corrupt"] is None
    assert freshness(tmp_path, "nohost")["newest"] is None


def test_freshness_names_a_corrupt_newest_sample(tmp_path, library):
    names = fill_spool(tmp_path, 2, library=library)
    (tmp_path / names[-1]).write_bytes(b"torn")
    report = freshness(tmp_path)
    assert report["newest"] == names[-1] and report["corrupt"]


def test_health_is_0_for_a_fresh_spool(tmp_path, library):
    fill_spool(tmp_path, 2, library=library)
    code, lines = health(tmp_path, "--mine", "--max-age", "30")
    assert code == 0 and lines[0].startswith("healthy:") and f"host {host_tag()}" in lines[0]


@pytest.mark.parametrize("case, options, message", [
    ("empty", [], "no samples"),
    ("stale", ["--max-age", "60"], "is 120 s old, expected at most 60 s"),
    ("others only", ["--mine"], f"no samples from host {host_tag()}"),
    ("corrupt", [], "is corrupt"),
    ("fresh", ["--max-age", "-5"], "--max-age -5.0: expected a positive number"),
    ("missing", [], "no such folder"),
])
def test_health_is_1_with_one_line_otherwise(tmp_path, library, case, options, message):
    spool = tmp_path / "spool"
    spool.mkdir()
    if case != "empty":
        names = fill_spool(spool, 1, library=library)
    if case == "stale":
        rename_as(spool, names[0], host_tag(), age_s=120.0)
    if case == "others only":
        rename_as(spool, names[0], "otherhost", age_s=0.0)
    if case == "corrupt":
        (spool / names[0]).write_bytes(b"torn")
    if case == "missing":
        spool = tmp_path / "nowhere"
    code, lines = health(spool, *options)
    # Docker reads 1 as unhealthy and reserves 2, the other commands' code for bad options.
    assert code == 1 and len(lines) == 1 and message in lines[0], lines


def poisoned(data: bytes, **changes) -> bytes:
    """A well-formed sample's bytes with fields replaced (a NaN keypoint, a ratio of Infinity)."""
    from shared.sample import decode_record, pack_record

    return pack_record({**decode_record(data), **changes})


def test_inspect_and_the_trainers_reader_count_non_finite_samples_as_corrupt_with_a_reason(tmp_path, library):
    import json

    import numpy as np

    from cuboidtrain.data.loader import SpoolBatches

    names = fill_spool(tmp_path, 4, library=library)
    good = (tmp_path / names[0]).read_bytes()
    keypoints = np.full(16, np.nan).tobytes()
    (tmp_path / names[1]).write_bytes(poisoned(good, keypoints=keypoints))
    (tmp_path / names[2]).write_bytes(poisoned(good, ratios={"depth_height": float("inf"), "width_height": 1.0}))
    result = runner.invoke(app, ["inspect", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["samples"] == 2 and report["corrupt"] == 2
    assert report["corrupt_reasons"] == {"keypoints: not finite": 1, "ratios: not finite": 1}
    batch = SpoolBatches(tmp_path, "box", 48)[names]
    assert batch.names == [names[0], names[3]] and batch.skipped["corrupt"] == 2
    assert np.isfinite(batch.keypoints.numpy()).all()


def test_a_flipped_bit_is_found_by_inspect_the_trainers_reader_and_eval_as_damaged(tmp_path, library):
    import json

    from cuboidtrain.data.loader import SpoolBatches
    from cuboidtrain.train.evaluate import load_batches

    names = fill_spool(tmp_path, 4, library=library)
    data = bytearray((tmp_path / names[1]).read_bytes())
    data[len(data) // 2] ^= 0x10  # one bit in the middle: a mask's packed bits
    (tmp_path / names[1]).write_bytes(bytes(data))
    result = runner.invoke(app, ["inspect", str(tmp_path), "--json"])
    report = json.loads(result.stdout)
    assert report["samples"] == 3 and report["corrupt"] == 1
    assert report["corrupt_reasons"] == {"checksum: mismatch": 1}
    batch = SpoolBatches(tmp_path, "box", 48)[names]
    assert batch.names == [names[0], *names[2:]] and batch.skipped["damaged"] == 1 and batch.skipped["corrupt"] == 0
    batches, skipped = load_batches(tmp_path, "box", 48, batch_size=4, max_samples=None)
    assert skipped["damaged"] == 1 and sum(len(b.names) for b in batches) == 3
