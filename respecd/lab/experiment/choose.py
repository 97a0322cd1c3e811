"""The table choice of docs/RESULTS.md, as code: which candidate wins on the validation worlds.

The rule was fixed before any held-out world was scored: count the headline's criteria a
candidate's validation run meets (every goal of ``bench scenarios --json`` except "static is
the ceiling", which does not depend on the table); most wins; ties go to the higher RL mAP@0.5
(differences under 0.005 count as equal), then to the larger accelerator-load cut against the heuristic.

usage: respecd experiment choose NAME=VAL.json NAME=VAL.json ...  (prints the winner's NAME)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from respecd.errors import InputError

MAP_EQUAL = 0.005  # RL mAP@0.5 differences below this are a tie


def criteria_met(run: dict[str, Any]) -> int:
    """The headline criteria a run meets, the static-ceiling goal left out."""
    return sum(1 for goal in run["goals"] if goal["met"] and not goal["goal"].startswith("static is"))


def choose(runs: dict[str, dict[str, Any]]) -> str:
    """The winning candidate's name among ``runs`` (name -> a ``bench scenarios --json`` document)."""
    if not runs:
        raise InputError("no candidates: expected NAME=FILE.json, one per `respecd bench scenarios --json` result")
    best = max(criteria_met(r) for r in runs.values())
    left = {n: r for n, r in runs.items() if criteria_met(r) == best}
    top_map = max(r["pooled"]["rl"]["map50"] for r in left.values())
    left = {n: r for n, r in left.items() if top_map - r["pooled"]["rl"]["map50"] < MAP_EQUAL}
    return max(left, key=lambda n: left[n]["summary"]["rl_vs_heuristic"]["load_reduction"])


def _read(arg: str) -> tuple[str, dict[str, Any]]:
    name, sep, path = arg.partition("=")
    if not sep or not name:
        raise InputError(f"{arg}: expected NAME=FILE.json")
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
        doc["goals"], doc["pooled"]["rl"]["map50"], doc["summary"]["rl_vs_heuristic"]["load_reduction"]
    except KeyError as err:
        raise InputError(f"{path}: no {err} in it: expected a `respecd bench scenarios --json` result") from err
    except (OSError, ValueError, TypeError) as err:
        raise InputError(f"{path}: expected a `respecd bench scenarios --json` result ({err})") from err
    return name, doc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("candidate", nargs="+", metavar="NAME=FILE.json",
                        help="a candidate table's `respecd bench scenarios --json` result on the validation worlds")


def main(args: argparse.Namespace) -> int:
    """Each candidate's criteria, RL mAP@0.5 and load cut on stderr; the winner's NAME on stdout."""
    candidates = dict(_read(a) for a in args.candidate)
    for n, r in candidates.items():
        print(f"{n}: {criteria_met(r)} criteria, RL mAP@0.5 {r['pooled']['rl']['map50']:.3f}, load "
              f"{-100 * r['summary']['rl_vs_heuristic']['load_reduction']:+.1f} % vs heuristic", file=sys.stderr)
    print(choose(candidates))
    return 0
