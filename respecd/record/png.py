"""Lossless PNG for the recorder: one fixed filter in numpy, deflate by ISA-L.

libpng (``cv2.imencode``) spends most of a 16-bit frame's time in zlib; ISA-L's deflate
(PyPI ``isal``, SIMD) writes a standard zlib stream in far less, and a fixed filter needs
no per-row trial. The file is a plain PNG (signature, IHDR, one IDAT, IEND,
CRC-32 on each chunk) that libpng, browsers and Foxglove read unchanged. Where ``isal``
cannot be imported, OpenCV's encoder writes it (``ENCODER`` says which one runs).
Filters were chosen on simulated and real frames (the journal linked from docs/RECORDING.md):
16-bit samples predict best from the left neighbour (Sub), 8-bit ones from the row above (Up).
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

try:
    from isal import isal_zlib
except ImportError:  # isal is a dependency; the fallback is for a platform without its wheel
    isal_zlib = None  # type: ignore[assignment]

ENCODER = "isal" if isal_zlib is not None else "opencv"  # the recorder logs it once at start
# ISA-L's fast level (0-3) with a 512-byte window and its smallest hash table: camera noise leaves no long
# matches, so the smaller tables stay in cache and find more short ones (as small as libpng's level 1)
LEVEL, WINDOW_BITS, MEM_LEVEL = 1, 9, 2
SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPES = {1: 0, 3: 2, 4: 6}  # channels -> PNG colour type (grey, RGB, RGBA)
_TO_PNG_ORDER = {3: cv2.COLOR_BGR2RGB, 4: cv2.COLOR_BGRA2RGBA}  # OpenCV's channel order to PNG's
_SUB, _UP = 1, 2  # PNG filter types

# OpenCV's encoder (the fallback): zlib level 1, one fixed filter (libpng's adaptive choice costs more than
# it gains; 8-bit colour predicts best from the average of left and up, 16-bit from the left neighbour),
# run-length matches only (flat areas, invalid depth), as noise leaves nothing longer
CV2_PARAMS = {
    1: [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_AVG,
        cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE],
    2: [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB,
        cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE],
}


def encode(image: np.ndarray) -> bytes:
    """``image`` (H, W) or (H, W, 3|4) uint8/uint16, OpenCV's BGR(A) order, as PNG bytes that
    ``cv2.imdecode(..., IMREAD_UNCHANGED)`` gives back exactly."""
    channels = _check(image)
    if isal_zlib is None:
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(image), CV2_PARAMS[image.itemsize])
        if not ok:
            raise ValueError(f"png encoding of a {image.shape} {image.dtype} image failed")
        return buf.tobytes()
    height, width = image.shape[:2]
    rows = _png_rows(image, channels)
    filtered = _filter(rows, channels * image.itemsize, _SUB if image.itemsize == 2 else _UP)
    header = struct.pack(">IIBBBBB", width, height, 8 * image.itemsize, _COLOUR_TYPES[channels], 0, 0, 0)
    deflate = isal_zlib.compressobj(LEVEL, isal_zlib.DEFLATED, WINDOW_BITS, MEM_LEVEL)
    idat = deflate.compress(filtered) + deflate.flush()
    return b"".join((SIGNATURE, _chunk(b"IHDR", header), _chunk(b"IDAT", idat), _chunk(b"IEND", b"")))


def _check(image: np.ndarray) -> int:
    """The channel count of an image PNG holds exactly; ValueError for anything else."""
    channels = image.shape[2] if image.ndim == 3 else 1
    if image.ndim not in (2, 3) or channels not in _COLOUR_TYPES or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"png: cannot encode a {image.shape} {image.dtype} image "
                         "(expected (H, W) or (H, W, 3|4) of uint8 or uint16)")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"png: cannot encode an empty {image.shape} image")
    return channels


def _png_rows(image: np.ndarray, channels: int) -> np.ndarray:
    """(H, W * channels * itemsize) uint8: the samples in PNG's order (RGB, big-endian)."""
    height = image.shape[0]
    if channels in _TO_PNG_ORDER:
        image = cv2.cvtColor(np.ascontiguousarray(image), _TO_PNG_ORDER[channels])
    if image.itemsize == 1:
        return image.reshape(height, -1)  # a view where it can be one; reshape copies otherwise
    return image.astype(">u2", order="C").reshape(height, -1).view(np.uint8)  # one pass: copy and byte swap


def _filter(rows: np.ndarray, pixel_bytes: int, kind: int) -> np.ndarray:
    """The filtered scanlines (filter-type byte, then the row's differences) in one buffer."""
    height, width = rows.shape
    out = np.empty((height, width + 1), np.uint8)
    out[:, 0] = kind
    body = out[:, 1:]
    if kind == _SUB:  # each byte minus the same byte of the pixel to its left
        body[:, :pixel_bytes] = rows[:, :pixel_bytes]
        np.subtract(rows[:, pixel_bytes:], rows[:, :-pixel_bytes], out=body[:, pixel_bytes:])
    else:  # Up: each byte minus the one above it
        body[0] = rows[0]
        np.subtract(rows[1:], rows[:-1], out=body[1:])
    return out


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = isal_zlib.crc32(data, isal_zlib.crc32(kind))
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)
