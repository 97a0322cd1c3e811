"""``respecd --replay LOG``: the shell around ``evaluate`` — the report file and its figure, the
comparison table, a progress bar on a terminal, SIGTERM, and ``--save-table``.

A replay learns in memory: it never writes a state directory's table. ``state_dir`` only says
where to read a table from (never renamed, whatever is wrong with it); ``save_table`` is the one
place a learned table is written. (A profile with ``perception.runtime`` other than torch caches
its exported graphs in the state directory's ``exported/``, as the daemon does.) ``record`` and
``foxglove`` write or serve the counterfactual session (``replay.watch``). SIGTERM/SIGINT end a
replay early, with the report of what was replayed so far.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import structlog

from respecd.control.persist import StoredTable
from respecd.replay import report_out
from respecd.replay.evaluate import Report, RunControl, evaluate

log = structlog.get_logger(__name__)


def run_replay(args: argparse.Namespace, signals: Any = None) -> int:
    """Entry point from ``respecd --replay``; InputError/ConfigError become exit 2."""
    table = getattr(args, "table", None)
    report = replay(args.replay, config=args.config, policy=args.policy, speed=str(getattr(args, "speed", None) or "1"),
                    seed=args.seed or 0, duration=args.duration, report=args.report, state_dir=args.state_dir,
                    save_table=getattr(args, "save_table", None), signals=signals,
                    topics=getattr(args, "topics", None), table=StoredTable.read(Path(table)) if table else None,
                    allow_no_table=bool(getattr(args, "allow_no_table", False)), record=getattr(args, "record", None),
                    foxglove=getattr(args, "foxglove", None))
    print(report_out.table(report))
    return 1 if _report_skipped(report) else 0


def _report_skipped(report: dict[str, Any]) -> bool:
    """A ROS bag's messages that could not be read, per topic (topic, index, why) on stderr; True if any
    (the exit status is then 1: the replay ran, but without those frames)."""
    skipped: dict[str, Any] = {}
    for entry in report["policies"].values():
        skipped.update(entry.get("skipped") or {})
    for topic, lost in skipped.items():
        first = "; ".join(f"index {s['index']}: {s['why']}" for s in lost["first"])
        more = f" (and {lost['count'] - len(lost['first'])} more)" if lost["count"] > len(lost["first"]) else ""
        print(f"respecd: {report['log']['path']}: {topic}: {lost['count']} message(s) skipped, unreadable: "
              f"{first}{more}", file=sys.stderr)
    return bool(skipped)


def replay(log_path: str | Path, *, config: str | Path | None = None, policy: str | None = None, speed: str = "max",
           seed: int = 0, duration: float | None = None, report: str | Path | None = None,
           state_dir: str | Path | None = None, save_table: str | Path | None = None,
           signals: Any = None, topics: str | None = None, observe: Any = None, table: StoredTable | None = None,
           allow_no_table: bool = False, record: str | None = None, foxglove: str | None = None) -> dict[str, Any]:
    """Replay ``log_path`` under ``policy``; the report (``{"log", "policies"}``), also merged
    into the JSON at ``report`` (with a PNG timeline) when given. ``config``: a profile file
    to replay with instead of the one recorded in the log. ``signals``: a ``StopSignals``
    whose SIGTERM/SIGINT end the replay early (the report then covers what was replayed).
    ``topics``: for a ROS bag, which topic is which sensor (``rgb=/cam/image_raw,imu=...``).
    ``observe``: called with the replay's ``Session`` before it starts (benchmarks attach hooks).
    ``record``/``foxglove``: the counterfactual session as a log / served live (``replay.watch``)."""
    bar = _Progress()
    control = RunControl(signals=signals, observe=observe, on_progress=bar.step,
                         state_dir=Path(state_dir) if state_dir else None, record=record, foxglove=foxglove)
    try:
        result = evaluate(log_path, config, policy, table, seed, duration=duration, topics=topics, speed=speed,
                          allow_no_table=allow_no_table, control=control)
    finally:
        bar.close()
    if result.result.get("truncated"):
        print(f"respecd: warning: {log_path} was cut short (no summary); replaying its "
              f"{result.result['replayed_s']:.2f} s up to the last complete chunk", file=sys.stderr)
    _save_learned(result, save_table)
    return _emit(report, Path(log_path), result)


def _save_learned(result: Report, save_table: str | Path | None) -> None:
    """Write the table a ``learn`` replay ended with where ``--save-table`` says (and nowhere else)."""
    if save_table is None:
        return
    if result.learned is None:
        log.warning("replay.save_table_ignored", policy=result.policy, reason="only learn updates a table")
        return
    result.learned.write(Path(save_table))
    log.info("qtable_saved", path=str(save_table), updates=result.learned.updates)


class _Progress:
    """A tqdm bar of log seconds replayed, on a terminal and for replays of 20 s or more."""

    def __init__(self) -> None:
        self.bar: Any = None

    def step(self, done: float, total: float) -> None:
        if self.bar is None:
            self.bar = _bar(total)
        done = round(done, 1)
        if done > self.bar.n:
            self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _bar(total: float) -> Any:
    return _progress_bar()(total=round(total, 1), unit="s", desc="replay", mininterval=1.0,
                           disable=not progress_shown(total, sys.stderr), file=sys.stderr, leave=False,
                           bar_format=BAR_FORMAT)


def _progress_bar() -> Any:
    try:
        from tqdm import tqdm
    except ImportError:  # the lab extra: without it a replay runs without a progress bar
        return _NoBar

    class Bar(tqdm):
        monitor_interval = 0  # no monitor thread: it would outlive the replay by 10 s

        @property
        def format_dict(self) -> dict[str, Any]:
            values = super().format_dict
            values["speed"] = speed_label(values["n"], values["elapsed"])
            return values

    return Bar


# log seconds over wall seconds is the replay's speed: "3.2x real time", not tqdm's "3.2s/s"
BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of log [{elapsed}<{remaining}, {speed}]"


def progress_shown(duration_s: float, stream: Any) -> bool:
    """A bar for a person at a terminal, on a replay long enough to watch; never in a pipe,
    a file or the journal, where its redraws would be lines of noise."""
    isatty = getattr(stream, "isatty", None)
    return duration_s >= 20 and isatty is not None and bool(isatty())


def speed_label(log_s: float, wall_s: float) -> str:
    """How fast a replay runs, as a person reads it."""
    return f"{log_s / wall_s:.1f}× real time" if wall_s > 0 and log_s > 0 else "– × real time"


class _NoBar:
    """The part of tqdm's interface the replay uses, doing nothing."""

    def __init__(self, **_: Any) -> None:
        self.n = 0.0

    def update(self, step: float) -> None:
        self.n += step

    def close(self) -> None:
        pass


def _emit(report_path: str | Path | None, log_path: Path, result: Report) -> dict[str, Any]:
    """The report of this policy, merged into and written as JSON + PNG at ``report_path``."""
    log_id = {"path": str(log_path.resolve()), "bytes": result.log["bytes"], "start_ns": result.log["start_ns"]}
    entry = result.entry()
    if report_path is None:
        return {"log": log_id, "policies": {result.policy: entry}}
    path = Path(report_path)
    report = report_out.merge(path, log_id, result.policy, entry)
    # stopped by a signal: the JSON only, the timeline figure would take the stop past its 2 s
    png = report_out.write(path, report, figure=not entry.get("stopped_early"))
    log.info("replay.report", json=str(path), png=str(png) if png else None, policies=list(report["policies"]))
    return report
