"""Building what every experiment command needs: the profile, the detector, the evaluator
with its cache, and the measured latency table."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from respecd.control.shipped import shipped_table_path
from respecd.lab.experiment.cache import OutcomeCache, fingerprint, model_hash
from respecd.lab.experiment.outcomes import Evaluator

if TYPE_CHECKING:
    from respecd.config import Profile
    from respecd.lab.experiment.platforms import LatencyTable

__all__ = ["add_validation_arguments", "latency_table", "load_detector", "make_evaluator", "perception_identity",
           "rgb_resolutions", "run_identity", "run_world_sets", "shipped_table_path"]

log = structlog.get_logger(__name__)

def load_detector(profile: Profile, weights: str | None = None, random_init: bool = False, seed: int = 0) -> Any:
    """The profile's detector (``weights`` overrides its checkpoint); ``random_init`` for tests."""
    import torch

    from respecd.perception.detector import FusionDetector
    from respecd.perception.model import FusionNet
    from respecd.perception.stage import calibration_from_profile

    torch.set_num_threads(profile.perception.torch_threads)
    config = profile.perception
    if weights:
        config = config.model_copy(update={"weights": weights})
    calibration = calibration_from_profile(profile)
    if random_init:
        torch.manual_seed(seed)
        return FusionDetector(FusionNet(config.model), config, calibration)
    return FusionDetector.load(config, calibration)


def perception_identity(detector: Any, profile: Profile) -> dict[str, Any]:
    """The perception settings that shape an outcome (not device, thread count or runtime: the runtimes give
    the same outcomes in f32, so a cache stays valid; a lower precision is part of the identity)."""
    from respecd.perception.stage import calibration_from_profile

    same = {"device", "torch_threads", "weights", "attribution_every_s", "runtime"}
    if detector.config.precision == "f32":
        same.add("precision")
    settings = detector.config.model_dump(mode="json", exclude=same)
    calibration = {k: (v.model_dump(mode="json") if v is not None else None)
                   for k, v in calibration_from_profile(profile).items()}
    identity = {"settings": settings, "calibration": calibration}
    scores = getattr(detector.model, "score_calibration", None)  # not in the state dict: the card's, per RGB size
    if scores is not None:
        identity["score_calibration"] = scores.to_payload()
    return identity


def make_evaluator(detector: Any, profile: Profile, use_cache: bool = True, directory: Path | None = None) -> Evaluator:
    fp = fingerprint(model_hash(detector.model), perception_identity(detector, profile))
    cache = OutcomeCache.for_fingerprint(fp, directory, enabled=use_cache)
    log.info("outcome_cache", path=str(cache.path) if cache.path else None, fingerprint=fp, entries=len(cache))
    return Evaluator(detector, cache, fp)


def rgb_resolutions(controller: Any) -> list[tuple[int, int]]:
    """Every RGB resolution the controller's action space can select."""
    out: list[tuple[int, int]] = []
    for slot in controller.space.slots:
        if slot.modality == "rgb":
            out += [(int(s[0]), int(s[1])) for s in slot.settings if isinstance(s, tuple)]
    return sorted(set(out), key=lambda r: r[0] * r[1])


def latency_table(profile: Profile, latency: str | Path) -> LatencyTable:
    """The latency table ``latency`` names (a platform or a file) for every RGB size the profile's
    static policy can select; a bad name or file fails here."""
    from respecd.lab.experiment import platforms
    from respecd.lab.experiment.rollout import controller_for

    return platforms.resolve(latency, rgb_resolutions(controller_for(profile, "static")))


def run_identity(profile: Profile, seed: int, worlds: int, duration_s: float, latency: str | Path) -> dict[str, Any]:
    """Which latency table and worlds a run is of: the keys an experiment's JSON shares with ``bench scenarios``'
    (whose duration key is ``duration_s_per_scenario``); a bad table name or file fails here."""
    from respecd.lab.experiment.compare import world_seed_range

    return {"latency_table": latency_table(profile, latency).label(),
            "world_seeds": world_seed_range(seed, worlds, profile.simulation.scenarios), "duration_s": duration_s}


def run_world_sets(profile: Profile, make_controller: Callable[[], Any], seed: int, worlds: int, duration_s: float,
                   latency: str | Path, cache_dir: Path | None = None, random_detector: bool = False) -> list[Any]:
    """A fresh ``make_controller()`` driving the benchmark's rollout (one accelerator, the latency table, one
    scored instant a second) on each of ``worlds`` world sets from ``seed``: one list of window records per set."""
    from respecd.lab.experiment.compare import world_sets
    from respecd.lab.experiment.rollout import Rollout

    table = latency_table(profile, latency)
    evaluator = make_evaluator(load_detector(profile, random_init=random_detector), profile, True, cache_dir)
    rollout = Rollout(profile, evaluator, table.latency, 1.0, table.accelerator_w)
    try:
        return [rollout.run(make_controller(), pieces)
                for pieces in world_sets(profile.simulation.scenarios, seed, worlds, duration_s)]
    finally:
        evaluator.cache.close()


def add_validation_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of a command that runs on validation worlds (seeds 500 on, disjoint from training's and
    every held-out set's): the profile, the worlds, the latency table and the outcome cache."""
    from respecd.argtypes import positive_float, positive_int, seed
    from respecd.lab.experiment.platforms import DEFAULT_PLATFORM

    parser.add_argument("--profile", default="builtin:sim-rover")
    parser.add_argument("--seed", type=seed, default=500, help="first world seed (default 500: validation)")
    parser.add_argument("--worlds", type=positive_int, default=3, help="sets of worlds, at least 1 (default 3)")
    parser.add_argument("--duration", type=positive_float, default=20.0, help="seconds a world (default 20)")
    parser.add_argument("--latency", default=DEFAULT_PLATFORM,
                        help=f"latency table: {DEFAULT_PLATFORM} (default), cpu or a file")
    parser.add_argument("--cache-dir", type=Path)
