"""``respecd eval``: mAP@0.5 and mAP@0.5:0.95 with and without each modality, and the mean
contribution scores per condition (day / night / occlusion / motion), as a Markdown table,
a PNG bar chart and JSON.

``--data sim`` renders held-out frames of the simulated scenarios (world seeds training
never uses); a folder in the LLVIP layout is evaluated pair by pair at half resolution.
Detections are scored down to confidence 0.01 (the usual mAP protocol), not the
daemon's operating threshold.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from respecd.errors import InputError

EVAL_SCORE_THRESHOLD = 0.01


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", default="sim", help="'sim' (held-out simulated scenes) or an LLVIP-layout folder")
    parser.add_argument("--weights", default="builtin:sim-rover", help="checkpoint path or builtin:NAME")
    parser.add_argument("--out", type=Path, default=Path("out/eval"),
                        help="folder for eval.md, contributions.png, eval.json")
    parser.add_argument("--frames", type=int, default=40, help="sim: frames per scenario (default 40)")
    parser.add_argument("--rgb", default="640x360", help="sim: RGB resolution WxH (default 640x360)")
    parser.add_argument("--scale", type=float, default=0.5, help="LLVIP: image scale (default 0.5 of 1280x1024)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--no-progress", "--quiet", dest="quiet", action="store_true",
                        help="no progress bars (--quiet is the old name)")


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise InputError(f"--rgb {text}: expected WIDTHxHEIGHT, e.g. 640x360") from err
    if w < 32 or h < 32:
        raise InputError(f"--rgb {text}: expected at least 32x32")
    return w, h


def main(args: argparse.Namespace) -> int:
    import torch

    from respecd.lab.detector import report as report_mod
    from respecd.lab.detector.evaluate import evaluate, sim_eval_set
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.detector import FusionDetector

    torch.set_num_threads(args.threads)
    pcfg = PerceptionConfig(weights=args.weights, score_threshold=EVAL_SCORE_THRESHOLD)
    if args.data == "sim":
        size = _resolution(args.rgb)
        detector = FusionDetector.load(pcfg.model_copy(update={"model": _spec_of(args.weights)}))
        samples = sim_eval_set(detector.config, args.frames, size, progress=not args.quiet)
        title = f"Simulated rover, held-out scenes, RGB {size[0]}x{size[1]} ({args.weights})"
    else:
        from respecd.lab.detector.data import LlvipSource

        root = Path(args.data)
        if not root.is_dir():
            raise InputError(f"--data {args.data}: expected 'sim' or an LLVIP-layout folder")
        detector = FusionDetector.load(pcfg.model_copy(update={"model": _spec_of(args.weights)}))
        source = LlvipSource(root, detector.config, args.scale)
        samples = [source[i] for i in range(len(source))]
        title = f"LLVIP layout {root.name} ({len(samples)} pairs, scale {args.scale}) ({args.weights})"
    result = evaluate(detector, samples, progress=not args.quiet)
    paths = report_mod.write(result, args.out, title)
    print(report_mod.markdown(result, title))
    print(f"wrote {paths['markdown']}, {paths['png']}, {paths['json']}")
    return 0


def _spec_of(weights: str):
    """The checkpoint's own spec: eval takes whatever network the file holds."""
    from respecd.perception import checkpoint
    from respecd.perception.config import ModelSpec

    payload = checkpoint.read(checkpoint.resolve(weights))
    return ModelSpec.model_validate(payload["spec"])
