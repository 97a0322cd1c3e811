"""``respecd experiment NAME ...``: the controller diagnoses of the lab, on simulated worlds.

Each names a module of respecd.lab.experiment with ``add_arguments(parser)`` and
``main(args) -> int``; its docstring is the command's description.
"""

from __future__ import annotations

import argparse
import importlib

EXPERIMENTS: dict[str, str] = {
    "fixed": "respecd.lab.experiment.fixed",
    "pin": "respecd.lab.experiment.pin",
    "probe": "respecd.lab.experiment.probe",
    "latency": "respecd.lab.experiment.latency",
    "choose": "respecd.lab.experiment.choose",
    "heuristic": "respecd.lab.experiment.heuristic",
    "platforms": "respecd.lab.experiment.platforms",
    "frontier": "respecd.lab.experiment.frontier",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="experiment", metavar="NAME", required=True)
    for name, module_name in EXPERIMENTS.items():
        doc = (importlib.import_module(module_name).__doc__ or "").strip()
        command = sub.add_parser(name, help=doc.splitlines()[0], description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
        importlib.import_module(module_name).add_arguments(command)


def main(args: argparse.Namespace) -> int:
    return int(importlib.import_module(EXPERIMENTS[args.experiment]).main(args))
