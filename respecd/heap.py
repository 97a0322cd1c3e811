"""What the C heap holds: bytes in use and bytes freed but kept (glibc's ``mallinfo2``).

RSS alone cannot tell a leak from an allocator that keeps freed memory: torch's CPU tensors
and the recorder's chunk buffers come from malloc at sizes that change with the sensors'
settings, and glibc keeps the holes they leave. ``in_use`` growing is a leak; ``free_held``
growing is the allocator, whose whole free pages ``trim`` hands back to the kernel.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import cache

MIB = 1024 * 1024


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]


@cache
def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    libc = ctypes.CDLL(name)
    if not hasattr(libc, "mallinfo2") or not hasattr(libc, "malloc_trim"):
        return None  # not glibc >= 2.33 (musl, macOS): nothing to read
    libc.mallinfo2.restype = _MallInfo2
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    libc.malloc_trim.restype = ctypes.c_int
    return libc


def available() -> bool:
    """Whether this C library can be read and trimmed (glibc >= 2.33)."""
    return _libc() is not None


def heap_mb() -> dict[str, float] | None:
    """MiB in use (small blocks + mmapped) and MiB free but held, over all arenas; None off glibc."""
    libc = _libc()
    if libc is None:
        return None
    info = libc.mallinfo2()
    return {"in_use": round((info.uordblks + info.hblkhd) / MIB, 1), "free_held": round(info.fordblks / MIB, 1)}


def trim() -> bool:
    """Give freed heap pages back to the kernel (``malloc_trim(0)``); False off glibc or when none were."""
    libc = _libc()
    return bool(libc is not None and libc.malloc_trim(0))
