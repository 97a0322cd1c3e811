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

``--runtime NAME|all`` also times the detector through each runtime (``perception.runtime``:
torch, onnxruntime, openvino; ``all``: those installed, plus OpenVINO in bf16 where the CPU has
it) into ``runtimes: {NAME: {"WxH": {"forward_ms", "attributed_ms", ...}}}`` in process CPU ms,
beside the net's ``gflop`` per size, this CPU's ``peak_gflops`` (one thread, f32 matmul) and
each forward's ratio to the limit that makes (``flops.py``).
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
RUNTIMES = ("torch", "onnxruntime", "openvino")
BF16 = "openvino-bf16"  # --runtime all: OpenVINO at bf16 as well, where the CPU has it
# name in ``methods``, attribution method, its sufficiency (the profile's default method first)
VARIANTS: tuple[tuple[str, Method, Sufficiency], ...] = (
    ("ablation", "ablation", "auto"), ("ablation+sufficiency", "ablation", "always"), ("gradient", "gradient", "auto"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", default="builtin:sim-rover", help="checkpoint (default the shipped one)")
    parser.add_argument("--repeats", type=positive_int, default=10, help="timed runs per resolution (default 10)")
    parser.add_argument("--threads", type=non_negative_int, default=0,
                        help="torch threads (default 0: the profile default)")
    parser.add_argument("--seed", type=seed, default=1, help="world seed >= 0 of the scene used as input")
    parser.add_argument("--runtime", choices=(*RUNTIMES, BF16, "all"), default="torch",
                        help="also time the detector through this runtime (all: every one installed; default torch)")


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
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.detector import FusionDetector

    config = PerceptionConfig(weights=args.weights, model=checkpoint.spec_of(args.weights))  # the file's own net
    threads = args.threads or config.torch_threads
    torch.set_num_threads(threads)
    config = config.model_copy(update={"torch_threads": threads})
    detector = FusionDetector.load(config, sim_calibration())  # the daemon's alignment of builtin:sim-rover
    every = {name: detector if name == "torch" else FusionDetector.load(runtime_config(config, name), sim_calibration())
             for name in runtime_names(args.runtime)}
    rows: list[dict[str, Any]] = []
    runtimes: dict[str, dict[str, dict[str, float]]] = {}
    for w, h in RESOLUTIONS:
        frames = _frames(args.seed, (w, h))
        rows.append(_torch_row(detector, frames, args.repeats))
        for name, row in _runtime_rows(every, detector.prepare(frames), args.repeats).items():
            runtimes.setdefault(name, {})[f"{w}x{h}"] = row
    figures = {"resolutions": rows, "model_params": detector.parameters, "torch_threads": threads,
               "method": config.attribution_method, "repeats": args.repeats, "weights": args.weights}
    figures.update(limits(detector.model, runtimes))
    figures["load_avg_1m"] = round(os.getloadavg()[0], 2)
    return figures


def runtime_names(choice: str) -> list[str]:
    """``--runtime``: torch and the runtime named, or (all) torch and every runtime installed."""
    if choice != "all":
        return ["torch"] if choice == "torch" else ["torch", choice]
    from respecd.perception.runtimes import installed

    names = ["torch", *(n for n in RUNTIMES[1:] if installed(n) and installed("onnx"))]
    if "openvino" in names:
        from respecd.perception.runtimes.openvino import load_openvino

        if "BF16" in load_openvino().Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"):
            names.append(BF16)
    return names


def runtime_config(config: Any, name: str) -> Any:
    """The perception config of runtime ``name`` (``openvino-bf16``: OpenVINO at bf16)."""
    if name == BF16:
        return config.model_copy(update={"runtime": "openvino", "precision": "bf16"})
    return config.model_copy(update={"runtime": name})


def _torch_row(detector: Any, frames: dict[str, Any], repeats: int) -> dict[str, Any]:
    """Alignment, forward and every attribution method through torch, wall and CPU ms."""
    from respecd.perception.attribution import Attributor

    align_ms, _ = _median_ms(lambda: detector.prepare(frames), repeats)
    aligned = detector.prepare(frames)
    w, h = aligned.size
    forward_ms, forward_cpu = _median_ms(lambda: detector.run(aligned, False), repeats)
    methods = {}
    for name, method, sufficiency in VARIANTS:
        detector.attributor = Attributor(detector.model, method, sufficiency)
        ms, cpu = _median_ms(lambda: detector.run(aligned, True), repeats)
        methods[name] = {"ms": round(ms, 1), "cpu_ms": round(cpu, 1), "ratio": round(ms / forward_ms, 2),
                         "cpu_ratio": round(cpu / forward_cpu, 2), **_passes(detector, aligned)}
    config = detector.config
    detector.attributor = Attributor(detector.model, config.attribution_method, config.attribution_sufficiency)
    detections = detector.run(aligned, False).detections
    chosen = methods[detector.config.attribution_method]
    return {"rgb": f"{w}x{h}", "forward_ms": round(forward_ms, 1), "attribution_ms": chosen["ms"],
            "ratio": chosen["ratio"], "forward_cpu_ms": round(forward_cpu, 1), "attribution_cpu_ms": chosen["cpu_ms"],
            "cpu_ratio": chosen["cpu_ratio"], "align_ms": round(align_ms, 1), "detections": len(detections),
            "methods": methods}


def _runtime_rows(detectors: dict[str, Any], aligned: Any, repeats: int) -> dict[str, dict[str, float]]:
    """Per runtime, forward and forward + the profile's attribution: median CPU ms (and wall). The runtimes
    take turns call by call, so a change in the machine's load falls on all of them alike."""
    forward = _interleaved({n: (lambda d=d: d.run(aligned, False)) for n, d in detectors.items()}, repeats)
    attributed = _interleaved({n: (lambda d=d: d.run(aligned, True)) for n, d in detectors.items()}, repeats)
    return {n: {"forward_ms": round(forward[n][1], 1), "attributed_ms": round(attributed[n][1], 1),
                "forward_wall_ms": round(forward[n][0], 1), "attributed_wall_ms": round(attributed[n][0], 1)}
            for n in detectors}


def _interleaved(calls: dict[str, Any], repeats: int) -> dict[str, tuple[float, float]]:
    """``_median_ms`` of each call, the calls alternating: median wall and CPU ms by name."""
    for call in calls.values():
        call()  # warm-up
    wall: dict[str, list[float]] = {n: [] for n in calls}
    cpu: dict[str, list[float]] = {n: [] for n in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            call()
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    return {n: (statistics.median(wall[n]) * 1000, statistics.median(cpu[n]) * 1000) for n in calls}


def limits(model: Any, runtimes: dict[str, dict[str, dict[str, float]]]) -> dict[str, Any]:
    """The net's GFLOP per RGB size (at its padded input), one core's peak, the forward that makes, and
    each runtime's forward over it (``to_limit``, written into ``runtimes``)."""
    from respecd.lab.bench.flops import model_gflop, peak_gflops
    from respecd.perception.boxes import pad_to_stride

    channels = len(model.spec.channels)
    gflop = {f"{w}x{h}": round(model_gflop(model, channels, *pad_to_stride(h, w)), 3) for w, h in RESOLUTIONS}
    peak = peak_gflops()
    limit_ms = {size: round(g / peak * 1000, 2) for size, g in gflop.items()}
    for sizes in runtimes.values():
        for size, row in sizes.items():
            row["to_limit"] = round(row["forward_ms"] / limit_ms[size], 2)
            row["attributed_ratio"] = round(row["attributed_ms"] / row["forward_ms"], 2)
    return {"runtimes": runtimes, "gflop": gflop, "peak_gflops": round(peak, 1), "limit_ms": limit_ms}
