"""Preparing the replay detector's next input while it runs on this one.

In a lockstep replay the detector is the critical path. While the log's clock waits for it,
the bundle it takes next is already queued: a niced worker thread prepares that bundle's input
then (decodes its images — a replay's frames are decoded when first read, ``record.lazy`` —
aligns and normalises them: ``FusionDetector.prepare``), so the detector only runs the network.
Only where a core is left beside the detector's threads, only for frames the detector will run
on, and an input is handed out once, for the very frame objects it was made from (a frame
re-made at another resolution keeps its seq and time) — else the detector prepares its own.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Collection
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from respecd.priority import lower_thread_priority

Prepare = Callable[[dict[Any, Any], tuple[int, int] | None], Any]


def core_beside(threads: int) -> bool:
    """A core is left beside the detector's ``threads`` (preparing ahead would not take one of its)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return threads < cores


@dataclasses.dataclass(frozen=True)
class _Ahead:
    """An input being prepared ahead: for which detector frames, and the preparer's job."""

    frames: dict[Any, Any]
    input: Future[Any]  # the AlignedInput, None if preparing failed


class InputPreparer:
    """One worker thread at the lowest priority, one input prepared ahead at a time."""

    def __init__(self, prepare: Prepare, inputs: Collection[str]) -> None:
        self._prepare = prepare
        self._inputs = frozenset(inputs)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="perception-prepare",
                                            initializer=lower_thread_priority)
        self._ahead: _Ahead | None = None

    def start(self, frames: dict[Any, Any], rgb_size: tuple[int, int] | None = None) -> None:
        """Prepare ``frames``' input in the worker (replacing whatever was prepared before); ``rgb_size``:
        the grid if they hold no RGB frame (``FusionDetector.prepare``)."""
        job = self._executor.submit(_quietly, self._prepare, frames, rgb_size)
        self._ahead = _Ahead(self._detector_frames(frames), job)

    def take(self, frames: dict[Any, Any]) -> Future[Any] | None:
        """The input prepared ahead for exactly these frames (the same frame objects for every
        detector input: same pixels, same resolution), else None; handed out once."""
        ahead, self._ahead = self._ahead, None
        if ahead is None:
            return None
        taken = self._detector_frames(frames)
        if taken.keys() == ahead.frames.keys() and all(taken[m] is frame for m, frame in ahead.frames.items()):
            return ahead.input
        ahead.input.cancel()
        return None

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)

    def _detector_frames(self, frames: dict[Any, Any]) -> dict[Any, Any]:
        return {m: f for m, f in frames.items() if m in self._inputs}


def _quietly(prepare: Prepare, frames: dict[Any, Any], rgb_size: tuple[int, int] | None) -> Any:
    """``prepare(frames, rgb_size)``, None on an error left for the detector to meet (as it would without
    preparing ahead)."""
    with contextlib.suppress(Exception):
        return prepare(frames, rgb_size)
    return None
