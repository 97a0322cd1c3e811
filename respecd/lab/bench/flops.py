"""What a frame costs in arithmetic and what this CPU can do: the detector's hardware limit.

``model_gflop`` counts the net's multiply-adds at an input size (torch's FlopCounterMode: a
convolution's or matmul's 2 x MACs; elementwise work is left out), ``peak_gflops`` measures
one core's f32 matmul throughput (the best of a few sizes, process CPU time, so a shared
machine's waiting is not counted). Their quotient is the fastest a forward pass could run on
one core in f32; a runtime's measured forward over it is how far it is from that limit.
"""

from __future__ import annotations

import time
from typing import Any

PROBE_SIZES = (256, 384, 512, 768)  # square matmuls: large enough for the kernels' steady state, cache-sized
PROBE_REPEATS = 12


def model_gflop(model: Any, channels: int, height: int, width: int) -> float:
    """GFLOP of one forward pass of ``model`` on a (1, channels, height, width) input (torch, no engine)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    engine, model.engine = getattr(model, "engine", None), None
    try:
        x = torch.rand(1, channels, height, width)
        with FlopCounterMode(display=False) as counter, torch.inference_mode():
            model(x, torch.ones(1, channels - 3))
    finally:
        model.engine = engine
    return counter.get_total_flops() / 1e9


def peak_gflops(sizes: tuple[int, ...] = PROBE_SIZES, repeats: int = PROBE_REPEATS) -> float:
    """This CPU's single-thread f32 matmul GFLOP/s: the best 2n^3 / CPU time over ``sizes`` and ``repeats``."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        best = 0.0
        for n in sizes:
            a, b = torch.rand(n, n), torch.rand(n, n)
            a @ b  # warm-up: the kernel's packing buffers
            for _ in range(repeats):
                start = time.process_time()
                a @ b
                spent = time.process_time() - start
                if spent > 0:
                    best = max(best, 2 * n**3 / spent / 1e9)
        return best
    finally:
        torch.set_num_threads(threads)
