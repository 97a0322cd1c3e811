"""The discrete state: six window-averaged factors in three ordinal bins each, plus the
dominant contribution modality.

``Observation`` is the window summary the stage builds from percepts and system probes
(see ``features.py``); ``StateSpace`` turns it into bin indices and one table index, and
back into named bins for logs and ``respecd policy show``. Pure and allocation-light: it
runs once per decision and sits inside the benchmarked step.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from respecd.control.config import Factor, Thresholds

BIN_NAMES: dict[str, tuple[str, str, str]] = {
    "illumination": ("dark", "dim", "bright"),
    "motion": ("still", "slow", "fast"),
    "radar_density": ("sparse", "medium", "dense"),
    "load": ("low", "medium", "high"),
    "sync": ("good", "fair", "poor"),
    "confidence": ("low", "medium", "high"),
}
NO_CONTRIBUTION = "none"


def bin3(value: float, edges: tuple[float, float]) -> int:
    """0 below ``low``, 1 from ``low`` up to (not including) ``high``, 2 at or above ``high``."""
    low, high = edges
    if value < low:
        return 0
    return 1 if value < high else 2


def motion_bin(obs: Observation, thresholds: Thresholds) -> int:
    """Still 0, slow 1, fast 2: the larger of the image and IMU bins (a still robot watching
    a moving target is still "moving"); the reward needs it even when the state omits it."""
    image = 0 if obs.motion_image is None else bin3(obs.motion_image, thresholds.motion_image)
    imu = 0 if obs.motion_imu is None else bin3(obs.motion_imu, thresholds.motion_imu_rad_s)
    return max(image, imu)


@dataclass(frozen=True, slots=True)
class Observation:
    """Window averages the state is computed from (None: no such signal in the window)."""

    t: float
    n_percepts: int = 0
    illumination: float | None = None  # mean RGB luminance, 0..1
    motion_image: float | None = None  # p99 / median block change between frames (imagestats)
    motion_imu: float | None = None  # mean gyro norm, rad/s
    radar_points: float | None = None  # mean points per radar frame
    load: float = 0.0  # max(CPU share, GPU share, latency / budget), 0..1
    latency_s: float = 0.0  # mean perception latency
    busy: float = 0.0  # detector seconds per second (sum of inference latencies / window)
    sync: float = 0.0  # mean synchronizer health, good=0 fair=1 poor=2
    conf_agg: float = 0.0  # mean ConfAgg
    truth_quality: float | None = None  # training only: mean F1 against the simulator's ground truth
    contributions: Mapping[str, float] | None = None  # mean scene score per modality
    power_w: float | None = None  # measured board power (rails); None: use the power model


def dominant(contributions: Mapping[str, float] | None, modalities: Sequence[str]) -> str:
    """The modality with the largest contribution among ``modalities`` ('none' if unknown)."""
    if not contributions:
        return NO_CONTRIBUTION
    best, best_score = NO_CONTRIBUTION, 0.0
    for modality in modalities:
        score = contributions.get(modality, 0.0)
        if score > best_score:
            best, best_score = modality, score
    return best


class StateSpace:
    """Named factors × bins ↔ one integer index (mixed radix, first factor most significant)."""

    def __init__(
        self,
        factors: Sequence[Factor],
        thresholds: Thresholds,
        contribution_modalities: Sequence[str] = (),
    ) -> None:
        self.factors: tuple[str, ...] = tuple(factors)
        self.thresholds = thresholds
        self.bin_names: list[tuple[str, ...]] = [BIN_NAMES[f] for f in self.factors]
        self.contribution_modalities = tuple(contribution_modalities)
        self._binners = [self._binner(f) for f in self.factors]
        if self.contribution_modalities:
            self.factors += ("dominant",)
            self.bin_names.append((NO_CONTRIBUTION, *self.contribution_modalities))
        self.dims = tuple(len(b) for b in self.bin_names)
        self.size = 1
        for d in self.dims:
            self.size *= d

    def bins(self, obs: Observation) -> tuple[int, ...]:
        """Bin index per factor for one observation."""
        out = [binner(obs) for binner in self._binners]
        if self.contribution_modalities:
            name = dominant(obs.contributions, self.contribution_modalities)
            out.append(self.bin_names[-1].index(name))
        return tuple(out)

    def _binner(self, factor: str) -> Callable[[Observation], int]:
        """One small function per factor, built once (bins() runs inside the timed step)."""
        th = self.thresholds
        if factor == "illumination":
            # unknown light (no RGB frame yet) is the middle bin, not "dark"
            return lambda o: 1 if o.illumination is None else bin3(o.illumination, th.illumination)
        if factor == "motion":
            return lambda o: motion_bin(o, th)
        if factor == "radar_density":
            return lambda o: 0 if o.radar_points is None else bin3(o.radar_points, th.radar_points)
        if factor == "load":
            return lambda o: bin3(o.load, th.load)
        if factor == "sync":
            return lambda o: bin3(o.sync, th.sync)
        return lambda o: bin3(o.conf_agg, th.confidence)

    def distances(self, bins: Sequence[int], others: np.ndarray) -> np.ndarray:
        """How far ``bins`` lies from each row of ``others`` (states as bins): ordinal factors
        count the bins between (dark is further from bright than dim is), the dominant modality
        counts 1 when it differs."""
        gaps = np.abs(others - np.asarray(bins))
        if self.contribution_modalities:
            gaps[:, -1] = gaps[:, -1] > 0
        return gaps.sum(axis=1)

    def index(self, bins: Sequence[int]) -> int:
        idx = 0
        for b, d in zip(bins, self.dims, strict=True):
            if not 0 <= b < d:
                raise ValueError(f"bin {b} out of range 0..{d - 1}")
            idx = idx * d + b
        return idx

    def unindex(self, index: int) -> tuple[int, ...]:
        if not 0 <= index < self.size:
            raise ValueError(f"state index {index} out of range 0..{self.size - 1}")
        out = []
        for d in reversed(self.dims):
            index, b = divmod(index, d)
            out.append(b)
        return tuple(reversed(out))

    def names(self, bins: Sequence[int]) -> dict[str, str]:
        return {f: names[b] for f, names, b in zip(self.factors, self.bin_names, bins, strict=True)}

    def from_names(self, names: Mapping[str, str]) -> tuple[int, ...]:
        """Bins from named values, e.g. {'illumination': 'dark', ...} (every factor required)."""
        return tuple(bn.index(names[f]) for f, bn in zip(self.factors, self.bin_names, strict=True))

    def describe(self, bins: Sequence[int]) -> str:
        return "/".join(self.names(bins).values())

    def parse(self, text: str) -> tuple[int, ...]:
        """The bins ``describe`` wrote ('bright/still/dense/medium/good/high/rgb'); ValueError saying what a
        state's text must hold."""
        values = text.split("/")
        if len(values) != len(self.factors):
            raise ValueError(f"state {text!r}: expected {len(self.factors)} values joined by '/', "
                             f"for {', '.join(self.factors)}")
        try:
            return self.from_names(dict(zip(self.factors, values, strict=True)))
        except ValueError:
            choices = "; ".join(f"{f}: {', '.join(b)}" for f, b in zip(self.factors, self.bin_names, strict=True))
            raise ValueError(f"state {text!r}: a value is not a bin of its factor ({choices})") from None

    def fingerprint_data(self) -> dict[str, Any]:
        """The table's row layout (thresholds are not part of it: retuning keeps the table)."""
        return {"factors": list(self.factors), "bins": [list(b) for b in self.bin_names]}
