"""Training: one step of ``respecd train --data sim`` per precision, and the rendering that feeds it.

What ``make weights`` costs is steps × step time, so this times the step itself: the same
simulated batches (each drawn once and used by both, as ``SimStream`` draws them: one RGB resolution a step,
320-wide full-height strips) through ``train.train_step`` — forward, loss, backward, AdamW
and the EMA — once per precision, the precisions alternating step by step so that a change
in the machine's load falls on both. ``render_ms`` is drawing one step's batch (rendering
frames, strips, photometric augmentation) on the same threads. Medians of wall time; the
1-minute load average says how shared the machine was. Compare precisions as the ratio
within one run, not across runs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import Any

from respecd.argtypes import seed
from respecd.errors import InputError

PRECISIONS = ("fp32", "bf16")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=12, help="timed steps per precision (default 12)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps per precision first (default 2)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2, as make weights)")
    parser.add_argument("--seed", type=seed, default=0,
                        help="seed >= 0 of the simulated world and the batches")


def run(args: argparse.Namespace) -> dict[str, Any]:
    import numpy as np
    import torch

    from respecd.lab.detector.finetune import initial_model
    from respecd.lab.detector.train import EMA, TrainConfig, _optimizer, build_pool, to_training_layout, train_step
    from respecd.perception.config import PerceptionConfig

    if args.steps < 1 or args.warmup < 0 or args.threads < 1:
        raise InputError(f"--steps {args.steps} --warmup {args.warmup} --threads {args.threads}: expected "
                         "steps >= 1, warmup >= 0, threads >= 1")
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    pcfg = PerceptionConfig()
    cfg = TrainConfig(data="sim", out=None, seed=args.seed)  # type: ignore[arg-type]  # nothing is written
    pool, _ = build_pool(cfg, pcfg)
    rng = np.random.default_rng([args.seed, 0, 11])
    runs = {}
    for precision in PRECISIONS:
        torch.manual_seed(args.seed)
        model = to_training_layout(initial_model(None, pcfg.model)).train()
        runs[precision] = (model, _optimizer(model, cfg), EMA(model))
    render_s: list[float] = []
    step_s: dict[str, list[float]] = {p: [] for p in PRECISIONS}
    for i in range(args.warmup + args.steps):  # one batch in memory at a time (a 640x360 one is ~25 MB)
        start = time.perf_counter()
        batch = pool.draw(rng)
        render_s.append(time.perf_counter() - start)
        for precision in PRECISIONS:  # alternating: the same load falls on both
            model, opt, ema = runs[precision]
            start = time.perf_counter()
            train_step(model, opt, ema, batch, bf16=precision == "bf16")
            if i >= args.warmup:
                step_s[precision].append(time.perf_counter() - start)
    median_ms = {p: round(statistics.median(v) * 1000, 1) for p, v in step_s.items()}
    render_ms = round(statistics.median(render_s) * 1000, 1)
    return {
        "threads": args.threads,
        "steps": args.steps,
        "step_ms": median_ms,
        "render_ms": render_ms,
        "bf16_over_fp32": round(median_ms["bf16"] / median_ms["fp32"], 3),
        "step_with_render_ms": {p: round(ms + render_ms, 1) for p, ms in median_ms.items()},
        "bf16_cpu": _bf16_hardware(),
        "load_avg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }


def summary(figures: dict[str, Any]) -> str:
    steps = figures["step_ms"]
    full = figures["step_with_render_ms"]
    return (f"training step ({figures['threads']} threads, median of {figures['steps']}): fp32 {steps['fp32']} ms, "
            f"bf16 {steps['bf16']} ms (ratio {figures['bf16_over_fp32']}); rendering {figures['render_ms']} ms; "
            f"with rendering fp32 {full['fp32']} / bf16 {full['bf16']} ms; bf16 instructions: "
            f"{figures['bf16_cpu']}; load {figures['load_avg_1m'][0]} -> {figures['load_avg_1m'][1]}")


def _bf16_hardware() -> bool | None:
    """Whether the CPU has native bf16 arithmetic (AVX512-BF16 or AMX); None where it cannot be read."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            flags = next((line for line in info if line.startswith("flags")), "")
    except OSError:
        return None
    return any(flag in flags.split() for flag in ("avx512_bf16", "amx_bf16"))
