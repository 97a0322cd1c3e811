"""``respecd.heap``: the C heap's bytes in use and freed-but-held, as glibc counts them."""

from __future__ import annotations

import numpy as np
import pytest

from respecd.heap import heap_mb


def test_in_use_and_free_held_follow_allocations() -> None:
    before = heap_mb()
    if before is None:
        pytest.skip("not glibc: mallinfo2 is not there to read")
    blocks = [np.ones(1000) for _ in range(20_000)]  # 8 KB each, under the mmap threshold: heap blocks
    grown = heap_mb()
    assert grown is not None and grown["in_use"] - before["in_use"] > 140  # 160 MB asked
    del blocks[::2]  # every other block freed: holes the heap keeps
    holed = heap_mb()
    assert holed is not None and holed["free_held"] - grown["free_held"] > 60
    assert grown["in_use"] - holed["in_use"] > 60
