"""``respecd [--config FILE] ...``: run the daemon (live), or ``--replay LOG`` a recorded session."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys
from typing import TYPE_CHECKING, Any

import structlog

from respecd.argtypes import positive_float, seed
from respecd.config import DEFAULT_PROFILE, read_profile
from respecd.errors import ConfigError, InputError

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)

POLICIES = ("learn", "exploit", "static", "heuristic")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--profile", "--config",
        dest="config",
        default=DEFAULT_PROFILE,
        metavar="FILE",
        help=f"profile YAML (default: the embedded {DEFAULT_PROFILE}, a simulated rover); --config is the old name",
    )
    parser.add_argument("--duration", type=positive_float, metavar="S",
                        help="stop after S seconds, S > 0 (default: run until SIGTERM)")
    parser.add_argument(
        "--log-format",
        choices=("json", "console", "auto"),
        default="auto",
        help="log format (auto: JSON lines when stdout is not a terminal)",
    )
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="debug level, and on a terminal also the per-decision and per-apply lines")
    parser.add_argument(
        "--seed", type=seed,
        help="seed >= 0 for the simulator and the controller (default: the profile's, else 0)"
    )
    parser.add_argument("--policy", choices=POLICIES, help="override controller.policy from the profile")
    parser.add_argument(
        "--state-dir", metavar="DIR",
        help="Q-table and state (default: $STATE_DIRECTORY, else $XDG_STATE_HOME/respecd, else ~/.local/state/respecd)"
    )
    parser.add_argument("--record", metavar="PATH",
                        help="record the session to this MCAP file (with --replay: the counterfactual session)")
    parser.add_argument("--foxglove", metavar="[HOST:]PORT",
                        help="serve the session live to Foxglove over its WebSocket protocol (off by default; "
                             "loopback unless HOST is given, e.g. 0.0.0.0:8765; with --replay: the counterfactual "
                             "session, best at --speed 1)")
    parser.add_argument("--replay", metavar="LOG",
                        help="replay a recorded MCAP session, or a ROS bag (rosbag2 directory or ROS 1 .bag), "
                             "through the pipeline")
    parser.add_argument("--topics", metavar="MAP",
                        help="replay of a ROS bag: which topic is which sensor, e.g. "
                             "rgb=/camera/image_raw,thermal=/thermal/image,radar=/radar/points,depth=...,imu=... "
                             "(default: guessed from message types, and the guess printed)")
    parser.add_argument(
        "--speed",
        choices=("1", "2", "max"),
        help="replay speed: real time (default), twice, or as fast as possible in lockstep (deterministic)",
    )
    parser.add_argument("--report", metavar="OUT.json", help="replay: write a report (JSON + PNG timeline)")
    parser.add_argument("--save-table", metavar="PATH",
                        help="replay: write the Q-table the replay learned here (a replay never writes the state "
                             "directory; with --state-dir it only reads the table there)")
    parser.add_argument("--table", metavar="FILE",
                        help="replay: the Q-table --policy exploit acts on (learn starts from it) instead of the state "
                             "directory's; one learned for another profile or layout is an error (exit 2)")
    parser.add_argument("--allow-no-table", action="store_true", default=None,
                        help="replay: --policy exploit with no Q-table that fits runs anyway, holding the "
                             "configuration; its report row says 'no table'")


def main(args: argparse.Namespace) -> int:
    """The daemon, or ``--replay``; SIGTERM/SIGINT stop either cleanly from the first moment."""
    from respecd.control.statelock import learning_into
    from respecd.logs import configure_logging
    from respecd.preflight import learns
    from respecd.signals import StopSignals

    check_flags(args)
    check_outputs(args)
    with StopSignals() as signals:
        fmt = configure_logging(args.log_format, args.log_level, verbose=getattr(args, "verbose", False))
        if args.replay:
            from respecd.replay.run import run_replay

            return run_replay(args, signals)
        loaded = read_profile(args.config)
        state_dir = prepare_state_dir(args.state_dir)
        preflight(loaded, state_dir, args.policy, record=args.record)
        with learning_into(state_dir) if learns(loaded, args.policy) else contextlib.nullcontext():
            return asyncio.run(run_live(loaded.model, args, signals, console=fmt == "console", state_dir=state_dir))


REPLAY_ONLY = ("speed", "report", "topics", "save_table", "table", "allow_no_table")


def check_flags(args: argparse.Namespace) -> None:
    """A flag that does nothing in this mode is an error, not silently ignored."""
    given = [name for name in REPLAY_ONLY if getattr(args, name, None) is not None]
    if not args.replay and given:
        flags = ", ".join(f"--{n.replace('_', '-')}" for n in given)
        raise ConfigError(f"{flags}: only with --replay LOG (this runs the live daemon)")


def check_outputs(args: argparse.Namespace) -> None:
    """Every file this run will write can be written, checked before the session starts: a replay's
    report and table are written only at its end, and a recording that cannot open its file loses
    the whole session (it pauses, the daemon runs on unrecorded)."""
    from respecd.outputs import check_output_file, recording_problem

    if args.replay:
        report = check_output_file("--report", args.report, example="report.json")  # report_out.write makes folders
        if report is not None:
            check_output_file("--report", report.with_suffix(".png"))  # the timeline beside it
        check_output_file("--save-table", args.save_table, example="qtable.npz")  # save_table makes folders
    if args.record is not None:
        problem = recording_problem(args.record)
        if problem:
            raise InputError(f"--record {problem}")


def prepare_state_dir(cli_value: str | None) -> Any:
    from respecd.control.persist import resolve_state_dir

    try:
        return resolve_state_dir(cli_value)
    except OSError as err:
        raise ConfigError(f"--state-dir: cannot use {cli_value!r}: {err}") from err


def preflight(loaded: Any, state_dir: Any, policy: str | None, record: str | None = None) -> None:
    """Fail at start (exit 2), not at the first save or inference: files, device, state directory,
    the profile's recording path (unless ``--record`` replaces it)."""
    from respecd.preflight import check_profile

    problems = check_profile(loaded, state_dir, policy, create_state_dir=True, record=record)
    if problems:
        raise ConfigError(f"{loaded.label}: {len(problems)} problem(s)", problems)


def status_printer(console: bool) -> Any:
    if console:
        from respecd.terminal import TERMINAL

        def sink(fields: dict[str, Any], line: str) -> None:
            if sys.stdout.isatty():
                TERMINAL.status(line)  # refreshed in place, log lines scroll above it
            else:
                try:
                    print(line, flush=True)
                except OSError:  # the reader of the pipe left: the daemon goes on (and stops cleanly)
                    pass
    else:

        def sink(fields: dict[str, Any], line: str) -> None:
            log.info("status", **fields)

    return sink


async def run_live(profile: Profile, args: argparse.Namespace, signals: Any, console: bool, state_dir: Any) -> int:
    from respecd.clock import MonotonicClock
    from respecd.daemon import Daemon
    from respecd.drivers.base import DriverContext
    from respecd.record import make_recorder
    from respecd.sdnotify import Notifier
    from respecd.session import Session
    from respecd.terminal import TERMINAL

    stop = signals.bind()
    clock = MonotonicClock()
    if args.seed is not None:
        profile = profile.model_copy(update={"controller": profile.controller.model_copy(update={"seed": args.seed})})
    context = DriverContext(seed=args.seed or 0, simulation=getattr(profile, "simulation", None))
    recorder = make_recorder(profile, args.record, clock, getattr(args, "foxglove", None))
    session = Session(profile, clock, context, policy=args.policy, state_dir=state_dir,
                      observers=[recorder] if recorder is not None else [])
    daemon = Daemon(session, notifier=Notifier(), status_sink=status_printer(console), recorder=recorder,
                    relay_stderr=True)  # OpenCV's own warnings become log events
    try:
        await daemon.run(duration=args.duration, stop=stop)
    finally:
        TERMINAL.close()
    if session.lingering:
        log.warning("abandoning_inflight_work", tasks=session.lingering)
    return 0


def exit_now(status: int) -> None:
    """End the process without the interpreter's teardown.

    Called by the console script once the daemon or a replay has shut down (or failed to
    start): the Q-table is saved, the log and report finished, and stdout flushed here.
    What is left is an inference that may still be running in its worker thread (it cannot
    be interrupted and nobody wants its result), a checkpoint still loading when a signal
    ended the start, and torch's module teardown; together they took 0.8-2 s on a loaded
    2-core machine, which would break the ~2 s SIGTERM budget that systemd's stop relies on.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
