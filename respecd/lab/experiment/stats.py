"""How sure a benchmark's mAP is: counts and a bootstrap over worlds.

A scenario's scored instants are not independent draws. Within one world the same one to
three people stand (or walk) in front of the same background for the whole run, and in a
static scene the frames differ only in sensor noise (four noise realizations, see
``frames.py``): thirty instants of one world are close to thirty copies of one image. What
varies is the world — where the people stand, how far, the light, the occluder — so the
unit of resampling is the world: per scenario, draw its worlds (one per world set) with
replacement, pool their images and recompute AP@0.5. The same draw serves every policy, so a
difference between two policies (paired: same worlds, same instants) has its own interval,
much narrower than either mAP's, and the headline's comparisons are judged on it.

Per scenario: ``worlds``, ``people`` (persons placed in them), ``instants`` (scored images
per policy), ``targets`` (non-ignored ground-truth boxes over the instants, one policy's:
they do not depend on the policy but for boxes too small at a low resolution), and per
policy the mAP's bootstrap standard error and its range over the world sets.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from respecd.lab.detector.metrics import ImageResult, ap_from_parts, ap_parts

BOOTSTRAP_DRAWS = 1000
Parts = tuple[np.ndarray, np.ndarray, int]  # scores, true-positive flags, ground-truth count


def _pool(parts: Sequence[Parts]) -> float:
    if not parts:
        return float("nan")
    scores = np.concatenate([p[0] for p in parts])
    tp = np.concatenate([p[1] for p in parts])
    return ap_from_parts(scores, tp, sum(p[2] for p in parts))


def _interval(values: np.ndarray) -> list[float] | None:
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return None
    return [round(float(np.percentile(values, 2.5)), 4), round(float(np.percentile(values, 97.5)), 4)]


def _se(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    return round(float(np.std(values, ddof=1)), 4) if len(values) > 1 else None


class WorldBootstrap:
    """AP parts per (policy, scenario, world set), and paired resampling of the worlds.

    ``images[policy][scenario][k]``: the scored images of scenario ``scenario`` in world set ``k``.
    """

    def __init__(self, images: Mapping[str, Mapping[str, Sequence[list[ImageResult]]]], seed: int = 0,
                 draws: int = BOOTSTRAP_DRAWS) -> None:
        self.policies = list(images)
        self.scenarios = list(next(iter(images.values())))
        self.parts = {p: {s: [ap_parts(world, 0.5) for world in images[p][s]] for s in self.scenarios}
                      for p in self.policies}
        rng = np.random.default_rng([seed, 20])
        self.draws = {s: rng.integers(0, len(self.parts[self.policies[0]][s]),
                                      size=(draws, len(self.parts[self.policies[0]][s])))
                      for s in self.scenarios}
        self.n_draws = draws

    def _resampled(self, policy: str, scenarios: Sequence[str]) -> np.ndarray:
        """AP@0.5 of each bootstrap draw, pooling the drawn worlds of ``scenarios``."""
        out = np.empty(self.n_draws)
        for b in range(self.n_draws):
            out[b] = _pool([self.parts[policy][s][k] for s in scenarios for k in self.draws[s][b]])
        return out

    def scenario(self, scenario: str) -> dict[str, Any]:
        """Per policy: the bootstrap standard error of the scenario's mAP, and its range over the sets."""
        out: dict[str, Any] = {}
        for policy in self.policies:
            by_set = [ap_from_parts(*part) for part in self.parts[policy][scenario]]
            finite = [v for v in by_set if np.isfinite(v)]
            out[policy] = {"map50_se": _se(self._resampled(policy, [scenario])),
                           "map50_by_set": [None if not np.isfinite(v) else round(float(v), 4) for v in by_set],
                           "map50_range": [round(min(finite), 4), round(max(finite), 4)] if finite else None}
        return out

    def pooled(self) -> dict[str, Any]:
        """Each policy's pooled mAP standard error, and 95 % intervals of the paired differences
        the headline is judged on (baseline − rl; static − the best other policy)."""
        draws = {p: self._resampled(p, self.scenarios) for p in self.policies}
        out: dict[str, Any] = {"map50_se": {p: _se(v) for p, v in draws.items()}, "draws": self.n_draws}
        diffs: dict[str, Any] = {}
        for base in ("static", "heuristic"):
            if base in draws and "rl" in draws:
                diffs[f"{base}_minus_rl"] = _interval(draws[base] - draws["rl"])
        others = [p for p in self.policies if p != "static"]
        if "static" in draws and others:
            diffs["static_minus_best_other"] = _interval(draws["static"] - np.max([draws[p] for p in others], axis=0))
        out["map50_difference_95"] = diffs
        return out


def counts(images: Sequence[list[ImageResult]], people: Sequence[int] | None) -> dict[str, Any]:
    """How much a scenario's mAP rests on: worlds, people, scored instants, ground-truth targets."""
    flat = [im for world in images for im in world]
    return {"worlds": len(images), "people": None if people is None else int(sum(people)),
            "instants": len(flat), "targets": int(sum(int((~im.gt_ignore).sum()) for im in flat))}
