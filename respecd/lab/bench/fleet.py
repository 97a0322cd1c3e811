"""fleet: fleet eval over N logs at each worker count — speed-up, overhead, cold start, memory.

It records N short simulated sessions (``respecd --duration S --seed i --record``, two at a
time) unless given logs (``--use``), then for each worker count: opens the backend and runs one
short task per worker — start-up is the time that took beyond the tasks (processes, a pool's
fork server importing torch, a Ray instance), each worker's cold start its first task's time
beyond its replay (the detector's first load, opening a log) — then times ``fleet eval`` over
all N logs, handed out largest first. Per log, the overhead is the wall time beyond the busiest
worker's tasks, per task it ran (handing a log out, its result back); the imbalance (how much
longer the busiest worker worked than the mean) is apart. The results' digest (SHA-256 of
every report without its timings) must be the same at every worker count. Timings depend on
the machine's load: the load average is in the figures.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from respecd.argtypes import positive_float, positive_int
from respecd.errors import InputError

POLICY = "heuristic"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--logs", type=positive_int, default=8, help="simulated logs to record and evaluate (8)")
    parser.add_argument("--seconds", type=positive_float, default=4.0, help="length of each recorded log (4 s)")
    parser.add_argument("--workers", default="1,2", help="worker counts to time, comma-separated (1,2)")
    parser.add_argument("--address", metavar="ADDR", help="run the worker counts on Ray (local, auto, HOST:PORT)")
    parser.add_argument("--use", nargs="+", metavar="LOG", help="evaluate these logs instead of recording new ones")
    parser.add_argument("--policy", default=POLICY, help=f"the policy evaluated (default {POLICY})")


def run(args: argparse.Namespace) -> dict[str, Any]:
    counts = _counts(args.workers)
    with tempfile.TemporaryDirectory(prefix="respecd-bench-fleet-") as scratch:
        from respecd.lab.fleet.logs import expand

        recorded: dict[str, Any] = {}
        if args.use:
            refs = expand(args.use)
        else:
            began = time.perf_counter()
            refs = expand([str(p) for p in _record(Path(scratch), args.logs, args.seconds)])
            recorded = {"record_s": round(time.perf_counter() - began, 1), "seconds_each": args.seconds}
        load_before = os.getloadavg()
        runs = {str(w): _timed(refs, w, args.address, args.policy) for w in counts}
    return _figures(refs, runs, load_before, recorded, args.address, args.policy)


def _counts(text: str) -> list[int]:
    try:
        counts = [int(x) for x in text.split(",") if x.strip()]
    except ValueError as err:
        raise InputError(f"--workers {text}: expected worker counts such as 1,2") from err
    if not counts or min(counts) < 1:
        raise InputError(f"--workers {text}: expected worker counts >= 1 such as 1,2")
    return counts


def _record(folder: Path, n: int, seconds: float) -> list[Path]:
    """N simulated sessions of the default profile (seeds 1..N), two recordings at a time."""
    logs = [folder / f"sim{i:02d}.mcap" for i in range(1, n + 1)]
    for pair in (logs[i:i + 2] for i in range(0, n, 2)):
        running = []
        for log in pair:
            seed = log.stem.removeprefix("sim")
            argv = [sys.executable, "-m", "respecd.cli", "--duration", f"{seconds:g}", "--seed", str(int(seed)),
                    "--record", str(log), "--state-dir", str(folder / f"state-{seed}"), "--log-level", "error"]
            running.append((log, subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)))
        for log, proc in running:
            out, _ = proc.communicate(timeout=600)
            if proc.returncode != 0 or not log.is_file():
                raise InputError(f"bench fleet: recording {log.name} failed: {out[-500:]}")
    return logs


def _timed(refs: list[Any], workers: int, address: str | None, policy: str) -> dict[str, Any]:
    from respecd.lab.fleet.eval import EvalSpec, eval_log, outcome_of
    from respecd.lab.fleet.run import Where, backend, run_map

    began = time.perf_counter()
    with backend(Where(workers, address)) as used:
        opened = time.perf_counter() - began
        warm = used.map(eval_log, EvalSpec(policy, duration=1.0), [refs[0]] * workers)
        warm_s = time.perf_counter() - began - opened
        start = time.perf_counter()
        answers = run_map(used, eval_log, EvalSpec(policy), refs, "logs")
        wall = time.perf_counter() - start
    outcomes = [outcome_of(r, a) for r, a in zip(refs, answers, strict=True)]
    warmed = [outcome_of(refs[0], a) for a in warm]
    rss = [o.timing["worker"]["max_rss_mb"] for o in [*outcomes, *warmed] if "worker" in o.timing]
    # a first task's time beyond its replay: imports left to it, the detector's load, opening the log
    cold = [o.timing["task_s"] - o.report["timing"]["wall_s"] for o in warmed if o.report is not None]
    busy: dict[int, list[float]] = {}  # per worker process, its tasks' seconds
    for o in outcomes:
        busy.setdefault(o.timing.get("worker", {}).get("pid", 0), []).append(o.timing.get("task_s", 0.0))
    critical = max(busy.values(), key=sum)  # the worker that finished last, as far as its tasks go
    tasks = sum(sum(b) for b in busy.values())
    return {
        # the backend up and its workers started (a pool's fork server imports torch once; Ray's instance)
        "startup_s": round(opened + warm_s - max((o.timing.get("task_s", 0.0) for o in warmed), default=0.0), 3),
        "cold_start_s": sorted(round(c, 3) for c in cold),
        "wall_s": round(wall, 3), "sum_task_s": round(tasks, 3),
        # what handing a log to a worker and its result back costs: the wall time beyond the tasks of the
        # busiest worker, per task it ran; what the workers' loads differ by is the imbalance, apart
        "overhead_ms_per_log": round(max(wall - sum(critical), 0.0) / len(critical) * 1000, 1),
        "imbalance_s": round(sum(critical) - tasks / workers, 3),
        "failed": sorted(o.name for o in outcomes if o.error is not None),
        "digest": digest(outcomes), "max_worker_rss_mb": max(rss, default=None),
        "pids": len(busy),
    }


def digest(outcomes: list[Any]) -> str:
    """SHA-256 of every log's report and error without timings, in name order."""
    from respecd.lab.fleet.eval import strip_timing

    body = [strip_timing(o.to_json()) for o in sorted(outcomes, key=lambda o: o.name)]
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()[:16]


def _figures(refs: list[Any], runs: dict[str, dict[str, Any]], load_before: tuple[float, ...],
             recorded: dict[str, Any], address: str | None, policy: str) -> dict[str, Any]:
    """Speed-up and efficiency against one worker (when timed), the top worker count's overhead."""
    base = runs["1"]["wall_s"] if "1" in runs else None
    speedup = {k: round(base / r["wall_s"], 2) for k, r in runs.items()} if base else {}
    digests = {r["digest"] for r in runs.values()}
    top = runs[max(runs, key=int)]
    return {
        "logs": len(refs), "policy": policy, "backend": "ray" if address else "serial/pool",
        "recorded": recorded, "runs": runs, "speedup": speedup,
        "efficiency": {k: round(s / int(k), 2) for k, s in speedup.items()},
        "overhead_ms_per_log": top["overhead_ms_per_log"], "digest": next(iter(digests)),
        "digests_agree": len(digests) == 1,
        "memory_mb": {"this_process": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                      "max_worker": max((r["max_worker_rss_mb"] or 0) for r in runs.values())},
        "load_avg": {"before": [round(x, 2) for x in load_before], "after": [round(x, 2) for x in os.getloadavg()]},
        "cpus": len(os.sched_getaffinity(0)),
    }


def summary(figures: dict[str, Any]) -> str:
    lines = [f"fleet eval of {figures['logs']} logs ({figures['backend']}), load {figures['load_avg']['before'][0]}"
             f" -> {figures['load_avg']['after'][0]} on {figures['cpus']} CPUs"]
    for k, r in figures["runs"].items():
        lines.append(f"  {k} worker(s): {r['wall_s']:.1f} s, speed-up {figures['speedup'].get(k, '-')}, "
                     f"overhead {r['overhead_ms_per_log']:.0f} ms/log, imbalance {r['imbalance_s']:.1f} s, "
                     f"start-up {r['startup_s']:.1f} s, "
                     f"cold start {r['cold_start_s']} s, failed {len(r['failed'])}")
    lines.append(f"digest {figures['digest']} ({'the same' if figures['digests_agree'] else 'DIFFERS'} at every "
                 f"worker count); max worker RSS {figures['memory_mb']['max_worker']} MB")
    return "\n".join(lines)
