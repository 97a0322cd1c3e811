"""Training loop: sim or folder data, AdamW + warmup/cosine, EMA weights, resumable.

On the simulator every step renders fresh frames at one of the three RGB resolutions and
trains on full-height strips of them (``simdata.SimStream``); a dataset folder gives
fixed-size crops and mosaics of its images. Every epoch ends with a resume file
(``OUT.resume``: model, EMA, optimizer, epoch); ``--resume`` picks it up, and since each
epoch's batches come from a generator seeded by (seed, epoch) a resumed run sees the same
data. The final file holds the EMA weights (they generalize better than the raw ones after
a short schedule) and a JSON card beside it.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
import structlog
import torch
from torch import nn

from respecd.errors import InputError
from respecd.lab.detector.augment import AugmentConfig, augment, collate
from respecd.lab.detector.finetune import finite, freeze, initial_model, keep_frozen_eval, reinit, validation_map
from respecd.lab.detector.loss import detection_loss
from respecd.lab.detector.yolo_loss import yolo_loss
from respecd.perception import checkpoint
from respecd.perception.config import PerceptionConfig
from respecd.perception.darknet_fusion import DarknetFusionNet
from respecd.perception.model import FusionNet

if TYPE_CHECKING:
    from respecd.lab.detector.data import Sample
    from respecd.lab.detector.simdata import SimStream

log = structlog.get_logger(__name__)


@dataclass
class TrainConfig:
    data: str  # "sim" or a dataset folder
    out: Path
    epochs: int = 10
    batch: int = 16  # folder data: crops per step (the simulator: sim_batch)
    lr: float = 2e-3
    weight_decay: float = 5e-4
    seed: int = 0
    sim_batch: int = 10  # strips per step at 640x360, fewer at larger sizes (simdata.SimStream)
    steps_per_epoch: int = 100  # folder data: 0 = one pass over the pool in batches
    threads: int = 1
    resume: bool = False
    progress: bool = True
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    init: str | None = None  # checkpoint or Darknet .weights to start from (finetune.initial_model)
    freeze: tuple[str, ...] = ()  # top-level parts kept as they are (e.g. "rgb", "head")
    reinit: tuple[str, ...] = ()  # parts given fresh weights before training (e.g. "aux")
    patience: int = 0  # folder data: stop after this many epochs without a better val mAP (0: never)
    modality: str = "auto"  # folder data whose images are one modality: rgb, thermal or auto
    data_scale: float = 0.5  # folder data: images decoded at this scale (LLVIP 1280x1024 -> 640x512)
    val_scale: float | None = None  # validation images at this scale (default: data_scale)
    val_limit: int = 300  # at most this many validation images per epoch (evenly spaced)
    scenario_weights: dict[str, float] | None = None  # sim: draw weights (None: simdata.SCENARIO_WEIGHTS)
    resolution_weights: dict[tuple[int, int], float] | None = None  # sim: RGB size draw weights (None: uniform)
    sim_mix: float = 0.0  # folder data: share of steps drawn from the simulator instead (0: folder only)
    extra_data: tuple[ExtraFolder, ...] = ()  # folder data: more folders' train splits, each a share of the crops
    precision: str = "fp32"  # "bf16": forward and backward under CPU autocast (weights and loss stay fp32)
    extra_loss: Callable[[nn.Module], torch.Tensor] | None = None  # a term added to every step's loss (adapt.py)


@dataclass(frozen=True)
class ExtraFolder:
    """Another folder whose train split (never its val split) gives ``share`` of the folder crops, zoomed by
    ``zoom`` (None: the run's ``--zoom``): e.g. drone-view thermal people, which need zooming in to be seen."""

    path: str
    share: float
    zoom: tuple[float, float] | None = None


class Samples(Protocol):
    """Anything indexable of Samples: a folder read lazily (``FolderSource``) or a list (adapt's frames)."""

    def __len__(self) -> int: ...

    def __getitem__(self, i: int, /) -> Sample: ...


Batch = tuple[list["Sample"], tuple[int, int]]  # one step's samples, (width, height) of its input


def draw_batches(pool, seed: int, first_epoch: int, epochs: int, steps: int) -> Iterator[Batch]:
    """Every step's batch, epoch by epoch; one generator per epoch, so a resumed run replays the same batches."""
    for epoch in range(first_epoch, epochs):
        rng = np.random.default_rng([seed, epoch, 11])
        for _ in range(steps):
            yield pool.draw(rng)


class EMA:
    """Exponential moving average of the weights; decay ramps up so early steps count."""

    def __init__(self, model: checkpoint.Net, decay: float = 0.999, tau: float = 300.0) -> None:
        self.model: checkpoint.Net = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, 0

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """One step of the average toward ``model``. Both state dicts are read afresh (under a millisecond):
        moving a net (``.to(memory_format=...)``) gives its parameters new storage, so pairs kept from an
        earlier call could be stale. The floating-point tensors move in one foreach lerp, cheaper than a multiply
        and an add per tensor; integer counters are copied."""
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        averages, sources = [], []
        for average, source in zip(self.model.state_dict().values(), model.state_dict().values(), strict=True):
            if average.dtype.is_floating_point:
                averages.append(average)
                sources.append(source)
            else:
                average.copy_(source)
        torch._foreach_lerp_(averages, sources, 1 - d)  # average + (1 - d)(source - average)


class CropSource:
    """Training batches from datasets of samples (folders): crops and mosaics of one size. Each crop comes
    from one of ``pools`` (samples, augmentation, share), drawn by share."""

    def __init__(self, pools: list[tuple[Samples, AugmentConfig, float]], cfg: TrainConfig,
                 aux: tuple[str, ...]) -> None:
        self.pools, self.cfg, self.aux = pools, cfg, aux
        shares = np.array([share for _, _, share in pools], dtype=np.float64)
        self.shares = shares / shares.sum()

    def __len__(self) -> int:
        return sum(len(pool) for pool, _, _ in self.pools)

    def draw(self, rng: np.random.Generator):
        batch = []
        for _ in range(self.cfg.batch):
            pool, augment_cfg, _ = self.pools[int(rng.choice(len(self.pools), p=self.shares))
                                              if len(self.pools) > 1 else 0]
            batch.append(augment(pool, rng, augment_cfg, self.aux))
        return batch, self.cfg.augment.size


class MixedSource:
    """Folder crops with a share of steps drawn from the simulator: a real set that lacks a
    condition (HIT-UAV: drone views only) keeps seeing the simulator's street-level scenes."""

    def __init__(self, folder: CropSource, sim: SimStream, share: float) -> None:
        self.folder, self.sim, self.share = folder, sim, share

    def __len__(self) -> int:
        return len(self.folder)

    def draw(self, rng: np.random.Generator):
        return (self.sim if rng.random() < self.share else self.folder).draw(rng)


def _sim_stream(cfg: TrainConfig, pcfg: PerceptionConfig) -> SimStream:
    from respecd.lab.detector.simdata import SimFrames, SimStream

    return SimStream(SimFrames(pcfg, cfg.seed), cfg.augment, cfg.sim_batch, pcfg.model.aux_modalities,
                     weights=cfg.scenario_weights, resolution_weights=cfg.resolution_weights)


def build_pool(cfg: TrainConfig, pcfg: PerceptionConfig):
    """Where batches come from, and validation samples (None for sim): frames rendered per step
    (the simulator), or a folder read lazily."""
    aux = pcfg.model.aux_modalities
    if cfg.data == "sim":
        return _sim_stream(cfg, pcfg), None
    from respecd.lab.detector.datasets import FolderSource, open_folder

    folder = open_folder(Path(cfg.data), pcfg.model.classes, cfg.modality, cfg.seed)
    for note in folder.notes:
        log.info("dataset", note=note)
    log.info("dataset", kind=folder.kind, train=len(folder.train), val=len(folder.val),
             modalities=",".join(sorted(folder.modalities)))
    if not folder.train:
        raise InputError(f"--data {cfg.data}: no training images (only a val split)")
    step = max(1, math.ceil(len(folder.val) / max(1, cfg.val_limit)))
    val_scale = cfg.val_scale or cfg.data_scale
    own_share = 1.0 - sum(extra.share for extra in cfg.extra_data)
    pools: list[tuple[Samples, AugmentConfig, float]] = [
        (FolderSource(folder.train, pcfg, cfg.data_scale), cfg.augment, own_share)]
    for extra in cfg.extra_data:
        other = open_folder(Path(extra.path), pcfg.model.classes, cfg.modality, cfg.seed, hold_out=False)
        if not other.train:
            raise InputError(f"--extra-data {extra.path}: no training images (only a val split)")
        log.info("dataset", extra=extra.path, kind=other.kind, train=len(other.train), share=extra.share)
        augment_cfg = replace(cfg.augment, scale=extra.zoom) if extra.zoom else cfg.augment
        pools.append((FolderSource(other.train, pcfg, cfg.data_scale), augment_cfg, extra.share))
    crops = CropSource(pools, cfg, aux)
    source = MixedSource(crops, _sim_stream(cfg, pcfg), cfg.sim_mix) if cfg.sim_mix > 0 else crops
    return source, FolderSource(folder.val[::step], pcfg, val_scale)


def _crops(pool) -> CropSource:
    """The folder crops of a pool (a folder's, or the folder half of a mix with the simulator)."""
    return pool.folder if isinstance(pool, MixedSource) else pool


def _extra_data_summary(cfg: TrainConfig, pool) -> list[dict]:
    """Each ``--extra-data`` folder with its train split's size (none with the simulator's pool: refused there)."""
    if not cfg.extra_data:
        return []
    return [{**asdict(extra), "pool": len(source)}
            for extra, (source, _, _) in zip(cfg.extra_data, _crops(pool).pools[1:], strict=True)]


def _optimizer(model: nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    decay: list[nn.Parameter] = []
    no_decay: list[nn.Parameter] = []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue  # frozen (--freeze)
        (decay if p.ndim == 4 and name.endswith("weight") else no_decay).append(p)  # conv kernels only
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=cfg.lr, betas=(0.9, 0.999), foreach=True)  # one op per step, not per tensor


def lr_at(step: int, total: int, base: float) -> float:
    warm = max(1, min(300, total // 10))
    if step < warm:
        return base * (step + 1) / warm
    progress = (step - warm) / max(1, total - warm)
    return base * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))


def train(cfg: TrainConfig, pcfg: PerceptionConfig | None = None, data: tuple | None = None) -> dict:
    """Train from scratch (or resume); returns a summary with the final file paths. ``data``: the
    batches' source and the validation samples, from the caller (``respecd adapt``) instead of ``cfg.data``."""
    pcfg = pcfg or PerceptionConfig()
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    started, cpu_started = time.perf_counter(), time.process_time()
    model = initial_model(cfg.init, pcfg.model)
    reinit(model, cfg.reinit, cfg.seed)
    pcfg = pcfg.model_copy(update={"model": model.spec})  # the data follows the net (e.g. its aux modalities)
    pool, val = data if data is not None else build_pool(cfg, pcfg)
    freeze(model, cfg.freeze)
    to_training_layout(model).train()
    keep_frozen_eval(model)
    ema = EMA(model)
    opt = _optimizer(model, cfg)
    steps = cfg.steps_per_epoch or max(1, len(pool) // cfg.batch)
    total = steps * cfg.epochs
    resume_path = cfg.out.with_name(cfg.out.name + ".resume")  # not *.pt: never packaged as weights
    first_epoch, curve = _maybe_resume(resume_path, cfg, model, ema, opt)
    batches = draw_batches(pool, cfg.seed, first_epoch, cfg.epochs, steps)
    curve = _train_epochs(model, ema, opt, batches, val, cfg, first_epoch, steps, curve, resume_path)
    best = _best_epoch(curve)
    sim = pool if cfg.data == "sim" else pool.sim if isinstance(pool, MixedSource) else None  # whose draw weights
    summary = {
        "data": cfg.data,
        "epochs": cfg.epochs,
        "steps": total,
        "batch": cfg.sim_batch if cfg.data == "sim" else cfg.batch,
        "lr": cfg.lr,  # the peak; with init and seed, what a later stage needs to be reproduced
        "pool": None if cfg.data == "sim" else len(pool),
        "train_size": "strips 320 wide, full frame height" if cfg.data == "sim" else list(cfg.augment.size),
        "train_s": round(time.perf_counter() - started, 1),
        "train_cpu_s": round(time.process_time() - cpu_started, 1),
        "seed": cfg.seed,
        "augment": asdict(cfg.augment),
        "sim_mix": cfg.sim_mix,
        "extra_data": _extra_data_summary(cfg, pool),
        "precision": cfg.precision,
        "threads": cfg.threads,
        "scenario_weights": sim.weights if sim is not None else None,
        "resolution_weights": sim.resolution_weights if sim is not None else None,
        "epoch_loss": [(r["epoch"], r["loss"]) for r in curve],  # for the CLI's curve
        "init": cfg.init,
        "freeze": list(cfg.freeze),
        "reinit": list(cfg.reinit),
        "curve": curve,
        "best_epoch": best,
    }
    final = checkpoint.load(str(cfg.out))[0] if best is not None else ema.model
    checkpoint.save(cfg.out, final, {"data": cfg.data, "train": summary})
    summary["out"] = str(cfg.out)
    return summary


def _train_epochs(model: checkpoint.Net, ema: EMA, opt: torch.optim.Optimizer, batches: Iterator[Batch], val,
                  cfg: TrainConfig, first_epoch: int, steps: int, curve: list[dict], resume_path: Path) -> list[dict]:
    """Epochs from ``first_epoch`` on: train, score on ``val``, save the best and a resume file; early stop."""
    total = steps * cfg.epochs
    for epoch in range(first_epoch, cfg.epochs):
        loss = _epoch(model, ema, opt, batches, cfg, epoch, steps, total)
        score = validation_map(ema.model, val) if val is not None and len(val) else None
        curve.append({"epoch": epoch + 1, "loss": round(loss, 4), "val_map50": finite(score)})
        if _is_best(curve):
            checkpoint.save(cfg.out, ema.model, {"data": cfg.data, "epoch": epoch + 1})
        checkpoint.save(resume_path, model, {"ema": ema.model.state_dict(), "optimizer": opt.state_dict(),
                                             "epoch": epoch + 1, "ema_updates": ema.updates, "curve": curve})
        log.info("epoch_done", epoch=epoch + 1, of=cfg.epochs, loss=round(loss, 4), val_map50=finite(score))
        if _stale(curve, cfg.patience):
            log.info("early_stop", epoch=epoch + 1, patience=cfg.patience)
            break
    return curve


def net_loss(model: checkpoint.Net, raw, input_hw: tuple[int, int], gt_boxes: torch.Tensor, gt_labels: torch.Tensor,
             gt_mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """The training objective of the net's head: YOLOv8's for the CSP net, YOLOv3/v5's for a Darknet head."""
    if isinstance(model, DarknetFusionNet):
        return yolo_loss(raw, model.yolo_specs, input_hw, gt_boxes, gt_labels, gt_mask)
    return detection_loss(raw[0], raw[1], input_hw, gt_boxes, gt_labels, gt_mask, model.spec.reg_max)


def _is_best(curve: list[dict]) -> bool:
    """The last epoch beats every earlier one (a tie keeps the earlier epoch, as _best_epoch reports)."""
    earlier = [r["val_map50"] for r in curve[:-1] if r["val_map50"] is not None]
    last = curve[-1]["val_map50"]
    return last is not None and all(last > s for s in earlier)


def _best_epoch(curve: list[dict]) -> int | None:
    scored = [r for r in curve if r["val_map50"] is not None]
    return max(scored, key=lambda r: (r["val_map50"], -r["epoch"]))["epoch"] if scored else None


def _stale(curve: list[dict], patience: int) -> bool:
    best = _best_epoch(curve)
    return patience > 0 and best is not None and curve[-1]["epoch"] - best >= patience


def _maybe_resume(path: Path, cfg: TrainConfig, model: checkpoint.Net, ema: EMA,
                  opt: torch.optim.Optimizer) -> tuple[int, list[dict]]:
    if not cfg.resume or not path.is_file():
        return 0, []
    saved, payload = checkpoint.load(str(path), expected=model.spec)
    model.load_state_dict(saved.state_dict())
    model.train()
    keep_frozen_eval(model)
    ema.model.load_state_dict(payload["ema"])
    ema.updates = int(payload.get("ema_updates", 0))
    opt.load_state_dict(payload["optimizer"])
    log.info("resumed", path=str(path), epoch=payload["epoch"])
    return int(payload["epoch"]), list(payload.get("curve", []))


def _epoch(model: checkpoint.Net, ema: EMA, opt: torch.optim.Optimizer, batches: Iterator[Batch], cfg: TrainConfig,
           epoch: int, steps: int, total: int) -> float:
    from respecd.lab.detector.data import progress

    running = 0.0
    bf16 = cfg.precision == "bf16"
    bar = progress(range(steps), cfg.progress, desc=f"epoch {epoch + 1}/{cfg.epochs}")
    for i in bar:
        step = epoch * steps + i
        for group in opt.param_groups:
            group["lr"] = lr_at(step, total, cfg.lr)
        loss, parts = train_step(model, opt, ema, next(batches), bf16, cfg.extra_loss)
        running = 0.9 * running + 0.1 * float(loss.detach()) if i else float(loss.detach())
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{running:.3f}", box=f"{parts['box']:.3f}", cls=f"{parts['cls']:.3f}")
    return running


def train_step(model: checkpoint.Net, opt: torch.optim.Optimizer, ema: EMA, batch: Batch, bf16: bool = False,
               extra_loss: Callable[[nn.Module], torch.Tensor] | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """One optimizer step on one batch (forward under bf16 autocast when asked); the loss and its parts."""
    samples, (w, h) = batch
    x, presence, boxes, labels, mask = collate(samples)
    x = x.contiguous(memory_format=_memory_format(model))
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        raw = model(x, presence)
    loss, parts = net_loss(model, _as_float(raw) if bf16 else raw, (h, w), boxes, labels, mask)
    if extra_loss is not None:
        loss = loss + extra_loss(model)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    opt.step()
    ema.update(model)
    return loss, parts


def to_training_layout(model: checkpoint.Net) -> checkpoint.Net:
    """The CSP net trains in channels-last memory (NHWC): oneDNN's CPU convolutions then need no
    reordering, which makes a training step cheaper (docs/PERFORMANCE.md). The Darknet nets (depthwise
    convolutions, not measured) stay as built."""
    return model.to(memory_format=_memory_format(model))  # type: ignore[call-overload]  # torch's stub lacks it


def _memory_format(model: nn.Module) -> torch.memory_format:
    return torch.channels_last if isinstance(model, FusionNet) else torch.contiguous_format


def _as_float(raw):
    """The head's outputs back in fp32, so the loss (assignment, IoU, DFL) runs at full precision."""
    if isinstance(raw, torch.Tensor):
        return raw.float()
    if isinstance(raw, (list, tuple)):
        return type(raw)(_as_float(r) for r in raw)
    return raw
