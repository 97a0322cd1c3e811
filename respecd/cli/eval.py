"""``respecd eval``: mAP@0.5 at every RGB resolution the controller can choose, mAP with each
sensor off, the contribution scores per condition and the faithfulness of their ranking
(deletion test), as Markdown tables, a PNG bar chart and JSON (``eval.json``; its keys are
listed in docs/PERCEPTION.md).

``--data sim`` renders held-out instants of the simulated scenarios (a world seed training
never uses) at 640x360, 960x540 and 1280x720; the ablation, contributions and deletion test
run at ``--rgb``. Contributions are those of the daemon's operating point (its score
threshold and attribution targets). A folder (LLVIP/VOC pairs, COCO json, YOLO txt; see ``lab/detector/datasets``)
is evaluated image by image at ``--scale`` (its val split if it has one). Detections are
scored down to confidence 0.01 (the usual mAP protocol), not the daemon's operating
threshold; the detection counts use the operating threshold. For a folder, eval.json also
has the top-level ``map50``, ``contributions`` (mean scene scores), ``dependence``,
``sufficiency`` and ``shapley`` (per sensor, means over the images with a detection),
``detections`` and ``detections_without_rgb``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from respecd.argtypes import positive_float, positive_int, resolution, seed, unit_interval
from respecd.errors import InputError
from respecd.outputs import check_output_dir

EVAL_SCORE_THRESHOLD = 0.01


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", default="sim",
                        help="'sim' (held-out simulated scenes) or a folder: LLVIP/VOC pairs, COCO json, YOLO txt")
    parser.add_argument("--weights", default="builtin:sim-rover",
                        help="checkpoint path, builtin:NAME, or a Darknet .weights file (imported untrained)")
    parser.add_argument("--out", type=Path, default=Path("out/eval"),
                        help="folder for eval.md, contributions.png, eval.json")
    parser.add_argument("--frames", type=positive_int, default=40,
                        help="sim: instants per scenario, at least 1 (default 40)")
    parser.add_argument("--seed", type=seed, default=None,
                        help="sim: world seed of the held-out scenes (default 1000003; training uses 0)")
    parser.add_argument("--rgb", default="640x360",
                        help="sim: RGB size WxH of the ablation, contributions and deletion test (default 640x360)")
    parser.add_argument("--method", choices=("ablation", "gradient"), default=None,
                        help="contribution method (default: the profile's, ablation)")
    parser.add_argument("--attribution-threshold", type=unit_interval, default=None,
                        help="confidence 0..1 a detection needs to be attributed (default: the daemon's, 0.25)")
    parser.add_argument("--scale", type=positive_float, default=0.5,
                        help="folder data: image scale > 0 (default 0.5: LLVIP's 1280x1024 -> 640x512)")
    parser.add_argument("--split", choices=("auto", "all", "train", "val"), default="auto",
                        help="folder data: which images (auto: the val split if the folder has one, else all)")
    parser.add_argument("--modality", choices=("auto", "rgb", "thermal"), default="auto",
                        help="folder data of one modality: which (auto: single-channel images are thermal)")
    parser.add_argument("--runtime", choices=("torch", "onnxruntime", "openvino"), default="torch",
                        help="what runs the net (perception.runtime; default torch): the exported graphs through "
                             "ONNX Runtime or OpenVINO")
    parser.add_argument("--precision", choices=("f32", "bf16", "f16"), default="f32",
                        help="inference precision of --runtime (perception.precision; default f32)")
    # 1 thread: on a 2-core box shared with other work, two spin-waiting threads ran up to 10x slower
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads, at least 1 (default 1)")
    parser.add_argument("--no-progress", "--quiet", dest="quiet", action="store_true",
                        help="no progress bars (--quiet is the old name)")
    parser.add_argument("--card", action="store_true",
                        help="folder data: also record the top-level results in the checkpoint's card (WEIGHTS .json)")


def main(args: argparse.Namespace) -> int:
    check_output_dir("--out", args.out)  # before the evaluation, not after it (report.write makes the folders)
    import torch

    from respecd.lab.detector import report as report_mod
    from respecd.lab.detector.evaluate import EVAL_SEED, OPERATING_THRESHOLD, evaluate_samples, evaluate_sim

    seed = EVAL_SEED if args.seed is None else args.seed  # --seed >= 0: checked by its argparse type
    torch.set_num_threads(args.threads)
    pcfg = _perception(args)
    detector = _detector(args.weights, pcfg)
    summary = None
    threshold = args.attribution_threshold if args.attribution_threshold is not None else OPERATING_THRESHOLD
    if args.data == "sim":
        result = evaluate_sim(detector, args.frames, resolution(args.rgb, "--rgb"), seed=seed,
                              progress=not args.quiet, attribution_threshold=threshold)
        title = f"Simulated rover, held-out scenes, world seed {seed} ({args.weights})"
    else:
        samples, title = _folder_samples(args, detector.config)
        result = evaluate_samples(detector, samples, progress=not args.quiet, attribution_threshold=threshold)
        summary = folder_summary(result)
        if args.card:
            _record_in_card(args, summary, len(samples), title)
    paths = report_mod.write(result, args.out, title, summary)
    print(report_mod.markdown(result, title))
    print(f"wrote {paths['markdown']}, {paths['png']}, {paths['json']}")
    return 0


def _folder_samples(args: argparse.Namespace, config) -> tuple[Any, str]:
    """The folder's evaluation images: its val split when it has one (else all), ``--split`` to choose."""
    from respecd.lab.detector.datasets import FolderSource, open_folder

    root = Path(args.data)
    if not root.is_dir():
        raise InputError(f"--data {args.data}: expected 'sim' or a dataset folder (LLVIP/VOC, COCO json, YOLO txt)")
    folder = open_folder(root, config.model.classes, args.modality, hold_out=False)
    split = args.split if args.split != "auto" else ("val" if folder.val else "all")
    items = {"all": folder.train + folder.val, "train": folder.train, "val": folder.val}[split]
    if not items:
        raise InputError(f"--data {args.data}: the {split} split is empty")
    source = FolderSource(items, config, args.scale, cache=1, scenario=root.name)  # decoded one at a time
    mods = "+".join(sorted(folder.modalities))
    return source, f"{root.name}: {folder.kind}, {split} split, {len(source)} images ({mods}), scale {args.scale} " \
                    f"({args.weights})"


def folder_summary(result: dict) -> dict:
    """Top-level eval.json keys for a real folder: mAP@0.5, mean scene contributions, dependence and
    sufficiency per sensor (the attribution method's, those it has), detection counts."""
    from respecd.lab.detector.evaluate import REDUNDANCY

    contributions = result["contributions"].get("all", {})
    return {
        "map50": result["map"]["all"]["none"]["map50"],
        "contributions": contributions,
        **{name: result[name].get("all", {}) for name in REDUNDANCY if name in result},
        "detections": result["detections"]["all"]["none"],
        "detections_without_rgb": result["detections"]["all"]["no_rgb"],
    }


def _record_in_card(args: argparse.Namespace, summary: dict, images: int, title: str) -> None:
    """The measured figures go into the model card, with the command that measured them."""
    import json
    import sys

    from respecd.perception import checkpoint

    if args.weights.endswith(".weights"):
        raise InputError("--card: a Darknet .weights file has no respecd card (import it with respecd train --init)")
    card = checkpoint.resolve(args.weights).with_suffix(".json")
    body = json.loads(card.read_text(encoding="utf-8")) if card.is_file() else {}
    body.setdefault("evaluations", {})[Path(args.data).name] = {
        **summary, "images": images, "what": title, "command": "respecd " + " ".join(sys.argv[1:]),
    }
    card.write_text(json.dumps(body, indent=2) + "\n", encoding="utf-8")


def _perception(args: argparse.Namespace) -> Any:
    """The perception config of the evaluated detector: every box, the runtime and precision asked for."""
    from pydantic import ValidationError

    from respecd.perception.config import PerceptionConfig

    if args.runtime != "torch" and args.weights.endswith(".weights"):
        raise InputError(f"--runtime {args.runtime}: exports a respecd checkpoint, not a Darknet .weights file")
    method = {"attribution_method": args.method} if args.method else {}
    try:
        return PerceptionConfig(weights=args.weights, score_threshold=EVAL_SCORE_THRESHOLD, runtime=args.runtime,
                                precision=args.precision, torch_threads=args.threads, **method)
    except ValidationError as err:
        raise InputError(f"--runtime {args.runtime}: {err.errors()[0]['msg'].removeprefix('Value error, ')}") from err


def _detector(weights: str, pcfg):
    """The checkpoint's own net; a Darknet ``.weights`` file is imported untrained into the fusion net
    (thermal = the same pretrained detector on replicated IR): the single-modality baselines."""
    from respecd.perception import checkpoint
    from respecd.perception.config import ModelSpec
    from respecd.perception.detector import FusionDetector

    if weights.endswith(".weights"):
        from respecd.perception.darknet_fusion import from_darknet

        if not Path(weights).is_file():
            raise InputError(f"--weights {weights}: no such Darknet weights file")
        spec = ModelSpec(backbone=f"darknet:{Path(weights).stem}", aux_modalities=("thermal",))
        config = pcfg.model_copy(update={"model": spec})
        return FusionDetector(from_darknet(spec, Path(weights)), config)
    return FusionDetector.load(pcfg.model_copy(update={"model": checkpoint.spec_of(weights)}))
