"""Argument values several commands share, parsed once with the same clear errors.

The number types below are argparse ``type=`` functions: a bad value stops the command while
its arguments are parsed, before a checkpoint loads or a simulation starts, with argparse's own
``error: argument --FLAG: expected ..., got ...`` and exit status 2 (no traceback). Without them
a negative seed, a zero thread count or a NaN duration reached numpy, torch or OpenCV and came
back as a traceback minutes later, or was silently replaced. A core module: the command line,
the lab's tools and the daemon's packages all parse with them.
"""

from __future__ import annotations

import argparse
import math

from respecd.errors import InputError

MAX_PORT = 65535
MAX_SEED = 2**63 - 1


def resolution(text: str, flag: str) -> tuple[int, int]:
    """'640x360' -> (640, 360); InputError naming ``flag`` for anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise InputError(f"{flag} {text}: expected WIDTHxHEIGHT, e.g. 640x360") from err
    if w < 32 or h < 32:
        raise InputError(f"{flag} {text}: expected at least 32x32")
    return w, h


def _integer(text: str, low: int, high: int | None = None) -> int:
    """``text`` as an int in [low, high]; ArgumentTypeError saying the range otherwise."""
    expected = f"an integer from {low} to {high}" if high is not None else f"an integer >= {low}"
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if value < low or (high is not None and value > high):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _number(text: str, expected: str) -> float:
    """``text`` as a finite float: nan and inf compare false with every bound, so they are refused here."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An int >= 0: counts where 0 means 'none' or 'all'."""
    return _integer(text, 0)


def seed(text: str) -> int:
    """A random seed 0..2**63-1: numpy refuses negative ones, torch.manual_seed overflows past 64 bits
    (and the tools add world offsets to a seed)."""
    value = _integer(text, 0)
    if value > MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0 and below 2**63, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An int >= 1: thread counts, repeats, steps, frames (0 of them leaves nothing to run or measure)."""
    return _integer(text, 1)


def port_number(text: str) -> int:
    """A TCP port 1..65535 (0, an ephemeral port, is not one a client could be pointed at)."""
    return _integer(text, 1, MAX_PORT)


def positive_float(text: str) -> float:
    """A finite number > 0: durations, rates, scales, learning rates."""
    value = _number(text, "a finite number > 0")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0: pauses and warm-ups, where 0 means none."""
    value = _number(text, "a finite number >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def unit_interval(text: str) -> float:
    """A number in [0, 1]: shares, probabilities, confidence thresholds."""
    value = _number(text, "a number in [0, 1]")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return value


def seed_list(text: str) -> list[int]:
    """World seeds: '503,510,517' -> [503, 510, 517], distinct and >= 0."""
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated world seeds, got {text!r}") from None
    if len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"expected distinct non-negative seeds, got {text!r}")
    return seeds
