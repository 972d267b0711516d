"""A numeric library's thread count held for a block and restored after: one core's pace, one order of sums."""
from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator


@contextlib.contextmanager
def threads_held(get: Callable[[], int], set_count: Callable[[int], object], count: int = 1) -> Iterator[None]:
    """`set_count(count)` inside the block, the count `get()` gave restored after (also on an error).
    For torch (`torch.get_num_threads`, `torch.set_num_threads`) or OpenCV (`cv2.getNumThreads`,
    `cv2.setNumThreads`): a library's parallel loops sum in another order on another thread count."""
    before = get()
    set_count(count)
    try:
        yield
    finally:
        set_count(before)
