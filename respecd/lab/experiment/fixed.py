"""What one configuration is worth in one scenario: mAP@0.5 with the sensors held fixed.

A diagnosis beside the benchmark (docs/CONTROLLER.md "Reward", docs/RESULTS.md): the benchmark says
which configuration a policy chose and what it scored; this says what each configuration would have
scored on the same worlds, so a loss can be traced to a knob (a stale camera, a radar mode, an RGB
size) before the reward or the scenarios are touched. Every configuration is scored at the same
instants: ``per_s`` a second at seeded random phases inside each second (a fixed phase would favour
the rates whose frames happen to fall just before it), on the frames that configuration delivers,
through the same cached detector outcomes as the benchmark.

usage: respecd experiment fixed SCENARIO --seeds 503,510,517 \\
           "rgb 640x360@1 thermal 160x120@9 radar range@1" "rgb 640x360@off thermal 160x120@9 radar range@1"
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from respecd.argtypes import positive_float, resolution, seed_list
from respecd.errors import InputError
from respecd.lab.detector.metrics import ImageResult, average_precision
from respecd.messages import SensorConfig

MODES = ("range", "velocity")


@dataclass(frozen=True)
class Scored:
    """One configuration's figures: pooled over worlds, and per world (in ``seeds`` order)."""

    map50: float
    conf_agg: float
    map50_by_world: tuple[float, ...]


def parse_configuration(text: str) -> dict[str, SensorConfig]:
    """'rgb 640x360@1 thermal 160x120@9 radar range@5' -> a SensorConfig per modality.

    ``@off`` disables an input (the detector sees it as turned off); the RGB camera keeps its size,
    at which the ground truth is drawn. The RGB camera is required."""
    words = text.split()
    if len(words) % 2:
        raise InputError(f"configuration {text!r}: expected pairs of MODALITY SETTING@RATE")
    out: dict[str, SensorConfig] = {}
    for modality, cell in zip(words[::2], words[1::2], strict=True):
        setting, sep, rate_text = cell.partition("@")
        if not sep or modality in out or modality not in ("rgb", "thermal", "radar"):
            raise InputError(f"configuration {text!r}: {modality} {cell}: expected rgb, thermal or radar once each, "
                             "as SETTING@RATE (640x360@5, range@10, ...@off)")
        enabled = rate_text != "off"
        try:
            rate = float(rate_text) if enabled else 1.0
        except ValueError:
            raise InputError(f"configuration {text!r}: {cell}: expected a rate in Hz or off") from None
        if not 0.0 < rate <= 60.0:
            raise InputError(f"configuration {text!r}: {cell}: expected a rate in (0, 60] Hz")
        if modality == "radar":
            if setting not in MODES:
                raise InputError(f"configuration {text!r}: radar {cell}: expected a mode of {', '.join(MODES)}")
            out[modality] = SensorConfig("radar", enabled, rate, None, setting)  # type: ignore[arg-type]
        else:
            out[modality] = SensorConfig(modality, enabled, rate, resolution(setting, f"configuration {modality}"))  # type: ignore[arg-type]
    if "rgb" not in out:
        raise InputError(f"configuration {text!r}: expected an rgb entry (its size places the ground truth)")
    return out


def instants(seed: int, duration_s: float, per_s: int) -> list[tuple[int, float]]:
    """(second, instant) pairs: ``per_s`` instants in each second at seeded random phases."""
    rng = np.random.default_rng(seed)
    return [(k, k + (j + rng.uniform(0.02, 0.98)) / per_s) for k in range(int(duration_s)) for j in range(per_s)]


def score(evaluator: Any, simulation: Any, scenario: str, seeds: list[int], configs: dict[str, SensorConfig],
          duration_s: float, per_s: int) -> Scored:
    """``configs`` held fixed over every world of ``scenario``."""
    from respecd.lab.experiment.rollout import Piece

    size = configs["rgb"].resolution
    assert size is not None, "parse_configuration gives the RGB camera a size"
    pooled: list[ImageResult] = []
    confs: list[float] = []
    per_world: list[float] = []
    for seed in seeds:
        piece = Piece(scenario, seed, duration_s)
        world = evaluator.world(piece, simulation)
        static = evaluator.static(piece)
        images = []
        for n, (_, t) in enumerate(instants(seed, duration_s, per_s)):
            out = evaluator.outcome(world, configs, t, False, n if static else None)  # n: the static scene's noise slot
            boxes, ignore = evaluator.truth(world, t, size)
            images.append(ImageResult(out.boxes, out.scores, boxes, ignore))
            confs.append(out.conf_agg)  # the detector's own ConfAgg of these boxes
        per_world.append(average_precision(images, 0.5))
        pooled.extend(images)
    return Scored(average_precision(pooled, 0.5), float(np.mean(confs)), tuple(per_world))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from respecd.sim.config import SCENARIOS

    parser.add_argument("scenario", choices=sorted(SCENARIOS))
    parser.add_argument("configuration", nargs="+", help="e.g. 'rgb 640x360@1 thermal 160x120@9 radar range@1'")
    parser.add_argument("--seeds", type=seed_list, required=True,
                        help="world seeds (validation worlds: 500 + 7k + the scenario's index in the profile)")
    parser.add_argument("--profile", default="builtin:sim-rover")
    parser.add_argument("--duration", type=positive_float, default=20.0, help="seconds a world (default 20)")
    parser.add_argument("--per-s", type=int, default=3, choices=range(1, 11), metavar="1..10",
                        help="instants scored a second (default 3)")
    parser.add_argument("--cache-dir", type=Path)
    parser.add_argument("--random-detector", action="store_true", help="an untrained net (smoke tests only)")
    parser.add_argument("--json", type=Path, help="write the figures here too")


def main(a: argparse.Namespace) -> int:
    import json

    from respecd.config import load_profile
    from respecd.lab.experiment.setup import load_detector, make_evaluator
    from respecd.outputs import check_output_dir, check_output_file

    check_output_file("--json", a.json, make_parents=False, example="fixed.json")  # written after the scoring
    check_output_dir("--cache-dir", a.cache_dir)
    configs = {text: parse_configuration(text) for text in a.configuration}
    profile = load_profile(a.profile)
    evaluator = make_evaluator(load_detector(profile, random_init=a.random_detector), profile, True, a.cache_dir)
    figures: dict[str, dict[str, Any]] = {}
    try:
        for text, config in configs.items():
            s = score(evaluator, profile.simulation, a.scenario, a.seeds, config, a.duration, a.per_s)
            figures[text] = {"map50": round(s.map50, 4), "conf_agg": round(s.conf_agg, 4),
                             "map50_by_world": [round(v, 4) for v in s.map50_by_world]}
            worlds = " ".join(f"{v:.3f}" for v in s.map50_by_world)
            print(f"{text}: mAP@0.5 {s.map50:.3f} (worlds {worlds}), ConfAgg {s.conf_agg:.3f}", flush=True)
    finally:
        evaluator.cache.close()
    if a.json:
        doc = {"scenario": a.scenario, "seeds": a.seeds, "duration_s": a.duration, "per_s": a.per_s,
               "configurations": figures}
        a.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return 0
