"""Measured detector wall time per RGB resolution: the basis of every compute figure.

Compute is never assumed: before a run, the real detector runs on real rendered frames at
each RGB resolution of the action space, plain and with attribution, and the median wall
time of a few calls is kept. A policy's compute is then ``forward time at the resolution
it chose x inferences per second`` plus the attribution's extra time once per decision.
The median over repeated calls resists the other processes sharing the CPU; on a machine
that is busy for the whole measurement, ``CLOCKS["cpu"]`` (the process's CPU time) keeps what
a quiet core would take where wall time would count the waits for a core too.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from respecd.errors import InputError
from respecd.lab.experiment.frames import frame_id, render
from respecd.messages import Frame, SensorConfig
from respecd.sim.world import World

# How a call is timed: wall time, or the process's CPU time (every thread; with
# perception.torch_threads 1 that is the detector's time on one core, waits excluded).
CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": time.process_time}


@dataclass(frozen=True)
class Latency:
    forward_s: float  # one inference (align + network + NMS)
    attribution_s: float  # one inference with attribution (forward with gradients + backward)

    @classmethod
    def of(cls, forward_s: float, attribution_s: float) -> Latency:
        """An attributed pass is a forward pass and more: a faster timing is noise."""
        return cls(forward_s, max(attribution_s, forward_s))


def measure(detector: Any, frames_for: Callable[[tuple[int, int]], dict[str, Frame]],
            resolutions: Iterable[tuple[int, int]], repeats: int = 3,
            clock: Callable[[], float] = time.perf_counter) -> dict[tuple[int, int], Latency]:
    """Median time of ``repeats`` calls per resolution on ``clock``, after one warm-up call each.

    ``frames_for(resolution)``: a realistic input at that RGB resolution (people in view).
    """
    table = {}
    for res in resolutions:
        frames = frames_for(tuple(res))  # type: ignore[arg-type]
        timings = {}
        for attribute in (False, True):
            detector.infer(frames, attribute)  # warm-up: allocator, first-call paths
            runs = []
            for _ in range(max(1, repeats)):
                start = clock()
                detector.infer(frames, attribute)
                runs.append(clock() - start)
            timings[attribute] = statistics.median(runs)
        table[(int(res[0]), int(res[1]))] = Latency.of(timings[False], timings[True])
    return table


def sim_frames(world: World, inputs: tuple[str, ...], t: float = 5.0) -> Callable[[tuple[int, int]], dict[str, Frame]]:
    """Rendered inputs at ``t`` in ``world``: RGB at the asked resolution, thermal and radar as default."""
    def frames_for(res: tuple[int, int]) -> dict[str, Frame]:
        configs = {"rgb": SensorConfig("rgb", rate_hz=30.0, resolution=res),
                   "thermal": SensorConfig("thermal", rate_hz=10.0, resolution=(160, 120)),
                   "radar": SensorConfig("radar", rate_hz=10.0, mode="range"),
                   "depth": SensorConfig("depth", rate_hz=15.0, resolution=(640, 480))}
        return {m: render(world, frame_id(c, t)) for m, c in configs.items() if m in inputs}

    return frames_for


def to_json(table: dict[tuple[int, int], Latency]) -> dict[str, dict[str, float]]:
    return {f"{w}x{h}": {"forward_ms": 1000 * v.forward_s, "attribution_ms": 1000 * v.attribution_s}
            for (w, h), v in table.items()}


def load(path: Path, resolutions: Iterable[tuple[int, int]]) -> dict[tuple[int, int], Latency]:
    """A latency table from ``path``: a ``bench scenarios --json`` result (its ``latency_ms``)
    or that mapping alone. Pinning the latency of a past run makes a rerun repeat its compute
    figures and, through the load factor, its actions; measured latency moves between runs.
    """
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise InputError(f"{path}: cannot read the latency file ({err.strerror or err})") from err
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"{path}: not JSON ({err})") from err
    table = doc.get("latency_ms", doc) if isinstance(doc, dict) else None
    if not isinstance(table, dict):
        raise InputError(f"{path}: expected an object with 'latency_ms' or 'WxH' keys")
    out = {}
    for w, h in resolutions:
        key = f"{w}x{h}"
        entry = table.get(key)
        values = [entry.get(k) for k in ("forward_ms", "attribution_ms")] if isinstance(entry, dict) else []
        if len(values) != 2 or not all(isinstance(v, int | float) and not isinstance(v, bool) and v > 0
                                       for v in values):
            raise InputError(f"{path}: latency_ms.{key}: expected {{forward_ms: >0, attribution_ms: >0}} "
                             f"(got {entry!r})")
        forward_ms, attribution_ms = (float(v) for v in values)  # type: ignore[arg-type]  # checked above
        out[(w, h)] = Latency.of(forward_ms / 1000.0, attribution_ms / 1000.0)
    return out


def write_reference(out: Path, profile_ref: str = "builtin:sim-rover", weights: str | None = None, repeats: int = 5,
                    clock: str = "cpu", seed: int = 500) -> dict[str, Any]:
    """Measure the profile's detector as ``bench scenarios`` does before a run (the same
    frames: scenario one of world ``seed``) and write a pinned latency file; scores nothing.
    A platform table's own facts already in ``out`` (its name, its accelerator's power and
    source) are kept."""
    from respecd.config import load_profile
    from respecd.lab.experiment.rollout import Piece, controller_for
    from respecd.lab.experiment.setup import load_detector, make_evaluator, rgb_resolutions

    profile = load_profile(profile_ref)
    detector = load_detector(profile, weights)
    evaluator = make_evaluator(detector, profile, use_cache=False)
    world = evaluator.world(Piece(profile.simulation.scenarios[0], seed, 10.0), profile.simulation)
    table = measure(detector, sim_frames(world, evaluator.inputs), rgb_resolutions(controller_for(profile, "static")),
                    repeats, CLOCKS[clock])
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    doc = {"about": f"Detector latency ({clock} time, median of {repeats}, torch {profile.perception.torch_threads} "
                    f"thread(s)) of {weights or profile.perception.weights} (outcome fingerprint "
                    f"{evaluator.fingerprint}), measured by `respecd experiment latency` at load "
                    f"average {load}. train-policy --latency and bench scenarios --latency read it.",
           **_platform_facts(out),
           "clock": clock, "repeats": repeats, "load_average": load, "detector_fingerprint": evaluator.fingerprint,
           "latency_ms": to_json(table)}
    out.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return doc


def _platform_facts(path: Path) -> dict[str, Any]:
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    keys = ("platform", "estimate", "accelerator_w", "accelerator_w_source")
    return {k: old[k] for k in keys if isinstance(old, dict) and k in old}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from respecd.argtypes import positive_int, seed

    parser.add_argument("out", type=Path, help="the pinned latency file to write (JSON)")
    parser.add_argument("--profile", default="builtin:sim-rover")
    parser.add_argument("--weights")
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed calls per resolution (default 5)")
    parser.add_argument("--clock", choices=sorted(CLOCKS), default="cpu")
    parser.add_argument("--seed", type=seed, default=500, help="world seed of the frames (default 500: validation)")


def main(a: argparse.Namespace) -> int:
    """A pinned latency file, for ``train-policy --latency`` and ``bench scenarios --latency``."""
    from respecd.outputs import check_output_file

    # the file is written after the measurement: a path that cannot take it is refused first
    check_output_file("OUT", a.out, make_parents=False, example="latency.json")
    doc = write_reference(a.out, a.profile, a.weights, a.repeats, a.clock, a.seed)
    print(json.dumps(doc["latency_ms"]))
    return 0
