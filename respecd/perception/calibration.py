"""Confidence calibration per RGB input size (Platt scaling), so a confidence means the same at every size.

The controller changes the RGB resolution online and compares what the detector reports across
the change: ConfAgg is its state and reward, and the daemon drops every box under one score
threshold. The net's raw confidences do not mean the same at each size — a low-scored box is a
real person far more often at 640x360 than at 1280x720 (docs/PERCEPTION.md "Confidence calibration"),
so at 640x360 most people found behind a curtain never reach the threshold.
Platt scaling maps each size's confidence ``p`` to ``sigmoid(a * logit(p) + b)`` with ``(a, b)``
fitted on matched validation boxes (``respecd calibrate``). The map is monotone, so the ranking
at one size, and with it mAP at that size, is unchanged; what moves is which boxes pass the
threshold and what ConfAgg reads. A checkpoint without a calibration keeps its raw confidences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from respecd.argtypes import resolution
from respecd.errors import ConfigError, InputError
from respecd.perception.boxes import pad_to_stride

EPS = 1e-6  # confidences are clipped to [EPS, 1 - EPS] before the logit


@dataclass(frozen=True)
class ScoreCalibration:
    """Platt parameters per RGB frame size ``"WxH"``; another size uses the nearest calibrated height."""

    by_size: dict[str, tuple[float, float]]
    # (padded input height, (a, b)) per size, worked out once: ``params`` runs on every inference
    _by_height: tuple[tuple[int, tuple[float, float]], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        heights = []
        for size, params in self.by_size.items():
            w, h = resolution(size, "score_calibration")
            heights.append((pad_to_stride(h, w)[0], params))
        object.__setattr__(self, "_by_height", tuple(heights))

    @classmethod
    def from_payload(cls, table: object, source: str) -> ScoreCalibration:
        """From a checkpoint's ``score_calibration`` ({"640x360": [a, b], ...}); ConfigError naming ``source``."""
        if not isinstance(table, dict) or not table:
            raise ConfigError(f"{source}: score_calibration: expected a mapping of 'WxH' to [a, b]")
        by_size = {}
        for size, params in table.items():
            if not (isinstance(size, str) and _is_frame_size(size) and isinstance(params, (list, tuple))
                    and len(params) == 2 and all(isinstance(v, (int, float)) and math.isfinite(v) for v in params)):
                raise ConfigError(f"{source}: score_calibration.{size}: expected 'WxH': [a, b] with finite numbers")
            if params[0] <= 0:
                raise ConfigError(f"{source}: score_calibration.{size}: slope a must be > 0 (a monotone map), "
                                  f"got {params[0]}")
            by_size[size] = (float(params[0]), float(params[1]))
        return cls(by_size)

    def to_payload(self) -> dict[str, list[float]]:
        return {size: [a, b] for size, (a, b) in self.by_size.items()}

    def params(self, input_hw: tuple[int, ...]) -> tuple[float, float]:
        """(a, b) for a padded network input of height/width ``input_hw``: the size whose padded height
        is nearest (the three sizes the controller chooses pad to 384, 544 and 736)."""
        return min(self._by_height, key=lambda entry: abs(entry[0] - input_hw[0]))[1]

    def apply(self, scores: torch.Tensor, input_hw: tuple[int, ...]) -> torch.Tensor:
        """Calibrated confidences, same shape; raw ones come from a net's ``decode``."""
        return platt(scores, *self.params(input_hw))


def platt(scores: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """sigmoid(a * logit(p) + b), elementwise."""
    p = scores.clamp(EPS, 1 - EPS)
    return torch.sigmoid(a * torch.log(p / (1 - p)) + b)


def raw_confidence_for(calibrated_confidence: float, a: float, b: float) -> float:
    """The raw confidence that ``platt`` maps to ``calibrated_confidence`` (its inverse)."""
    target = math.log(calibrated_confidence / (1 - calibrated_confidence))
    return 1 / (1 + math.exp(-(target - b) / a))


def calibrated(calibration: ScoreCalibration | None, scores: torch.Tensor, input_hw: tuple[int, ...]) -> torch.Tensor:
    """What a net's ``decode`` returns: its raw confidences when it has no calibration."""
    return scores if calibration is None else calibration.apply(scores, input_hw)


def fit_platt(scores: np.ndarray, is_true: np.ndarray, ridge: float = 1e-3) -> tuple[float, float]:
    """(a, b) minimising the logistic loss of ``is_true`` on ``a * logit(score) + b`` (Newton's method).

    ``ridge`` pulls (a, b) towards the identity (1, 0), so a size with few boxes stays near its raw
    confidences instead of fitting noise."""
    if len(scores) != len(is_true) or len(scores) == 0:
        raise ValueError("fit_platt needs as many true/false flags as scores, at least one")
    p = np.clip(scores.astype(np.float64), EPS, 1 - EPS)
    x = np.log(p / (1 - p))
    y = is_true.astype(np.float64)
    theta = np.array([1.0, 0.0])
    prior = np.array([1.0, 0.0])
    for _ in range(100):
        q = 1 / (1 + np.exp(-(theta[0] * x + theta[1])))
        w = q * (1 - q)
        grad = np.array([((q - y) * x).sum(), (q - y).sum()]) + ridge * len(x) * (theta - prior)
        hess = np.array([[(w * x * x).sum(), (w * x).sum()], [(w * x).sum(), w.sum()]]) + ridge * len(x) * np.eye(2)
        step = np.linalg.solve(hess, grad)
        theta = theta - step
        if np.abs(step).max() < 1e-9:
            break
    return float(theta[0]), float(theta[1])


def expected_calibration_error(scores: np.ndarray, is_true: np.ndarray, bins: int = 10) -> float:
    """Mean |confidence - precision| over equal-width confidence bins, weighted by boxes per bin."""
    if len(scores) == 0:
        return float("nan")
    index = np.minimum((scores * bins).astype(int), bins - 1)
    error = 0.0
    for i in range(bins):
        inside = index == i
        if inside.any():
            error += inside.sum() * abs(scores[inside].mean() - is_true[inside].mean())
    return float(error / len(scores))


def _is_frame_size(size: str) -> bool:
    """'640x360' and the like (``cli.args.resolution``'s rule)."""
    try:
        resolution(size, "score_calibration")
    except InputError:
        return False
    return True
