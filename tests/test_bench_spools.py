"""The benchmarks' seeded validation spools: asking for more samples gives more distinct ones."""
import sys
from pathlib import Path

from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy"))
from bench_accuracy import spool_for  # noqa: E402


def _seeds(spool: Path) -> list[int]:
    return [decode(read_sample_bytes(spool, name)).seed for name in enumerate_spool(spool)]


def test_a_spool_asked_for_more_is_the_seeded_sequence_longer_not_repeated(tmp_path):
    first = _seeds(spool_for(tmp_path, "box", "street", 3))
    longer = _seeds(spool_for(tmp_path, "box", "street", 7))
    assert len(first) == 3
    assert len(longer) == 7 and len(set(longer)) == 7  # a top-up with the same seed repeated the first three
    assert longer[:3] == first  # and the first masks are the same masks whatever was asked before
