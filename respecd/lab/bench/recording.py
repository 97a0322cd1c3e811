"""Recording encodings: what each costs on disk, and how far the replay's detections move.

One simulated session (lockstep, so every recorder sees the same frames) is recorded at
once in several encodings: ``raw`` (every camera a RawImage: the reference), ``lossless``
(the recording defaults: PNG for every camera), ``profile`` (what the profile's
``recording:`` section says) and ``jpegQQ`` (RGB as JPEG at quality QQ, thermal and
depth lossless). Each log is then replayed with the detector (policy static, lockstep:
deterministic) and its detections are compared, inference by inference, with the raw
log's: a lossless log must give the very same detections; a JPEG one moves them. Size is
on-disk bytes over the messages' time span (what ``../shared/checks/real-logs`` computes).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from respecd.argtypes import positive_float, resolution, seed

if TYPE_CHECKING:
    from respecd.config import Profile

FORMATS = {
    "raw": {"rgb_format": "raw", "thermal_format": "raw", "depth_format": "raw"},
    "lossless": {"rgb_format": "png", "thermal_format": "png", "depth_format": "png"},
}
ONE_FILE = float(1 << 20)  # MiB: no rotation, each encoding's replay covers the whole session
IOU_MATCH = 0.5  # a detection moved, not vanished, when its best match overlaps this much


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=positive_float, default=10.0, help="simulated session length (s)")
    parser.add_argument("--resolution", default="1280x720", help="RGB resolution WxH (default 1280x720)")
    parser.add_argument("--formats", default="raw,lossless,profile,jpeg80,jpeg90",
                        help="encodings to compare: raw, lossless, profile, jpegQQ (default %(default)s)")
    parser.add_argument("--seed", type=seed, default=0, help="simulator seed >= 0")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from respecd.config import load_profile

    names = [n.strip() for n in args.formats.split(",") if n.strip()]
    profile = _profile(load_profile("builtin:sim-rover"), resolution(args.resolution, "--resolution"))
    with tempfile.TemporaryDirectory(prefix="respecd-bench-recording-") as work:
        return compare(profile, names, args.seconds, args.seed, Path(work))


def recording_config(profile: Profile, name: str) -> dict[str, Any]:
    """The ``recording:`` overrides an encoding name stands for."""
    if name in FORMATS:
        return FORMATS[name]
    if name == "profile":
        return {}
    if name.startswith("jpeg") and name[4:].isdigit():
        return {"rgb_format": "jpeg", "jpeg_quality": int(name[4:]), "thermal_format": "png", "depth_format": "png"}
    from respecd.errors import InputError

    raise InputError(f"--formats: unknown encoding {name!r}; expected raw, lossless, profile or jpegQQ (jpeg80)")


def compare(profile: Profile, names: list[str], seconds: float, sim_seed: int, work: Path) -> dict[str, Any]:
    """Record ``seconds`` of the simulated rover in every encoding of ``names``, replay each with
    the detector; per encoding: MB/s on disk and how its detections differ from the raw log's."""
    logs = record(profile, {n: recording_config(profile, n) for n in ["raw", *names]}, seconds, sim_seed, work)
    reference = detections(profile, logs["raw"], work / "replay-raw")
    out: dict[str, Any] = {"seconds": seconds, "rgb": "x".join(map(str, _rgb(profile).resolution)),
                           "load_average_1min": round(os.getloadavg()[0], 2), "formats": {}}
    for name in names:
        found = reference if name == "raw" else detections(profile, logs[name], work / f"replay-{name}")
        out["formats"][name] = {"recording": recording_config(profile, name), "mb_per_s": mb_per_s(logs[name]),
                                **difference(reference, found)}
    return out


def _rgb(profile: Profile) -> Any:
    return next(s for s in profile.sensors if s.modality == "rgb")


def _profile(base: Profile, size: tuple[int, int]) -> Profile:
    """The sim rover with RGB at ``size``, policy static (the replays differ only by their log)."""
    sensors = [s.model_copy(update={"resolution": size}) if s.modality == "rgb" else s for s in base.sensors]
    actions = base.controller.actions.model_copy(update={"rgb_resolutions": (size,)})
    controller = base.controller.model_copy(update={"policy": "static", "actions": actions})
    return base.model_copy(update={"sensors": sensors, "controller": controller})


def record(profile: Profile, encodings: dict[str, dict[str, Any]], seconds: float, sim_seed: int,
           work: Path) -> dict[str, Path]:
    """One lockstep simulated session (no detector) recorded by one recorder per encoding."""
    from respecd.record.recorder import Recorder
    from respecd.record.simulated import run_recorded

    paths = {name: work / f"{name}.mcap" for name in encodings}
    recorders = run_recorded(profile, lambda quiet, clock: [
        Recorder(profile.recording.model_copy(update={**over, "enabled": True, "path": str(paths[name]),
                                                      "queue_size": 65536, "rotate_mib": ONE_FILE}),
                 quiet, clock, drain_s=None)
        for name, over in encodings.items()], seconds, sim_seed)
    for recorder in recorders:
        if recorder.dropped or recorder.errors:
            raise RuntimeError(f"{recorder.paths}: {recorder.dropped} dropped, {recorder.errors} not encoded")
    return paths


def detections(profile: Profile, log: Path, work: Path) -> list[tuple[float, tuple[Any, ...]]]:
    """(bundle time, detections) of every inference of a lockstep replay of ``log``."""
    import yaml

    from respecd.replay.run import replay

    work.mkdir(parents=True, exist_ok=True)
    config = work / "profile.yaml"
    config.write_text(yaml.safe_dump(profile.model_dump(mode="json")))
    found: list[tuple[float, tuple[Any, ...]]] = []

    def observe(session: Any) -> None:
        session.hooks.inference.append(lambda percept: found.append((percept.t, percept.detections)))

    replay(log, config=config, policy="static", speed="max", observe=observe)
    return sorted(found, key=lambda item: item[0])


def mb_per_s(path: Path) -> float:
    """File size over the time span of its messages (MB/s)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    stats = summary.statistics if summary is not None else None
    if stats is None:
        return 0.0
    span = (stats.message_end_time - stats.message_start_time) / 1e9
    return round(path.stat().st_size / span / 1e6, 3) if span > 0 else 0.0


def difference(reference: list[tuple[float, tuple[Any, ...]]],
               found: list[tuple[float, tuple[Any, ...]]]) -> dict[str, Any]:
    """How far ``found``'s detections are from ``reference``'s, inference by inference."""
    same = identical = 0
    ious, shifts, missing, extra = [], [], 0, 0
    theirs = dict(found)
    for t, ours in reference:
        other = theirs.get(t)
        if other is None:
            continue
        same += 1
        identical += other == ours
        for det in ours:
            best = max(other, key=lambda d: _iou(det.box, d.box), default=None)
            if best is None or _iou(det.box, best.box) < IOU_MATCH:
                missing += 1
                continue
            ious.append(_iou(det.box, best.box))
            shifts.append(abs(best.confidence - det.confidence))
        extra += sum(1 for d in other if max((_iou(d.box, o.box) for o in ours), default=0.0) < IOU_MATCH)
    return {"inferences": len(reference), "compared": same, "identical_inferences": identical,
            "detections": sum(len(d) for _, d in reference), "lost": missing, "new": extra,
            "mean_iou_matched": round(sum(ious) / len(ious), 4) if ious else None,
            "max_confidence_change": round(max(shifts), 4) if shifts else None}


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0
