"""``respecd calibrate``: fit the detector's confidence calibration per RGB size and write it into a checkpoint.

The net's raw confidence for the same person depends on the RGB size the controller runs; the
daemon drops every box under one threshold and the controller reads ConfAgg across sizes, so
the shipped checkpoint carries a per-size Platt map fitted here (docs/PERCEPTION.md
"Confidence calibration"). The state dict is copied unchanged; only ``score_calibration`` is
added (or replaced: the fit always starts from the raw confidences). ``--check-seed`` scores the
fitted map on a second world that took no part in the fit.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from respecd.argtypes import non_negative_int, positive_int, seed
from respecd.errors import InputError
from respecd.outputs import check_output_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", required=True, help="checkpoint to calibrate: a path or builtin:NAME")
    parser.add_argument("--out", required=True, type=Path,
                        help="calibrated checkpoint to write (may be --weights' own file); its card goes beside it")
    parser.add_argument("--seed", type=seed, default=2_000_003,
                        help="world seed of the simulated scenes the map is fitted on (default 2000003, a "
                             "validation world: neither training nor respecd eval's default uses it)")
    parser.add_argument("--check-seed", type=non_negative_int, default=None,
                        help="also score the map on this world (e.g. 3000003); nothing is fitted there")
    parser.add_argument("--frames", type=int, default=40, help="instants per scenario (default 40)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads, at least 1 (default 1)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    parser.add_argument("--no-progress", dest="quiet", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    check_output_file("--out", args.out, example="model.pt")  # before the fit; save_payload makes the folders
    check_output_file("--json", args.json, example="calibration.json")
    import torch

    from respecd.lab.detector import calibrate
    from respecd.perception import checkpoint
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.detector import FusionDetector

    if args.frames < 2:
        raise InputError(f"--frames {args.frames}: expected at least 2 instants per scenario")
    torch.set_num_threads(args.threads)
    source = checkpoint.resolve(args.weights)
    model, payload = checkpoint.load(args.weights)  # raw confidences: load never applies a calibration
    if "sim" != payload.get("data"):
        raise InputError(f"--weights {args.weights}: trained on {payload.get('data')!r}; respecd calibrate fits on "
                         "the simulated rover's worlds and needs a checkpoint trained with --data sim")
    config = PerceptionConfig(weights=args.weights, model=model.spec, score_threshold=0.01)  # every box, as eval
    detector = FusionDetector(model, config)
    images = calibrate.resolution_images(detector, args.frames, args.seed, progress=not args.quiet)
    calibration = calibrate.fit(images)
    report = {"frames_per_scenario": args.frames,
              "fit": {"seed": args.seed, "sizes": calibrate.measure(images, calibration)}}
    if args.check_seed is not None:
        held_out = calibrate.resolution_images(detector, args.frames, args.check_seed, progress=not args.quiet)
        report["check"] = {"seed": args.check_seed, "sizes": calibrate.measure(held_out, calibration)}
    report["command"] = "respecd " + " ".join(sys.argv[1:])
    checkpoint.save_payload(args.out, {**payload, "score_calibration": calibration.to_payload()})
    _write_card(source, args.out, calibration.to_payload(), report)
    print(table(report))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {args.out}" + (f", {args.json}" if args.json else ""))
    return 0


def table(report: dict) -> str:
    """Markdown: per size, the map and what it does at the daemon's threshold (fit world, then check world)."""
    lines = ["| world | size | a | b | boxes (matched) | raw confidence at the threshold | calibration error raw → "
             "calibrated | delivered mAP@0.5 raw → calibrated |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for label in ("fit", "check"):
        part: dict = report.get(label) or {"sizes": {}}
        for size, m in part["sizes"].items():
            lines.append(f"| {label} {part['seed']} | {size} | {m['a']:.3f} | {m['b']:.3f} | "
                         f"{m['boxes']} ({m['matched']}) | {m['raw_confidence_at_threshold']:.3f} | "
                         f"{m['ece_raw']:.3f} → {m['ece_calibrated']:.3f} | "
                         f"{m['delivered_map50_raw']:.3f} → {m['delivered_map50_calibrated']:.3f} |")
    return "\n".join(lines)


def _write_card(source: Path, out: Path, table_payload: dict, report: dict) -> None:
    """The source checkpoint's card, copied beside ``out`` with the calibration and how it was fitted."""
    card = source.with_suffix(".json")
    body = json.loads(card.read_text(encoding="utf-8")) if card.is_file() else {}
    body["score_calibration"] = {"table": table_payload, **report}
    body["checkpoint_bytes"] = out.stat().st_size
    out.with_suffix(".json").write_text(json.dumps(body, indent=2) + "\n", encoding="utf-8")
