"""The fleet commands' work, backend in hand: map the per-log task over the logs (a progress
bar on a terminal), then the serial part (pool the reports, learn the table)."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from respecd.lab.fleet import worker
from respecd.lab.fleet.backends import Backend, WorkerLost, open_backend
from respecd.lab.fleet.eval import EvalSpec, eval_log, outcome_of, pooled
from respecd.lab.fleet.learn import Learned, learn
from respecd.lab.fleet.logs import LogRef, largest_first
from respecd.lab.fleet.transitions import LogSteps, steps_of


@dataclass(frozen=True)
class Where:
    """Where the work runs: ``workers`` and ``address`` as the command line gave them."""

    workers: int = 1
    address: str | None = None
    settings: worker.Settings = worker.Settings()


@contextmanager
def backend(where: Where) -> Iterator[Backend]:
    opened = open_backend(where.workers, where.address, where.settings)
    try:
        yield opened
    finally:
        opened.close()


def describe(used: Backend) -> dict[str, Any]:
    """The backend, for a document's ``timing`` (two backends give equal documents without it)."""
    return {"backend": used.kind, "workers": used.workers, "startup_s": round(used.startup_s, 3),
            "load_avg": [round(x, 2) for x in os.getloadavg()]}


def run_map(used: Backend, fn: Callable[[Any, Any], Any], common: Any, refs: Sequence[LogRef],
            what: str) -> list[Any]:
    """``fn(common, ref)`` for every log, in ``refs``' order, handed out largest first; a progress
    bar on a terminal."""
    order = largest_first(refs)
    bar = _bar(len(refs), what)
    try:
        answers = used.map(fn, common, [refs[i] for i in order], on_done=lambda _i, _r: bar.update(1))
    finally:
        bar.close()
    results: list[Any] = [None] * len(refs)
    for answer, i in zip(answers, order, strict=True):
        results[i] = answer
    return results


def eval_fleet(refs: Sequence[LogRef], spec: EvalSpec, where: Where) -> dict[str, Any]:
    """``fleet.json``: pooled, one entry per log (by name), and the run's timing."""
    began = time.perf_counter()
    with backend(where) as used:
        answers = run_map(used, eval_log, spec, refs, "logs")
        run = describe(used)
    outcomes = sorted((outcome_of(r, a) for r, a in zip(refs, answers, strict=True)), key=lambda o: o.name)
    run["wall_s"] = round(time.perf_counter() - began, 3)
    return {"pooled": pooled(outcomes), "logs": [o.to_json() for o in outcomes], "timing": run}


def read_steps(refs: Sequence[LogRef], profile: dict[str, Any] | None, where: Where) -> tuple[list[LogSteps], dict]:
    """Every log's recorded decisions (in parallel where the backend allows), and the run's timing."""
    began = time.perf_counter()
    with backend(where) as used:
        answers = run_map(used, steps_of, profile, refs, "logs")
        run = describe(used)
    logs = [LogSteps(r.name, error=a.reason) if isinstance(a, WorkerLost) else a
            for r, a in zip(refs, answers, strict=True)]
    run["read_s"] = round(time.perf_counter() - began, 3)
    return logs, run


def learn_fleet(refs: Sequence[LogRef], profile: dict[str, Any] | None, where: Where, **options: Any) -> Learned:
    logs, _ = read_steps(refs, profile, where)
    return learn(logs, **options)


def _bar(total: int, what: str) -> Any:
    """tqdm on a terminal (stderr), nothing in a pipe or a journal."""
    try:
        from tqdm import tqdm
    except ImportError:
        tqdm = None
    if tqdm is None or not sys.stderr.isatty():
        return _Quiet()
    return tqdm(total=total, unit=what[:-1] if what.endswith("s") else what, desc="fleet", file=sys.stderr,
                leave=False)


class _Quiet:
    def update(self, _: int) -> None:
        """No bar where nobody watches."""

    def close(self) -> None:
        """Nothing to close."""
