"""Command line: ``respecd`` runs the daemon; subcommands validate, train, inspect, bench.

Subcommands live in their own modules, listed in ``COMMANDS`` and imported only when used,
so ``respecd check-config`` does not import torch. Each module provides
``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from respecd import __version__
from respecd.errors import ConfigError, InputError, report

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "check-config": ("respecd.cli.check_config", "validate profiles; print FILE:LINE: problems, exit 2 if any"),
    "schema": ("respecd.cli.schema", "print the profile JSON Schema (for editors), or check files against it"),
    "bench": ("respecd.cli.bench", "run a benchmark, print figures, write JSON"),
    "experiment": ("respecd.cli.experiment", "diagnose the controller on simulated worlds: what a configuration "
                   "is worth (fixed), a table with one sensor pinned (pin), static below its maximum (probe), "
                   "detector latency (latency), the winning table (choose)"),
    "train": ("respecd.cli.train", "train the fusion detector on the simulated rover or an LLVIP-layout folder"),
    "adapt": ("respecd.cli.adapt", "learn the detector's thermal path from recorded sessions: the RGB detector's "
              "confident boxes in good light teach it, no labels"),
    "eval": ("respecd.cli.eval", "mAP per RGB resolution and with each sensor off, contributions, faithfulness"),
    "calibrate": ("respecd.cli.calibrate", "fit the detector's confidence calibration per RGB size into a checkpoint"),
    "radar-profile": ("respecd.cli.radar_profile", "print the radar chirp cfg and its four figures"),
    "radar-dump": ("respecd.cli.radar_dump", "decode a recorded radar data-port capture, one line per frame"),
    "log": ("respecd.cli.log", "inspect or convert a session log: `log info LOG|BAG`, "
            "`log export LOG --to rosbag2 DIR`"),
    "train-policy": ("respecd.cli.train_policy", "train the Q-table on the simulated scenarios (cached outcomes)"),
    "policy": ("respecd.cli.policy", "print a learned Q-table as a policy: `policy show FILE`"),
    "export": ("respecd.cli.export", "write a checkpoint's net as ONNX graphs: `export CKPT --to onnx OUT`"),
    "fleet": ("respecd.cli.fleet", "many logs at once, serially, in a process pool or on Ray: `fleet eval` a policy, "
              "`fleet learn` one Q-table, `fleet sweep` reward weights"),
}


def build_parser() -> argparse.ArgumentParser:
    from respecd.cli.run import add_arguments as add_run_arguments

    parser = argparse.ArgumentParser(prog="respecd", description="Adaptive multispectral sensing daemon (ReSPEC).", allow_abbrev=False)  # noqa: E501 (`bench scenarios --log` is not an abbreviation of --log-level)
    parser.add_argument("--version", action="version", version=f"respecd {__version__}")
    add_run_arguments(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        command = sub.add_parser(name, help=help_text, description=help_text)
        importlib.import_module(module_name).add_arguments(command)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse and run one command; its exit status (2: bad input, said in one line each)."""
    return _run(build_parser().parse_args(argv))


def entry() -> None:
    """The console script (and ``python -m respecd.cli``): like ``main``, but the daemon and a
    replay end the process without the interpreter's teardown (``run.exit_now``). A stop signal
    is noted from the first line, while the command line is built (``signals.note_early``)."""
    from respecd.signals import note_early, release_early

    note_early()
    args = build_parser().parse_args()
    if args.command is not None:
        release_early()
    status = _run(args)
    if args.command is None:
        from respecd.cli.run import exit_now

        exit_now(status)
    sys.exit(status)


def _run(args: argparse.Namespace) -> int:
    module_name = COMMANDS[args.command][0] if args.command else "respecd.cli.run"
    try:
        return int(importlib.import_module(module_name).main(args) or 0)
    except (ConfigError, InputError) as err:
        return report(err, "respecd")
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `respecd policy show q.npz | head`: the reader left, nothing is wrong
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 141

