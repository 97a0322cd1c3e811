"""Is static the ceiling? The static policy with one knob held below its maximum.

A diagnosis for docs/RESULTS.md, not a baseline (the benchmark's ``static`` stays "everything
at its maximum"): each smaller RGB resolution, and every rate capped at 10 Hz, with every
other sensor setting at its maximum, scored on the same worlds and instants as the benchmark.
Beside mAP@0.5 it reports the mean ConfAgg at the scored instants, the quality signal the agent's
reward and state read, so one can see whether that signal rises where accuracy does.

usage: respecd experiment probe --seed 500 --worlds 3 --duration 20 [--latency orin-nano|cpu|FILE]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from respecd.argtypes import unit_interval
from respecd.lab.detector.metrics import ImageResult, average_precision
from respecd.messages import conf_agg


def variants(actions: Any) -> dict[str, dict[str, Any]]:
    """The static variants: name -> the action-space fields replaced."""
    out: dict[str, dict[str, Any]] = {"everything at maximum": {}}
    for res in actions.rgb_resolutions[:-1]:
        out[f"rgb {res[0]}x{res[1]}, the rest at maximum"] = {"rgb_resolutions": (res,)}
    out["every rate <= 10 Hz"] = {"rate_levels_hz": tuple(r for r in actions.rate_levels_hz if r <= 10)}
    return out


def mean_conf_agg(images: list[ImageResult]) -> float:
    """Mean ConfAgg (the daemon's: top min(3, N) detections) over scored instants; 0 when none."""
    return sum(conf_agg(image.pred_scores.tolist()) for image in images) / len(images) if images else 0.0


def probe(profile_ref: str | Path, seed: int, worlds: int, duration_s: float, latency: str | Path,
          cache_dir: Path | None = None, random_detector: bool = False,
          score_threshold: float | None = None) -> dict[str, dict[str, dict[str, float]]]:
    """{"map50": {variant: {"pooled": mAP@0.5, scenario: mAP@0.5}}, "conf_agg": {variant: {"pooled":
    mean ConfAgg, scenario: mean ConfAgg}}} over ``worlds`` sets from ``seed`` (``random_detector``: an
    untrained net, for tests; ``score_threshold``: the daemon's box threshold in place of the profile's, to
    see what it hides — the benchmark scores only the boxes the daemon delivers)."""
    from respecd.config import load_profile
    from respecd.lab.experiment.compare import world_sets
    from respecd.lab.experiment.rollout import Rollout, controller_for
    from respecd.lab.experiment.setup import latency_table, load_detector, make_evaluator

    base = load_profile(profile_ref)
    if score_threshold is not None:
        perception = base.perception.model_copy(update={"score_threshold": score_threshold})
        base = base.model_copy(update={"perception": perception})
    evaluator = make_evaluator(load_detector(base, random_init=random_detector), base, True, cache_dir)
    pinned = latency_table(base, latency).latency
    actions = base.controller.actions
    pieces_sets = world_sets(base.simulation.scenarios, seed, worlds, duration_s)
    results: dict[str, dict[str, dict[str, float]]] = {"map50": {}, "conf_agg": {}}
    try:
        for name, change in variants(actions).items():
            controller = base.controller.model_copy(update={"actions": actions.model_copy(update=change)})
            profile = base.model_copy(update={"controller": controller})
            rollout = Rollout(profile, evaluator, pinned, 1.0)
            per: dict[str, list[ImageResult]] = {}
            for pieces in pieces_sets:
                for record in rollout.run(controller_for(profile, "static"), pieces):
                    per.setdefault(record.scenario, []).extend(record.images)
            pooled = [image for images in per.values() for image in images]
            for key, score in (("map50", lambda v: average_precision(v, 0.5)), ("conf_agg", mean_conf_agg)):
                results[key][name] = {"pooled": score(pooled), **{s: score(v) for s, v in per.items()}}
                cells = " ".join(f"{s} {v:.3f}" for s, v in results[key][name].items())
                print(f"{name} ({key}): {cells}", flush=True)
    finally:
        evaluator.cache.close()
    return results


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from respecd.lab.experiment.setup import add_validation_arguments

    add_validation_arguments(parser)
    parser.add_argument("--json", type=Path, help="write the table here too")
    parser.add_argument("--score-threshold", type=unit_interval,
                        help="box score threshold 0..1 (default: the profile's)")


def main(a: argparse.Namespace) -> int:
    import json

    from respecd.outputs import check_output_dir, check_output_file

    check_output_file("--json", a.json, make_parents=False, example="probe.json")  # written after the probe
    check_output_dir("--cache-dir", a.cache_dir)
    table = probe(a.profile, a.seed, a.worlds, a.duration, a.latency, a.cache_dir, score_threshold=a.score_threshold)
    if a.json:
        a.json.write_text(json.dumps(table, indent=2) + "\n", encoding="utf-8")
    return 0
