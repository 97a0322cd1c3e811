"""Inference: fusion detector forward and forward+attribution time per RGB resolution.

Inputs are real simulated frames (a lit scene with people, so NMS and attribution have
targets), aligned once; the timed part is what the perception worker does per bundle:
network + NMS (``forward_ms``), or network + NMS + the contributions of the profile's
method (``attribution_ms``, ``ratio`` = attribution / forward; ``ablation`` by default:
one more aux-backbone pass per aux sensor, fusion + neck + head on the targets' windows per
sensor off, which with two sensors also gives each one's sufficiency). Every method is timed
too (``methods``), and the ablation with each sensor's sufficiency however many sensors are on
(``ablation+sufficiency``: ``perception.attribution_sufficiency: always``; ``fusion_passes``
counts the subsets each ran). Medians over ``--repeats`` runs after a warm-up, as wall time and
as process CPU time (``*_cpu_ms``); the 1-minute load average says how shared the machine was.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import TYPE_CHECKING, Any

from respecd.argtypes import non_negative_int, positive_int, seed

if TYPE_CHECKING:
    from respecd.perception.attribution import Method, Sufficiency

RESOLUTIONS = ((1280, 720), (960, 540), (640, 360))
# name in ``methods``, attribution method, its sufficiency (the profile's default method first)
VARIANTS: tuple[tuple[str, Method, Sufficiency], ...] = (
    ("ablation", "ablation", "auto"), ("ablation+sufficiency", "ablation", "always"), ("gradient", "gradient", "auto"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", default="builtin:sim-rover", help="checkpoint (default the shipped one)")
    parser.add_argument("--repeats", type=positive_int, default=10, help="timed runs per resolution (default 10)")
    parser.add_argument("--threads", type=non_negative_int, default=0,
                        help="torch threads (default 0: the profile default)")
    parser.add_argument("--seed", type=seed, default=1, help="world seed >= 0 of the scene used as input")


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    """Median wall ms and median process-CPU ms of ``fn``.

    On a machine shared with other work the wall time includes waiting for a core; with one
    torch thread the CPU time is what the same call takes on an idle core.
    """
    fn()  # warm-up: allocator and oneDNN kernel selection for this shape
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall) * 1000, statistics.median(cpu) * 1000


def _frames(seed: int, size: tuple[int, int]):
    import numpy as np

    from respecd.messages import Frame
    from respecd.sim.render import render_lepton, render_radar, render_rgb
    from respecd.sim.world import SimulationConfig, World

    state = World(SimulationConfig(scenarios=["good-light-static"]), seed).state_at(10.0)
    while len(state.targets) < 3:  # a scene with three people: NMS and attribution have targets
        seed += 1
        state = World(SimulationConfig(scenarios=["good-light-static"]), seed).state_at(10.0)
    rng = np.random.default_rng(seed)
    data = {"rgb": render_rgb(state, size, 1 / 30, rng), "thermal": render_lepton(state, (160, 120), rng),
            "radar": render_radar(state, "range", 10.0, rng)}
    return {k: Frame(k, state.t, 0, v) for k, v in data.items()}  # type: ignore[arg-type]


def _passes(detector: Any, aligned: Any) -> dict[str, int]:
    """How many fusion + neck + head passes an ablation runs per input (nothing on is a constant), none for gradient."""
    if detector.attributor.method != "ablation":
        return {}
    import torch

    from respecd.perception.ablation import needed_subsets, sensors_on

    x, presence = torch.from_numpy(aligned.tensor)[None], torch.from_numpy(aligned.presence)[None]
    on = sensors_on(detector.attributor.modalities, x, presence)
    return {"fusion_passes": sum(1 for s in needed_subsets(on, detector.attributor.always_alone) if s)}


def run(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from respecd.lab.detector.simdata import sim_calibration
    from respecd.perception import checkpoint
    from respecd.perception.attribution import Attributor
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.detector import FusionDetector

    config = PerceptionConfig(weights=args.weights, model=checkpoint.spec_of(args.weights))  # the file's own net
    threads = args.threads or config.torch_threads
    torch.set_num_threads(threads)
    detector = FusionDetector.load(config, sim_calibration())  # the daemon's alignment of builtin:sim-rover
    rows = []
    for w, h in RESOLUTIONS:
        frames = _frames(args.seed, (w, h))
        align_ms, _ = _median_ms(lambda f=frames: detector.prepare(f), args.repeats)
        aligned = detector.prepare(frames)
        forward_ms, forward_cpu = _median_ms(lambda a=aligned: detector.run(a, False), args.repeats)
        methods = {}
        for name, method, sufficiency in VARIANTS:
            detector.attributor = Attributor(detector.model, method, sufficiency)
            ms, cpu = _median_ms(lambda a=aligned: detector.run(a, True), args.repeats)
            methods[name] = {"ms": round(ms, 1), "cpu_ms": round(cpu, 1), "ratio": round(ms / forward_ms, 2),
                             "cpu_ratio": round(cpu / forward_cpu, 2), **_passes(detector, aligned)}
        detector.attributor = Attributor(detector.model, config.attribution_method, config.attribution_sufficiency)
        detections = detector.run(aligned, False).detections
        chosen = methods[config.attribution_method]
        rows.append({
            "rgb": f"{w}x{h}",
            "forward_ms": round(forward_ms, 1),
            "attribution_ms": chosen["ms"],
            "ratio": chosen["ratio"],
            "forward_cpu_ms": round(forward_cpu, 1),
            "attribution_cpu_ms": chosen["cpu_ms"],
            "cpu_ratio": chosen["cpu_ratio"],
            "align_ms": round(align_ms, 1),
            "detections": len(detections),
            "methods": methods,
        })
    return {"resolutions": rows, "model_params": detector.parameters, "torch_threads": threads,
            "method": config.attribution_method, "repeats": args.repeats, "weights": args.weights,
            "load_avg_1m": round(os.getloadavg()[0], 2)}
