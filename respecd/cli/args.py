"""Argument values several commands share, parsed once with the same clear errors."""

from __future__ import annotations

from respecd.errors import InputError


def resolution(text: str, flag: str) -> tuple[int, int]:
    """'640x360' -> (640, 360); InputError naming ``flag`` for anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise InputError(f"{flag} {text}: expected WIDTHxHEIGHT, e.g. 640x360") from err
    if w < 32 or h < 32:
        raise InputError(f"{flag} {text}: expected at least 32x32")
    return w, h
