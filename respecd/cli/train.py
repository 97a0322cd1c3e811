"""``respecd train``: train the fusion detector on the simulated rover or an LLVIP-layout folder.

The defaults are the recipe of the shipped ``builtin:sim-rover`` checkpoint (``make
weights``). Writes OUT (state dict + spec), OUT with .json (the model card) and, after each
epoch, OUT.resume so that ``--resume`` continues an interrupted run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from respecd.argtypes import non_negative_int, positive_float, positive_int, seed, unit_interval
from respecd.errors import InputError
from respecd.outputs import check_output_file

if TYPE_CHECKING:
    from respecd.lab.detector.augment import AugmentConfig
    from respecd.lab.detector.train import ExtraFolder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True,
                        help="'sim' (simulated rover) or a folder: LLVIP/VOC pairs, COCO json or YOLO txt")
    parser.add_argument("--out", required=True, type=Path, help="checkpoint to write (.pt); the card goes beside it")
    parser.add_argument("--epochs", type=non_negative_int, default=10,
                        help="epochs of --steps steps each (default 10; 0 with --init: import, no training)")
    parser.add_argument("--batch", type=positive_int, default=None,
                        help="sim: strips per step at 640x360, fewer at larger sizes (default 10); "
                             "folder data: crops per step (default 16)")
    parser.add_argument("--lr", type=positive_float, default=2e-3, help="AdamW peak learning rate > 0 (default 0.002)")
    parser.add_argument("--seed", type=seed, default=0,
                        help="seed >= 0 of the simulated world and the augmentation")
    parser.add_argument("--steps", type=non_negative_int, default=100,
                        help="steps per epoch (0: one pass over the pool; default 100)")
    # 1 thread: on a 2-core box shared with other work, two spin-waiting threads ran 3x slower per step
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads, at least 1 (default 1)")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                        help="bf16: forward and backward under CPU autocast (about 1.5x faster per step where the CPU "
                             "has AVX512-BF16 or AMX, slower where not); weights and loss stay fp32 (default fp32)")
    parser.add_argument("--eval-frames", type=non_negative_int, default=10,
                        help="sim: held-out instants per scenario evaluated for the model card (0: skip; default 10)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT.resume if present")
    parser.add_argument("--init", help="start from this checkpoint (path or builtin:NAME) or Darknet .weights file "
                        "(RGB.weights,AUX.weights: backbone 2 from another Darknet model)")
    parser.add_argument("--aux", default="thermal,radar",
                        help="non-RGB modalities of a new net, in order (default thermal,radar)")
    parser.add_argument("--aux-scale", type=positive_float, default=1.0,
                        help="Darknet nets: backbone 2 sees the aux planes at this scale (default 1.0)")
    parser.add_argument("--rgb-aware-fusion", action="store_true",
                        help="Darknet nets from .weights: the aux evidence gets its own 1x1 map while RGB is on too "
                             "(fuse.*.both, started as W_aux): the aux sensors alone and beside RGB train apart")
    parser.add_argument("--freeze", default="",
                        help="comma-separated parts kept fixed, e.g. rgb,head,fuse or fuse.*.rgb")
    parser.add_argument("--reinit", default="",
                        help="comma-separated parts of --init's net given fresh weights first, e.g. aux (a new "
                             "thermal branch; with --epochs 0: a checkpoint whose thermal path is damaged)")
    parser.add_argument("--patience", type=non_negative_int, default=0,
                        help="folder data: stop after N epochs without a better validation mAP@0.5 (0: never)")
    parser.add_argument("--modality", choices=("auto", "rgb", "thermal"), default="auto",
                        help="folder data of one modality: which (auto: single-channel images are thermal)")
    parser.add_argument("--scale", type=positive_float, default=0.5,
                        help="folder data: decode images at this scale > 0 (default 0.5)")
    parser.add_argument("--val-limit", type=positive_int, default=300,
                        help="folder data: validation images scored per epoch, evenly spaced, at least 1 "
                             "(default 300)")
    parser.add_argument("--val-scale", type=positive_float,
                        help="folder data: validation image scale > 0 (default --scale)")
    parser.add_argument("--crop", default="256x160", help="training crop WxH, multiples of 32 (default 256x160)")
    parser.add_argument("--zoom", default="0.6,2.0", help="training zoom range LO,HI of the decoded image")
    parser.add_argument("--strip-zoom", action="append", metavar="[WxH=]LO,HI",
                        help="sim: zoom range LO,HI of the full-height training strips (default 0.8,1.25); "
                             "WxH=LO,HI sets one RGB size's range (repeat the flag for several)")
    parser.add_argument("--keep-cut", type=unit_interval, default=0.9,
                        help="a box a training window cuts to less than this share 0..1 of its area is ignored, "
                             "not a positive (default 0.9)")
    parser.add_argument("--radar-alone", type=unit_interval, default=0.12,
                        help="modality dropout: weight of 'radar only' among the kept-sensor subsets (default 0.12)")
    parser.add_argument("--scenario-weight", default="", metavar="NAME=W,...",
                        help="sim: how often a scenario is drawn, relative to 1 (default: simdata.SCENARIO_WEIGHTS)")
    parser.add_argument("--resolution-weight", default="", metavar="WxH=W,...",
                        help="sim: how often an RGB resolution is drawn per step, relative to 1 (default: uniform)")
    parser.add_argument("--sim-mix", type=float, default=0.0, metavar="P",
                        help="folder data: draw this share of steps from the simulator instead, 0 <= P < 1 "
                             "(default 0: the folder only)")
    parser.add_argument("--extra-data", action="append", metavar="DIR=SHARE[@LO,HI]",
                        help="folder data: another folder's train split gives SHARE (0..1) of the crops, zoomed by "
                             "LO,HI if given (default --zoom); repeat for several; --data's val split validates")
    parser.add_argument("--pseudo-rgb", type=unit_interval, default=0.0,
                        help="thermal-only data: share 0..1 of crops whose RGB shows the thermal image (default 0)")
    parser.add_argument("--curve", type=Path, metavar="PNG",
                        help="training curve: loss per epoch and the held-out mAP (default: OUT with -curve.png)")
    parser.add_argument("--no-progress", "--quiet", dest="quiet", action="store_true",
                        help="no progress bars (--quiet is the old name)")


def main(args: argparse.Namespace) -> int:
    check_output_file("--out", args.out, example="model.pt")  # before training; checkpoint.save makes the folders
    check_output_file("--curve", args.curve or args.out.with_name(args.out.stem + "-curve.png"))
    from respecd.lab.detector.augment import AugmentConfig
    from respecd.lab.detector.train import TrainConfig, train
    from respecd.perception.config import PerceptionConfig

    _check(args)
    zoom, zoom_at = _strip_zoom(args.strip_zoom or [])
    augment = AugmentConfig(size=_pair(args.crop, "--crop", int), scale=_pair(args.zoom, "--zoom", float, ","),
                            zoom=zoom, zoom_at=zoom_at, pseudo_rgb=args.pseudo_rgb, keep_cut=args.keep_cut)
    augment = _with_radar_alone(augment, args.radar_alone)
    if augment.size[0] % 32 or augment.size[1] % 32:
        raise InputError(f"--crop {args.crop}: both sides must be multiples of 32")
    sim = args.data == "sim"
    cfg = TrainConfig(
        data=args.data, out=args.out, epochs=args.epochs, batch=16 if sim else (args.batch or 16),
        sim_batch=(args.batch or 10) if sim else min(args.batch or 10, 10), lr=args.lr, seed=args.seed,
        steps_per_epoch=args.steps, threads=args.threads, resume=args.resume,
        progress=not args.quiet, augment=augment, init=args.init,
        freeze=tuple(p for p in args.freeze.split(",") if p), reinit=tuple(p for p in args.reinit.split(",") if p),
        patience=args.patience, modality=args.modality,
        data_scale=args.scale, val_scale=args.val_scale, val_limit=args.val_limit,
        scenario_weights=_scenario_weights(args.scenario_weight),
        resolution_weights=_resolution_weights(args.resolution_weight), sim_mix=args.sim_mix,
        extra_data=_extra_data(args.extra_data or [], args.data),
        precision=args.precision,
    )
    aux = tuple(m for m in args.aux.split(",") if m)
    try:
        pcfg = PerceptionConfig(model={"aux_modalities": aux, "aux_scale": args.aux_scale,
                                       "rgb_aware_fusion": args.rgb_aware_fusion})
    except ValueError as err:
        raise InputError(f"--aux {args.aux} --aux-scale {args.aux_scale}: expected modalities among thermal, radar, "
                         "depth and a scale above 0.1, at most 1") from err
    summary = train(cfg, pcfg)
    train_input = "strips 320 wide, full frame height" if sim else list(cfg.augment.size)
    card = {"name": args.out.stem, "data": args.data, "input_sizes": {"train": train_input,
            "rgb": [[1280, 720], [960, 540], [640, 360]]}, "train": summary, "metrics": None}
    if args.data == "sim" and args.eval_frames > 0:
        card["metrics"] = _card_metrics(args, pcfg)
    elif summary["best_epoch"] is not None:
        best = next(r for r in summary["curve"] if r["epoch"] == summary["best_epoch"])
        card["metrics"] = {"val_map50": best["val_map50"], "best_epoch": summary["best_epoch"],
                           "val": "the folder's val split (or a seeded 10 % hold-out)"}
    from respecd.perception import checkpoint

    model, _ = checkpoint.load(str(args.out))
    card_path = checkpoint.write_card(args.out, model, card)
    curve = save_curve(summary, card["metrics"], args.curve or args.out.with_name(args.out.stem + "-curve.png"))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.1f} MB), {card_path} and {curve}")
    print(json.dumps({"train_s": summary["train_s"], "metrics": card["metrics"]}, indent=2))
    return 0


def save_curve(summary: dict, metrics: dict | None, path: Path) -> Path:
    """Loss per epoch and, when the card has one, the held-out mAP@0.5 reached."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs, losses = zip(*summary["epoch_loss"], strict=True) if summary["epoch_loss"] else ((), ())
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    ax.plot(epochs, losses, "o-", color="#1f4e8c", label="training loss (running mean at epoch end)")
    ax.set_xlabel("epoch")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_ylabel("detection loss (box + class)")
    map50 = ((metrics or {}).get("by_resolution") or {}).get("640x360", {}).get("map50")  # every sensor on
    val = [(r["epoch"], r["val_map50"]) for r in summary.get("curve", []) if r.get("val_map50") is not None]
    if val:  # folder data: the validation mAP of every epoch; the best one is the result
        ax2 = ax.twinx()
        ax2.plot(*zip(*val, strict=True), "s-", color="#c67a3a", label="validation mAP@0.5 (EMA weights)")
        best = max(val, key=lambda v: v[1])
        ax2.annotate(f"best {best[1]:.3f}", best, textcoords="offset points", xytext=(0, 8), ha="center")
        ax2.set_ylim(0, 1)
        ax2.set_ylabel("mAP@0.5", color="#c67a3a")
    elif isinstance(map50, (int, float)):
        ax2 = ax.twinx()
        ax2.plot([epochs[-1]], [map50], "s", color="#c67a3a", label=f"held-out mAP@0.5 = {map50:.3f}")
        ax2.set_ylim(0, 1)
        ax2.set_ylabel("mAP@0.5", color="#c67a3a")
    steps = summary["steps"] // max(1, summary["epochs"])
    ax.set_title(f"respecd train: {summary['data']}, {summary['epochs']} epochs of {steps} steps")
    handles = [h for a in fig.axes for h in a.get_legend_handles_labels()[0]]
    fig.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 0.9), fontsize=8)  # outside the data
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    return path


def _check(args: argparse.Namespace) -> None:
    if args.epochs < (0 if args.init else 1) or (args.batch is not None and args.batch < 1):  # --epochs 0 --init
        raise InputError(f"--epochs and --batch must be at least 1, or --epochs 0 with --init "
                         f"(got {args.epochs}, {args.batch})")
    if args.data != "sim" and not Path(args.data).is_dir():
        raise InputError(f"--data {args.data}: expected 'sim' or a dataset folder (LLVIP/VOC, COCO json, YOLO txt)")
    if not 0.0 <= args.sim_mix < 1.0 or (args.sim_mix and args.data == "sim"):
        raise InputError(f"--sim-mix {args.sim_mix}: expected a share 0 <= P < 1 of steps, with --data a folder")
    if args.out.suffix != ".pt":
        raise InputError(f"--out {args.out}: expected a .pt file name")
    if args.reinit and not args.init:
        raise InputError(f"--reinit {args.reinit}: re-initialises parts of --init's net; give --init")


def _extra_data(items: list[str], data: str) -> tuple[ExtraFolder, ...]:
    """['DIR=0.3@1.5,4', ...] -> the extra folders; their shares leave the --data folder some of the crops."""
    from respecd.lab.detector.train import ExtraFolder

    extras = []
    for item in items:
        path, sep, rest = item.rpartition("=")
        share_text, _, zoom_text = rest.partition("@")
        try:
            share = float(share_text)
        except ValueError:
            share = -1.0
        if not sep or not path or not 0 < share < 1:
            raise InputError(f"--extra-data {item}: expected DIR=SHARE[@LO,HI] with 0 < SHARE < 1")
        if data == "sim" or not Path(path).is_dir():
            raise InputError(f"--extra-data {item}: expected a dataset folder, with --data a folder too")
        zoom = _pair(zoom_text, "--extra-data", float, ",") if zoom_text else None
        extras.append(ExtraFolder(path, share, zoom))
    if sum(e.share for e in extras) >= 1:
        raise InputError(f"--extra-data: the shares add up to {sum(e.share for e in extras):g}; "
                         "they must leave --data some of the crops (below 1)")
    return tuple(extras)


def _with_radar_alone(augment: AugmentConfig, weight: float) -> AugmentConfig:
    """The dropout table with the 'radar only' subset's weight replaced (the others keep theirs)."""
    return dataclasses.replace(augment, keep=tuple((s, weight if s == ("radar",) else p) for s, p in augment.keep))


K = TypeVar("K")


def _weight_list(text: str, flag: str, names: dict[str, K], label: str = "NAME") -> dict[K, float]:
    """'A=3,B=2' -> {key of A: 3.0, key of B: 2.0}; ``names`` maps each accepted name (lower case) to its key."""
    weights: dict[K, float] = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        try:
            weight = float(value)
        except ValueError:
            weight = -1.0
        if name.lower() not in names or weight < 0:
            raise InputError(f"{flag} {item}: expected {label}=W with {label} one of {', '.join(names)} and W >= 0")
        weights[names[name.lower()]] = weight
    return weights


def _scenario_weights(text: str) -> dict[str, float] | None:
    """'behind-curtain=3,occlusion-partial=2' -> the simulator's draw weights with these replaced."""
    if not text:
        return None
    from respecd.lab.detector.simdata import SCENARIO_WEIGHTS
    from respecd.sim.world import SCENARIOS

    given = _weight_list(text, "--scenario-weight", {name: name for name in SCENARIOS})
    return {**SCENARIO_WEIGHTS, **given}


def _resolution_weights(text: str) -> dict[tuple[int, int], float] | None:
    """'640x360=2' -> {(640, 360): 2.0}; the other controller resolutions keep weight 1."""
    if not text:
        return None
    from respecd.lab.detector.simdata import RESOLUTIONS

    weights = _weight_list(text, "--resolution-weight", {f"{w}x{h}": (w, h) for w, h in RESOLUTIONS}, "WxH")
    if not any(weights.get(size, 1.0) > 0 for size in RESOLUTIONS):
        raise InputError(f"--resolution-weight {text}: at least one resolution needs a weight above 0")
    return weights


def _strip_zoom(items: list[str]) -> tuple[tuple[float, float], tuple]:
    """['0.7,2.0', '640x360=0.7,1.4'] -> ((0.7, 2.0), (((640, 360), (0.7, 1.4)),)): the default range
    (0.8,1.25 unless a plain LO,HI is given) and the per-size ones."""
    from respecd.lab.detector.simdata import RESOLUTIONS

    sizes = {f"{w}x{h}": (w, h) for w, h in RESOLUTIONS}
    zoom, zoom_at = (0.8, 1.25), {}
    for item in items:
        name, sep, span = item.rpartition("=")
        if sep and name.lower() not in sizes:
            raise InputError(f"--strip-zoom {item}: expected LO,HI or WxH=LO,HI with WxH one of {', '.join(sizes)}")
        pair = _pair(span, "--strip-zoom", float, ",")
        if sep:
            zoom_at[sizes[name.lower()]] = pair
        else:
            zoom = pair
    return zoom, tuple(sorted(zoom_at.items()))


def _pair(text: str, flag: str, kind, sep: str = "x") -> tuple:
    try:
        a, b = (kind(v) for v in text.lower().split(sep))
    except ValueError as err:
        raise InputError(f"{flag} {text}: expected two numbers separated by {sep!r}") from err
    if a <= 0 or b <= 0 or (sep == "," and a > b):
        raise InputError(f"{flag} {text}: expected positive numbers{' with LO <= HI' if sep == ',' else ''}")
    return a, b


def _card_metrics(args: argparse.Namespace, pcfg) -> dict:
    """Held-out sim mAP per resolution and with each sensor off, contributions, faithfulness, for the card."""
    from respecd.lab.detector.evaluate import evaluate_sim
    from respecd.perception.detector import FusionDetector

    eval_cfg = pcfg.model_copy(update={"weights": str(args.out), "score_threshold": 0.01})
    report = evaluate_sim(FusionDetector.load(eval_cfg), args.eval_frames, progress=not args.quiet)
    keep = ("by_resolution", "ablation", "contributions", "faithfulness", "frames", "attribution")
    return {"eval_frames_per_scenario": args.eval_frames, **{k: report[k] for k in keep}}
