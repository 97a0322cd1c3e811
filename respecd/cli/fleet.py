"""``respecd fleet eval|learn|sweep LOGS...``: one policy, one table, one reward over many logs.

LOGS are files, folders and globs (or object-store URLs, with fsspec). Serial by default;
``--workers N`` a process pool; ``--address local`` a Ray instance on this machine,
``--address auto|HOST:PORT|ray://HOST:PORT`` a Ray cluster (``pip install 'respecd[fleet]'``).
Exit status 0 when every log ran, 1 when some failed (each said in one line), 2 for bad input.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from respecd.argtypes import positive_float, positive_int, seed

POLICIES = ("learn", "exploit", "static", "heuristic")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="fleet_command", metavar="VERB", required=True)
    evaluate = sub.add_parser("eval", help="replay every log under one policy: a report per log and a pooled one")
    _common(evaluate)
    evaluate.add_argument("--policy", choices=POLICIES, help="the policy to evaluate (default: each profile's)")
    evaluate.add_argument("--table", metavar="FILE", help="the Q-table exploit acts on (learn starts from it)")
    evaluate.add_argument("--allow-no-table", action="store_true",
                          help="exploit with no Q-table that fits runs anyway; its rows say 'no table'")
    evaluate.add_argument("--seed", type=seed, default=0, help="the controller's seed, the same for every log")
    evaluate.add_argument("--duration", type=positive_float, metavar="S", help="replay at most S seconds of each log")
    evaluate.add_argument("--topics", metavar="MAP", help="ROS bags: which topic is which sensor (as --replay)")
    evaluate.add_argument("--out", metavar="DIR", required=True,
                          help="writes DIR/fleet.json, fleet.txt, fleet.png and logs/NAME.json")
    learn = sub.add_parser("learn", help="one Q-table from every log's recorded transitions, through one learner")
    _common(learn)
    learn.add_argument("--init", metavar="FILE", help="a Q-table of the same layout to continue from")
    learn.add_argument("--out", metavar="TABLE", required=True, help="the table to write (.npz)")
    sweep = sub.add_parser("sweep", help="reward weights over the fleet, from the logged reward terms")
    _common(sweep)
    sweep.add_argument("--grid", metavar="KEY=V1,V2,...", action="append", required=True,
                       help="reward.* or learning.* values, every combination, e.g. "
                            "reward.alpha=0,2,4,reward.beta=0.02,0.05 (repeatable)")
    sweep.add_argument("--out", metavar="DIR", required=True, help="writes DIR/sweep.json and DIR/tables/POINT.npz")


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOGS", help="log files, folders, globs or object-store URLs")
    parser.add_argument("--profile", metavar="FILE", help="replay every log with this profile (default: its own)")
    parser.add_argument("--workers", type=positive_int, default=1,
                        help="processes (or Ray tasks in flight) working through the logs (default 1: this one)")
    parser.add_argument("--address", metavar="ADDR",
                        help="run on Ray: 'local' starts an instance here, auto|HOST:PORT|ray://HOST:PORT joins one")
    parser.add_argument("--log-level", default="warning", choices=("debug", "info", "warning", "error"),
                        help="log level of this process and its workers (default warning)")


def main(args: argparse.Namespace) -> int:
    from respecd.lab.fleet import worker
    from respecd.lab.fleet.logs import expand
    from respecd.lab.fleet.run import Where
    from respecd.logs import configure_logging

    fmt = configure_logging("auto", args.log_level)
    refs = expand(args.logs)
    where = Where(args.workers, args.address, worker.Settings(fmt, args.log_level))
    profile = _profile(args.profile)
    command = {"eval": _eval, "learn": _learn, "sweep": _sweep}[args.fleet_command]
    return command(args, refs, where, profile)


def _profile(path: str | None) -> dict[str, Any] | None:
    if path is None:
        return None
    from respecd.config import load_profile

    return dict(load_profile(path).model_dump(mode="json"))


def _eval(args: argparse.Namespace, refs: list[Any], where: Any, profile: dict[str, Any] | None) -> int:
    from respecd.control.persist import StoredTable
    from respecd.lab.fleet import out
    from respecd.lab.fleet.eval import EvalSpec
    from respecd.lab.fleet.run import eval_fleet
    from respecd.lab.fleet.tables import check_table
    from respecd.outputs import check_output_file

    target = Path(args.out)
    check_output_file("--out", str(target / "fleet.json"))
    table = StoredTable.read(Path(args.table)) if args.table else None
    if table is not None:
        check_table(table, refs, profile, args.policy)  # exit 2 naming the mismatch, before any replay
    spec = EvalSpec(args.policy, profile, table, args.seed, args.duration, args.topics, args.allow_no_table)
    document = eval_fleet(refs, spec, where)
    out.write(target, document)
    print(out.table(document))
    print(f"wrote {target / 'fleet.json'} (+ fleet.txt, fleet.png, logs/)")
    return 1 if document["pooled"]["failed"] else 0


def _learn(args: argparse.Namespace, refs: list[Any], where: Any, profile: dict[str, Any] | None) -> int:
    from respecd.control.persist import StoredTable
    from respecd.errors import InputError
    from respecd.lab.fleet.learn import MERGE
    from respecd.lab.fleet.run import learn_fleet
    from respecd.outputs import check_output_file

    check_output_file("--out", args.out, example="fleet-qtable.npz")
    init = StoredTable.read(Path(args.init)) if args.init else None
    learned = learn_fleet(refs, profile, where, init=init)
    if learned.table is None:
        raise InputError("fleet learn: no log could be learned from: " +
                         "; ".join(f"{k}: {v}" for k, v in learned.refused.items()))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    learned.table.write(Path(args.out))
    print(f"{args.out}: {learned.transitions} transitions of {len(learned.used)} logs, "
          f"{learned.table.updates} updates, fingerprint {learned.table.meta['fingerprint']}")
    print(f"merged: {MERGE}")
    for name, why in learned.refused.items():
        print(f"not learned from: {name}: {why}")
    return 1 if learned.refused else 0


def _sweep(args: argparse.Namespace, refs: list[Any], where: Any, profile: dict[str, Any] | None) -> int:
    from respecd.atomicfile import write_atomically
    from respecd.lab.fleet import sweep
    from respecd.lab.fleet.run import read_steps

    grid = sweep.parse_grid(args.grid)  # a bad or replay-only key: exit 2 before reading any log
    logs, _ = read_steps(refs, profile, where)
    rows = sweep.sweep(logs, grid)
    target = Path(args.out)
    (target / "tables").mkdir(parents=True, exist_ok=True)
    for row in rows:
        table = row.pop("table")
        if table is not None:
            row["table"] = f"tables/{row['name']}.npz"
            table.write(target / row["table"])
    refused = {log.name: log.error for log in logs if log.error is not None}
    for row in rows:
        refused.update(row["refused"])
    document = {"grid": grid, "points": rows, "refused": dict(sorted(refused.items()))}
    write_atomically(target / "sweep.json", (json.dumps(document, indent=1) + "\n").encode())
    print(sweep.table(rows))
    for name, why in sorted(refused.items()):
        print(f"not used: {name}: {why}")
    print(f"wrote {target / 'sweep.json'} and the learned tables in {target / 'tables'}; what a table is worth in "
          "detections and energy is a replay: respecd fleet eval LOGS --policy exploit --table TABLE")
    return 1 if refused else 0
