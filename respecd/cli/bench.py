"""``respecd bench NAME [--json OUT]``: run one benchmark, print its figures, write JSON."""

from __future__ import annotations

import argparse
import importlib
import json
import platform
from pathlib import Path
from typing import Any

from respecd.lab.bench import BENCHES
from respecd.outputs import check_output_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, module_name in BENCHES.items():
        module = importlib.import_module(module_name)
        bench = sub.add_parser(name, help=(module.__doc__ or "").strip().splitlines()[0])
        bench.add_argument("--json", metavar="OUT", help="also write the figures as JSON")
        module.add_arguments(bench)


def main(args: argparse.Namespace) -> int:
    from respecd.logs import configure_logging

    check_output_file("--json", args.json, example=f"bench-{args.bench}.json")  # before the run; folders are made
    configure_logging("console", "warning")
    figures: dict[str, Any] = importlib.import_module(BENCHES[args.bench]).run(args)
    figures.setdefault(
        "machine", {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()}
    )
    module = importlib.import_module(BENCHES[args.bench])
    if hasattr(module, "summary"):  # a short human summary; the figures go to --json
        print(module.summary(figures))
    else:
        for key, value in figures.items():
            print(f"{key}: {json.dumps(value) if isinstance(value, (dict, list)) else value}")
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(figures, indent=2) + "\n", encoding="utf-8")
    return 0
