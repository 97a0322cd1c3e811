"""Image statistics for the state: block means on a fixed grid, and a noise-relative motion score.

Every image, whatever its resolution, is read as 36×64 blocks; each block is the mean of a
4×4 pixel patch at the block's centre (two ``take`` gathers of 144 rows and 256 columns,
then an exact 4×4 area average: cheap enough for the event loop and independent of the
resolution the controller chose; docs/PERFORMANCE.md "controller").
Averaging the patch divides per-pixel sensor noise by 4, and the fixed grid lets two frames
of different resolutions be compared block by block.

Motion is scored as p99 / median of the absolute block change between consecutive frames.
The median block change measures the noise (shot noise grows with the auto-exposure gain
in the dark); the 99th percentile is what the few blocks covering a moving person do. For
a static scene the ratio is ~3.5–4 in any light (measured on the simulator's six
scenarios); a walking person lifts it to 5–50 depending on the frame interval. Being a
ratio, it needs no units: it works the same on RGB luminance and on thermal counts.

Block means are taken in float (QUANTIZATION). An integer image's block mean rounded back to
whole counts, as ``cv2.resize`` does for uint8/uint16 input, turns a low-noise stream's
block changes into a few integers: on the simulated thermal camera (noise under one
centikelvin count per block) the median change became exactly 1 count and the 99th
percentile 4 or 5, so a static scene scored exactly 4.0 or 5.0, and 5.0 sits on the
still/slow edge: in the four static scenarios 26-100 % of the windows read "slow". In float
the same frames score 3.5-4.2.
"""

from __future__ import annotations

import cv2
import numpy as np

BLOCKS = (36, 64)  # rows, cols
PATCH = 4  # pixels per side averaged per block
NOISE_FLOOR = 1e-3  # median change below this (0..1 scale) counts as this: a noiseless render
_BGR_LUMA = np.array([0.114, 0.587, 0.299], dtype=np.float32) / 255.0  # Rec. 601, BGR order


class BlockSampler:
    """Block means of an image; the gather indices are cached per image size."""

    def __init__(self) -> None:
        self._index: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def blocks(self, image: np.ndarray) -> np.ndarray:
        """(36, 64) float32 block means: luminance 0..1 for BGR uint8, raw units otherwise."""
        rows, cols = self._indices(image.shape[0], image.shape[1])
        patches = image.take(rows, axis=0).take(cols, axis=1)  # (36*4, 64*4[, 3]); take beats fancy indexing 8x
        # INTER_AREA at an exact 4x integer ratio is the plain 4x4 block mean. In float: on an
        # integer image cv2 rounds the mean back to whole counts, which undoes the noise
        # averaging and quantizes the motion score (see QUANTIZATION in the module docstring)
        means = cv2.resize(patches.astype(np.float32), (BLOCKS[1], BLOCKS[0]), interpolation=cv2.INTER_AREA)
        if means.ndim == 3:
            return means @ _BGR_LUMA  # BGR 0..255 -> luminance 0..1
        return means

    def _indices(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        key = (height, width)
        if key not in self._index:
            self._index[key] = (_axis(height, BLOCKS[0]), _axis(width, BLOCKS[1]))
        return self._index[key]


def _axis(size: int, blocks: int) -> np.ndarray:
    """Pixel indices of PATCH adjacent pixels at each block centre (clipped to the image)."""
    centres = ((np.arange(blocks) + 0.5) * size / blocks).astype(np.intp)
    start = np.clip(centres - PATCH // 2, 0, max(size - PATCH, 0))
    return np.minimum(start[:, None] + np.arange(PATCH)[None, :], size - 1).reshape(-1)


class MotionMeter:
    """Frame-to-frame motion score of one image stream (see the module docstring)."""

    def __init__(self) -> None:
        self._last: np.ndarray | None = None
        self._last_key: tuple[int, tuple[int, ...]] | None = None

    def seen(self, seq: int, shape: tuple[int, ...]) -> bool:
        """``update`` would return None for this frame: it is the one scored last."""
        return self._last_key is not None and seq == self._last_key[0]

    def update(self, seq: int, shape: tuple[int, ...], blocks: np.ndarray, scale: float = 1.0) -> float | None:
        """Score against the previous frame; None for the first frame, a repeat of the same
        frame (a slow camera sits in several bundles) or a resolution change."""
        key = (seq, shape)
        if self._last_key is not None and key[0] == self._last_key[0]:
            return None
        previous, previous_shape = self._last, self._last_key[1] if self._last_key else None
        self._last, self._last_key = blocks, key
        if previous is None or previous_shape != shape:
            return None
        change = np.abs(blocks - previous).ravel() / scale
        k = change.size
        ranked = np.partition(change, (k // 2, int(k * 0.99)))
        return float(ranked[int(k * 0.99)] / max(float(ranked[k // 2]), NOISE_FLOOR))


def spread(blocks: np.ndarray) -> float:
    """Robust value range of a non-luminance image (thermal counts), for a unit-free change."""
    low, high = np.percentile(blocks, (1, 99))
    return max(float(high - low), 1e-9)
