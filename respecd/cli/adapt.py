"""``respecd adapt LOG... --out CKPT``: learn the thermal path from recorded sessions, no labels.

The RGB detector's confident boxes on good-light frames, carried into the thermal view by the
session's recorded calibration, train the checkpoint's thermal path (``lab/detector/adapt.py``).
Prints what was used and, on the held-back frames, mAP@0.5 against the teacher's boxes before and
after: thermal only, every recorded sensor on, RGB only. Writes CKPT and its card (CKPT .json).
A log without both cameras, without their calibration, or that is no respecd session log is
refused with exit status 2, naming the log and what it lacks.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from respecd.argtypes import non_negative_float, positive_float, positive_int, resolution, seed, unit_interval
from respecd.errors import InputError
from respecd.outputs import check_output_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG", type=Path,
                        help="session logs recorded with RGB and thermal (respecd --record)")
    parser.add_argument("--out", required=True, type=Path, help="adapted checkpoint to write (.pt); card beside it")
    parser.add_argument("--weights", help="checkpoint to adapt, path or builtin:NAME (default: the one the first "
                        "log's session ran, else builtin:sim-rover)")
    parser.add_argument("--teacher", help="RGB detector whose boxes teach, run with RGB alone (default: --weights)")
    parser.add_argument("--config", "--profile", dest="config", metavar="FILE",
                        help="profile whose sensors' calibration replaces the recorded one (same sensor names)")
    parser.add_argument("--confident", type=unit_interval, default=0.5,
                        help="teacher confidence 0..1 a box needs to be a label (default 0.5)")
    parser.add_argument("--unsure", type=unit_interval, default=0.2,
                        help="a frame with a teacher box between this and --confident is left out (default 0.2)")
    parser.add_argument("--min-light", type=non_negative_float, default=20.0,
                        help="mean RGB level 0..255 below which a frame is too dark to teach (default 20)")
    parser.add_argument("--every", type=positive_float, default=0.5, metavar="S",
                        help="seconds between the RGB frames used (default 0.5)")
    parser.add_argument("--max-skew", type=positive_float, default=0.1, metavar="S",
                        help="seconds a thermal frame may be from its RGB frame (default 0.1)")
    parser.add_argument("--width", type=positive_int, default=640, help="RGB frames scaled down to this width "
                        "(default 640)")
    parser.add_argument("--val-share", type=unit_interval, default=0.2,
                        help="share of the frames held back, in whole --block stretches (default 0.2)")
    parser.add_argument("--block", type=positive_float, default=10.0, metavar="S",
                        help="seconds of a session held back together (default 10)")
    parser.add_argument("--epochs", type=positive_int, default=8, help="epochs (default 8)")
    parser.add_argument("--steps", type=positive_int, default=100, help="steps per epoch (default 100)")
    parser.add_argument("--batch", type=positive_int, default=8, help="crops per step (default 8)")
    parser.add_argument("--lr", type=positive_float, default=2e-3, help="AdamW peak learning rate (default 0.002)")
    parser.add_argument("--crop", default="320x192", help="training crop WxH, multiples of 32 (default 320x192)")
    parser.add_argument("--freeze", help="comma-separated parts kept fixed (default: all that serves RGB too: "
                        "rgb,neck,head; a Darknet net rgb,head,fuse.*.rgb)")
    parser.add_argument("--seed", type=seed, default=0, help="seed >= 0 of the hold-back and the augmentation")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads, at least 1 (default 1)")
    parser.add_argument("--no-progress", dest="quiet", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    check_output_file("--out", args.out, example="adapted.pt")
    if args.out.suffix != ".pt":
        raise InputError(f"--out {args.out}: expected a .pt file name")
    if args.unsure > args.confident:
        raise InputError(f"--unsure {args.unsure}: expected at most --confident ({args.confident})")
    crop = resolution(args.crop, "--crop")
    if crop[0] % 32 or crop[1] % 32:
        raise InputError(f"--crop {args.crop}: both sides must be multiples of 32")
    import torch

    from respecd.lab.detector.adapt import AdaptConfig, adapt

    torch.set_num_threads(args.threads)
    profile = _profile(args.config)
    cfg = AdaptConfig(
        logs=tuple(args.logs), out=args.out, weights=args.weights or _recorded_weights(args.logs[0], profile),
        teacher=args.teacher, profile=profile, confident=args.confident, unsure=args.unsure,
        min_light=args.min_light, every_s=args.every, max_skew_s=args.max_skew, width=args.width,
        val_share=args.val_share, block_s=args.block, epochs=args.epochs, steps=args.steps, batch=args.batch,
        lr=args.lr, crop=crop, freeze=tuple(p for p in args.freeze.split(",") if p) if args.freeze else None,
        seed=args.seed, threads=args.threads, progress=not args.quiet,
    )
    report = adapt(cfg)
    print(table(report))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.1f} MB) and {args.out.with_suffix('.json')}")
    return 0


def _profile(config: str | None) -> dict[str, Any] | None:
    if config is None:
        return None
    from respecd.config import load_profile

    return dict(load_profile(config).model_dump(mode="json"))


def _recorded_weights(first: Path, profile: dict[str, Any] | None) -> str:
    """The checkpoint the session ran (the profile's perception.weights); builtin:sim-rover without one."""
    from respecd.lab.detector.recorded import open_recording

    if profile is None:
        profile = open_recording(first).session.profile_dict() or {}
    perception = profile.get("perception") or {}
    return str(perception.get("weights") or "builtin:sim-rover")


def table(report: dict[str, Any]) -> str:
    """What was used, and the before/after scores as Markdown."""
    f = report["frames"]
    lines = [
        f"adapt {report['weights']} (teacher: {report['teacher']}, RGB alone): {f['seen']} frame pairs, "
        f"{f['too_dark']} too dark, {f['unsure']} with unsure teacher boxes; trained on {f['train']}, held back "
        f"{f['held_out']} ({f['teacher_boxes']} teacher boxes in all); best epoch {report['best_epoch']}, "
        f"{report['train_s']:.0f} s",
        "",
        f"mAP@0.5 against the teacher's boxes, {f['held_out']} held-back frames:",
        "",
        "| sensors on | before | after |",
        "|---|---:|---:|",
    ]
    for name, before in report["before"].items():
        lines.append(f"| {name} | {_fmt(before)} | {_fmt(report['after'][name])} |")
    return "\n".join(lines) + "\n\n" + json.dumps({"before": report["before"], "after": report["after"]})


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"
