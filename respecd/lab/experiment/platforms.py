"""Latency tables per target platform: what one inference costs on the accelerator that runs it.

Every compute and load figure of the experiment rests on the detector's time per RGB size
(``latency.py``). It differs by platform, so each platform has its table, shipped beside this
module (``latency_tables/NAME.json``, read by ``bench scenarios --latency NAME`` and
``train-policy --latency NAME``):

* ``cpu`` — measured here: one core of the project's 2-core x86-64 machine (AMD EPYC), the
  process's CPU time, median of 5 (``make latency-cpu`` re-measures it);
* ``orin-nano`` — the paper's platform, an **estimate** until measured on a device: the
  network's FLOPs per RGB size (counted by torch's ``FlopCounterMode``) through a line fitted
  to published PyTorch latencies of YOLO networks of similar FLOPs on a Jetson Orin Nano
  (``ORIN_PUBLISHED``); attribution costs the same multiple of a forward pass as on the CPU
  (``respecd experiment platforms orin-nano`` re-derives it).

A table also names what its accelerator draws while busy (``accelerator_w``, cited): the
experiment's energy adds busy share x that figure to the sensors' power model.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from respecd.errors import InputError
from respecd.lab.experiment.latency import Latency, load

PLATFORMS = ("orin-nano", "cpu")
DEFAULT_PLATFORM = "orin-nano"

# (network, GFLOPs at 640x640, PyTorch latency ms on a Jetson Orin Nano): the .pt rows of
# github.com/the0807/YOLOv8-ONNX-TensorRT (README, "Tested on Nvidia Jetson Orin Nano", commit f54cfee),
# GFLOPs as Ultralytics publishes them. The two nearest our network's 3-12 GFLOPs set the line;
# github.com/hokwangchoi/jetson-orin-nano-benchmarks (vision-benchmarks/assets/results/
# yolov8_20260414_223810.json: YOLOv8n, PyTorch FP32, CUDA events, MAXN_SUPER) measured 20.88 ms
# for the first row, at 11.39 W of board input power (VDD_IN): the table's accelerator_w.
ORIN_PUBLISHED = (("yolov8n", 8.7, 20.0), ("yolov8s", 28.6, 30.0))
ORIN_CROSS_CHECK_MS = 20.88
ORIN_BOARD_W = 11.39
SOURCES = ("https://github.com/the0807/YOLOv8-ONNX-TensorRT (README, Jetson Orin Nano, yolov8n.pt 20 ms, "
           "yolov8s.pt 30 ms)",
           "https://github.com/hokwangchoi/jetson-orin-nano-benchmarks (YOLOv8n PyTorch FP32 20.88 ms, VDD_IN 11.39 W)")


@dataclass(frozen=True)
class LatencyTable:
    """One platform's table: its name, the file, the latency per RGB size, the busy power."""

    name: str
    path: Path | None
    latency: dict[tuple[int, int], Latency]
    accelerator_w: float | None
    estimate: bool = False

    def label(self) -> str:
        """What ``latency_table`` in a result says."""
        where = f" ({self.path.name})" if self.path is not None else ""
        return f"{self.name}{where}{', estimate' if self.estimate else ''}"


def table_path(name: str) -> Path:
    return Path(str(resources.files("respecd.lab.experiment") / "latency_tables" / f"{name}.json"))


def resolve(spec: str | Path, resolutions: Iterable[tuple[int, int]]) -> LatencyTable:
    """A named platform's table (``orin-nano``, ``cpu``) or a file (a table, or a past result)."""
    named = str(spec) in PLATFORMS
    path = table_path(str(spec)) if named else Path(spec)
    latency = load(path, resolutions)
    doc = json.loads(path.read_text(encoding="utf-8"))
    watts = doc.get("accelerator_w") if isinstance(doc, dict) else None
    if watts is not None and (not isinstance(watts, int | float) or isinstance(watts, bool) or watts < 0):
        raise InputError(f"{path}: accelerator_w: expected watts >= 0 (got {watts!r})")
    name = str(spec) if named else str(doc.get("platform", path.stem)) if isinstance(doc, dict) else path.stem
    return LatencyTable(name, path, latency, None if watts is None else float(watts),
                        bool(doc.get("estimate", False)) if isinstance(doc, dict) else False)


LATENCY_HELP = ("detector latency: a platform's table (orin-nano, the paper's platform, an estimate; cpu, measured on "
                "this project's machine), a file (a table, or a past run's --json result), or 'measured' (timed now "
                "on this machine: figures then move with its load)")


def pinned(spec: str, resolutions: Iterable[tuple[int, int]]) -> LatencyTable | None:
    """The table ``--latency`` names, read before anything slow (a bad file fails first);
    None for ``measured``."""
    return None if spec == "measured" else resolve(spec, resolutions)


def measured(latency: dict[tuple[int, int], Latency], clock: str) -> LatencyTable:
    return LatencyTable(f"measured ({clock} time)", None, latency, None)


def network_gflops(model: Any, resolution: tuple[int, int]) -> float:
    """GFLOPs (2 x multiply-adds, as Ultralytics counts) of one forward pass at an RGB size,
    on the padded input the detector feeds (multiples of 32), every aux input present."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    w, h = (-(-v // 32) * 32 for v in resolution)
    aux = len(model.spec.aux_modalities)
    with FlopCounterMode(display=False) as counter, torch.inference_mode():
        model(torch.zeros(1, 3 + aux, h, w), torch.ones(1, aux))
    return counter.get_total_flops() / 1e9


def orin_line() -> tuple[float, float]:
    """Intercept (ms) and slope (ms per GFLOP) through the two published points."""
    (_, g0, ms0), (_, g1, ms1) = ORIN_PUBLISHED
    slope = (ms1 - ms0) / (g1 - g0)
    return ms0 - slope * g0, slope


def derive_orin(profile_ref: str = "builtin:sim-rover") -> dict[str, Any]:
    """The Orin Nano table: FLOPs per RGB size through ``orin_line``, attribution at the CPU
    table's multiple of a forward pass."""
    from respecd.config import load_profile
    from respecd.lab.experiment.rollout import controller_for
    from respecd.lab.experiment.setup import load_detector, rgb_resolutions

    profile = load_profile(profile_ref)
    model = load_detector(profile, random_init=True).model.eval()  # FLOPs do not depend on the weights
    resolutions = rgb_resolutions(controller_for(profile, "static"))
    cpu = load(table_path("cpu"), resolutions)
    intercept, slope = orin_line()
    table, gflops = {}, {}
    for w, h in resolutions:
        g = network_gflops(model, (w, h))
        forward = intercept + slope * g
        ratio = cpu[(w, h)].attribution_s / cpu[(w, h)].forward_s
        gflops[f"{w}x{h}"] = round(g, 3)
        table[f"{w}x{h}"] = {"forward_ms": round(forward, 2), "attribution_ms": round(forward * ratio, 2)}
    about = (f"ESTIMATE for a Jetson Orin Nano (PyTorch on its GPU, as the daemon runs there) until measured on a "
             f"device: forward = {intercept:.2f} ms + {slope:.4f} ms/GFLOP x the network's GFLOPs at each RGB size, "
             f"the line through published PyTorch latencies of YOLOv8n and YOLOv8s on an Orin Nano; attribution at "
             f"the CPU table's multiple of a forward pass. Derived by `respecd experiment platforms orin-nano`.")
    return {"about": about, "platform": "orin-nano", "estimate": True, "sources": list(SOURCES),
            "published_ms": [{"network": n, "gflops": g, "pytorch_ms": ms} for n, g, ms in ORIN_PUBLISHED],
            "cross_check": f"YOLOv8n PyTorch FP32 GPU time {ORIN_CROSS_CHECK_MS} ms (line: "
                           f"{intercept + slope * ORIN_PUBLISHED[0][1]:.2f} ms)",
            "gflops": gflops, "accelerator_w": ORIN_BOARD_W,
            "accelerator_w_source": "board input power (VDD_IN) while the GPU runs YOLOv8n in PyTorch FP32, "
                                    "MAXN_SUPER (hokwangchoi/jetson-orin-nano-benchmarks); idle draw included",
            "latency_ms": table}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("platform", choices=("orin-nano",), help="the table to derive")
    parser.add_argument("out", type=Path, nargs="?", help="where to write it (default: the shipped table)")


def main(a: argparse.Namespace) -> int:
    """Re-derive the Orin Nano table from the published figures and the network's FLOPs."""
    out = a.out or table_path("orin-nano")
    out.write_text(json.dumps(derive_orin(), indent=2) + "\n", encoding="utf-8")
    print(out)
    return 0
