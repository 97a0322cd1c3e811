"""The bootstrap over worlds: paired, per scenario and pooled, on hand-made detections."""

from __future__ import annotations

import numpy as np
import pytest

from respecd.lab.detector.metrics import ImageResult, average_precision
from respecd.lab.experiment.stats import WorldBootstrap, counts

BOX = np.array([[10.0, 10.0, 50.0, 90.0]])


def image(found: bool, confidence: float = 0.9) -> ImageResult:
    if found:
        return ImageResult(BOX.copy(), np.array([confidence]), BOX.copy())
    return ImageResult(np.zeros((0, 4)), np.zeros(0), BOX.copy())


def worlds(hits: list[bool], instants: int = 3) -> list[list[ImageResult]]:
    """One world per flag: a person found (or missed) at every instant of that world."""
    return [[image(hit) for _ in range(instants)] for hit in hits]


def test_a_policy_that_never_misses_is_certain_and_one_that_misses_a_world_is_not() -> None:
    images = {"static": {"a": worlds([True] * 8)},
              "heuristic": {"a": worlds([True] * 7 + [False])},
              "rl": {"a": worlds([False] + [True] * 7)}}
    boot = WorldBootstrap(images, draws=400)
    per = boot.scenario("a")
    assert per["static"]["map50_se"] == 0.0 and per["static"]["map50_range"] == [1.0, 1.0]
    assert per["rl"]["map50_by_set"] == [0.0] + [1.0] * 7 and per["rl"]["map50_range"] == [0.0, 1.0]
    assert 0.03 < per["rl"]["map50_se"] < 0.2  # one world in eight decides an eighth of the targets
    pooled = boot.pooled()
    assert pooled["map50_se"]["static"] == 0.0
    low, high = pooled["map50_difference_95"]["static_minus_rl"]
    assert low >= 0.0 and high > 0.0  # static is never below rl on any draw of these worlds
    assert pooled["map50_difference_95"]["static_minus_best_other"][0] >= 0.0  # static is the best on every draw


def test_pooled_ap_from_parts_is_the_ap_of_the_pooled_images() -> None:
    rng = np.random.default_rng(3)
    hits = [bool(h) for h in rng.random(6) < 0.6]
    images = {p: {"a": worlds(hits, 2), "b": worlds(hits[::-1], 2)} for p in ("static", "heuristic", "rl")}
    boot = WorldBootstrap(images, draws=50)
    everything = [im for s in ("a", "b") for world in images["rl"][s] for im in world]
    from respecd.lab.experiment.stats import _pool

    parts = [part for s in ("a", "b") for part in boot.parts["rl"][s]]
    assert _pool(parts) == pytest.approx(average_precision(everything, 0.5))


def test_counts_say_what_a_scenario_rests_on() -> None:
    c = counts(worlds([True, False, True], instants=4), people=[1, 2, 3])
    assert c == {"worlds": 3, "people": 6, "instants": 12, "targets": 12}
