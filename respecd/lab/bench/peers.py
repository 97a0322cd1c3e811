"""Peers: the radar parser, the synchronizer and the detector against the code people use instead.

Three sections, each a ratio measured in one run (peer time / ours: above 1, ours is faster):

* ``radar_parser``: ours vs TI's reference parser and juhasch/xwr68xxisk on the real IWR6843
  capture, outputs compared value for value (``respecd.lab.bench.peer_radar``);
* ``synchronizer``: ours vs ROS 2 message_filters' ApproximateTimeSynchronizer on the same
  five-sensor stream (``respecd.lab.bench.peer_sync``);
* ``detector``: the fusion detector's forward (network + box decoding, no NMS) vs YOLOv8n's
  (ultralytics, architecture only: no weights are needed for speed) at the same input size,
  one torch thread, calls alternated so both see the same machine.

No peer is a dependency: TI's parser, juhasch's package and message_filters are not on PyPI
and load from checkouts in ``--peers DIR`` (docs/PERFORMANCE.md "Peers" lists the layout and
the commits measured); ultralytics comes from ``make bench-peers``. A section whose peer is
missing says so and still measures ours.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from respecd.argtypes import positive_float, resolution
from respecd.errors import InputError
from respecd.lab.bench import peer_radar, peer_sync
from respecd.lab.bench.drivers import DEFAULT_DATA


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--peers", type=Path,
                        help="folder of the peers' checkouts (ti/, xwr68xxisk/, message_filters/)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of the real radar captures")
    parser.add_argument("--repeat", type=int, default=10, help="passes over the capture per timed round")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds; the best one is reported")
    parser.add_argument("--sync-seconds", type=positive_float, default=60.0,
                        help="length of the synchronizer's stream (s)")
    parser.add_argument("--resolution", default="640x360", help="detector RGB input WxH (default 640x360)")
    parser.add_argument("--detector-repeats", type=int, default=10, help="timed forwards per detector (median)")
    parser.add_argument("--weights", default="builtin:sim-rover", help="our detector's checkpoint")


def run(args: argparse.Namespace) -> dict[str, Any]:
    if min(args.repeat, args.rounds, args.detector_repeats) < 1 or args.sync_seconds <= 0:
        raise InputError("--repeat, --rounds and --detector-repeats must be at least 1, --sync-seconds above 0")
    load_before = os.getloadavg()[0]
    figures: dict[str, Any] = {"radar_parser": radar_parser(args), "synchronizer": synchronizer(args),
                               "detector": detector(args)}
    figures["load_avg_1m"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]  # before, after
    return figures


def radar_parser(args: argparse.Namespace) -> dict[str, Any]:
    path = args.data / peer_radar.CAPTURE
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read the radar capture ({err.strerror}); "
                         "pass --data shared/data/real") from err
    mine = peer_radar.decode_ours(peer_radar.ours(data))
    out: dict[str, Any] = {"capture": peer_radar.CAPTURE, "bytes": len(data),
                           "ours": peer_radar.time_parser(peer_radar.ours, data, args.repeat, args.rounds)}
    for name, make in (("ti", peer_radar.ti_parser), ("juhasch", peer_radar.juhasch_parser)):
        parser = _peer(make, args.peers)
        if isinstance(parser, str):
            out[name] = {"skipped": parser}
            continue
        parse, decode = parser
        row = peer_radar.time_parser(parse, data, args.repeat, args.rounds)
        row |= peer_radar.compare(mine, decode(parse(data)))
        row["x_ours"] = round(row["cpu_us_per_frame"] / out["ours"]["cpu_us_per_frame"], 2)
        out[name] = row
    return out


def synchronizer(args: argparse.Namespace) -> dict[str, Any]:
    arrivals = peer_sync.stream(args.sync_seconds)
    out: dict[str, Any] = {"seconds": args.sync_seconds, "rates_hz": peer_sync.RATES,
                           "slop_s": peer_sync.TOLERANCE_S, "ours": peer_sync.ours(arrivals)}
    checkout = _peer(lambda peers: peers / "message_filters", args.peers)
    if isinstance(checkout, str):
        out["message_filters"] = {"skipped": checkout}
        return out
    try:
        row = peer_sync.peer(arrivals, checkout)
    except FileNotFoundError as err:
        out["message_filters"] = {"skipped": str(err)}
        return out
    row["x_ours"] = round(row["us_per_input"] / out["ours"]["us_per_input"], 2)
    out["message_filters"] = row
    return out


def detector(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    torch.set_num_threads(1)
    ours, x = _our_forward(args)
    out: dict[str, Any] = {"input": list(x.shape), "torch_threads": 1}
    peer = _yolov8n(x)
    if isinstance(peer, str):
        out["ours"] = {"cpu_ms": _timed([ours], args.detector_repeats)[0]}
        out["yolov8n"] = {"skipped": peer}
        return out
    forward, params, version = peer
    ours_ms, theirs_ms = _timed([ours, forward], args.detector_repeats)
    out["ours"] = {"cpu_ms": ours_ms, "weights": args.weights}
    out["yolov8n"] = {"cpu_ms": theirs_ms, "params": params, "ultralytics": version,
                      "x_ours": round(theirs_ms / ours_ms, 2)}
    return out


def _our_forward(args: argparse.Namespace) -> tuple[Callable[[], object], Any]:
    import torch

    from respecd.lab.bench.inference import _frames
    from respecd.lab.detector.simdata import sim_calibration
    from respecd.perception import checkpoint
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.detector import FusionDetector

    w, h = resolution(args.resolution, "--resolution")
    config = PerceptionConfig(weights=args.weights, model=checkpoint.spec_of(args.weights))
    model = FusionDetector.load(config, sim_calibration())
    aligned = model.prepare(_frames(1, (w, h)))
    x = torch.from_numpy(aligned.tensor).unsqueeze(0)
    presence = torch.from_numpy(aligned.presence).unsqueeze(0)
    net = model.model

    def forward() -> object:
        with torch.inference_mode():
            return net.decode(net(x, presence), tuple(x.shape[2:]))

    return forward, x


def _yolov8n(x: Any) -> tuple[Callable[[], object], int, str] | str:
    """YOLOv8n (80 classes, as published) built from ultralytics' own yaml, or why not."""
    import torch

    if "YOLO_CONFIG_DIR" not in os.environ:  # ultralytics writes its settings there, not in ~/.config
        os.environ["YOLO_CONFIG_DIR"] = tempfile.mkdtemp(prefix="respecd-yolo-")
    try:
        import ultralytics
        from ultralytics.nn.tasks import DetectionModel
    except ImportError as err:
        return f"ultralytics is not installed (make bench-peers): {err}"
    model = DetectionModel("yolov8n.yaml", nc=80, verbose=False).eval()
    rgb = x[:, :3].contiguous()

    def forward() -> object:
        with torch.inference_mode():
            return model(rgb)

    return forward, sum(p.numel() for p in model.parameters()), ultralytics.__version__


def _timed(calls: list[Callable[[], object]], repeats: int) -> list[float]:
    """Median CPU ms of each call; the calls alternate so each sees the same machine."""
    for call in calls:
        call()  # warm-up: oneDNN picks its kernels for this shape
    samples: list[list[float]] = [[] for _ in calls]
    for _ in range(repeats):
        for call, out in zip(calls, samples, strict=True):
            started = time.process_time()
            call()
            out.append(time.process_time() - started)
    return [round(statistics.median(s) * 1000, 1) for s in samples]


def _peer(make: Callable[[Path], Any], peers: Path | None) -> Any:
    """What ``make`` builds from the peers folder, or the reason it cannot."""
    if peers is None:
        return "no --peers DIR given"
    try:
        return make(peers)
    except (FileNotFoundError, ImportError) as err:
        return str(err)


def summary(figures: dict[str, Any]) -> str:
    """One line per peer; the figures go to --json."""
    radar, sync, det = figures["radar_parser"], figures["synchronizer"], figures["detector"]
    lines = [f"load average {figures['load_avg_1m'][0]} -> {figures['load_avg_1m'][1]}",
             f"radar parser: ours {radar['ours']['cpu_us_per_frame']} CPU-us/frame ({radar['ours']['frames']} frames)"]
    for name in ("ti", "juhasch"):
        row = radar[name]
        lines.append(f"  {name}: " + (row["skipped"] if "skipped" in row else
                     f"{row['cpu_us_per_frame']} us/frame = {row['x_ours']}x ours; "
                     f"identical {row['frames_identical']}/{row['frames_compared']} frames"))
    row = sync["message_filters"]
    lines.append(f"synchronizer: ours {sync['ours']['us_per_input']} CPU-us/input; message_filters ATS: "
                 + (row["skipped"] if "skipped" in row else f"{row['us_per_input']} us/input = {row['x_ours']}x ours"))
    row = det["yolov8n"]
    lines.append(f"detector forward {det['input']}: ours {det['ours']['cpu_ms']} CPU-ms; YOLOv8n: "
                 + (row["skipped"] if "skipped" in row else
                    f"{row['cpu_ms']} CPU-ms (ours = {round(det['ours']['cpu_ms'] / row['cpu_ms'], 2)}x its time)"))
    return "\n".join(lines)
