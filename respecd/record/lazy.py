"""Logged frames whose pixels are decoded on first use.

A replay serves every logged RGB frame, but the detector runs on a few of them (a 30 Hz
camera and a detector at ~10 Hz: two of three frames are superseded before anything looks
at their pixels). Decoding a 640x360 JPEG costs about as much CPU as everything else the
replay does with the frame (a PNG more), so a ``LazyFrame`` carries the encoded bytes and its size, and
decodes when ``data`` is first read — in whichever thread needs the pixels (usually the
detector's worker), once, under a lock. Everything else (rate decimation, pairing, queues)
only needs ``t``, ``seq``, ``meta`` and the size.

It is a ``Frame`` (same fields, frozen, ``dataclasses.replace`` works and decodes), so no
consumer needs to know. A replay's resize is deferred the same way (``derive``), and a pure
upscale remembers its source (``upscale_of``), so that a consumer that resamples anyway (the
detector's aligner warps thermal into the RGB view) can resample the logged pixels once
instead of twice.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from respecd.errors import UndecodableImageError
from respecd.messages import Frame, Modality

_DATA = Frame.__dict__["data"]  # the slot that holds a Frame's pixels
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}  # start-of-frame markers
_NO_LENGTH = {0x01, 0xD8, *range(0xD0, 0xD8)}  # markers without a length field


class LazyFrame(Frame):
    """A ``Frame`` whose ``data`` is produced by ``decode()`` the first time it is read."""

    __slots__ = ("_decode", "_lock", "_shape", "upscale_of")
    _decode: Callable[[], np.ndarray] | None
    _lock: threading.Lock
    _shape: tuple[int, ...]
    upscale_of: Frame | None

    def __init__(self, modality: Modality, t: float, seq: int, data: np.ndarray | None = None,
                 meta: dict[str, Any] | None = None, *, decode: Callable[[], np.ndarray] | None = None,
                 shape: tuple[int, ...] | None = None, upscale_of: Frame | None = None) -> None:
        if data is None and (decode is None or shape is None):
            raise ValueError("a LazyFrame needs data, or decode and shape")
        for name, value in (("modality", modality), ("t", t), ("seq", seq), ("meta", {} if meta is None else meta),
                            ("_decode", decode), ("_lock", threading.Lock()), ("upscale_of", upscale_of),
                            ("_shape", tuple(data.shape) if data is not None else shape)):
            object.__setattr__(self, name, value)
        if data is not None:
            _DATA.__set__(self, data)

    @property
    def data(self) -> np.ndarray:
        try:
            return _DATA.__get__(self, Frame)
        except AttributeError:
            pass
        with self._lock:
            try:
                return _DATA.__get__(self, Frame)
            except AttributeError:
                assert self._decode is not None
                try:
                    data = self._decode()
                except UndecodableImageError as err:  # say which frame: the decoder only saw bytes
                    raise UndecodableImageError(f"{self.modality} frame {self.seq} (t {self.t:.3f} s): {err}") from None
                _DATA.__set__(self, data)
                object.__setattr__(self, "_decode", None)  # the encoded bytes can go
                return data

    @property
    def shape(self) -> tuple[int, ...]:
        return self._shape

    @property
    def decoded(self) -> bool:
        try:
            _DATA.__get__(self, Frame)
        except AttributeError:
            return False
        return True



def derive(frame: Frame, transform: Callable[[np.ndarray], np.ndarray], shape: tuple[int, ...],
           meta: dict[str, Any], upscale: bool = False) -> LazyFrame:
    """``frame`` after ``transform`` of its pixels, run when they are first read. ``upscale``:
    the result holds nothing its source did not (``upscale_of`` names that source)."""
    source = getattr(frame, "upscale_of", None) or frame
    return LazyFrame(frame.modality, frame.t, frame.seq, meta=meta, decode=lambda: transform(frame.data), shape=shape,
                     upscale_of=source if upscale else None)


def jpeg_shape(data: bytes | memoryview) -> tuple[int, ...] | None:
    """(height, width[, channels]) as ``cv2.imdecode(IMREAD_UNCHANGED)`` gives a JPEG, read
    from its start-of-frame marker; None when the bytes are not a JPEG this can size."""
    buf = bytes(data[:65536]) if len(data) > 65536 else bytes(data)
    if buf[:2] != b"\xff\xd8":
        return None
    i, n = 2, len(buf)
    while i + 4 <= n:
        if buf[i] != 0xFF:
            return None
        marker = buf[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _NO_LENGTH:
            i += 2
            continue
        if marker in _SOF and i + 10 <= n:
            height, width = int.from_bytes(buf[i + 5:i + 7], "big"), int.from_bytes(buf[i + 7:i + 9], "big")
            components = buf[i + 9]
            if height == 0 or width == 0 or components not in (1, 3):
                return None
            return (height, width) if components == 1 else (height, width, 3)
        i += 2 + int.from_bytes(buf[i + 2:i + 4], "big")
    return None


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 6: 4}  # IHDR colour type -> channels cv2.imdecode(IMREAD_UNCHANGED) gives


def png_shape(data: bytes | memoryview) -> tuple[int, ...] | None:
    """(height, width[, channels]) of a PNG from its IHDR chunk, as ``cv2.imdecode(IMREAD_UNCHANGED)``
    gives it; None for what this does not size (palette, grey with alpha, not a PNG)."""
    head = bytes(data[:26])
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    channels = _PNG_CHANNELS.get(head[25])
    if channels is None or width == 0 or height == 0:
        return None
    return (height, width) if channels == 1 else (height, width, channels)


def encoded_shape(data: bytes | memoryview) -> tuple[int, ...] | None:
    """The decoded shape of a JPEG or PNG, read from its header (None: decode to know)."""
    return jpeg_shape(data) if bytes(data[:2]) == b"\xff\xd8" else png_shape(data)
