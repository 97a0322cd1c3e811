"""What any policy could reach by holding one configuration per scene: the accuracy-load frontier.

A bound for docs/RESULTS.md ("What limits the agent"), not a policy: every configuration of a
small family is run as ``static`` on the benchmark's worlds and instants, under the same
accelerator and latency table — every sensor at one rate (the detector runs on every new
frame of its fastest input, so a slower sensor beside a faster one saves bytes, not load), each
RGB and thermal size, the radar in range mode, an attributed pass each decision as for every
policy. Then, told each world's scenario (what no policy is told) and scored on the very worlds
it chooses on, a greedy descent from the most accurate choice per scenario trades the least
pooled mAP@0.5 per unit of load saved, one scenario at a time: each step is a point of the
frontier. ``--against`` reads a ``bench scenarios`` JSON of the same worlds and says, for each
of its policies, the least load the frontier needs within ``--tolerance`` of its mAP@0.5. Chosen on
the worlds it is scored on, the frontier is optimistic; ``--choices-from`` scores another run's
frontier (chosen on validation worlds) on these worlds, which is not.

usage: respecd experiment frontier --seed 8000 --worlds 5 --duration 30 [--latency orin-nano]
       [--jobs 2] [--against docs/results.json] [--choices-from VALIDATION.json] [--json OUT]
"""

from __future__ import annotations

import argparse
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from respecd.lab.detector.metrics import ImageResult, average_precision

RADAR_MODE = "range"


@dataclass
class Cell:
    """One configuration in one scenario, over every world set: what was scored, what it cost."""

    images: list[ImageResult] = field(default_factory=list)
    busy: list[float] = field(default_factory=list)  # the accelerator's share, per decision window
    read_bps: list[float] = field(default_factory=list)  # bandwidth of the sensors the detector reads

    @property
    def map50(self) -> float:
        return average_precision(self.images, 0.5)

    @property
    def load(self) -> float:
        return float(np.mean(self.busy)) if self.busy else 0.0


def family(actions: Any) -> dict[str, dict[str, Any]]:
    """The configurations: name -> the action-space fields that pin it (rate, RGB size, thermal size)."""
    out: dict[str, dict[str, Any]] = {}
    for rate, rgb, thermal in itertools.product(actions.rate_levels_hz, actions.rgb_resolutions,
                                                actions.thermal_resolutions):
        label = f"rgb {rgb[0]}x{rgb[1]} thermal {thermal[0]}x{thermal[1]} radar {RADAR_MODE} @{rate:g}"
        out[label] = {"rate_levels_hz": (rate,), "rgb_resolutions": (rgb,), "thermal_resolutions": (thermal,),
                      "radar_modes": (RADAR_MODE,)}
    return out


def pooled(cells: dict[str, Cell]) -> tuple[float, float, float]:
    """(mAP@0.5 over every scored image, mean load and read bandwidth over every window) of one choice."""
    images = [im for c in cells.values() for im in c.images]
    busy = [b for c in cells.values() for b in c.busy]
    read = [b for c in cells.values() for b in c.read_bps]
    return average_precision(images, 0.5), float(np.mean(busy)), float(np.mean(read))


def _efficient(row: dict[str, Cell]) -> list[str]:
    """The scenario's configurations no other beats on both its mAP@0.5 and its load."""
    scored = {name: (cell.map50, cell.load) for name, cell in row.items()}
    return [n for n, (m, ld) in scored.items()
            if not any(m2 >= m and l2 <= ld and (m2, l2) != (m, ld) for m2, l2 in scored.values())]


def point(table: dict[str, dict[str, Cell]], choice: dict[str, str]) -> dict[str, Any]:
    """The pooled figures of one configuration per scenario."""
    m, load, read = pooled({s: table[s][n] for s, n in choice.items()})
    return {"map50": round(m, 4), "accelerator_load": round(load, 4), "bandwidth_read_bps": round(read, 0),
            "choice": dict(choice)}


def descend(table: dict[str, dict[str, Cell]]) -> list[dict[str, Any]]:
    """The frontier, most accurate first: from each scenario's most accurate configuration, move
    one scenario at a time to the cheaper configuration that loses the least pooled mAP@0.5 per
    unit of load saved, until none is cheaper."""
    options = {s: _efficient(row) for s, row in table.items()}
    choice = {s: max(options[s], key=lambda n: (table[s][n].map50, -table[s][n].load)) for s in table}
    points = [point(table, choice)]
    while True:
        here = points[-1]
        best: tuple[float, dict[str, Any]] | None = None
        for s, names in options.items():
            for n in names:
                if table[s][n].load >= table[s][choice[s]].load:
                    continue
                trial = point(table, {**choice, s: n})
                saved = here["accelerator_load"] - trial["accelerator_load"]
                if saved <= 0:
                    continue
                price = (here["map50"] - trial["map50"]) / saved
                if best is None or price < best[0]:
                    best = (price, trial)
        if best is None:
            return points
        choice = best[1]["choice"]
        points.append(best[1])


def cheapest_within(points: list[dict[str, Any]], map50: float, tolerance: float) -> dict[str, Any] | None:
    """The frontier's least-load point at mAP@0.5 ≥ ``map50 − tolerance``; None when none is."""
    near = [p for p in points if p["map50"] >= map50 - tolerance - 1e-9]
    return min(near, key=lambda p: p["accelerator_load"]) if near else None


def against(points: list[dict[str, Any]], bench: dict[str, Any], tolerance: float) -> dict[str, Any]:
    """Per policy of a ``bench scenarios`` JSON: the frontier's least load within ``tolerance`` of its
    mAP@0.5, and the cut that is against the policy's own load."""
    out: dict[str, Any] = {}
    for policy, row in bench["pooled"].items():
        best = cheapest_within(points, row["map50"], tolerance)
        out[policy] = {"map50": row["map50"], "accelerator_load": row["accelerator_load"],
                       "frontier_load": best and best["accelerator_load"],
                       "frontier_map50": best and best["map50"],
                       "load_reduction": best and round(1 - best["accelerator_load"] / row["accelerator_load"], 4)}
    return out


def run(profile_ref: str, seed: int, worlds: int, duration_s: float, latency: str, cache_dir: Path | None = None,
        random_detector: bool = False, jobs: int = 1,
        choices: list[dict[str, str]] | None = None) -> dict[str, Any]:
    """Every configuration of ``family`` on every world set (``jobs`` processes, one outcome cache), then the
    frontier; ``choices`` (another run's frontier) scored on these worlds as ``chosen_elsewhere``."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from respecd.config import load_profile
    from respecd.lab.experiment.setup import run_identity

    profile = load_profile(profile_ref)
    identity = run_identity(profile, seed, worlds, duration_s, latency)  # a bad table fails here
    names = list(family(profile.controller.actions))
    todo = [(profile_ref, seed, worlds, duration_s, latency, cache_dir, random_detector, n) for n in names]
    cells: dict[str, dict[str, Cell]] = {}
    with ProcessPoolExecutor(max(1, jobs), mp_context=get_context("spawn")) as pool:
        for name, per_scenario in zip(names, pool.map(_configuration, todo), strict=True):
            for scenario, cell in per_scenario.items():
                cells.setdefault(scenario, {})[name] = cell
            print(f"{name}: " + " ".join(f"{s} {c.map50:.3f}/{c.load:.3f}" for s, c in per_scenario.items()),
                  flush=True)
    return {**identity,
            "configurations": {s: {name: {"map50": round(c.map50, 4), "accelerator_load": round(c.load, 4)}
                                   for name, c in row.items()} for s, row in cells.items()},
            "frontier": descend(cells), "chosen_elsewhere": [point(cells, c) for c in choices or []]}


def _configuration(job: tuple[Any, ...]) -> dict[str, Cell]:
    """One configuration held by ``static`` on every world set (a worker process): a cell per scenario."""
    from respecd.config import load_profile
    from respecd.lab.experiment.rollout import controller_for
    from respecd.lab.experiment.setup import run_world_sets

    profile_ref, seed, worlds, duration_s, latency, cache_dir, random_detector, name = job
    base = load_profile(profile_ref)
    actions = base.controller.actions
    pinned = actions.model_copy(update=family(actions)[name])
    profile = base.model_copy(update={"controller": base.controller.model_copy(update={"actions": pinned})})
    runs = run_world_sets(profile, lambda: controller_for(profile, "static"), seed, worlds, duration_s, latency,
                          cache_dir, random_detector)
    out: dict[str, Cell] = {}
    for record in itertools.chain.from_iterable(runs):
        cell = out.setdefault(record.scenario, Cell())
        cell.images.extend(record.images)
        cell.busy.append(record.load.busy)
        cell.read_bps.append(record.bandwidth_read_bps)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from respecd.argtypes import positive_int, unit_interval
    from respecd.lab.experiment.setup import add_validation_arguments

    add_validation_arguments(parser)
    parser.add_argument("--random-detector", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--jobs", type=positive_int, default=1, help="configurations run at once (default 1)")
    parser.add_argument("--against", type=Path, help="a bench scenarios JSON of the same worlds to compare")
    parser.add_argument("--choices-from", type=Path,
                        help="another run's --json (e.g. on validation worlds): score its frontier's choices here")
    parser.add_argument("--tolerance", type=unit_interval, default=0.01,
                        help="mAP@0.5 a frontier point may lose against a policy (default 0.01)")
    parser.add_argument("--json", type=Path, help="write every configuration's figures and the frontier here")


def main(a: argparse.Namespace) -> int:
    from respecd.outputs import check_output_dir, check_output_file

    check_output_file("--json", a.json, make_parents=False, example="frontier.json")
    check_output_dir("--cache-dir", a.cache_dir)
    bench = _read_bench(a.against, _worlds(a)) if a.against else None
    choices = _read_choices(a.choices_from, a.profile) if a.choices_from else None
    result = run(a.profile, a.seed, a.worlds, a.duration, a.latency, a.cache_dir, a.random_detector, a.jobs,
                 choices)
    for key in ("frontier", "chosen_elsewhere"):
        for p in result[key]:
            print(f"{key}: mAP@0.5 {p['map50']:.3f} load {p['accelerator_load']:.3f} "
                  f"read {p['bandwidth_read_bps'] / 1e6:.2f} MB/s")
    for key, points in (("against", result["frontier"]), ("against_chosen_elsewhere", result["chosen_elsewhere"])):
        if bench is None or not points:
            continue
        result[key] = against(points, bench, a.tolerance)
        for policy, row in result[key].items():
            cut = "none within reach" if row["load_reduction"] is None else f"{-row['load_reduction']:+.1%}"
            print(f"{key} {policy}: mAP@0.5 {row['map50']:.3f} load {row['accelerator_load']:.3f}; "
                  f"within {a.tolerance:g}: load {row['frontier_load']} ({cut})")
    if a.json:
        a.json.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    return 0


def _worlds(a: argparse.Namespace) -> dict[str, Any]:
    """What a bench JSON must share with this run to be compared: the table, the worlds, their length."""
    from respecd.config import load_profile
    from respecd.lab.experiment.setup import run_identity

    identity = run_identity(load_profile(a.profile), a.seed, a.worlds, a.duration, a.latency)
    identity["duration_s_per_scenario"] = identity.pop("duration_s")
    return identity


def _read_bench(path: Path, expected: dict[str, Any]) -> dict[str, Any]:
    """A ``bench scenarios`` JSON of the same worlds, read before the long run starts."""
    from respecd.errors import InputError

    try:
        bench = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"--against {path}: not a readable JSON file ({exc})") from None
    rows = bench.get("pooled") if isinstance(bench, dict) else None
    if not isinstance(rows, dict) or not all(isinstance(r, dict) and {"map50", "accelerator_load"} <= set(r)
                                            for r in rows.values()):
        raise InputError(f"--against {path}: expected a bench scenarios JSON with pooled.POLICY.map50 and "
                         ".accelerator_load")
    for key, ours in expected.items():
        if bench.get(key) != ours:
            raise InputError(f"--against {path}: {key} {bench.get(key)!r}, expected {ours!r} (compare a run "
                             "of the same worlds under the same table: --seed, --worlds, --duration, --latency)")
    return bench


def _read_choices(path: Path, profile_ref: str) -> list[dict[str, str]]:
    """The frontier's choices of another run's ``--json``: one configuration of ``family`` per scenario."""
    from respecd.config import load_profile
    from respecd.errors import InputError

    profile = load_profile(profile_ref)
    names, scenarios = set(family(profile.controller.actions)), set(profile.simulation.scenarios)
    try:
        points = json.loads(path.read_text(encoding="utf-8"))["frontier"]
        choices = [dict(p["choice"]) for p in points]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"--choices-from {path}: expected a frontier --json with frontier[].choice "
                         f"({exc!r})") from None
    for i, choice in enumerate(choices):
        if set(choice) != scenarios or not set(choice.values()) <= names:
            raise InputError(f"--choices-from {path}: frontier[{i}].choice is not one configuration of this "
                             f"profile's family per scenario of {sorted(scenarios)}")
    return choices
