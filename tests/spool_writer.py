"""A stand-alone spool writer for the tests' concurrent and kill -9 scenarios.

python -m tests.spool_writer SPOOL LIMIT COUNT EVICT_EVERY SIZE  (COUNT 0 = forever)
"""
import sys

from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidgen.config import PAPER
from shared.sample import encode
from shared.spool import SpoolWriter


def main(spool: str, limit: int, count: int, evict_every: int, size: int) -> None:
    library = OccluderLibrary.builtin(variants_per_kind=1)
    data = [encode(make_sample("box", PAPER, size, seed, library)) for seed in range(8)]
    with SpoolWriter(spool, limit=limit, evict_every=evict_every) as writer:
        print("ready", flush=True)
        i = 0
        while count == 0 or i < count:
            writer.publish(data[i % len(data)])
            i += 1


if __name__ == "__main__":
    main(sys.argv[1], *(int(a) for a in sys.argv[2:6]))
