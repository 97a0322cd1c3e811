"""Attacks: the "Open doors" review's kinds of attack, each tried N times against this checkout.

An escape is an outcome the daemon's contract forbids: a hang (a stop request must always end
it), a traceback, a crash or a restart loop, a wrong exit status, a log flood, data lost or
deleted, a foreign origin let in. Each kind is a function ``try(ctx, i) -> None | str`` (the
escape's description); the figures are tries and escapes per kind, with the first escape
named. The live view's kinds run against a real daemon (``attacks_live``); the others are files
and processes (``attacks_files``) and logs and the state directory (``attacks_bags``).
docs/RELIABILITY.md is this bench's table.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

Try = Callable[["Context", int], "str | None"]
REPO = Path(__file__).resolve().parents[3]


@dataclass(frozen=True)
class Kind:
    name: str
    group: str
    tries: int
    attempt: Try
    what: str  # the attack, for the table


class Context:
    """A scratch folder, a profile without the detector (fast starts), and the daemon as a command."""

    def __init__(self, root: Path) -> None:
        self.root = root
        profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
        profile["perception"] = {"enabled": False}
        self.profile = root / "noperc.yaml"
        self.profile.write_text(yaml.safe_dump(profile))
        self.base = profile
        self._n = 0

    def fresh(self, name: str = "t") -> Path:
        self._n += 1
        path = self.root / f"{name}-{self._n}"
        path.mkdir(parents=True)
        return path

    def respecd(self, *argv: str, timeout: float = 60, **kw: Any) -> subprocess.CompletedProcess[str] | None:
        """The CLI as a child process; None when it is still running after ``timeout`` (a hang)."""
        try:
            return subprocess.run([sys.executable, "-m", "respecd.cli", *argv], capture_output=True, text=True,
                                  timeout=timeout, cwd=REPO, **kw)
        except subprocess.TimeoutExpired:
            return None


def refused(result: subprocess.CompletedProcess[str] | None, status: int = 2, said: str = "") -> str | None:
    """The escape, if ``result`` is not a clean refusal with ``status`` (and ``said`` on stderr)."""
    if result is None:
        return "hung (killed by the timeout)"
    if "Traceback" in result.stderr + result.stdout:
        return "traceback: " + result.stderr.strip().splitlines()[-1][:160]
    if result.returncode != status:
        return f"exit {result.returncode} (want {status}): {result.stderr.strip()[-160:]}"
    if said and said not in result.stderr:
        return f"stderr does not say {said!r}: {result.stderr.strip()[-160:]}"
    return None


def escape(work: Callable[[], Any], refusal: type[Exception], where: str = "") -> str | None:
    """The escape, if ``work()`` raises anything but ``refusal`` (its clear error); None when it
    succeeds or refuses. ``where`` prefixes the message (which input did it)."""
    try:
        work()
    except refusal:
        return None
    except Exception as err:  # noqa: BLE001 - the outcome under test
        return f"{where}{type(err).__name__}: {err}"[:200]
    return None


def at_once(work: Callable[[], Any], unblock: Path | None = None, limit_s: float = 10.0) -> tuple[Any, str | None]:
    """``work()`` in a thread: (its result or error, None), or (None, "blocked") after ``limit_s``
    (then a writer opens ``unblock``, a FIFO, so that the thread ends)."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = work()
        except BaseException as err:  # noqa: BLE001 - handed back as the outcome
            box["value"] = err

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(limit_s)
    if thread.is_alive():
        if unblock is not None:
            fd = os.open(unblock, os.O_WRONLY | os.O_NONBLOCK)
            os.close(fd)
        return None, f"blocked for {limit_s:g} s"
    return box.get("value"), None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--only", metavar="NAMES", help="comma-separated kinds to run (default: all)")
    parser.add_argument("--scale", type=float, default=1.0, metavar="X",
                        help="tries per kind times X (at least 1 each; default 1)")


def kinds() -> list[Kind]:
    from respecd.lab.bench import attacks_bags, attacks_files, attacks_live

    return [*attacks_files.KINDS, *attacks_bags.KINDS, *attacks_live.KINDS]


def run(args: argparse.Namespace) -> dict[str, Any]:
    from respecd.logs import configure_logging

    configure_logging("console", "error")  # what the attacks make the daemon's code warn about is expected
    only = set(args.only.split(",")) if args.only else None
    rows = []
    with tempfile.TemporaryDirectory(prefix="respecd-attacks-", dir="/tmp") as folder:
        os.chmod(folder, 0o755)
        ctx = Context(Path(folder))
        for kind in kinds():
            if only is not None and kind.name not in only:
                continue
            rows.append(_run_kind(ctx, kind, max(1, round(kind.tries * args.scale))))
    return {"kinds": rows, "tries": sum(r["tries"] for r in rows), "escapes": sum(r["escapes"] for r in rows),
            "loadavg": os.getloadavg()[0]}


def _run_kind(ctx: Context, kind: Kind, tries: int) -> dict[str, Any]:
    started, escapes, first = time.monotonic(), 0, None
    for i in range(tries):
        try:
            escape = kind.attempt(ctx, i)
        except Exception as err:  # noqa: BLE001 - the harness's own failure is an escape too, and named
            escape = f"harness: {type(err).__name__}: {err}"
        if escape:
            escapes += 1
            first = first or f"try {i}: {escape}"
    return {"kind": kind.name, "group": kind.group, "what": kind.what, "tries": tries, "escapes": escapes,
            "first_escape": first, "seconds": round(time.monotonic() - started, 1)}


def summary(figures: dict[str, Any]) -> str:
    lines = [f"{'kind':<24} {'tries':>5} {'escapes':>7}  first escape"]
    for row in figures["kinds"]:
        lines.append(f"{row['kind']:<24} {row['tries']:>5} {row['escapes']:>7}  {row['first_escape'] or '-'}")
    lines.append(f"{len(figures['kinds'])} kinds, {figures['tries']} tries, {figures['escapes']} escapes "
                 f"(load average {figures['loadavg']:.1f})")
    return "\n".join(lines)
