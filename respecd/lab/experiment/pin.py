"""What a table's own run would have been with one sensor's choice pinned.

A diagnosis beside ``fixed`` (which holds every sensor): the table chooses as it would, except that one
column of a factored table — one sensor's setting and rate, as ``respecd policy show`` names it — is taken
wherever that sensor chooses. The run as trained and each pinned run go over the same worlds and
instants, and for each this prints mAP@0.5, the mean reward and its terms, compute and bandwidth, and
whether the pinned run saw the same sequence of states. Same states and a higher reward mean that on these
worlds the table's choice for that sensor is not what its reward asks for: an artefact of how its values were
learned, or a hedge against what the same states lead to in other worlds (a still state whose people start
walking) — docs/journal/2026-12-05-results-m44-uncapped.md "Where the agent wins and where it loses".

usage: respecd experiment pin good-light-static --seeds 500,507,514 \\
           --profile respecd/lab/profiles/sim-rover-per-sensor-slowest-44-immediate.yaml \\
           --latency cpu "rgb 640x360@1Hz"
"""

from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from respecd.argtypes import positive_float, seed_list
from respecd.control.qlearning import FactoredQTable, block_spans
from respecd.errors import InputError
from respecd.lab.detector.metrics import average_precision

TERMS = ("conf_agg", "power", "latency", "staleness", "bandwidth", "switch")


@dataclass(frozen=True)
class PinnedRun:
    """One run's figures: per decision window, means of the reward and its terms."""

    windows: int
    map50: float
    reward: float
    terms: dict[str, float]
    compute_ms_per_s: float
    bandwidth_mb_s: float
    states: tuple[str, ...]  # the state seen at the end of each window, in order

    def busiest(self, n: int = 3) -> list[tuple[str, int]]:
        return collections.Counter(self.states).most_common(n)

    def states_differing(self, reference: PinnedRun) -> int:
        """Windows whose state differs from ``reference``'s (same worlds, so the same window count)."""
        return sum(a != b for a, b in zip(self.states, reference.states, strict=True))


def pin(table: FactoredQTable, column: int) -> None:
    """Make ``column`` its block's choice in every state: one above the block's best value, and counted
    as tried wherever the block was (exploit's "never learned here" test reads the visits)."""
    start, end = next((a, b) for a, b in block_spans(table.blocks) if a <= column < b)
    table.q[:, column] = table.q[:, start:end].max(axis=1) + 1.0
    tried = table.visits[:, start:end].sum(axis=1) > 0
    table.visits[tried, column] = np.maximum(table.visits[tried, column], 1)


def column_of(controller: Any, name: str) -> int:
    """The table column ``name`` ('rgb 640x360@1Hz', as `respecd policy show` prints the cells)."""
    names = controller.space.descriptions()
    if controller.space.mode != "factored":
        raise InputError("the table is not factored: a sensor's choice is not a column of its own")
    if name not in names:
        raise InputError(f"{name!r} is not a column of this table; expected one of: {', '.join(names)}")
    return names.index(name)


def run(controller: Any, rollout: Any, pieces: list[Any]) -> PinnedRun:
    """``controller`` over ``pieces`` in sequence (one rollout, as the benchmark runs a world set)."""
    records = rollout.run(controller, pieces)
    terms = {k: float(np.mean([r.decision.terms.get(k, 0.0) for r in records])) for k in TERMS}
    images = [image for r in records for image in r.images]
    return PinnedRun(
        windows=len(records),
        map50=average_precision(images, 0.5) if images else 0.0,
        reward=float(np.mean([r.decision.reward for r in records])),
        terms=terms,
        compute_ms_per_s=float(np.mean([r.compute_ms for r in records])),
        bandwidth_mb_s=float(np.mean([r.bandwidth_bps for r in records])) / 1e6,
        states=tuple(controller.states.describe(r.decision.state) for r in records),
    )


def as_json(result: PinnedRun, reference: PinnedRun) -> dict[str, Any]:
    return {"windows": result.windows, "map50": round(result.map50, 4), "reward": round(result.reward, 4),
            "terms": {k: round(v, 4) for k, v in result.terms.items()},
            "compute_ms_per_s": round(result.compute_ms_per_s, 1), "bandwidth_mb_s": round(result.bandwidth_mb_s, 3),
            "same_states": not result.states_differing(reference), "busiest_states": result.busiest()}


def line(label: str, result: PinnedRun, reference: PinnedRun) -> str:
    differ = result.states_differing(reference)
    same = "same states" if not differ else f"states differ in {differ} of {result.windows} windows"
    terms = result.terms
    return (f"{label}: mAP@0.5 {result.map50:.3f}, reward {result.reward:.4f} a decision (ConfAgg "
            f"{terms['conf_agg']:.3f}, power {terms['power']:.4f}, bandwidth {terms['bandwidth']:.4f}), "
            f"{result.compute_ms_per_s:.0f} ms/s, {result.bandwidth_mb_s:.2f} MB/s; {same}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from respecd.sim.config import SCENARIOS

    parser.add_argument("scenario", choices=sorted(SCENARIOS))
    parser.add_argument("column", nargs="+", help="a table column to pin, e.g. 'rgb 640x360@1Hz'")
    parser.add_argument("--seeds", type=seed_list, required=True, help="world seeds, run in this order")
    parser.add_argument("--table", type=Path, help="Q-table (default: the shipped one)")
    parser.add_argument("--profile", default="builtin:sim-rover", help="the profile whose reward the terms follow")
    parser.add_argument("--latency", default="orin-nano",
                        help="latency table: orin-nano (default), cpu or a file")
    parser.add_argument("--duration", type=positive_float, default=20.0, help="seconds a world (default 20)")
    parser.add_argument("--cache-dir", type=Path)
    parser.add_argument("--random-detector", action="store_true", help="an untrained net (smoke tests only)")
    parser.add_argument("--json", type=Path, help="write the figures here too")


def main(a: argparse.Namespace) -> int:
    import json

    from respecd.config import load_profile
    from respecd.control.shipped import shipped_table_path
    from respecd.lab.experiment import platforms
    from respecd.lab.experiment.compare import rl_controller
    from respecd.lab.experiment.rollout import Piece, Rollout
    from respecd.lab.experiment.setup import load_detector, make_evaluator, rgb_resolutions
    from respecd.outputs import check_output_dir, check_output_file

    check_output_file("--json", a.json, make_parents=False, example="pin.json")  # written after the runs
    check_output_dir("--cache-dir", a.cache_dir)
    profile = load_profile(a.profile)
    table = a.table or shipped_table_path()
    reference_controller = rl_controller(profile, table)
    columns = [column_of(reference_controller, name) for name in a.column]
    latency = platforms.resolve(a.latency, rgb_resolutions(reference_controller)).latency
    evaluator = make_evaluator(load_detector(profile, random_init=a.random_detector), profile, True, a.cache_dir)
    rollout = Rollout(profile, evaluator, latency)
    pieces = [Piece(a.scenario, seed, a.duration) for seed in a.seeds]
    try:
        reference = run(reference_controller, rollout, pieces)
        print(line("as trained", reference, reference), flush=True)
        figures = {"as trained": as_json(reference, reference)}
        for name, column in zip(a.column, columns, strict=True):
            controller = rl_controller(profile, table)
            pin(controller.table, column)
            result = run(controller, rollout, pieces)
            print(line(f"{name} pinned", result, reference), flush=True)
            figures[name] = as_json(result, reference)
    finally:
        evaluator.cache.close()
    if a.json:
        doc = {"scenario": a.scenario, "seeds": a.seeds, "duration_s": a.duration, "table": str(table),
               "profile": profile.name, "runs": figures}
        a.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return 0
